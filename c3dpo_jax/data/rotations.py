"""Rotation matrices in numpy for the data generators and importers (seeded, no jax).

Glossary: M samples. The convention is ``so3``'s: rotations act on column vectors,
``x_cam = R @ x``, so row-stored points ``(N, 3)`` turn as ``X @ R.T``; y is up for
upright objects (people, furniture) and the camera looks along z.

- ``axis_rotation(axis, angle)``: about x, y or z, counter-clockwise (right-hand rule).
- ``random_rotations(rng, m)``: uniform (Haar) on SO(3), through normalised Gaussian
  quaternions (``so3.quaternion_to_matrix``, the formula the training loss uses).
- ``upright_rotations(rng, m, max_elevation)``: cameras around an upright object.
"""

import numpy as np

from c3dpo_jax.so3 import quaternion_to_matrix


def axis_rotation(axis: str, angle) -> np.ndarray:
    """Rotations ``(..., 3, 3)`` by ``angle`` (radians, any shape ``(...)``) about the
    coordinate axis ``"x"``, ``"y"`` or ``"z"`` (either case)."""
    c, s = np.cos(angle), np.sin(angle)
    one, zero = np.ones_like(c), np.zeros_like(c)
    rows = {"x": [[one, zero, zero], [zero, c, -s], [zero, s, c]],
            "y": [[c, zero, s], [zero, one, zero], [-s, zero, c]],
            "z": [[c, -s, zero], [s, c, zero], [zero, zero, one]]}[axis.lower()]
    return np.stack([np.stack(row, -1) for row in rows], -2)


def random_rotations(rng: np.random.Generator, m: int) -> np.ndarray:
    """(m, 3, 3) rotations, uniform on SO(3) (normalised Gaussian quaternions)."""
    q = rng.normal(size=(m, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return quaternion_to_matrix(q)


def upright_rotations(rng: np.random.Generator, m: int, max_elevation: float) -> np.ndarray:
    """(m, 3, 3) cameras looking at an upright object (y up) from any azimuth:
    ``R = Rz(roll) Rx(elevation) Ry(azimuth)``.

    Azimuth uniform in [-pi, pi), elevation uniform in +-max_elevation and roll in half
    of that, like the cameras around a standing person (Human3.6M) or the release's
    up3d views.
    """
    yaw = rng.uniform(-np.pi, np.pi, m)
    pitch = rng.uniform(-max_elevation, max_elevation, m)
    roll = rng.uniform(-max_elevation, max_elevation, m) / 2
    ry, rx, rz = axis_rotation("y", yaw), axis_rotation("x", pitch), axis_rotation("z", roll)
    return np.einsum("mij,mjk,mkl->mil", rz, rx, ry)
