"""Bad numbers in data files: absurd or non-finite visible values are one-line errors
naming the split, the file, the entry and the field; hidden values are ignored; data
with no spread is refused."""

import json
import os
import subprocess
import sys

import numpy as np
import pytest
from absl import logging

from c3dpo_jax.data import KeypointData, json_dataset, load_splits
from c3dpo_jax.data.dataset import check_spread
from configs import default

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _entries(m=8, k=6, seed=0, scale=50.0, offset=300.0):
    rng = np.random.default_rng(seed)
    return [
        {
            "kp_loc": (rng.normal(size=(2, k)) * scale + offset).tolist(),
            "kp_vis": [1] * k,
            "kp_loc_3d": rng.normal(size=(3, k)).tolist(),
        }
        for _ in range(m)
    ]


def _write(path, entries):
    path.write_text(json.dumps(entries))
    return str(path)


def _data_cfg(train, test, **kw):
    c = default.get_config().data
    c.train_path, c.test_path = train, test
    c.update(kw)
    return c


@pytest.mark.parametrize("value", [1e20, -1e13, 1e7])
def test_an_absurd_visible_value_names_split_file_entry_and_field(tmp_path, value):
    bad = _entries()
    bad[5]["kp_loc"][1][3] = value
    cfg = _data_cfg(_write(tmp_path / "tr.json", bad), _write(tmp_path / "te.json", _entries()))
    with pytest.raises(ValueError) as err:
        load_splits(cfg)
    text = str(err.value)
    assert "\n" not in text
    assert text.startswith(
        f"train split: {tmp_path / 'tr.json'}: 1 invalid of 8 entries: "
        f"entry 5: field 'kp_loc' has {value:.3g} at visible point 3, far "
        "outside the file's other points"
    )
    assert "drop_invalid=True" in text


def test_an_absurd_3d_value_in_the_test_file_is_an_error(tmp_path):
    bad = _entries()
    bad[2]["kp_loc_3d"][2][0] = 1.4e17
    cfg = _data_cfg(_write(tmp_path / "tr.json", _entries()), _write(tmp_path / "te.json", bad))
    with pytest.raises(
        ValueError,
        match=r"^test split: .*te\.json: 1 invalid of 8 entries: "
        r"entry 2: field 'kp_loc_3d' has 1.4e\+17 at point 0",
    ):
        load_splits(cfg)


def test_drop_invalid_drops_the_absurd_entry(tmp_path):
    bad = _entries()
    bad[1]["kp_loc"][0][0] = 1e20
    data = json_dataset.load(_write(tmp_path / "a.json", bad), drop_invalid=True)
    assert len(data) == 7 and np.abs(data.kp).max() < 1e4


def test_hidden_values_are_not_data_and_are_stored_as_zero():
    entries = _entries()
    for i, junk in ((0, float("nan")), (1, float("inf")), (2, 1e20), (3, -1e38)):
        entries[i]["kp_vis"][4] = 0
        entries[i]["kp_loc"][0][4] = junk
    data = json_dataset.parse(entries)
    assert len(data) == 8 and np.all(data.kp[:4, 4] == 0) and np.all(np.isfinite(data.kp))
    entries[6]["kp_loc"][1][2] = float("nan")  # but a visible NaN is an error
    with pytest.raises(
        ValueError, match="entry 6: field 'kp_loc' contains NaN or inf at visible point 2"
    ):
        json_dataset.parse(entries)


def test_outlier_rule_over_random_datasets():
    """Property over 60 seeded random files: views differing in scale (x0.1..x10) and
    position are never flagged; one value 1e5 times the typical spread always is, at its
    entry and point."""
    rng = np.random.default_rng(1)
    for case in range(60):
        m, k = int(rng.integers(3, 30)), int(rng.integers(3, 20))
        entries = _entries(m, k, seed=case, scale=1.0, offset=0.0)
        for e in entries:
            s, t = 10 ** rng.uniform(-1, 1), rng.uniform(-20, 20, size=(2, 1))
            e["kp_loc"] = (np.array(e["kp_loc"]) * s + t).tolist()
            e["kp_vis"] = (rng.uniform(size=k) > 0.2).astype(int).tolist()
            e["kp_vis"][:2] = [1, 1]
        assert len(json_dataset.parse(entries, min_visible=0)) == m, case
        i, j = int(rng.integers(m)), int(rng.integers(2))
        entries[i]["kp_loc"][rng.integers(2)][j] = float(rng.choice([-1, 1]) * 1e5 * 25)
        with pytest.raises(
            ValueError, match=f"entry {i}: field 'kp_loc' has .* at visible point {j}"
        ):
            json_dataset.parse(entries, min_visible=0)


def test_unreadable_files_name_themselves(tmp_path):
    binary = tmp_path / "bin.json"
    binary.write_bytes(b'[{"kp_loc": \xff\xfe\x00]')
    with pytest.raises(
        ValueError,
        match=r"bin\.json is not a UTF-8 text \(JSON\) file: "
        r"byte 12 is b'\\xff'",
    ):
        json_dataset.load(str(binary))
    truncated = tmp_path / "cut.json"
    truncated.write_text(json.dumps(_entries())[:200])
    with pytest.raises(ValueError, match=r"^.*cut\.json is not valid JSON"):
        json_dataset.load(str(truncated))


def test_every_reader_of_the_release_json_reads_a_file_with_a_byte_order_mark(tmp_path):
    """Windows tools write UTF-8 with a BOM: training read such a file, and the pictures
    after it (which read the file's drawing style) failed on it."""
    from c3dpo_jax import predict, visualise
    from c3dpo_jax.data import importers

    path = tmp_path / "bom.json"
    wrapper = {"dataset": "mine", "y_up": True, "skeleton": [[0, 1]], "data": _entries()}
    path.write_text(json.dumps(wrapper), encoding="utf-8-sig")
    assert path.read_bytes().startswith(b"\xef\xbb\xbf")
    assert len(json_dataset.load(str(path), cache=False)) == 8
    assert visualise.data_file_style(str(path)) == {"skeleton": [[0, 1]], "y_up": True}
    assert predict.read_input(str(path))["kp"].shape == (8, 6, 2)
    coco = tmp_path / "coco.json"
    coco.write_text(json.dumps({"annotations": [{"keypoints": [1, 2, 2, 3, 4, 2]}]}),
                    encoding="utf-8-sig")
    importers.main(["coco", str(coco), "--out", str(tmp_path / "o.json")])
    assert json_dataset.load(str(tmp_path / "o.json")).n_keypoints == 2


def test_training_data_without_spread_is_refused(tmp_path):
    zeros = _entries()
    for e in zeros:
        e["kp_loc"] = np.zeros((2, 6)).tolist()
    cfg = _data_cfg(_write(tmp_path / "z.json", zeros), _write(tmp_path / "t.json", _entries()))
    with pytest.raises(
        ValueError,
        match=r"^train split 'z': no view has two distinct visible "
        "points",
    ):
        load_splits(cfg)
    hidden = _entries()
    for e in hidden:
        e["kp_vis"] = [0] * 6
    cfg = _data_cfg(
        _write(tmp_path / "h.json", hidden), _write(tmp_path / "t.json", _entries()), min_visible=0
    )
    with pytest.raises(ValueError, match="train split 'h': no view has two distinct"):
        load_splits(cfg)


def test_some_coincident_views_are_a_warning(monkeypatch):
    rng = np.random.default_rng(0)
    kp = rng.normal(size=(5, 4, 2))
    kp[[1, 3]] = 7.0
    logged = []
    monkeypatch.setattr(logging, "warning", lambda msg, *a: logged.append(msg % a))
    check_spread(KeypointData(kp=kp, vis=np.ones((5, 4)), name="d"), "train")
    assert logged == [
        "train split 'd': 2 of 5 views have visible points that all coincide "
        "(entries [1, 3]); they carry no shape"
    ]
    logged.clear()
    vis = np.ones((5, 4))
    vis[1, 1:] = 0  # one visible point: min_visible's business, not a warning
    kp[3] = rng.normal(size=(4, 2))
    check_spread(KeypointData(kp=kp, vis=vis, name="d"), "train")
    assert logged == []


def test_views_with_two_points_and_repeated_views_are_warnings(monkeypatch):
    rng = np.random.default_rng(0)
    kp = rng.normal(size=(6, 12, 2))
    logged = []
    monkeypatch.setattr(logging, "warning", lambda msg, *a: logged.append(msg % a))
    vis = np.zeros((6, 12))
    vis[:, :2] = 1
    vis[0] = 1
    check_spread(KeypointData(kp=kp, vis=vis, name="d"), "train")
    assert logged == ["train split 'd': half of the views show 2 point(s) or fewer; a view's "
                      "depth is learnt from how its visible points move together, and two "
                      "points say almost nothing about it"]
    logged.clear()
    kp[2:] = kp[0]  # five copies of one view; what a hidden point holds does not count
    kp[4, 5] = 99.0
    vis = np.ones((6, 12))
    vis[4, 5] = 0
    vis[5] = vis[4]
    check_spread(KeypointData(kp=kp, vis=vis, name="d"), "train")
    assert logged == ["train split 'd': only 3 of its 6 views differ from each other; repeated "
                      "views add nothing to learn from"]


def test_cli_names_the_bad_entry_in_one_line(tmp_path):
    bad = _entries(k=20)
    bad[3]["kp_loc"][0][7] = 1e20
    train = _write(tmp_path / "tr.json", bad)
    test = _write(tmp_path / "te.json", _entries(k=20))
    out = subprocess.run(
        [
            sys.executable,
            "-m",
            "c3dpo_jax.main",
            "--config=configs/synthetic.py:smoke",
            f"--workdir={tmp_path / 'run'}",
            f"--config.data.train_path={train}",
            f"--config.data.test_path={test}",
        ],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert out.returncode == 2, out.stderr[-3000:]
    last = out.stderr.strip().splitlines()[-1]
    assert last.startswith(
        f"error: train split: {train}: 1 invalid of 8 entries: entry 3: "
        "field 'kp_loc' has 1e+20 at visible point 7"
    ), out.stderr
