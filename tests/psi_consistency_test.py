"""experiments/psi_consistency: the spread measure on hand-made shapes, and the smoke run."""

import importlib.util
import json
import os
import subprocess
import sys

import numpy as np
import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
EXPERIMENT = os.path.join(ROOT, "experiments", "psi_consistency")


def _load_consistency():
    spec = importlib.util.spec_from_file_location(
        "psi_consistency_measures", os.path.join(EXPERIMENT, "consistency.py"))
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


consistency = _load_consistency()


def _shape(seed=0, n=17):
    return np.random.default_rng(seed).normal(size=(n, 3))


def test_identical_canonical_shapes_have_no_spread():
    shapes = np.broadcast_to(_shape(), (5, 7, 17, 3))  # 5 poses, 7 angles
    np.testing.assert_allclose(consistency.canonical_spread(shapes), np.zeros(5), atol=1e-12)
    np.testing.assert_allclose(consistency.deviation_per_angle(shapes), np.zeros((5, 7)),
                               atol=1e-12)
    np.testing.assert_allclose(consistency.spread_own_radius(shapes), np.zeros(5), atol=1e-12)


def test_spread_of_two_shapes_a_known_offset_apart():
    shape = _shape()
    offset = np.array([0.3, -0.4, 1.2])  # length 1.3
    shapes = np.stack([shape, shape + offset])  # (A=2, N, 3)
    radius = np.sqrt(((shape - shape.mean(0)) ** 2).sum(-1).mean())
    # Both lie half the offset from their mean, whose radius is the shape's.
    np.testing.assert_allclose(consistency.deviation_per_angle(shapes), [0.65 / radius] * 2)
    np.testing.assert_allclose(consistency.canonical_spread(shapes), 0.65 / radius)
    np.testing.assert_allclose(consistency.spread_own_radius(shapes), 0.65 / radius)
    # Scale-free: the same shapes in other units.
    np.testing.assert_allclose(consistency.canonical_spread(3.0 * shapes), 0.65 / radius)


def test_turned_poses_are_centred_rotations_about_the_vertical():
    pose = _shape()[None] + 5.0
    turned = consistency.rotate_about_y(pose, np.deg2rad([0.0, 90.0, 180.0]))
    centred = pose[0] - pose[0].mean(0)
    np.testing.assert_allclose(turned[0, 0], centred, atol=1e-12)
    np.testing.assert_allclose(turned[0, 1], np.stack([centred[:, 2], centred[:, 1],
                                                       -centred[:, 0]], -1), atol=1e-12)
    np.testing.assert_allclose(turned[0, 2], centred * [-1, 1, -1], atol=1e-12)
    # A "canonical" shape that turns with the view is far from view-invariant.
    assert consistency.canonical_spread(turned)[0] > 0.3


def test_sign_agreement_counts_views_whose_depth_sign_is_right():
    gt = _shape()[None].repeat(4, 0)
    pred = gt.copy()
    pred[2, :, 2] *= -1  # the third view mirrored in depth
    assert consistency.sign_agreement(pred, gt) == pytest.approx(0.75)
    assert consistency.mpjpe(pred, gt) == pytest.approx(0.0, abs=1e-12)


def test_smoke_run_writes_both_models(tmp_path, smoke_subprocess_env):
    out = tmp_path / "psi"
    cmd = [sys.executable, os.path.join(EXPERIMENT, "run.py"), "--smoke", f"--out={out}",
           "--n_poses=4", "--n_angles=6", "--n_shown_angles=3"]
    subprocess.run(cmd, check=True, capture_output=True, text=True, cwd=str(tmp_path),
                   env=smoke_subprocess_env())
    with open(out / "consistency.json") as f:
        results = json.load(f)
    assert list(results["models"]) == ["C3DPO", "C3DPO-equiv (no Psi)"]
    for info in results["models"].values():
        assert info["steps"] == 20
        assert np.isfinite(info["test_mpjpe"]) and info["canonical_spread"] >= 0
        assert len(info["curve"]) == 6 and len(info["spread_per_pose"]) == 4
        assert 0 <= info["turned_views_sign_agreement"] <= 1
    assert results["settings"]["angles_deg"] == [0, 60, 120, 180, 240, 300]
    assert (out / "consistency.png").stat().st_size > 10_000
    assert (out / "runs" / "full" / "eval_results.json").exists()
    assert (out / "runs" / "equiv" / "eval_results.json").exists()
