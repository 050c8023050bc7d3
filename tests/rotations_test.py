"""Numpy rotations of the data layer: proper rotations in so3's convention, one
quaternion formula for numpy and jax, upright cameras keep y up within their bounds."""

import jax.numpy as jnp
import numpy as np

from c3dpo_jax import so3
from c3dpo_jax.data import rotations


def _proper(r: np.ndarray) -> None:
    eye = np.broadcast_to(np.eye(3), r.shape)
    np.testing.assert_allclose(r @ np.swapaxes(r, -1, -2), eye, atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(r), 1.0, atol=1e-12)


def test_axis_rotations_are_so3_exp_maps_about_the_axes():
    angles = np.array([[-2.0, 0.3], [0.0, 1.5]])
    for i, axis in enumerate("xyz"):
        r = rotations.axis_rotation(axis.upper() if i == 1 else axis, angles)
        assert r.shape == (2, 2, 3, 3)
        _proper(r)
        w = np.zeros(3)
        w[i] = 0.3
        np.testing.assert_allclose(r[0, 1], so3.exp_map(jnp.asarray(w)), atol=1e-6)


def test_random_rotations_use_the_quaternion_formula_of_so3():
    r = rotations.random_rotations(np.random.default_rng(0), 5)
    assert r.shape == (5, 3, 3) and r.dtype == np.float64
    _proper(r)
    q = np.random.default_rng(0).normal(size=(5, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    np.testing.assert_allclose(r, so3.quaternion_to_matrix(jnp.asarray(q, jnp.float32)),
                               atol=1e-6)


def test_upright_cameras_keep_y_up_within_the_elevation_bound():
    r = rotations.upright_rotations(np.random.default_rng(1), 200, max_elevation=0.4)
    _proper(r)
    up = r @ np.array([0.0, 1.0, 0.0])  # the object's up axis in the camera
    tilt = np.arccos(np.clip(up[:, 1], -1, 1))  # angle from the camera's y
    assert tilt.max() <= 0.4 * np.sqrt(1.25) + 1e-9 and tilt.max() > 0.2
