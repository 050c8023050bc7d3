"""experiments/robustness: the corruption of the views and the grid's table and figure."""

import json
import os

import numpy as np
import pytest


@pytest.fixture(scope="module")
def robustness(load_script):
    return load_script("experiments/robustness/run.py")


def test_corruption_adds_noise_of_the_asked_size_and_hides_points(robustness):
    from c3dpo_jax.data import KeypointData

    rng = np.random.default_rng(0)
    kp3d = rng.normal(size=(4000, 20, 3)).astype(np.float32)
    data = KeypointData(kp=kp3d[..., :2].copy(), vis=np.ones((4000, 20), np.float32), kp3d=kp3d)
    out = robustness.corrupt(data, sigma=0.1, p=0.3, radius=2.0, rng=np.random.default_rng(1))
    shown = out.vis > 0
    assert abs(1 - shown.mean() - 0.3) < 0.01  # each point hidden with probability p
    assert (shown.sum(1) >= 2).all()
    noise = (out.kp - data.kp)[shown]
    assert abs(noise.std() - 0.2) < 0.005 and abs(noise.mean()) < 0.005  # sigma * radius
    assert (out.kp[~shown] == 0).all()  # hidden points zeroed, as the release's files
    np.testing.assert_array_equal(out.kp3d, kp3d)  # the ground truth stays clean
    # Nothing asked, nothing changed.
    same = robustness.corrupt(data, 0.0, 0.0, 2.0, np.random.default_rng(1))
    np.testing.assert_array_equal(same.kp, data.kp)
    np.testing.assert_array_equal(same.vis, data.vis)


def test_views_that_would_lose_all_points_keep_two(robustness):
    from c3dpo_jax.data import KeypointData

    kp3d = np.ones((50, 5, 3), np.float32)
    data = KeypointData(kp=kp3d[..., :2], vis=np.ones((50, 5), np.float32), kp3d=kp3d)
    out = robustness.corrupt(data, 0.0, 1.0, 1.0, np.random.default_rng(0))
    np.testing.assert_array_equal(out.vis.sum(1), 2)


def test_report_tables_every_cell_and_draws_the_heat_maps(robustness, tmp_path):
    grid = [(d, s, p) for d in (0, 80) for s in (0.0, 0.1) for p in (0.0, 0.4)]
    scores = {}
    for i, cell in enumerate(grid[:-1]):  # the last cell is not run yet
        workdir = tmp_path / "runs" / robustness.cell_name(*cell)
        workdir.mkdir(parents=True)
        (workdir / "eval_results.json").write_text(json.dumps({"final": {"mpjpe": 0.0}}))
        scores[cell] = dict(mpjpe=0.1 + i / 100, rigid=0.2 + i / 100, visible=1.0)
        (workdir / "joints.json").write_text(json.dumps(scores[cell]))
    text = robustness.report(str(tmp_path), grid)
    assert "**17 keypoints**" in text and "**97 keypoints**" in text
    rows = [line for line in text.splitlines() if line.startswith("| 0.1 |")]
    assert rows[0] == "| 0.1 | 0.120 (0.220) | 0.130 (0.230) |"  # 17 points, sigma 0.1
    assert rows[1] == "| 0.1 | 0.160 (0.260) | - |"  # 97 points: the missing cell
    assert os.path.getsize(tmp_path / "robustness.png") > 1000


def test_report_averages_the_seeds_and_says_when_one_is_missing(robustness, tmp_path):
    grid = [(0, 0.0, 0.0), (0, 0.0, 0.4)]
    for cell, seed, mpjpe in ((grid[0], 0, 0.10), (grid[0], 1, 0.14), (grid[1], 1, 0.30)):
        workdir = tmp_path / "runs" / robustness.cell_name(*cell, seed)
        workdir.mkdir(parents=True)
        (workdir / "eval_results.json").write_text(json.dumps({"final": {"mpjpe": 0.0}}))
        (workdir / "joints.json").write_text(json.dumps(dict(mpjpe=mpjpe, rigid=0.2 + seed / 10,
                                                             visible=1.0)))
    assert robustness.cell_name(0, 0.0, 0.0, 0) == "k17_s0_p0"  # seed 0 keeps its name
    row = next(line for line in robustness.report(str(tmp_path), grid, (0, 1)).splitlines()
               if line.startswith("| 0 |"))
    assert row == "| 0 | 0.120 ± 0.020 (0.250) | 0.300 (n=1) (0.300) |"


def test_rescoring_the_rigid_baseline_keeps_the_model_score(robustness, tmp_path):
    from c3dpo_jax.data import json_dataset

    cell = robustness.make_cell(0, 0.05, 0.4, str(tmp_path), seed=1)
    from_files = robustness.rigid_mpjpe(json_dataset.load(cell["train"]),
                                        json_dataset.load(cell["test"]))
    workdir = tmp_path / "runs" / robustness.cell_name(0, 0.05, 0.4, 1)
    workdir.mkdir(parents=True)
    (workdir / "joints.json").write_text(json.dumps(dict(mpjpe=0.123, rigid=9.0, visible=0.6)))
    robustness.rescore_rigid(str(workdir), 0, 0.05, 0.4, seed=1)
    scores = json.loads((workdir / "joints.json").read_text())
    assert scores["mpjpe"] == 0.123 and scores["visible"] == 0.6
    assert scores["rigid"] == pytest.approx(from_files, rel=1e-6)  # views remade alike
    assert 0.05 < scores["rigid"] < 0.3
    robustness.rescore_rigid(str(tmp_path / "runs" / "not_run"), 0, 0.05, 0.4, seed=1)  # no-op
