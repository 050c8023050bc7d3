"""Synthetic object categories (a PASCAL3D+ analogue), generated in code (numpy, seeded).

Several rigid object classes, each with its own keypoint set built from a few shape
parameters (length, width, height, ...) drawn per instance, so shapes vary within a
class as PASCAL3D+ cars or chairs do. As in PASCAL3D+, the classes' keypoints are
packed into one layout of N = sum of the classes' counts: each sample fills only its
class's block, ``class_mask`` (and ``kp_defined``) mark that block, and ``group`` /
``group_names`` name the class (the ``pascal3d`` evaluation protocol averages per class).
Views: upright cameras (any azimuth, elevation within ``max_elevation``), orthographic,
points hidden at random with probability ``occlusion`` (at least 3 stay visible).
Object frame: x right, y up, z forward, about unit size.
"""

import numpy as np

from c3dpo_jax.data.dataset import KeypointData
from c3dpo_jax.data.rotations import upright_rotations


def _box(length, width, height, y0=0.0):
    """(B, 8, 3) corners of boxes centred on the y axis, bottom at ``y0``."""
    signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (0, 1) for sz in (-1, 1)])
    size = np.stack([width / 2, height, length / 2], -1)[:, None]
    corners = signs * size
    corners[..., 1] += np.asarray(y0)[..., None] if np.ndim(y0) else y0
    return corners


def _car(p):
    length, width, height = p[:, 0] * 1.6 + 3.2, p[:, 1] * 0.3 + 1.6, p[:, 2] * 0.3 + 1.2
    body = _box(length, width, height * 0.55, 0.35 * height)
    wheels = np.stack([np.stack([sx * width / 2, 0.35 * height, sz * length * 0.32], -1)
                       for sx in (-1, 1) for sz in (-1, 1)], 1)
    return np.concatenate([body, wheels], 1) / 4.0  # 12 points


def _chair(p):
    seat, height, back = p[:, 0] * 0.1 + 0.45, p[:, 1] * 0.1 + 0.45, p[:, 2] * 0.2 + 0.5
    feet = _box(seat, seat, 0 * seat)[:, ::2]
    top = _box(seat, seat, 0 * seat, height)[:, ::2]
    backrest = np.stack([np.stack([sx * seat / 2, height + back, -seat / 2], -1)
                         for sx in (-1, 1)], 1)
    return np.concatenate([feet, top, backrest], 1)  # 10 points


def _aeroplane(p):
    length, span, fin = p[:, 0] * 0.3 + 1.0, p[:, 1] * 0.4 + 1.0, p[:, 2] * 0.1 + 0.25
    z = np.zeros_like(length)
    pts = [(z, z, length / 2), (z, z, -length / 2), (-span / 2, z, 0.05 * length),
           (span / 2, z, 0.05 * length), (-span / 5, z, -0.45 * length),
           (span / 5, z, -0.45 * length), (z, fin, -0.45 * length), (z, -0.08 + z, 0.1 * length)]
    return np.stack([np.stack(q, -1) for q in pts], 1)  # 8 points


def _bottle(p):
    height, radius, neck = p[:, 0] * 0.3 + 1.0, p[:, 1] * 0.05 + 0.2, p[:, 2] * 0.1 + 0.3
    z = np.zeros_like(height)
    pts = [(-radius, z, z), (radius, z, z), (z, z, radius), (-radius, height * (1 - neck), z),
           (radius, height * (1 - neck), z), (z, height, z), (z, height * (1 - neck), radius)]
    return np.stack([np.stack(q, -1) for q in pts], 1)  # 7 points


def _table(p):
    length, width, height = p[:, 0] * 0.4 + 1.4, p[:, 1] * 0.2 + 0.8, p[:, 2] * 0.1 + 0.75
    return np.concatenate([_box(length, width, 0 * height)[:, ::2],
                           _box(length, width, 0 * height, height)[:, ::2]], 1)  # 8 points


CLASSES = {"aeroplane": (_aeroplane, 8), "bottle": (_bottle, 7), "car": (_car, 12),
           "chair": (_chair, 10), "diningtable": (_table, 8)}


def make_split(
    n_samples: int,
    *,
    classes=tuple(CLASSES),
    variation: float | int = 1.0,
    occlusion: float | int = 0.1,
    noise: float | int = 0.0,
    max_elevation: float | int = 0.6,
    seed: int = 0,
) -> KeypointData:
    """``n_samples`` views, classes drawn uniformly; keypoints packed class after class."""
    rng = np.random.default_rng(seed)
    counts = np.array([CLASSES[c][1] for c in classes])
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    n = int(counts.sum())
    cls = rng.integers(len(classes), size=n_samples)
    shapes = np.zeros((n_samples, n, 3))
    mask = np.zeros((n_samples, n), np.float32)
    for c, name in enumerate(classes):
        rows = np.flatnonzero(cls == c)
        params = variation * rng.uniform(-1, 1, size=(len(rows), 3))
        pts = CLASSES[name][0](params)
        pts = pts - pts.mean(1, keepdims=True)
        block = slice(starts[c], starts[c] + counts[c])
        shapes[rows, block] = pts + 0.01 * variation * rng.normal(size=pts.shape)
        mask[rows, block] = 1.0
    rots = upright_rotations(rng, n_samples, max_elevation)
    kp3d = np.einsum("mij,mnj->mni", rots, shapes) * mask[..., None]
    vis = mask * (rng.uniform(size=mask.shape) >= occlusion)
    # At least three visible points of the sample's own class.
    order = np.argsort(rng.uniform(size=mask.shape) - 2 * mask, axis=1)[:, :3]
    np.put_along_axis(vis, order, 1.0, axis=1)
    kp = (kp3d[..., :2] + noise * rng.normal(size=(n_samples, n, 2))) * vis[..., None]
    return KeypointData(
        kp=kp.astype(np.float32), vis=vis.astype(np.float32), kp3d=kp3d.astype(np.float32),
        class_mask=mask, kp_defined=mask.copy(), group=cls.astype(np.int32),
        group_names=tuple(classes), name="categories")


def make_splits(
    n_train: int = 5000,
    n_test: int = 1000,
    classes=tuple(CLASSES),
    variation: float | int = 1.0,
    occlusion: float | int = 0.1,
    noise: float | int = 0.0,
    max_elevation: float | int = 0.6,
    seed: int = 0,
) -> tuple[KeypointData, KeypointData]:
    """Train and test splits (different instances and views); reproducible from ``seed``."""
    common = dict(classes=tuple(classes), variation=variation, occlusion=occlusion,
                  noise=noise, max_elevation=max_elevation)
    return (make_split(n_train, seed=seed * 2 + 1, **common),
            make_split(n_test, seed=seed * 2 + 2, **common))


def n_keypoints(classes=tuple(CLASSES)) -> int:
    """Size of the packed layout for ``classes``."""
    return int(sum(CLASSES[c][1] for c in classes))
