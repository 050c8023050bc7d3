"""Keypoint normalisation, projection and intrinsics."""

import jax.numpy as jnp
import numpy as np
import pytest

from c3dpo_jax import geometry


def _kp(seed=0, n=9):
    rng = np.random.default_rng(seed)
    kp = rng.normal(size=(n, 2)).astype(np.float32) * 50 + 300
    vis = (rng.uniform(size=n) > 0.3).astype(np.float32)
    vis[:2] = 1
    return jnp.asarray(kp), jnp.asarray(vis)


def test_masked_mean_ignores_invisible_points():
    kp, vis = _kp()
    expected = np.asarray(kp)[np.asarray(vis) > 0].mean(0)
    np.testing.assert_allclose(geometry.masked_mean(kp, vis), expected, rtol=1e-6)


@pytest.mark.parametrize("norm_type", ["to_mean", "to_root"])
def test_normalise_then_unnormalise_is_the_identity(norm_type):
    kp, vis = _kp()
    norm, centre = geometry.normalise_keypoints(
        kp, vis, norm_type=norm_type, rescale=0.01, root_joint=1
    )
    np.testing.assert_allclose(geometry.unnormalise_keypoints(norm, centre, 0.01), kp, rtol=1e-5)
    anchor = geometry.masked_mean(norm, vis) if norm_type == "to_mean" else norm[1]
    np.testing.assert_allclose(anchor, 0.0, atol=1e-3)


def test_orthographic_and_perspective_projection():
    x = jnp.array([[1.0, 2.0, 4.0], [3.0, -1.0, -2.0]])
    xy, depth = geometry.project(x, projection_type="orthographic")
    np.testing.assert_allclose(xy, x[:, :2])
    xy, depth = geometry.project(x, projection_type="perspective", depth_threshold=0.5)
    np.testing.assert_allclose(xy, [[0.25, 0.5], [6.0, -2.0]])  # behind the camera: clamped
    np.testing.assert_allclose(depth, x[:, 2])


def test_argmin_translation_is_the_least_squares_shift():
    kp, vis = _kp()
    proj = kp[::-1] * 0.5
    shifted = geometry.argmin_translation(proj, kp, vis)
    v = np.asarray(vis) > 0
    residual = np.asarray(shifted - kp)[v]
    np.testing.assert_allclose(residual.mean(0), 0.0, atol=1e-3)


def test_calibrate_then_uncalibrate_is_the_identity():
    kp, _ = _kp()
    k = jnp.array([[500.0, 0.0, 320.0], [0.0, 480.0, 240.0], [0.0, 0.0, 1.0]])
    cal = geometry.calibrate(kp, k)
    np.testing.assert_allclose(cal[:, 0], (kp[:, 0] - 320.0) / 500.0, rtol=1e-5)
    np.testing.assert_allclose(geometry.uncalibrate(cal, k), kp, rtol=1e-5)
