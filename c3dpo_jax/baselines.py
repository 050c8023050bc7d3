"""Trivial 3D-lifting baselines that any learned NRSfM method must beat (numpy only).

Glossary: M samples, N keypoints. ``mean_shape (N, 3)`` is the Procrustes mean of the
training ground truth. Baselines produce ``(M, N, 3)`` predictions in the input's
units, scored with the same protocol as the model:

- ``fitted mean shape``: the mean training shape rigidly fitted (scaled orthographic
  camera, least squares on the visible points) to each view; observed x, y are kept
  for visible points and the depth is the fitted shape's.
- ``zero depth``: the same x, y with depth 0 (what a method learns if it learns nothing).
- ``oracle mean shape`` (``oracle_mean_shape``, needs the test split's 3D ground truth):
  the mean shape rotated and translated onto each ground-truth shape (best rotation,
  Kabsch); its error is the part of the shapes that no rigid model explains.
"""

import numpy as np


def _kabsch(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """(M, 3, 3) rotations minimising ||R src_m - dst_m||, no reflections.

    ``src`` is (M, N, 3); ``dst`` is (N, 3) or (M, N, 3)."""
    h = np.einsum("mni,mnj->mij", src, np.broadcast_to(dst, src.shape))
    u, _, vt = np.linalg.svd(h)
    d = np.sign(np.linalg.det(np.einsum("mij,mjk->mik", u, vt)))
    u[:, :, 2] *= d[:, None]
    return np.einsum("mij,mjk->mki", u, vt)


def procrustes_mean_shape(kp3d: np.ndarray, iters: int = 5, max_samples: int = 5000) -> np.ndarray:
    """Mean of the shapes after rotating each onto a common reference (GPA)."""
    x = kp3d[:max_samples].astype(np.float64)
    x = x - x.mean(1, keepdims=True)
    ref = x[0]
    for _ in range(iters):
        rot = _kabsch(x, ref)
        aligned = np.einsum("mij,mnj->mni", rot, x)
        ref = aligned.mean(0)
    return ref


def fit_mean_shape(mean_shape: np.ndarray, kp: np.ndarray, vis: np.ndarray) -> np.ndarray:
    """Fits ``s R2 S + t`` to the visible points of each view; returns 3D predictions."""
    w = vis.astype(np.float64)
    count = np.maximum(w.sum(1), 1.0)[:, None]
    kp_mean = (kp * w[..., None]).sum(1) / count
    s_mean = np.einsum("mn,nc->mc", w, mean_shape) / count
    y = (kp - kp_mean[:, None]) * w[..., None]
    s = (mean_shape[None] - s_mean[:, None]) * w[..., None]
    # Least-squares 2x3 camera per view, then the nearest scaled orthonormal rows.
    sts = np.einsum("mni,mnj->mij", s, s) + 1e-9 * np.eye(3)
    yts = np.einsum("mni,mnj->mij", y, s)
    cam = np.einsum("mij,mjk->mik", yts, np.linalg.inv(sts))
    u, sig, vt = np.linalg.svd(cam, full_matrices=False)
    rows = np.einsum("mij,mjk->mik", u, vt)
    scale = sig.mean(1)
    axis = np.cross(rows[:, 0], rows[:, 1])
    centred = mean_shape[None] - s_mean[:, None]
    xy = scale[:, None, None] * np.einsum("mij,mnj->mni", rows, centred) + kp_mean[:, None]
    xy = np.where(w[..., None] > 0, kp, xy)
    depth = scale[:, None] * np.einsum("mnj,mj->mn", centred, axis)
    return np.concatenate([xy, depth[..., None]], axis=-1)


def oracle_mean_shape(mean_shape: np.ndarray, kp3d: np.ndarray, vis: np.ndarray) -> np.ndarray:
    """The mean shape under each sample's best rotation onto ``kp3d`` (visible points)."""
    w = vis.astype(np.float64)[..., None]
    count = np.maximum(w.sum(1, keepdims=True), 1.0)
    gt_mean = (kp3d * w).sum(1, keepdims=True) / count
    src_mean = (mean_shape[None] * w).sum(1, keepdims=True) / count
    src = (mean_shape[None] - src_mean) * w
    dst = (kp3d - gt_mean) * w
    rot = _kabsch(src, dst)
    return np.einsum("mij,mnj->mni", rot, mean_shape[None] - src_mean) + gt_mean


def predict(mean_shape: np.ndarray, kp: np.ndarray, vis: np.ndarray) -> dict[str, np.ndarray]:
    """Predictions of every baseline, by name."""
    fitted = fit_mean_shape(mean_shape, kp, vis)
    return {"fitted mean shape": fitted, "zero depth": fitted * np.array([1.0, 1.0, 0.0])}
