"""experiments/dense_points: the runs' CLI calls, the joints' scores and the report."""

import json
import os

import jax
import numpy as np
import pytest

from c3dpo_jax import baselines, evaluation, model
from c3dpo_jax.reconstruct import C3DPOParams, reconstruct, save_workdir

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


@pytest.fixture(scope="module")
def dense(load_script):
    return load_script("experiments/dense_points/run.py")


def test_a_run_is_the_humans_config_with_k_points_and_the_asked_steps(dense, monkeypatch):
    from absl import flags
    from ml_collections import config_flags

    monkeypatch.chdir(ROOT)
    cmd = dense.command(517, 3, 3000, "/tmp/w")
    assert cmd[1:3] == ["-m", "c3dpo_jax.main"]
    argv = ["prog"] + [a for a in cmd[3:] if a.startswith("--config")]
    fv = flags.FlagValues()  # parsed as the CLI parses its command line
    config_flags.DEFINE_config_file("config", None, flag_values=fv, lock_config=True,
                                    sys_argv=argv)
    fv(argv)
    c = fv.config
    assert c.model.n_keypoints == 517 and c.data.humans.dense_points == 500
    assert c.seed == 3 and c.train.num_steps == 3000
    steps = c.train.epochs * c.train.samples_per_epoch // c.train.batch_size
    decay_at = c.optim.lr_milestones[0] * c.train.samples_per_epoch // c.train.batch_size
    assert steps == 3000 and decay_at == 2400  # x0.1 for the last 20%


@pytest.fixture(scope="module")
def saved_run(tmp_path_factory, dense):
    """An initialised model on 17 joints + 3 surface points, saved as a finished run."""
    from configs import humans as humans_cfg

    c = humans_cfg.get_config("smoke")
    c.data.humans.dense_points = 3
    c.data.humans.n_train_poses, c.data.humans.n_test_poses = 6, 3
    c.data.humans.views_per_pose = 4
    cfg = model.ModelConfig(n_keypoints=20, shape_basis_size=3, n_fully_connected=16,
                            n_layers=1, canonicalization_n_fully_connected=16,
                            canonicalization_n_layers=1)
    params = C3DPOParams(model.init_variables(jax.random.key(0), cfg), cfg)
    workdir = save_workdir(params, str(tmp_path_factory.mktemp("dense") / "k20_s0"),
                           c.to_dict())
    with open(os.path.join(workdir, "eval_results.json"), "w") as f:
        json.dump({"final": {"mpjpe": 0.0}}, f)
    return workdir, params, c


def test_score_takes_the_joints_of_the_reconstruction_and_fits_the_rigid_baseline_to_them(
        dense, saved_run):
    from c3dpo_jax.data import KeypointData, load_splits

    workdir, params, c = saved_run
    got = dense.score(workdir)
    train, test = load_splits(c.data)
    assert test.n_keypoints == got["n_keypoints"] == 20
    # Independently: the 17 first points of the full reconstruction, scored with the
    # protocol's per-view flip, written out here with numpy.
    pred = np.asarray(reconstruct(params, test.kp, test.vis).shape_3d)[:, :17]
    gt = test.kp3d[:, :17]
    pred, gt = pred.copy(), gt.copy()
    pred[..., 2] -= pred[..., 2].mean(1, keepdims=True)  # up3d: mean depth set to 0
    gt[..., 2] -= gt[..., 2].mean(1, keepdims=True)
    flip = pred * np.array([1, 1, -1])
    err = np.minimum(np.linalg.norm(pred - gt, axis=-1).mean(1),
                     np.linalg.norm(flip - gt, axis=-1).mean(1))
    np.testing.assert_allclose(got["joints"], err.mean(), rtol=1e-4)
    assert got["all_points"] != pytest.approx(got["joints"])  # scored on all 20
    rigid = baselines.fit_mean_shape(baselines.procrustes_mean_shape(train.kp3d[:, :17]),
                                     test.kp[:, :17], test.vis[:, :17])
    joints = KeypointData(kp=test.kp[:, :17], vis=test.vis[:, :17], kp3d=test.kp3d[:, :17])
    assert got["rigid"] == pytest.approx(evaluation.evaluate(rigid, joints, "up3d")["mpjpe"])
    # Kept beside the run: a second call reads it back.
    with open(os.path.join(workdir, "joints.json")) as f:
        assert json.load(f) == got


def test_report_tables_cost_and_accuracy_and_draws_the_figure(dense, tmp_path):
    (tmp_path / "cost").mkdir()
    for k, rate in ((17, 50.0), (517, 10.0)):
        (tmp_path / "cost" / f"k{k}.json").write_text(json.dumps(dict(
            steps_per_s=rate, train_samples_per_s=256 * rate, compile_s=7.0,
            eval_samples_per_s=1e5 / k, peak_rss_mb=900.0 + k)))
    for k, seed, joints in ((17, 0, 0.10), (17, 1, 0.12), (517, 0, 0.08)):
        workdir = tmp_path / "runs" / dense.run_name(k, seed)
        workdir.mkdir(parents=True)
        (workdir / "eval_results.json").write_text(json.dumps({"final": {"mpjpe": 0.0}}))
        (workdir / "joints.json").write_text(json.dumps(dict(
            joints=joints, all_points=joints + 0.01, rigid=0.11, visible=0.9, n_keypoints=k)))
    text = dense.report(str(tmp_path), [17, 517, 2017], [17, 517, 2017], [0, 1], steps=3000)
    assert "| 17 | 50.00 | 12800 | 7.0 | 5882 | 917 |" in text  # cost row
    assert "| 2017 | - |" in text  # not benchmarked yet
    acc = [line for line in text.splitlines() if line.startswith("| 17 | 2 |")]
    # Minutes: the steps at the benchmarked rate (3000 / 50 steps/s = 1 minute).
    assert acc == ["| 17 | 2 | 0.110 ± 0.010 | 0.120 ± 0.010 | 0.110 | 0.92x | 1.0 |"]
    assert "| 517 | 1 | 0.080 | 0.090 | 0.110 | 1.38x | 5.0 |" in text
    assert "| 2017 | 0 | - |" in text
    assert os.path.getsize(tmp_path / "dense_points.png") > 1000
