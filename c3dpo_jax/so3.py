"""Rotations: hat operator, Rodrigues exponential map, log map, random rotations.

Convention (stated once, used everywhere): rotations act on **column** vectors,
``x_cam = R @ x``. Points are stored as rows ``(N, 3)``, so a whole point set is
rotated as ``X @ R.T``. ``exp_map(w)`` is the rotation by angle ``|w|`` about the
axis ``w / |w|``, counter-clockwise seen from the axis' tip (right-hand rule: the
thumb along ``w``),
i.e. ``exp_map(w) == expm(hat(w))`` as in the paper (``R(theta) = expm [theta]_x``).

Paper: Sec. 3.3 (camera ``R = expm(hat(theta))``), Sec. 3.4 (random rotations for
the canonicalisation loss), Sec. 3.5 (in-plane rotations).
"""

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from c3dpo_jax.types import Rot, Vec3

# Below this squared angle the Taylor series is used: its truncation error
# (theta^6 / 5040 ~ 2e-16) is far below float32 precision.
_SMALL_ANGLE_SQ = 1e-4


def hat(w: Vec3) -> Rot:
    """Skew-symmetric matrix with ``hat(w) @ x == cross(w, x)``."""
    zero = jnp.zeros_like(w[0])
    return jnp.stack(
        [
            jnp.stack([zero, -w[2], w[1]]),
            jnp.stack([w[2], zero, -w[0]]),
            jnp.stack([-w[1], w[0], zero]),
        ]
    )


def vee(m: Rot) -> Vec3:
    """Inverse of ``hat`` on the skew-symmetric part of ``m``."""
    return 0.5 * jnp.stack([m[2, 1] - m[1, 2], m[0, 2] - m[2, 0], m[1, 0] - m[0, 1]])


def _sinc_sq(theta_sq: Float[Array, ""]) -> Float[Array, ""]:
    """``sin(t) / t`` as a function of ``t**2``, exact and differentiable at 0."""
    small = theta_sq < _SMALL_ANGLE_SQ
    safe = jnp.where(small, 1.0, theta_sq)
    t = jnp.sqrt(safe)
    series = 1.0 - theta_sq / 6.0 + theta_sq**2 / 120.0
    return jnp.where(small, series, jnp.sin(t) / t)


def _check_shape(x, shape: tuple[int, ...], name: str, what: str):
    """``x`` as a floating-point array (a list or integers too) when it is one ``what`` of
    ``shape``, else an error (batches go through ``jax.vmap``)."""
    if jnp.shape(x) != shape:
        raise ValueError(f"{name} takes one {what} of shape {shape}, got {jnp.shape(x)} "
                         f"(for a batch: jax.vmap({name}))")
    x = jnp.asarray(x)
    return x if jnp.issubdtype(x.dtype, jnp.floating) else x.astype(jnp.float32)


def exp_map(w: Vec3) -> Rot:
    """Rodrigues' formula ``R = I + A hat(w) + B hat(w)^2`` for ``expm(hat(w))``.

    ``A = sin(t)/t`` and ``B = (1 - cos t)/t^2 = A(t/2)^2 / 2``; the half-angle form
    avoids the cancellation of ``1 - cos t`` in float32, so the result is
    orthonormal to float32 precision for every angle, and the Taylor branch gives
    exact values and finite gradients at ``w = 0``. The release instead divides by
    ``t + 1e-4``, which is not orthonormal for small angles.
    """
    w = _check_shape(w, (3,), "exp_map", "rotation vector")
    theta_sq = jnp.sum(w * w)
    a = _sinc_sq(theta_sq)
    b = 0.5 * _sinc_sq(theta_sq / 4.0) ** 2
    k = hat(w)
    return jnp.eye(3, dtype=w.dtype) + a * k + b * (k @ k)


def log_map(r: Rot) -> Vec3:
    """Rotation vector ``w`` with ``exp_map(w) == r`` and ``|w| <= pi``.

    Uses ``atan2(|vee(R - R^T)|, tr(R) - 1)`` for the angle, which is accurate
    everywhere, and near ``pi`` (where ``R - R^T`` vanishes) reads the axis from the
    largest column of ``(R + R^T)/2 + (1 - cos t) ... = I cos t + (1-cos t) a a^T``.
    """
    r = _check_shape(r, (3, 3), "log_map", "rotation matrix")
    s = vee(r)
    # |s| with a finite gradient at the identity (that of a norm at 0 is NaN).
    sin_sq = jnp.sum(s * s)
    positive = sin_sq > 0
    sin_t = jnp.where(positive, jnp.sqrt(jnp.where(positive, sin_sq, 1.0)), 0.0)
    cos_t = 0.5 * (jnp.trace(r) - 1.0)
    theta = jnp.arctan2(sin_t, cos_t)
    # Generic branch: w = theta / sin(theta) * s, with the series near 0.
    theta_sq = theta**2
    small = theta_sq < _SMALL_ANGLE_SQ
    factor = jnp.where(small, 1.0 + theta_sq / 6.0, theta / jnp.where(small, 1.0, sin_t))
    w_generic = factor * s
    # Near-pi branch: a a^T = (sym(R) - cos t I) / (1 - cos t).
    outer = (0.5 * (r + r.T) - cos_t * jnp.eye(3, dtype=r.dtype)) / jnp.maximum(1.0 - cos_t, 1e-6)
    col = jnp.argmax(jnp.diagonal(outer))
    axis = outer[:, col] / jnp.sqrt(jnp.maximum(outer[col, col], 1e-12))
    # Choose the sign of the axis that agrees with the (small) skew part.
    axis = jnp.where(jnp.dot(axis, s) < 0.0, -axis, axis)
    w_pi = theta * axis
    return jnp.where(cos_t < -0.9, w_pi, w_generic)


def random_rotation(
    key: jax.Array, max_angle: float | None = None, axis: Vec3 | None = None
) -> Rot:
    """Draws one random rotation.

    Args:
      key: PRNG key.
      max_angle: ``None`` draws from the uniform (Haar) measure on SO(3), through a
        normalised 4D Gaussian quaternion. A number draws an angle uniformly in
        ``[-max_angle, max_angle]`` about ``axis``.
      axis: fixed rotation axis (e.g. the optical axis ``[0, 0, 1]`` for in-plane
        rotations). ``None`` with a ``max_angle`` draws the axis uniformly on the
        sphere, which is the release's (non-Haar) distribution.

    Returns:
      A rotation matrix.
    """
    if max_angle is None:
        q = jax.random.normal(key, (4,))
        q = q / jnp.linalg.norm(q)
        return quaternion_to_matrix(q)
    k_axis, k_angle = jax.random.split(key)
    if axis is None:
        axis = jax.random.normal(k_axis, (3,))
    axis = jnp.asarray(axis, dtype=jnp.float32)
    axis = axis / jnp.linalg.norm(axis)
    angle = jax.random.uniform(k_angle, (), minval=-max_angle, maxval=max_angle)
    return exp_map(angle * axis)


def in_plane_rotation(key: jax.Array, max_angle: float) -> Float[Array, "2 2"]:
    """Random 2D rotation, the top-left block of a rotation about the optical axis."""
    return random_rotation(key, max_angle, axis=jnp.array([0.0, 0.0, 1.0]))[:2, :2]


def quaternion_to_matrix(
    q: Float[np.ndarray | Array, "*B 4"],
) -> Float[np.ndarray | Array, "*B 3 3"]:
    """Unit quaternions ``(w, x, y, z)`` to rotation matrices; numpy in, numpy out (the
    data generators' cameras, ``data.rotations``), else jax (``random_rotation``)."""
    xp = np if isinstance(q, np.ndarray) else jnp
    w, x, y, z = (q[..., i] for i in range(4))
    rows = [
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ]
    return xp.stack([xp.stack(row, -1) for row in rows], -2)
