"""Rotation code against independent computations (expm, scipy, finite differences)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.scipy.linalg import expm
from scipy.spatial.transform import Rotation

from c3dpo_jax import so3

ANGLES = [0.0, 1e-8, 1e-4, 1e-2, 0.5, 2.0, np.pi - 1e-3, np.pi - 1e-6, np.pi, 5.0, 20.0]


def _axis(seed):
    v = np.random.default_rng(seed).normal(size=3)
    return v / np.linalg.norm(v)


def test_hat_is_the_cross_product():
    w, x = np.array([0.3, -1.2, 2.0]), np.array([1.5, 0.1, -0.7])
    np.testing.assert_allclose(so3.hat(jnp.asarray(w)) @ x, np.cross(w, x), rtol=1e-6)


@pytest.mark.parametrize("angle", ANGLES)
def test_exp_map_is_orthonormal_with_unit_determinant(angle):
    r = np.asarray(so3.exp_map(jnp.asarray(angle * _axis(1), jnp.float32)), np.float64)
    np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-6)
    assert abs(np.linalg.det(r) - 1.0) < 1e-6


@pytest.mark.parametrize("angle", ANGLES)
def test_exp_map_matches_matrix_exponential_and_scipy(angle):
    w = angle * _axis(2)
    with jax.enable_x64(True):
        reference = np.asarray(expm(so3.hat(jnp.asarray(w, jnp.float64))))
        ours64 = np.asarray(so3.exp_map(jnp.asarray(w, jnp.float64)))
    np.testing.assert_allclose(ours64, reference, atol=1e-12)
    np.testing.assert_allclose(Rotation.from_rotvec(w).as_matrix(), reference, atol=1e-12)
    ours32 = np.asarray(so3.exp_map(jnp.asarray(w, jnp.float32)))
    np.testing.assert_allclose(ours32, reference, atol=2e-6)


def test_convention_rotates_column_vectors_counter_clockwise():
    r = np.asarray(so3.exp_map(jnp.array([0.0, 0.0, np.pi / 2])))
    np.testing.assert_allclose(r @ np.array([1.0, 0.0, 0.0]), [0.0, 1.0, 0.0], atol=1e-6)


@pytest.mark.parametrize(
    "w0", [np.zeros(3), np.array([1e-5, -2e-5, 0.0]), np.array([0.3, -0.8, 1.1])]
)
def test_exp_map_gradients_are_finite_and_match_finite_differences(w0):
    probe = np.random.default_rng(3).normal(size=(3, 3))

    def f(w):
        return jnp.sum(so3.exp_map(w) * probe)

    with jax.enable_x64(True):
        g = np.asarray(jax.grad(f)(jnp.asarray(w0, jnp.float64)))
        h = 1e-6
        fd = [
            (f(jnp.asarray(w0 + h * e)) - f(jnp.asarray(w0 - h * e))) / (2 * h) for e in np.eye(3)
        ]
    assert np.all(np.isfinite(g))
    np.testing.assert_allclose(g, np.asarray(fd), atol=1e-7)


@pytest.mark.parametrize("angle", [0.0, 1e-6, 1e-3, 1.0, 3.0, np.pi - 1e-4, np.pi - 1e-7])
def test_log_map_inverts_exp_map_and_matches_scipy(angle):
    w = angle * _axis(4)
    with jax.enable_x64(True):
        r = so3.exp_map(jnp.asarray(w))
        back = np.array(so3.log_map(r))
    r = np.array(r)
    reference = Rotation.from_matrix(r).as_rotvec()
    if angle > np.pi - 1e-3:  # the axis sign is ambiguous at pi: compare rotations
        np.testing.assert_allclose(Rotation.from_rotvec(back).as_matrix(), np.asarray(r), atol=1e-6)
    else:
        np.testing.assert_allclose(back, reference, atol=1e-8)
        np.testing.assert_allclose(back, w, atol=1e-8)


def test_a_geodesic_rotation_loss_has_finite_gradients_at_and_near_its_solution():
    # |log(R(w)^T R(w0))|^2: zero gradient at w = w0 (the identity inside log_map), and
    # central finite differences (float64, an independent computation) next to it.
    w0 = jnp.array([0.1, 0.2, 0.3])

    def loss(w):
        return jnp.sum(so3.log_map(so3.exp_map(w).T @ so3.exp_map(w0)) ** 2)

    np.testing.assert_allclose(jax.grad(loss)(w0), 0.0, atol=1e-6)
    assert np.isfinite(np.asarray(jax.jacrev(so3.log_map)(jnp.eye(3)))).all()
    w = np.array([0.12, 0.19, 0.315])

    def angle_sq(v):  # the same loss by scipy, in float64
        rel = Rotation.from_rotvec(v).inv() * Rotation.from_rotvec(np.asarray(w0, np.float64))
        return rel.magnitude() ** 2

    eps = 1e-6
    numeric = [(angle_sq(w + eps * e) - angle_sq(w - eps * e)) / (2 * eps) for e in np.eye(3)]
    np.testing.assert_allclose(jax.grad(loss)(jnp.asarray(w, jnp.float32)), numeric, rtol=1e-3,
                               atol=1e-5)


def test_one_rotation_at_a_time_or_a_clear_error():
    # The check itself (the test run's type checker answers first for a wrong shape).
    with pytest.raises(ValueError, match=r"exp_map takes one rotation vector of shape \(3,\), "
                       r"got \(5, 3\) \(for a batch: jax.vmap\(exp_map\)\)"):
        so3._check_shape(jnp.ones((5, 3)), (3,), "exp_map", "rotation vector")
    so3._check_shape(jnp.ones(3), (3,), "exp_map", "rotation vector")
    # A list, or integers, is one too (in a notebook: exp_map([0.1, 0.2, 0.3])).
    w = so3._check_shape([0, 1, 0], (3,), "exp_map", "rotation vector")
    assert w.dtype == jnp.float32 and w.tolist() == [0.0, 1.0, 0.0]
    assert jax.vmap(so3.exp_map)(jnp.ones((5, 3))).shape == (5, 3, 3)


def test_haar_rotations_have_the_uniform_angle_distribution(key):
    rots = jax.vmap(so3.random_rotation)(jax.random.split(key, 20000))
    rots = np.asarray(rots, np.float64)
    np.testing.assert_allclose(
        np.einsum("mij,mkj->mik", rots, rots), np.broadcast_to(np.eye(3), rots.shape), atol=1e-5
    )
    angles = np.linalg.norm(Rotation.from_matrix(rots).as_rotvec(), axis=1)
    # Haar: P(angle <= t) = (t - sin t) / pi.
    for t in (0.5, 1.5, 2.5):
        expected = (t - np.sin(t)) / np.pi
        assert abs(np.mean(angles <= t) - expected) < 0.01
    # E[R] = 0 for the uniform measure (a biased sampler has a non-zero mean).
    assert np.abs(rots.mean(0)).max() < 0.02


def test_bounded_rotations_stay_within_the_angle_about_the_given_axis(key):
    rots = jax.vmap(lambda k: so3.random_rotation(k, 0.3, axis=jnp.array([0.0, 0.0, 1.0])))(
        jax.random.split(key, 2000)
    )
    rotvec = Rotation.from_matrix(np.asarray(rots, np.float64)).as_rotvec()
    np.testing.assert_allclose(rotvec[:, :2], 0.0, atol=1e-6)
    assert np.abs(rotvec[:, 2]).max() <= 0.3 + 1e-6
    assert np.abs(rotvec[:, 2]).max() > 0.28  # the whole range is used ...
    assert (rotvec[:, 2] < 0).mean() > 0.4  # ... in both directions


def test_in_plane_rotation_is_a_2d_rotation(key):
    r = np.asarray(so3.in_plane_rotation(key, 1.0))
    np.testing.assert_allclose(r @ r.T, np.eye(2), atol=1e-6)
    assert abs(np.linalg.det(r) - 1) < 1e-6
