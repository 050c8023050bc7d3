"""The predict CLI: release JSON and COCO annotations in, the same numbers as reconstruct() out."""

import json
import os
import subprocess
import sys

import jax
import numpy as np
import pytest

from c3dpo_jax import lift, model, predict
from c3dpo_jax.data import synthetic
from c3dpo_jax.reconstruct import C3DPOParams, reconstruct, save_workdir

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
CFG = model.ModelConfig(n_keypoints=17, shape_basis_size=3, n_fully_connected=16, n_layers=1,
                        canonicalization_n_fully_connected=16, canonicalization_n_layers=1)


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    root = tmp_path_factory.mktemp("predict")
    params = C3DPOParams(model.init_variables(jax.random.key(0), CFG), CFG)
    workdir = save_workdir(params, str(root / "run"))
    data = synthetic.make_split(5, n_keypoints=17, n_modes=2, deformation=0.3, occlusion=0.2,
                                noise=0.0, perspective=False, shape_seed=0, seed=1)
    return root, params, workdir, data


def _run(*args):
    return subprocess.run([sys.executable, "-m", "c3dpo_jax.predict", *args], cwd=ROOT,
                          capture_output=True, text=True, timeout=300)


def test_release_json_in_npz_out_with_figures(setup):
    root, params, workdir, data = setup
    entries = [{"kp_loc": data.kp[i].T.tolist(), "kp_vis": data.vis[i].tolist(),
                "kp_loc_3d": data.kp3d[i].T.tolist()} for i in range(len(data))]
    path = root / "poses.json"
    path.write_text(json.dumps(entries))
    out, figs = str(root / "new" / "dir" / "out.npz"), str(root / "figs")  # parent made
    proc = _run(f"--workdir={workdir}", f"--input={path}", f"--output={out}", f"--figures={figs}",
                "--n_figures=2")
    assert proc.returncode == 0, proc.stderr[-3000:]
    # Only the useful line: no orbax or JAX backend chatter.
    assert proc.stderr.splitlines() == [
        f"wrote 5 reconstructions to {out}"]
    got = np.load(out)
    want = reconstruct(params, data.kp, data.vis)
    np.testing.assert_allclose(got["shape_3d"], want.shape_3d, atol=1e-4)
    np.testing.assert_allclose(got["rotation"], want.rotation, atol=1e-5)
    assert got["index"].tolist() == list(range(5))
    assert sorted(os.listdir(figs)) == ["reconstruction_0.png", "reconstruction_1.png"]


def test_coco_annotations_in_json_out_skipping_empty_ones(setup):
    root, params, workdir, data = setup
    anns = []
    for i in range(3):
        v = np.where(data.vis[i] > 0, 2, 0)
        anns.append({"id": 10 + i, "keypoints": np.column_stack([data.kp[i], v]).ravel().tolist()})
    anns.insert(1, {"id": 99, "keypoints": [0, 0, 0] * 17})
    path = root / "coco.json"
    path.write_text(json.dumps({"annotations": anns}))
    out = str(root / "out.json")
    proc = _run(f"--workdir={workdir}", f"--input={path}", f"--output={out}")
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "no visible keypoint: skipped" in proc.stderr
    with open(out) as f:
        rows = json.load(f)
    assert [r["index"] for r in rows] == [0, 2, 3]
    want = reconstruct(params, data.kp[:3], data.vis[:3])
    np.testing.assert_allclose([r["shape_3d"] for r in rows], want.shape_3d, atol=1e-4)


def test_input_errors_are_one_line_before_any_work(setup):
    root, _, workdir, _ = setup
    (root / "broken.json").write_text("[{")
    bad_json = _run(f"--workdir={workdir}", f"--input={root / 'broken.json'}",
                    f"--output={root / 'o.json'}")
    assert bad_json.returncode == 2
    assert bad_json.stderr.startswith(f"error: {root / 'broken.json'} is not valid JSON: ")
    assert len(bad_json.stderr.splitlines()) == 1
    with pytest.raises(ValueError, match="must end in .json or .npz"):
        predict.run("no/such/workdir", "no/such/input.json", str(root / "o.txt"))


def test_release_json_entries_with_one_visible_point_are_lifted_and_none_skipped(
        setup, tmp_path, caplog):
    _, params, _, data = setup
    vis = np.zeros(17)
    vis[4] = 1.0
    entries = [{"kp_loc": data.kp[0].T.tolist(), "kp_vis": vis.tolist()}]
    path = tmp_path / "one.json"
    path.write_text(json.dumps(entries))
    got = predict.read_input(str(path))
    assert got["vis"].sum() == 1
    want = reconstruct(params, data.kp[:1], vis[None])
    assert np.isfinite(want.shape_3d).all()
    none = {"kp_loc": data.kp[0].T.tolist(), "kp_vis": [0.0] * 17}
    path.write_text(json.dumps([none]))
    with pytest.raises(ValueError, match="no entry has a visible point"):
        predict.read_input(str(path))
    # Among others, an entry with no visible point is skipped (as a COCO annotation is) and
    # ``index`` says which input each row is.
    path.write_text(json.dumps([entries[0], none, entries[0]]))
    with caplog.at_level("WARNING"):
        got = predict.read_input(str(path))
    assert got["index"].tolist() == [0, 2] and got["kp"].shape == (2, 17, 2)
    assert "1 of 3 entries have no visible point: skipped (entries [1])" in caplog.text


def test_coordinates_far_from_zero_keep_their_precision_and_k_is_named(setup, tmp_path,
                                                                         caplog):
    """The release's JSON read for inference keeps float64 points (1e6 + x in float32 is
    x to within 0.06), and intrinsics given to an orthographic model are said to be unused."""
    _, params, workdir, data = setup
    entries = [{"kp_loc": (data.kp[i].T.astype(np.float64) + 1e6).tolist(),
                "kp_vis": data.vis[i].tolist(), "K": np.eye(3).tolist()} for i in range(3)]
    path = tmp_path / "far.json"
    path.write_text(json.dumps(entries))
    with caplog.at_level("WARNING"):
        got = predict.run(workdir, str(path), str(tmp_path / "far.npz"))
    assert "holds intrinsics (K);" in caplog.text and "ignores them" in caplog.text
    want = reconstruct(params, data.kp[:3], data.vis[:3])
    np.testing.assert_allclose(got.shape_3d - [1e6, 1e6, 0], want.shape_3d, atol=1e-4)


def test_coco_reader_rejects_malformed_keypoints():
    with pytest.raises(ValueError, match=r"annotation 0: 'keypoints' is not a list of numbers"):
        predict.read_coco({"annotations": [{"keypoints": "abc"}]})
    with pytest.raises(ValueError, match=r"\[x, y, v\] \* N"):
        predict.read_coco({"annotations": [{"keypoints": [1, 2]}]})
    with pytest.raises(ValueError, match=r"annotation 1 has 1 keypoints, most others 2 \(1 of"):
        predict.read_coco({"annotations": [{"keypoints": [1, 2, 1, 3, 4, 1]},
                                           {"keypoints": [1, 2, 1]}]})
    # The odd one out is named, wherever it is (here the first).
    two, three = [1, 2, 1, 3, 4, 1], [1, 2, 1, 3, 4, 1, 5, 6, 1]
    with pytest.raises(ValueError, match=r"annotation 0 has 2 keypoints, most others 3 \(1 of 3"):
        predict.read_coco({"annotations": [{"keypoints": k} for k in (two, three, three)]})


def test_pictures_take_skeleton_and_up_from_flags_else_input_else_training(setup, tmp_path):
    _, _, workdir, _ = setup
    kp = np.zeros((1, 17, 2))
    from_file = {"kp": kp, "style": {"skeleton": [[0, 1]], "y_up": True}}
    assert predict.picture_style(workdir, from_file) == ([(0, 1)], True, "")
    assert predict.picture_style(workdir, from_file, "1-2", False) == ([(1, 2)], False, "")
    assert predict.picture_style(workdir, {"kp": kp}) == ([], False, "")  # nothing known
    humans = tmp_path / "humans_run"
    humans.mkdir()
    (humans / "config.json").write_text(json.dumps({"data": {"source": "humans"}}))
    edges, y_up, unit = predict.picture_style(str(humans), {"kp": kp, "style": {"y_up": False}})
    assert len(edges) == 16 and y_up is False and unit == "m"  # the input's up wins
    with pytest.raises(ValueError, match="unknown skeleton 'hand'"):
        predict.picture_style(workdir, {"kp": kp}, "hand")
    coco = tmp_path / "coco.json"
    coco.write_text(json.dumps({"categories": [{"id": 1, "skeleton": [[1, 2]]}],
                                "annotations": [{"keypoints": [1, 2, 2, 3, 4, 2]}]}))
    assert predict.read_input(str(coco))["style"] == {"y_up": False, "unit": "px",
                                                      "skeleton": [(0, 1)]}


def test_inference_flags_and_picture_flags_are_checked_before_the_work(setup, tmp_path, caplog):
    root, params, workdir, data = setup
    entries = [{"kp_loc": data.kp[i].T.tolist(), "kp_vis": data.vis[i].tolist()}
               for i in range(2)]
    path = tmp_path / "poses.json"
    path.write_text(json.dumps(entries))
    out = str(tmp_path / "o.npz")
    # --refine_iters / --turns reach reconstruct (the model here refines nothing: compare
    # with what reconstruct gives for the same arguments).
    rec = predict.run(workdir, str(path), out, refine_iters=0, turns=1)
    np.testing.assert_allclose(rec.shape_3d, reconstruct(params, data.kp[:2], data.vis[:2],
                                                         refine_iters=0).shape_3d, atol=1e-5)
    with pytest.raises(ValueError, match=r"^turns=0 "):
        predict.run(workdir, str(path), out, turns=0)
    # Picture flags that cannot work are refused before anything is computed or written.
    (tmp_path / "a_file.png").write_text("")
    for kwargs, match in [({"figures": str(tmp_path / "a_file.png")}, "is a file"),
                          ({"figures": str(tmp_path / "figs"), "n_figures": 0},
                           r"--n_figures=0 \(must be >= 1")]:
        with pytest.raises(ValueError, match=match):
            predict.run("no/such/workdir", str(path), out, **kwargs)
    assert not (tmp_path / "figs").exists()
    with caplog.at_level("WARNING"):
        predict.run(workdir, str(path), out, skeleton="h36m")
    assert "--skeleton and --y_up shape the pictures only" in caplog.text


def test_every_inference_option_is_a_flag_of_its_name(setup):
    """c3dpo-predict has a flag for each ``InferenceConfig`` field, which reaches
    ``reconstruct`` under that name."""
    root, params, workdir, data = setup
    helpfull = _run("--helpfull").stdout
    for name in lift.FIELDS:
        assert f"--{name}:" in helpfull or f"--[no]{name}:" in helpfull, name
    entries = [{"kp_loc": data.kp[i].T.tolist(), "kp_vis": data.vis[i].tolist()}
               for i in range(3)]
    path = root / "flags.json"
    path.write_text(json.dumps(entries))
    out = str(root / "flags.npz")
    proc = _run(f"--workdir={workdir}", f"--input={path}", f"--output={out}", "--turns=4",
                "--turn_span=circle", "--noreplace_keypoints_with_input", "--refine_iters=2",
                "--refine_prior=0.5")
    assert proc.returncode == 0, proc.stderr[-3000:]
    want = reconstruct(params, data.kp[:3], data.vis[:3], turns=4, turn_span="circle",
                       replace_keypoints_with_input=False, refine_iters=2, refine_prior=0.5)
    np.testing.assert_allclose(np.load(out)["shape_3d"], want.shape_3d, atol=1e-4)
    assert np.abs(want.shape_3d - reconstruct(params, data.kp[:3], data.vis[:3]).shape_3d
                  ).max() > 1e-4  # the options changed the output
