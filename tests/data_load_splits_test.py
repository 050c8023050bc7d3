"""config.data -> splits for every source, with the default config's sections."""

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


def _k_files(tmp_path, mode):
    """Files of 17 and 18 points; the run (``mode``) and own_json's smoke config (K = 17, a
    human body's handedness looked for: "auto")."""
    from c3dpo_jax import evaluate_workdir, train
    from c3dpo_jax.data import json_dataset, synthetic

    for k in (17, 18):
        data = synthetic.make_split(32, n_keypoints=k, n_modes=2, deformation=0.3,
                                    occlusion=0.0, noise=0.0, perspective=False, shape_seed=0,
                                    seed=3)
        json_dataset.save(data, str(tmp_path / f"k{k}.json"))
    run = train.train_and_evaluate if mode == "train" else evaluate_workdir.evaluate_checkpoint
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
