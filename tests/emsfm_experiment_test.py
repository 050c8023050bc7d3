"""experiments/emsfm: the run on a generated low-rank JSON pair writes and prints its rows."""

import json
import os
import subprocess
import sys

import numpy as np
from scipy.spatial.transform import Rotation

from c3dpo_jax.data import KeypointData, json_dataset

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _split(n_views, seed):
    """Views of one shape deformed along one mode, under random rotations."""
    shape_rng = np.random.default_rng(0)  # the same shape space in both splits
    mean = shape_rng.normal(size=(10, 3)) * [1.0, 0.7, 0.5]
    mode = 0.3 * shape_rng.normal(size=(10, 3))
    rng = np.random.default_rng(seed)
    shapes = mean + rng.normal(size=(n_views, 1, 1)) * mode
    gt = np.einsum("mij,mnj->mni", Rotation.random(n_views, random_state=seed).as_matrix(),
                   shapes)
    return KeypointData(kp=gt[..., :2], vis=np.ones(gt.shape[:2]), kp3d=gt)


def test_run_scores_emsfm_beside_the_rigid_fit(tmp_path):
    json_dataset.save(_split(60, 1), str(tmp_path / "wave_train.json"))
    json_dataset.save(_split(40, 2), str(tmp_path / "wave_test.json"))
    out = tmp_path / "results"
    cmd = [sys.executable, os.path.join(ROOT, "experiments", "emsfm", "run.py"),
           f"--data_dir={tmp_path}", "--datasets=wave", "--n_basis=0,1", "--n_iters=50",
           f"--out={out}"]
    printed = subprocess.run(cmd, check=True, capture_output=True, text=True).stdout
    with open(out / "wave.json") as f:
        rows = json.load(f)["rows"]
    assert list(rows) == ["rigid fit of the training mean", "EM-SfM, D=0", "EM-SfM, D=1"]
    assert "| EM-SfM, D=1 |" in printed and "wave (40 test views)" in printed
    # Noiseless views of a one-mode shape space: D=1 recovers them, a rigid shape cannot.
    assert rows["EM-SfM, D=1"]["mpjpe"] < 1e-3 < 0.05 < rows["rigid fit of the training mean"][
        "mpjpe"]
    assert rows["EM-SfM, D=1"]["e3d/sequence"] < 1e-2
    assert 0 < rows["EM-SfM, D=1"]["iterations"] <= 50
