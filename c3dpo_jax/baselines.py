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
- ``fitted PCA basis`` (``pca_shape_basis`` + ``fit_shape_basis``, needs the training
  split's 3D ground truth): the probabilistic PCA of the aligned training shapes with
  C3DPO's basis size, its coefficients and camera fitted to each view's visible points
  (MAP under the PCA's Gaussian prior); observed x, y kept. A linear shape model learnt
  *with* 3D supervision and fitted per view by optimisation: a reference for what C3DPO's
  linear basis could reach, not a baseline it is expected to beat.
"""

from typing import NamedTuple

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


def _lift(shapes: np.ndarray, kp: np.ndarray, vis: np.ndarray, n_iters: int = 0,
          refit=None) -> np.ndarray:
    """Fits ``s R2 S_m + t`` to the visible points of each view; returns 3D predictions.

    ``shapes`` is (N, 3) or (M, N, 3). ``refit(proj)``, if given, is called ``n_iters``
    times with the current per-view scaled 2x3 projections (M, 2, 3) and returns new
    (M, N, 3) shapes (alternation between camera and shape)."""
    w = vis.astype(np.float64)
    shapes = np.broadcast_to(shapes, kp.shape[:2] + (3,))
    for it in range(n_iters + 1):
        scale, rows, centred, kp_mean = fit_camera(shapes, kp, vis)
        if it < n_iters:
            shapes = refit(scale[:, None, None] * rows)
    axis = np.cross(rows[:, 0], rows[:, 1])
    xy = scale[:, None, None] * np.einsum("mij,mnj->mni", rows, centred) + kp_mean[:, None]
    xy = np.where(w[..., None] > 0, kp, xy)
    depth = scale[:, None] * np.einsum("mnj,mj->mn", centred, axis)
    return np.concatenate([xy, depth[..., None]], axis=-1)


def visible_mean(x: np.ndarray, vis: np.ndarray) -> np.ndarray:
    """(..., M, C) mean of each view's visible points of ``x`` (..., M, N, C); views with no
    visible point get 0."""
    w = np.asarray(vis, np.float64)
    return np.einsum("mn,...mnc->...mc", w, x) / np.maximum(w.sum(1), 1.0)[:, None]


def fit_camera(shapes: np.ndarray, kp: np.ndarray, vis: np.ndarray):
    """The scaled orthographic camera of each view: least-squares 2x3 projection of the
    shapes' visible points onto ``kp``, then the nearest scaled orthonormal rows.

    ``shapes`` is (N, 3) or (M, N, 3). Returns ``(scale (M,), rows (M, 2, 3), centred
    shapes (M, N, 3), kp_mean (M, 2))``: the projection of point n of view m is
    ``scale[m] * rows[m] @ centred[m, n] + kp_mean[m]`` (both means over visible points)."""
    w = vis.astype(np.float64)
    kp_mean = visible_mean(kp, w)
    y = (kp - kp_mean[:, None]) * w[..., None]
    shapes = np.broadcast_to(shapes, kp.shape[:2] + (3,))
    centred = shapes - visible_mean(shapes, w)[:, None]
    s = centred * w[..., None]
    sts = np.einsum("mni,mnj->mij", s, s) + 1e-9 * np.eye(3)
    yts = np.einsum("mni,mnj->mij", y, s)
    cam = np.einsum("mij,mjk->mik", yts, np.linalg.inv(sts))
    u, sig, vt = np.linalg.svd(cam, full_matrices=False)
    return sig.mean(1), np.einsum("mij,mjk->mik", u, vt), centred, kp_mean


def fit_mean_shape(mean_shape: np.ndarray, kp: np.ndarray, vis: np.ndarray) -> np.ndarray:
    """Fits ``s R2 S + t`` to the visible points of each view; returns 3D predictions.

    ``mean_shape`` is one shape (N, 3) for every view, or one per view (M, N, 3)."""
    return _lift(mean_shape, kp, vis)


class ShapeBasis(NamedTuple):
    """Probabilistic PCA of aligned 3D shapes: ``S = mean + sum_d a_d basis_d + noise``,
    ``a_d ~ N(0, variances_d)``, noise ~ N(0, noise_var) per coordinate."""

    mean: np.ndarray  # (N, 3)
    basis: np.ndarray  # (D, N, 3), orthonormal when flattened
    variances: np.ndarray  # (D,)
    noise_var: float


def pca_shape_basis(kp3d: np.ndarray, n_basis: int, max_samples: int = 5000) -> ShapeBasis:
    """PPCA (Tipping and Bishop's maximum-likelihood solution) of the training shapes,
    each rotated onto their Procrustes mean."""
    mean = procrustes_mean_shape(kp3d, max_samples=max_samples)
    x = kp3d[:max_samples].astype(np.float64)
    x = x - x.mean(1, keepdims=True)
    aligned = np.einsum("mij,mnj->mni", _kabsch(x, mean), x)
    dev = (aligned - mean).reshape(len(x), -1)
    _, sing, vt = np.linalg.svd(dev, full_matrices=False)
    eig = np.zeros(dev.shape[1])
    eig[: len(sing)] = sing**2 / len(x)
    n_basis = min(n_basis, len(sing) - 1, dev.shape[1] - 1)  # fewer shapes than D: fewer
    noise_var = max(float(eig[n_basis:].mean()), 1e-12)
    basis = vt[:n_basis].reshape(n_basis, *mean.shape)
    return ShapeBasis(mean, basis, np.maximum(eig[:n_basis], 1e-12), noise_var)


def fit_shape_basis(model: ShapeBasis, kp: np.ndarray, vis: np.ndarray, n_iters: int = 20,
                    chunk: int = 1024) -> np.ndarray:
    """The PPCA shape model fitted to each view (MAP coefficients under the Gaussian prior,
    alternating with the scaled orthographic camera of ``fit_mean_shape``, which is the
    zero-coefficient start); observed x, y kept, depth from the fitted shape. Views are
    processed ``chunk`` at a time (the per-view design matrices are (N * 2, D))."""
    if len(model.basis) == 0:
        return _lift(model.mean, kp, vis)
    if len(kp) > chunk:
        return np.concatenate([
            fit_shape_basis(model, kp[i:i + chunk], vis[i:i + chunk], n_iters, chunk)
            for i in range(0, len(kp), chunk)])
    w = vis.astype(np.float64)

    def centre(x):  # (..., M, N, C): minus each view's visible-point mean, hidden points 0
        return (x - visible_mean(x, w)[..., None, :]) * w[..., None]

    m_c = centre(np.broadcast_to(model.mean, kp.shape[:2] + (3,)))
    b_c = centre(np.broadcast_to(model.basis[:, None], (len(model.basis),) + m_c.shape))
    y = centre(kp)
    prior = model.noise_var / model.variances  # ridge per coefficient, in shape units

    def refit(proj):
        # Residual of the projected mean shape, linear in the coefficients; the image-space
        # ridge is the shape-space one times the camera scale squared.
        a_mat = np.einsum("mij,dmnj->mnid", proj, b_c).reshape(len(kp), -1, len(model.basis))
        r = (y - np.einsum("mij,mnj->mni", proj, m_c)).reshape(len(kp), -1)
        scale2 = (np.linalg.norm(proj, axis=(1, 2)) ** 2 / 2)[:, None, None]
        ata = np.einsum("mkd,mke->mde", a_mat, a_mat) + scale2 * np.diag(prior)
        coef = np.linalg.solve(ata, np.einsum("mkd,mk->md", a_mat, r)[..., None])[..., 0]
        return model.mean + np.einsum("md,dnc->mnc", coef, model.basis)

    return _lift(model.mean, kp, vis, n_iters, refit)


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
