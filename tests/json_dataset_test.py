"""Release JSON format: parsing, validation messages, drop_invalid, and the npz cache."""

import json
import os

import numpy as np
import pytest
from absl import logging

from c3dpo_jax import evaluation
from c3dpo_jax.data import json_dataset


def _entries(m=4, k=5, seed=0):
    rng = np.random.default_rng(seed)
    return [{"kp_loc": rng.normal(size=(2, k)).tolist(), "kp_vis": [1] * k,
             "kp_loc_3d": rng.normal(size=(3, k)).tolist(), "image_path": f"im{i}.jpg",
             "h36m_info": {"scale": 2.0, "action_name": "Walking" if i % 2 else "Eating"}}
            for i in range(m)]


def test_parse_reads_every_field_and_transposes_once():
    entries = _entries()
    entries = [dict(e, class_mask=[1] * 5, kp_defined=[1] * 5, K=np.eye(3).tolist())
               for e in entries]
    data = json_dataset.parse({"dataset": "toy", "data": entries})
    assert data.name == "toy" and data.kp.shape == (4, 5, 2) and data.kp3d.shape == (4, 5, 3)
    np.testing.assert_allclose(data.kp[1], np.array(entries[1]["kp_loc"]).T, rtol=1e-6)
    assert data.group_names == ("Eating", "Walking") and list(data.group) == [0, 1, 0, 1]
    assert list(data.image_path) == [f"im{i}.jpg" for i in range(4)]
    assert data.intrinsics.shape == (4, 3, 3) and np.all(data.scale == 2.0)


def test_pascal_bbox_rule_hides_points_outside_the_enlarged_box():
    e = {"kp_loc": [[0.0, 5.0, 11.5], [0.0, 5.0, 5.0]], "kp_vis": [1, 1, 1],
         "p3d_info": {"p3d_class": "car", "bbox": [0, 0, 10, 10]}}
    data = json_dataset.parse([e])
    assert data.vis.tolist() == [[1, 1, 0]] and data.group_names == ("car",)


@pytest.mark.parametrize("mutate, message", [
    (lambda e: e[2].pop("kp_vis"), "entry 2: required field 'kp_vis' is missing"),
    (lambda e: e[1]["kp_loc"][0].pop(), "entry 1: field 'kp_loc' is a ragged or non-numeric"),
    (lambda e: e[2]["kp_loc"][0].__setitem__(1, "1.5"),
     "entry 2: field 'kp_loc' is a ragged or non-numeric"),  # a number as a string
    (lambda e: e[0]["kp_loc"][1].__setitem__(0, None),
     "entry 0: field 'kp_loc' contains NaN or inf at visible point 0 (or null)"),
    (lambda e: e[0]["kp_vis"].__setitem__(1, float("nan")),
     "entry 0: field 'kp_vis' has value nan at point 1 (must be 0 or 1)"),
    (lambda e: e[3]["kp_loc_3d"][2].__setitem__(4, None),
     "entry 3: field 'kp_loc_3d' contains NaN or inf"),  # a point that counts
    (lambda e: e[3].update(kp_vis=[1] * 4), "entry 3: field 'kp_vis' has 4 keypoints but the "
     "dataset has 5 keypoints (K must be the same in every entry)"),
    (lambda e: e[0]["kp_loc"][1].__setitem__(2, float("nan")),
     "entry 0: field 'kp_loc' contains NaN or inf"),
    (lambda e: e[2]["kp_loc_3d"][0].__setitem__(0, float("inf")),
     "entry 2: field 'kp_loc_3d' contains NaN or inf"),
    (lambda e: e[1]["kp_vis"].__setitem__(3, 2), "entry 1: field 'kp_vis' has value 2 at point 3 "
     "(must be 0 or 1)"),
    (lambda e: e[3].update(kp_vis=[1, 0, 0, 0, 0]), "entry 3: field 'kp_vis' has 1 visible "
     "points, fewer than min_visible=2"),
    (lambda e: e[2].pop("kp_loc_3d"), "entry 2: field 'kp_loc_3d' is missing (other entries"),
    (lambda e: e[1]["kp_loc_3d"].pop(), "entry 1: field 'kp_loc_3d' has shape (2, 5), "
     "expected (3, 5)"),
])
def test_each_problem_is_reported_with_entry_and_field(mutate, message):
    entries = _entries()
    mutate(entries)
    with pytest.raises(ValueError) as err:
        json_dataset.parse(entries, name="toy")
    assert message in str(err.value)
    assert "drop_invalid=True" in str(err.value)


def test_points_that_do_not_count_may_hold_null_nan_or_a_placeholder():
    # What other tools write for a missing value: null (JSON.stringify(NaN), pandas) at a
    # hidden 2D point, and at a 3D point that kp_defined marks as undefined, NaN or a
    # placeholder far away. They are stored as 0 and none of them is scored.
    entries = [dict(e, kp_defined=[1, 1, 1, 1, 0]) for e in _entries()]
    entries[0]["kp_vis"][3] = 0
    entries[0]["kp_loc"][0][3] = None
    entries[1]["kp_loc_3d"][1][4] = None
    entries[2]["kp_loc_3d"][0][4] = float("nan")
    for e in entries[3:]:
        e["kp_loc_3d"][2][4] = 1e9
    data = json_dataset.parse(entries)
    assert np.all(data.kp[0, 3] == 0) and np.all(data.kp3d[:, 4] == 0)
    pred = data.kp3d.copy()
    pred[:, 4] = 1e6  # garbage where the ground truth is undefined
    for protocol in ("default", "up3d", "h36m", "pascal3d"):
        assert evaluation.evaluate(pred, data, protocol)["mpjpe"] == pytest.approx(0.0, abs=1e-6)


def test_singular_intrinsics_are_named():
    entries = [dict(e, K=[[500.0, 0, 2], [0, 500, 1], [0, 0, 1]]) for e in _entries()]
    entries[2]["K"] = [[0, 0, 0], [0, 0, 0], [0, 0, 1]]
    with pytest.raises(ValueError, match=r"entry 2: field 'K' is singular \(the intrinsics "
                       "must be invertible\)"):
        json_dataset.parse(entries)


def test_drop_invalid_drops_counts_and_logs(monkeypatch):
    entries = _entries(6)
    entries[1]["kp_vis"][0] = 5
    entries[4].pop("kp_loc")
    logged = []
    monkeypatch.setattr(logging, "warning", lambda msg, *a: logged.append(msg % a))
    data = json_dataset.parse(entries, drop_invalid=True)
    assert len(data) == 4
    np.testing.assert_allclose(data.kp[1], np.array(entries[2]["kp_loc"]).T, rtol=1e-6)
    assert "dropped 2 of 6 invalid entries" in logged[0]


def test_min_visible_threshold_is_a_parameter():
    entries = _entries()
    entries[0]["kp_vis"] = [1, 1, 0, 0, 0]
    assert len(json_dataset.parse(entries, min_visible=2)) == 4
    with pytest.raises(ValueError, match="entry 0: field 'kp_vis' has 2 visible points"):
        json_dataset.parse(entries, min_visible=3)


def test_file_level_errors_are_clear(tmp_path):
    with pytest.raises(ValueError, match="non-empty list of entries"):
        json_dataset.parse([])
    with pytest.raises(ValueError, match="needs a 'data' list"):
        json_dataset.parse({"dataset": "x"})
    bad = tmp_path / "bad.json"
    bad.write_text("[{")
    with pytest.raises(ValueError, match="bad.json is not valid JSON"):
        json_dataset.load(str(bad))
    with pytest.raises(FileNotFoundError, match="does not exist"):
        json_dataset.load(str(tmp_path / "missing.json"))
    # A byte-order mark, as some Windows tools write before UTF-8 text, is not an error.
    marked = tmp_path / "bom.json"
    marked.write_bytes(b"\xef\xbb\xbf" + json.dumps(_entries()).encode())
    assert len(json_dataset.load(str(marked), cache=False)) == 4


def test_check_n_keypoints_names_the_fix():
    data = json_dataset.parse(_entries())
    json_dataset.check_n_keypoints(data, 5)
    with pytest.raises(ValueError, match=r"has K=5 keypoints but the model expects 17; set "
                       r"--config.model.n_keypoints=5"):
        json_dataset.check_n_keypoints(data, 17)


def test_save_then_load_round_trips(tmp_path):
    data = json_dataset.parse(_entries())
    path = str(tmp_path / "toy.json")
    json_dataset.save(data, path)
    back = json_dataset.load(path, cache=False)
    for field in ("kp", "vis", "kp3d", "scale", "group", "image_path"):
        np.testing.assert_array_equal(getattr(back, field), getattr(data, field))
    assert back.group_names == data.group_names


def test_cache_is_written_used_and_rebuilt_when_stale_or_corrupt(tmp_path, monkeypatch):
    path = tmp_path / "toy.json"
    path.write_text(json.dumps(_entries()))
    cache = tmp_path / "toy.c3dpo_cache.npz"
    first = json_dataset.load(str(path))
    assert cache.exists()
    calls = []
    real_parse = json_dataset.parse
    monkeypatch.setattr(
        json_dataset, "parse", lambda *a, **k: calls.append(1) or real_parse(*a, **k)
    )
    cached = json_dataset.load(str(path))
    assert calls == [] and cached.group_names == first.group_names
    np.testing.assert_array_equal(cached.kp, first.kp)
    np.testing.assert_array_equal(cached.image_path, first.image_path)
    # Another parse option is another key.
    json_dataset.load(str(path), min_visible=3)
    assert calls == [1]
    # A changed source (new content and mtime) is re-parsed.
    entries = _entries(seed=1)
    path.write_text(json.dumps(entries))
    os.utime(path, ns=(1, 1))
    changed = json_dataset.load(str(path))
    assert calls == [1, 1]
    np.testing.assert_allclose(changed.kp[0], np.array(entries[0]["kp_loc"]).T, rtol=1e-6)
    # A corrupt cache is rebuilt, not trusted.
    cache.write_bytes(b"not an npz")
    again = json_dataset.load(str(path))
    assert calls == [1, 1, 1]
    np.testing.assert_array_equal(again.kp, changed.kp)
    assert json_dataset.load(str(path)).kp.shape == (4, 5, 2) and calls == [1, 1, 1]
