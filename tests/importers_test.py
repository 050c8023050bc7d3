"""Importers: 3D sequences (.npz/.mat), BVH, COCO -> JSON; a round trip that trains."""

import json
import re

import numpy as np
import pytest
import scipy.io

from c3dpo_jax import train
from c3dpo_jax.data import importers, json_dataset
from configs import default

TINY_BVH = """HIERARCHY
ROOT hip
{
  OFFSET 0 0 0
  CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation
  JOINT knee
  {
    OFFSET 0 -10 0
    CHANNELS 3 Zrotation Xrotation Yrotation
    End Site
    {
      OFFSET 0 -8 0
    }
  }
}
MOTION
Frames: 2
Frame Time: 0.0333
0 0 0 0 0 0 0 0 0
1 2 3 0 0 0 90 0 0
"""


def _sequence(f=60, k=9, seed=0):
    rng = np.random.default_rng(seed)
    base, mode = rng.normal(size=(k, 3)), rng.normal(size=(k, 3))
    return (base + np.sin(np.arange(f) / 5)[:, None, None] * 0.3 * mode) * 40.0


def test_load_sequence_reads_npz_and_mat_layouts(tmp_path):
    x = _sequence()
    np.savez(tmp_path / "s.npz", X=np.swapaxes(x, 1, 2).astype(np.float32))  # (F, 3, K)
    np.testing.assert_allclose(importers.load_sequence(str(tmp_path / "s.npz")), x, rtol=1e-5)
    scipy.io.savemat(tmp_path / "s.mat", {"W": np.swapaxes(x, 1, 2).reshape(-1, 9)})
    np.testing.assert_allclose(importers.load_sequence(str(tmp_path / "s.mat")), x)
    np.savez(tmp_path / "bad.npz", X=np.zeros((4, 5)))
    with pytest.raises(ValueError, match=r"has shape \(4, 5\); expected"):
        importers.load_sequence(str(tmp_path / "bad.npz"))


def test_an_array_layout_is_named_or_refused_when_its_shape_is_ambiguous(tmp_path, caplog):
    x = _sequence(f=60, k=9)
    # MATLAB's (K, 3, F) has the shape of an (F, 3, K) array: the log says what was read,
    # and --layout reads it the other way.
    scipy.io.savemat(tmp_path / "k3f.mat", {"X": np.transpose(x, (1, 2, 0))})
    with caplog.at_level("INFO"):
        importers.load_sequence(str(tmp_path / "k3f.mat"))
    assert "read as F3K: F=9 frames of K=60 points, fewer frames than points" in caplog.text
    np.testing.assert_allclose(importers.load_sequence(str(tmp_path / "k3f.mat"), layout="K3F"),
                               x)
    # Three points: (F, 3, 3) could be either of two layouts, so it is refused.
    np.savez(tmp_path / "k3.npz", X=x[:, :3])
    with pytest.raises(ValueError, match=r"could be several layouts; pass the axis order"):
        importers.load_sequence(str(tmp_path / "k3.npz"))
    np.testing.assert_allclose(importers.load_sequence(str(tmp_path / "k3.npz"), layout="FK3"),
                               x[:, :3])
    scipy.io.savemat(tmp_path / "w.mat", {"W": np.swapaxes(x, 1, 2).reshape(-1, 9)})
    with pytest.raises(ValueError, match=r"is 2D \(180, 9\): --layout names the axes of a 3D"):
        importers.load_sequence(str(tmp_path / "w.mat"), layout="F3K")
    # Several arrays: the points and the clips are chosen by name, from the command line too.
    np.savez(tmp_path / "p.npz", pose=x, shot=np.repeat([0, 1, 2], 20), fps=30.0)
    with pytest.raises(ValueError, match=r"no array 'X'; it holds \['fps', 'pose', 'shot'\] "
                       r"\(choose one: --key"):
        importers.load_sequence(str(tmp_path / "p.npz"))
    importers.main(["sequence", str(tmp_path / "p.npz"), "--out_dir", str(tmp_path), "--key",
                    "pose", "--clip_key", "shot", "--hold_out", "clips", "--views_per_frame",
                    "2"])
    test = json_dataset.load(str(tmp_path / "p_test.json"))
    assert test.n_keypoints == 9 and len(test) == 20 * 2  # one whole clip of three


def test_sequences_that_cannot_make_a_split_are_refused_at_import(tmp_path):
    x = _sequence(f=60, k=9)
    for seq, kwargs, match in [
            (x[:1], {}, "the split of 1 frame\\(s\\) leaves no test frame"),
            (np.ones((20, 6, 3)), {}, "6 point\\(s\\) coincide in every frame"),
            (x[:, :1], {}, "1 point\\(s\\) coincide"),
            (x, {"views_per_frame": 0}, "views_per_frame=0"),
            (x, {"test_fraction": 0}, "test_fraction=0 \\(must be between 0 and 1"),
            (x, {"test_fraction": 1.0}, "test_fraction=1.0 "),
            (x, {"n_blocks": 1}, "n_blocks=1 \\(must be >= 2"),
            (x, {"hold_out": "clips"}, "hold_out='clips' needs per-frame clip ids")]:
        with pytest.raises(ValueError, match=match):
            importers.views_from_sequence(seq, **kwargs)


def test_the_up_axis_is_turned_to_y_by_a_rotation():
    x = _sequence(f=5, k=4)
    for up in "xyz":
        unit = np.eye(3)["xyz".index(up)]
        np.testing.assert_allclose(importers.to_y_up(unit[None, None], up)[0, 0], [0, 1, 0],
                                   atol=1e-12)
        turned = importers.to_y_up(x, up)  # a rotation: distances and handedness kept
        np.testing.assert_allclose(np.linalg.norm(turned[:, 1] - turned[:, 0], axis=-1),
                                   np.linalg.norm(x[:, 1] - x[:, 0], axis=-1))
        assert np.linalg.det(importers.to_y_up(np.eye(3)[None], up)[0]) == pytest.approx(1.0)


def test_views_split_by_frame_blocks_and_normalise_scale():
    x = _sequence(f=50)
    train_d, test_d = importers.views_from_sequence(x, views_per_frame=3, test_fraction=0.2,
                                                    n_blocks=5, occlusion=0.3, seed=1)
    assert len(train_d) == 40 * 3 and len(test_d) == 10 * 3
    test_mask = importers.frame_blocks_split(50, 0.2, 5, 1)
    assert np.ptp(np.flatnonzero(test_mask)) == 9  # one contiguous block of frames
    radius = np.sqrt((train_d.kp3d**2).sum(-1).mean(-1))
    assert 0.5 < radius.mean() < 1.5 and np.allclose(train_d.scale, train_d.scale[0])
    assert train_d.vis.sum(1).min() >= 3 and 0.5 < train_d.vis.mean() < 0.9
    np.testing.assert_allclose(train_d.kp[train_d.vis == 1],
                               train_d.kp3d[..., :2][train_d.vis == 1], atol=1e-6)


def test_bvh_forward_kinematics():
    pos, names = importers.bvh_positions(TINY_BVH, include_end_sites=True)
    assert names == ["hip", "knee", "knee_end"] and pos.shape == (2, 3, 3)
    np.testing.assert_allclose(pos[0], [[0, 0, 0], [0, -10, 0], [0, -18, 0]], atol=1e-9)
    # Frame 1: root moved by (1, 2, 3); knee turned 90 degrees about z: the shin points +x.
    np.testing.assert_allclose(pos[1], [[1, 2, 3], [1, -8, 3], [9, -8, 3]], atol=1e-9)
    with pytest.raises(ValueError, match="no HIERARCHY"):
        importers.parse_bvh("MOTION")


def test_bvh_position_channels_of_a_joint_replace_its_offset():
    """Files that animate every joint's position repeat each joint's translation from its
    parent in its position channels: the same skeleton as offsets alone, not one whose bones
    are twice as long; a changed translation moves the joint to it (a stretched bone)."""
    six = TINY_BVH.replace(
        "OFFSET 0 -10 0\n    CHANNELS 3 Zrotation Xrotation Yrotation",
        "OFFSET 0 -10 0\n    CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation "
        "Yrotation").replace("0 0 0 0 0 0 0 0 0\n1 2 3 0 0 0 90 0 0",
                             "0 0 0 0 0 0 0 -10 0 0 0 0\n1 2 3 0 0 0 0 -12 0 90 0 0")
    assert six != TINY_BVH
    pos, _ = importers.bvh_positions(six, include_end_sites=True)
    np.testing.assert_allclose(pos[0], [[0, 0, 0], [0, -10, 0], [0, -18, 0]], atol=1e-9)
    np.testing.assert_allclose(pos[1], [[1, 2, 3], [1, -10, 3], [9, -10, 3]], atol=1e-9)


def test_coco_annotations_become_a_2d_training_set(caplog):
    obj = {"images": [{"id": 7, "file_name": "a.jpg"}],
           "annotations": [{"image_id": 7, "keypoints": [10, 20, 2, 30, 40, 1, 0, 0, 0]},
                           {"image_id": 7, "keypoints": [1, 2, 2, 0, 0, 0, 0, 0, 0]}]}
    data = importers.coco_to_data(obj)
    assert len(data) == 1 and data.kp3d is None and list(data.image_path) == ["a.jpg"]
    np.testing.assert_array_equal(data.vis, [[1, 1, 0]])
    np.testing.assert_array_equal(data.kp[0], [[10, 20], [30, 40], [0, 0]])
    assert importers.coco_to_data(obj, min_v=2, min_visible=1).vis.tolist() == [[1, 0, 0]] * 2
    with pytest.raises(ValueError, match="expected one length 3K"):
        importers.coco_to_data({"annotations": [{"keypoints": [1, 2]}]})


def test_one_coco_reader_keeps_the_positions_of_the_annotations_it_reads(caplog):
    obj = {"annotations": [{"bbox": [0, 0, 1, 1]},  # not a keypoint annotation
                           {"category_id": 2, "keypoints": [1, 2, 2, 3, 4, 2]},
                           {"category_id": 1, "keypoints": [0, 0, 0, 0, 0, 0]},
                           {"category_id": 1, "keypoints": [5, 6, 1, 7, 8, 0]}]}
    data, index = importers.read_coco(obj)
    assert index.tolist() == [1, 3] and data.vis.tolist() == [[1, 1], [1, 0]]
    assert "1 of 3 annotations have no visible keypoint: skipped (annotations [2])" in caplog.text
    assert importers.read_coco(obj, category_id=1)[1].tolist() == [3]
    with pytest.raises(ValueError, match="annotation 3 has 1 keypoints, most others 2"):
        importers.read_coco({"annotations": obj["annotations"][:3] + [{"keypoints": [1, 2, 1]}]})
    with pytest.raises(ValueError, match="every COCO annotation with keypoints has no visible"):
        importers.read_coco({"annotations": obj["annotations"][2:3]})


def test_cli_writes_json_for_each_kind(tmp_path, capsys):
    (tmp_path / "walk.bvh").write_text(TINY_BVH * 1)
    importers.main(["bvh", str(tmp_path / "walk.bvh"), "--out_dir", str(tmp_path),
                    "--views_per_frame", "4", "--n_blocks", "2", "--test_fraction", "0.5"])
    train = json_dataset.load(str(tmp_path / "walk_train.json"))
    assert train.kp.shape == (4, 2, 2)
    out = capsys.readouterr().out  # the factor that turns errors into the file's units
    assert f"units: the sequence was divided by {float(train.scale[0]):.6g} (its RMS" in out
    (tmp_path / "c.json").write_text(json.dumps(
        {"annotations": [{"keypoints": [1, 2, 2, 3, 4, 2]}]}))
    importers.main(["coco", str(tmp_path / "c.json"), "--out", str(tmp_path / "o.json")])
    assert json_dataset.load(str(tmp_path / "o.json")).n_keypoints == 2
    assert "wrote" in capsys.readouterr().out


def test_files_say_how_to_draw_them(tmp_path):
    """Views of motion capture are y-up with the BVH file's bones; COCO's image coordinates
    are y-down with the category's skeleton (1-based there); --skeleton overrides both."""
    assert importers.bvh_bones(TINY_BVH) == [(0, 1)]
    assert importers.bvh_bones(TINY_BVH, include_end_sites=True) == [(0, 1), (1, 2)]
    (tmp_path / "walk.bvh").write_text(TINY_BVH)
    args = ["bvh", str(tmp_path / "walk.bvh"), "--out_dir", str(tmp_path), "--n_blocks", "2"]
    importers.main(args)
    wrapper = json.loads((tmp_path / "walk_test.json").read_text())
    assert wrapper["y_up"] is True and wrapper["skeleton"] == [[0, 1]]
    importers.main([*args, "--skeleton", "1-0", "--cameras", "uniform"])
    wrapper = json.loads((tmp_path / "walk_train.json").read_text())
    assert wrapper["y_up"] is False and wrapper["skeleton"] == [[1, 0]]
    with pytest.raises(ValueError, match="unknown skeleton 'hand'"):
        importers.main([*args, "--skeleton", "hand"])
    coco = {"categories": [{"id": 1, "skeleton": [[1, 2], [2, 3]]}],
            "annotations": [{"keypoints": [1, 2, 2, 3, 4, 2, 5, 6, 2]}]}
    (tmp_path / "c.json").write_text(json.dumps(coco))
    importers.main(["coco", str(tmp_path / "c.json"), "--out", str(tmp_path / "o.json")])
    wrapper = json.loads((tmp_path / "o.json").read_text())
    assert wrapper["y_up"] is False and wrapper["skeleton"] == [[0, 1], [1, 2]]
    assert wrapper["unit"] == "px" and "unit" not in json.loads((tmp_path / "walk_train.json")
                                                               .read_text())
    assert json_dataset.load(str(tmp_path / "o.json")).n_keypoints == 3


def test_sequence_round_trip_trains(tmp_path):
    np.savez(tmp_path / "seq.npz", X=np.swapaxes(_sequence(f=40, k=8), 1, 2))
    importers.main(["sequence", str(tmp_path / "seq.npz"), "--out_dir", str(tmp_path),
                    "--views_per_frame", "8", "--occlusion", "0.1", "--noise", "0.01"])
    c = default.apply_variants(default.get_config(), "smoke")
    c.data.train_path = str(tmp_path / "seq_train.json")
    c.data.test_path = str(tmp_path / "seq_test.json")
    c.model.n_keypoints, c.model.shape_basis_size = 8, 3
    c.train.progress_bar = False
    c.train.ckpt_every = c.train.log_every = 20
    results = train.train_and_evaluate(c, str(tmp_path / "run"))
    assert results["final"]["step"] == 20 and np.isfinite(results["final"]["mpjpe"])
    assert (tmp_path / "seq_train.c3dpo_cache.npz").exists()


def test_clip_split_holds_out_blocks_of_every_clip_or_whole_clips():
    clip = np.repeat([0, 1, 2, 3], [30, 50, 20, 40])
    test = importers.clip_split(clip, 0.2, 5, seed=3)
    for c in range(4):  # a fifth of every clip, as one contiguous block
        frames = np.flatnonzero(test & (clip == c))
        assert len(frames) == round((clip == c).sum() / 5)
        assert np.ptp(frames) == len(frames) - 1
    whole = importers.clip_split(clip, 0.5, 5, seed=3, hold_out="clips")
    held = {c for c in range(4) if whole[clip == c].all()}
    assert len(held) == 2 and all(not whole[clip == c].any() for c in set(range(4)) - held)
    with pytest.raises(ValueError, match="at least two clips"):
        importers.clip_split(np.zeros(10, int), 0.2, 5, seed=0, hold_out="clips")


def test_views_from_sequence_with_clips_and_the_npz_clip_array(tmp_path):
    x = _sequence(f=60)
    clip = np.repeat([0, 1, 2], 20)
    np.savez(tmp_path / "s.npz", X=np.swapaxes(x, 1, 2), clip=clip)
    loaded = importers.load_clips(str(tmp_path / "s.npz"))
    np.testing.assert_array_equal(loaded, clip)
    train_d, test_d = importers.views_from_sequence(x, views_per_frame=2, clip=loaded,
                                                    hold_out="clips", test_fraction=0.3)
    assert len(test_d) == 20 * 2 and len(train_d) == 40 * 2
    with pytest.raises(ValueError, match="clip has shape"):
        importers.views_from_sequence(x, clip=clip[:5])


def test_the_import_command_reports_input_errors_in_one_line(tmp_path, monkeypatch, capsys):
    x = _sequence(f=6, k=4)
    x[2, 3] = np.nan  # a gap in the capture: frame 2, point 3
    np.savez(tmp_path / "gap.npz", X=np.swapaxes(x, 1, 2))
    cases = [
        (["sequence", str(tmp_path / "gap.npz")], "the sequence has NaN or inf at 1 points of "
         "1 frames (first: frame 2, point 3)"),
        (["sequence", str(tmp_path / "gap.json")], f"{tmp_path / 'gap.json'}: a sequence is "
         "read from a .npz or .mat file"),
        (["coco", str(tmp_path / "none.json"), "--out", str(tmp_path / "o.json")],
         "[Errno 2] No such file or directory"),
    ]
    for args, message in cases:
        if args[0] == "sequence":
            args = [*args, "--out_dir", str(tmp_path)]
        monkeypatch.setattr("sys.argv", ["c3dpo-import", *args])
        with pytest.raises(SystemExit) as stop:
            importers.cli_main()
        *logged, last = capsys.readouterr().err.splitlines()
        assert stop.value.code == 2 and last.startswith(f"error: {message}"), last
        assert all("read as" in line for line in logged), logged  # what was read, if anything
        if args[0] == "sequence" and args[1].endswith(".npz"):  # the command says what it read
            assert "gap.npz: array 'X' read as F3K: F=6 frames of K=4 points" in logged[0]
    monkeypatch.setattr("sys.argv", ["c3dpo-import", *cases[0][0], "--out_dir", str(tmp_path),
                                     "--verbose"])
    with pytest.raises(ValueError, match="NaN or inf"):  # --verbose: the exception itself
        importers.cli_main()


def test_awkward_bvh_and_coco_files_are_read_or_named():
    # A joint whose own name ends in "_end" is a joint; End Sites are left out unless asked.
    named = TINY_BVH.replace("JOINT knee", "JOINT knee_end")
    assert importers.bvh_positions(named)[1] == ["hip", "knee_end"]
    assert importers.bvh_positions(named, include_end_sites=True)[1] == [
        "hip", "knee_end", "knee_end_end"]
    with pytest.raises(ValueError, match=r"header says 2 frames of 9 channels, the MOTION "
                       r"section holds 1\.6 frames' worth of numbers: is the file cut short"):
        importers.parse_bvh(TINY_BVH[:-10])
    # COCO: an empty keypoint list is passed over like an annotation without keypoints; the
    # categories are named where they are the fix.
    ann = lambda cat, k: {"category_id": cat, "keypoints": [1, 2, 2] * k}  # noqa: E731
    obj = {"categories": [{"id": 1, "skeleton": [[1, 2]]}, {"id": 2, "skeleton": [[2, 3]]}],
           "annotations": [ann(2, 3), {"category_id": 2, "keypoints": []}, ann(2, 3)]}
    data, index = importers.read_coco(obj)
    assert index.tolist() == [0, 2] and data.n_keypoints == 3
    assert importers.coco_skeleton(obj) == [(1, 2)]  # the annotations' category, not the first
    with pytest.raises(ValueError, match=r"of category_id 7 \(the keypoint annotations' "
                       r"categories: 2\)"):
        importers.read_coco(obj, category_id=7)
    obj["annotations"] += [ann(1, 2)]
    assert importers.coco_skeleton(obj) is None  # several categories: no one skeleton
    with pytest.raises(ValueError, match=r"annotation 3 has 2 keypoints, most others 3 .*; they "
                       r"hold 2 categories: keep one with category_id \(--category_id\)"):
        importers.read_coco(obj)


def test_the_files_hold_the_float32_values_as_their_shortest_decimals(tmp_path):
    """362.79 as 362.79, not as the float64 of its float32 (362.7900085449219), and read
    back bit for bit."""
    (tmp_path / "c.json").write_text(json.dumps(
        {"annotations": [{"keypoints": [362.79, 10.1, 2, 0.3, 1e-5, 2, 7, 8, 0]}]}))
    importers.main(["coco", str(tmp_path / "c.json"), "--out", str(tmp_path / "o.json")])
    entry = json.loads((tmp_path / "o.json").read_text())["data"][0]
    assert entry["kp_loc"] == [[362.79, 0.3, 0.0], [10.1, 1e-5, 0.0]]
    x = _sequence(f=20, k=5)
    train, _ = importers.views_from_sequence(x, views_per_frame=2, n_blocks=2, noise=0.01)
    json_dataset.save(train, str(tmp_path / "s.json"))
    back = json_dataset.load(str(tmp_path / "s.json"), cache=False)
    for field in ("kp", "vis", "kp3d", "scale"):
        assert getattr(back, field).tobytes() == getattr(train, field).tobytes(), field
    text = (tmp_path / "s.json").read_text()
    assert max(len(n) for n in re.findall(r"-?\d[\d.e+-]*", text)) <= 16  # no float64 tails


@pytest.mark.parametrize(("argv0", "usage"), [
    ("/env/bin/c3dpo-import", "usage: c3dpo-import "),
    (importers.__file__, "usage: python -m c3dpo_jax.data.importers ")])
def test_the_help_names_the_command_as_it_was_typed(monkeypatch, capsys, argv0, usage):
    monkeypatch.setattr("sys.argv", [argv0, "--help"])
    with pytest.raises(SystemExit) as stop:
        importers.cli_main()
    assert stop.value.code == 0 and capsys.readouterr().out.startswith(usage)


def _coco_people(n_images: int, per_image: int = 2, k: int = 5) -> dict:
    rng = np.random.default_rng(0)
    images = [{"id": i, "file_name": f"im{i}.jpg"} for i in range(n_images)]
    annotations = [{"image_id": i, "keypoints": np.column_stack(
        [rng.uniform(0, 640, size=(k, 2)).round(1), np.full(k, 2)]).ravel().tolist()}
                   for i in range(n_images) for _ in range(per_image)]
    return {"images": images, "annotations": annotations}


def test_one_coco_file_becomes_train_and_test_files_of_different_images(tmp_path, capsys):
    (tmp_path / "people.json").write_text(json.dumps(_coco_people(10)))
    importers.main(["coco", str(tmp_path / "people.json"), "--out_dir", str(tmp_path / "d"),
                    "--test_fraction", "0.3"])
    train_d = json_dataset.load(str(tmp_path / "d" / "people_train.json"))
    test_d = json_dataset.load(str(tmp_path / "d" / "people_test.json"))
    assert (len(train_d), len(test_d)) == (14, 6)  # 7 and 3 images, two people in each
    assert not set(train_d.image_path) & set(test_d.image_path)
    assert len(set(train_d.image_path) | set(test_d.image_path)) == 10
    wrapper = json.loads((tmp_path / "d" / "people_test.json").read_text())
    assert wrapper["unit"] == "px" and wrapper["y_up"] is False
    out = capsys.readouterr().out
    assert "K=5: --config.model.n_keypoints=5" in out and "--config.data.protocol=none" in out
    # Without file names every annotation is its own picture; one image cannot be split.
    assert importers.image_split(np.array([""] * 4), 0.5, seed=0).sum() == 2
    with pytest.raises(ValueError, match="the annotations are all of one image"):
        importers.image_split(np.array(["a.jpg"] * 4), 0.5, seed=0)
