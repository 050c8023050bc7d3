"""config.data -> splits for every source, with the default config's sections."""

import json
import re

import numpy as np
import pytest

from c3dpo_jax.data import download, load_splits
from configs import categories as categories_cfg
from configs import default, own_json
from configs import humans as humans_cfg


def test_builtin_sources_match_their_configs():
    for module in (humans_cfg, categories_cfg):
        c = module.get_config("smoke")
        train, test = load_splits(c.data)
        assert train.n_keypoints == test.n_keypoints == c.model.n_keypoints
        assert len(train) > len(test) > 0


def test_humans_keypoint_count_follows_the_dense_points_given_on_the_command_line():
    from absl import flags
    from ml_collections import config_flags

    def parse(*args):  # as the CLI parses its command line
        argv = ["prog", *args]
        fv = flags.FlagValues()
        config_flags.DEFINE_config_file("config", None, flag_values=fv, lock_config=True,
                                        sys_argv=argv)
        fv(argv)
        return fv.config

    c = parse("--config=configs/humans.py:smoke", "--config.data.humans.dense_points=6")
    assert c.model.n_keypoints == 23
    train, _ = load_splits(c.data)
    assert train.n_keypoints == 23
    c = parse("--config=configs/humans.py", "--config.data.humans.dense_points=6",
              "--config.model.n_keypoints=40")  # an explicit K still wins (and is then checked)
    assert c.model.n_keypoints == 40


def test_synthetic_source_is_unchanged():
    c = default.apply_variants(default.get_config(), "smoke")
    train, _ = load_splits(c.data)
    assert train.kp.shape == (256, 20, 2) and train.name == "synthetic"


def test_own_json_needs_paths_and_release_resolves_names(tmp_path, monkeypatch):
    with pytest.raises(ValueError, match="--config.data.train_path=TRAIN.json"):
        load_splits(own_json.get_config().data)
    c = default.get_config()
    c.data.source, c.data.name, c.data.data_dir = "release", "h36m", str(tmp_path)
    seen = {}
    monkeypatch.setattr(download, "dataset_files",
                        lambda name, directory: seen.update(n=name, d=directory) or ("a", "b"))
    with pytest.raises(FileNotFoundError, match="'a' does not exist"):
        load_splits(c.data)
    assert seen == {"n": "h36m", "d": str(tmp_path)}
    c.data.source = "nope"
    with pytest.raises(ValueError, match="unknown config.data.source 'nope'"):
        load_splits(c.data)


def test_auto_keypoint_rescale_is_the_inverse_median_rms_radius_in_any_units():
    from c3dpo_jax.data import KeypointData, auto_keypoint_rescale

    rng = np.random.default_rng(0)
    kp = rng.normal(size=(7, 5, 2)) * rng.uniform(0.5, 2.0, size=(7, 1, 1)) + 3.0
    vis = (rng.uniform(size=(7, 5)) > 0.2).astype(np.float32)
    vis[:, :2] = 1
    vis[6] = [1, 0, 0, 0, 0]  # one visible point: no radius, ignored
    radii = []
    for m in range(6):
        pts = kp[m][vis[m] > 0]
        radii.append(np.sqrt(((pts - pts.mean(0)) ** 2).sum(1).mean()))
    data = KeypointData(kp=kp, vis=vis)
    assert auto_keypoint_rescale(data) == pytest.approx(1 / np.median(radii), rel=1e-6)
    in_pixels = KeypointData(kp=kp * 100, vis=vis)
    assert auto_keypoint_rescale(in_pixels) == pytest.approx(auto_keypoint_rescale(data) / 100)
    with pytest.raises(ValueError, match="cannot be set"):
        auto_keypoint_rescale(KeypointData(kp=kp[6:], vis=vis[6:]))


def test_resolve_input_scale_only_replaces_zero():
    from c3dpo_jax import resolve
    from c3dpo_jax.data import KeypointData
    data = KeypointData(kp=np.array([[[0.0, 0.0], [2.0, 0.0]]]), vis=np.ones((1, 2)))
    c = own_json.get_config()
    assert c.model.keypoint_rescale == 0
    assert resolve.resolve_input_scale(c, data).model.keypoint_rescale == pytest.approx(1.0)
    assert c.model.keypoint_rescale == 0  # a copy, the caller's config is unchanged
    c.model.keypoint_rescale = 0.25
    assert resolve.resolve_input_scale(c, data).model.keypoint_rescale == 0.25


def test_the_input_scale_uses_the_intrinsics_only_for_a_perspective_model():
    from c3dpo_jax import resolve
    from c3dpo_jax.data import KeypointData
    # Two points 2 px apart (RMS radius 1), 0.004 apart once calibrated by a focal length
    # of 500 px (RMS radius 0.002).
    k = np.array([[[500.0, 0, 320], [0, 500, 240], [0, 0, 1]]])
    data = KeypointData(kp=np.array([[[320.0, 240.0], [322.0, 240.0]]]), vis=np.ones((1, 2)),
                        intrinsics=k)
    c = own_json.get_config()
    assert resolve.resolve_input_scale(c, data).model.keypoint_rescale == pytest.approx(1.0)
    c.model.projection_type = "perspective"
    assert resolve.resolve_input_scale(c, data).model.keypoint_rescale == pytest.approx(500.0)


def test_alike_view_size_ratio_compares_each_view_with_the_one_most_like_it():
    """Views in pairs, each pair one random shape at two sizes a known factor apart (and
    shifted; a hidden point in one copy): every view's most alike view is its pair, so the
    ratio is the median of the factors; the same views at one size give 1."""
    from c3dpo_jax.data import KeypointData, alike_view_size_ratio

    rng = np.random.default_rng(0)
    for k in (12, 100):  # 100: more points than the shapes are compared on
        shapes = rng.normal(size=(30, k, 2))
        factors = rng.uniform(1.1, 3.0, 30)
        kp = np.stack([shapes, shapes * factors[:, None, None] + 5.0], 1).reshape(60, k, 2)
        vis = np.ones((60, k))
        vis[1::2, 0] = 0  # hidden in the scaled copy
        assert alike_view_size_ratio(KeypointData(kp=kp, vis=vis)) == pytest.approx(
            np.median(factors), rel=0.05)
        same = np.repeat(shapes, 2, axis=0)
        assert alike_view_size_ratio(KeypointData(kp=same, vis=vis)) == pytest.approx(
            1.0, abs=0.05)


def test_each_view_is_scaled_by_its_own_size_when_alike_views_differ_in_size():
    """``keypoint_scaling="auto"``: views of people at one distance keep one input scale;
    the same views each scaled by a factor 0.5-2x apart get "per_view"; a perspective model,
    a value that is not "auto" and a saved config's value are kept, "global" for a saved
    config that predates the option."""
    from c3dpo_jax import resolve
    from c3dpo_jax.data import alike_view_size_ratio, humans

    people = humans.make_split(60, views_per_pose=10, seed=1)
    rng = np.random.default_rng(0)
    factor = np.exp(rng.uniform(np.log(0.5), np.log(2.0), len(people)))[:, None, None]
    far_and_near = type(people)(kp=people.kp * factor, vis=people.vis)
    assert alike_view_size_ratio(people) < resolve.ALIKE_SIZE_RATIO
    assert alike_view_size_ratio(far_and_near) > resolve.ALIKE_SIZE_RATIO
    c = own_json.get_config()
    assert c.model.keypoint_scaling == "auto"
    assert resolve.resolve_keypoint_scaling(c, people).model.keypoint_scaling == "global"
    assert resolve.resolve_keypoint_scaling(c, far_and_near).model.keypoint_scaling == "per_view"
    assert c.model.keypoint_scaling == "auto"  # a copy
    saved = {"model": {"keypoint_scaling": "global"}}
    assert resolve.resolve_keypoint_scaling(c, far_and_near, saved).model.keypoint_scaling == (
        "global")
    older = {"model": {"n_keypoints": 17}}  # a run made before the option: one input scale
    assert resolve.resolve_keypoint_scaling(c, far_and_near, older).model.keypoint_scaling == (
        "global")
    c.model.projection_type = "perspective"
    assert resolve.resolve_keypoint_scaling(c, far_and_near).model.keypoint_scaling == "global"
    c.model.keypoint_scaling = "per_view"
    assert resolve.resolve_keypoint_scaling(c, people) is c


def test_coco_detections_of_people_at_different_distances_resolve_both_settings(tmp_path):
    """People photographed at different distances, as a detector's COCO file gives them
    (COCO's 17 keypoints, image coordinates: y down, pixels, hidden points v=0), read by
    the importer: ``configs/own_json.py``'s "auto" settings take the coco body's handedness
    and scale each view by its own size."""
    from c3dpo_jax import resolve
    from c3dpo_jax.data import humans, importers, json_dataset

    people = humans.make_split(40, views_per_pose=10, seed=2)
    rng = np.random.default_rng(1)
    size = np.exp(rng.uniform(np.log(60.0), np.log(240.0), len(people)))  # pixels per metre
    # The camera turned upside down about its axis: image rows grow downwards.
    xy = -humans.coco_from_h36m(people.kp3d)[..., :2] * size[:, None, None] + [320.0, 240.0]
    vis = humans.coco_visibility_from_h36m(people.vis)
    annotations = [{"image_id": i, "category_id": 1, "keypoints": np.concatenate(
        [xy[i], 2 * vis[i, :, None]], 1).reshape(-1).tolist()} for i in range(len(xy))]
    path = tmp_path / "person_keypoints.json"
    path.write_text(json.dumps({"annotations": annotations}))
    importers.main(["coco", str(path), "--out", str(tmp_path / "coco.json")])
    data = json_dataset.load(str(tmp_path / "coco.json"))
    c = own_json.get_config()
    c.model.n_keypoints = 17
    got = resolve.resolve_from_data(c, data).model
    assert got.keypoint_scaling == "per_view"
    assert (got.test_time_handedness_reference, got.test_time_one_handedness) == ("coco", True)


def test_handedness_from_a_body_whose_projections_fit_the_training_views():
    """``"auto"``: people in the h36m body's joint order (the built-in humans' views, upright
    cameras, self-occlusion) get the body's handedness with one handedness on, in COCO's
    order (the face points' visibility the head's) the coco body's; the same
    views with their points in another order, another number of points, a perspective
    model or a value that is not "auto" keep what the config says; a saved config's value
    is kept."""
    from c3dpo_jax import model, resolve
    from c3dpo_jax.data import humans

    people = humans.make_split(20, views_per_pose=5, seed=1)
    body = np.asarray(model.handedness_reference("h36m"))
    order = np.random.default_rng(0).permutation(17)
    shuffled = type(people)(kp=people.kp[:, order], vis=people.vis[:, order])
    assert resolve.body_fit_2d(body, people) < 0.5 * resolve.BODY_FIT_2D
    assert resolve.body_fit_2d(body, shuffled) > 1.2 * resolve.BODY_FIT_2D
    c = own_json.get_config()
    c.model.n_keypoints = 17
    assert c.model.test_time_handedness_reference == "auto"
    assert not c.model.test_time_one_handedness
    got = resolve.resolve_handedness(c, people).model
    assert (got.test_time_handedness_reference, got.test_time_one_handedness) == ("h36m", True)
    assert c.model.test_time_handedness_reference == "auto"  # a copy
    # The same people in COCO's order (the detectors'): the coco body fits, the h36m one not.
    vis = humans.coco_visibility_from_h36m(people.vis)  # the face: the head's
    coco = type(people)(kp=humans.coco_from_h36m(people.kp3d)[..., :2], vis=vis)
    coco_body = np.asarray(model.handedness_reference("coco"))
    assert resolve.body_fit_2d(coco_body, coco) < 0.5 * resolve.BODY_FIT_2D
    assert resolve.body_fit_2d(body, coco) > 1.2 * resolve.BODY_FIT_2D
    assert resolve.body_fit_2d(coco_body, people) > 1.2 * resolve.BODY_FIT_2D
    got = resolve.resolve_handedness(c, coco).model
    assert (got.test_time_handedness_reference, got.test_time_one_handedness) == ("coco", True)
    for data, change in ((shuffled, {}), (people, {"projection_type": "perspective"}),
                         (people, {"n_keypoints": 20})):
        c2 = own_json.get_config()
        c2.model.n_keypoints = 17
        c2.model.update(change)
        got = resolve.resolve_handedness(c2, data).model
        assert (got.test_time_handedness_reference, got.test_time_one_handedness) == (
            "mean_shape", False)
    saved = {"model": {"test_time_handedness_reference": "mean_shape",
                       "test_time_one_handedness": True}}
    got = resolve.resolve_handedness(c, people, saved).model
    assert (got.test_time_handedness_reference, got.test_time_one_handedness) == (
        "mean_shape", True)
    c.model.test_time_handedness_reference = "mean_shape"
    assert resolve.resolve_handedness(c, people) is c



def _k_files(tmp_path, mode):
    """Files of 17 and 18 points; the run (``mode``) and own_json's smoke config (K = 17, a
    human body's handedness looked for: "auto")."""
    from c3dpo_jax import train
    from c3dpo_jax.data import json_dataset, synthetic

    for k in (17, 18):
        data = synthetic.make_split(32, n_keypoints=k, n_modes=2, deformation=0.3,
                                    occlusion=0.0, noise=0.0, perspective=False, shape_seed=0,
                                    seed=3)
        json_dataset.save(data, str(tmp_path / f"k{k}.json"))
    run = train.train_and_evaluate if mode == "train" else train.evaluate_checkpoint
    return run, own_json.get_config("smoke")


@pytest.mark.parametrize("mode", ["train", "eval"])
def test_the_keypoint_count_is_checked_before_the_settings_worked_out_from_the_data(
        tmp_path, mode):
    """The bodies' handedness is looked for among those of the model's K, which would fail
    on points of another K."""
    run, c = _k_files(tmp_path, mode)
    c.data.train_path = c.data.test_path = str(tmp_path / "k18.json")
    with pytest.raises(ValueError, match="^" + re.escape(
            "train split has 18 keypoints but config.model.n_keypoints is 17; set "
            "--config.model.n_keypoints=18")):
        run(c, str(tmp_path / "run"))
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize("mode", ["train", "eval"])
def test_train_and_test_files_of_other_keypoint_counts_are_named_both(tmp_path, mode):
    """Not the test file's K as the fix: it would then fail on the train file."""
    run, c = _k_files(tmp_path, mode)
    c.model.n_keypoints = 18
    c.data.train_path, c.data.test_path = str(tmp_path / "k18.json"), str(tmp_path / "k17.json")
    with pytest.raises(ValueError, match="^" + re.escape(
            "the train split has 18 keypoints and the test split 17: the two files disagree "
            "(config.data.train_path and test_path must hold the same points)")):
        run(c, str(tmp_path / "run"))
