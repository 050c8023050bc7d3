"""Errors of the NRSfM literature, next to the release's MPJPE and stress (numpy only).

Glossary: M frames (views), N points; ``pred`` and ``gt`` are ``(M, N, 3)``; the optional
``mask (M, N)`` selects the points that count (all when absent). The metrics are
scale-dependent: no scale is fitted (the reconstructions of this package are in the input's
units).

Both metrics first centre every frame of ``pred`` and ``gt`` on its (masked) centroid, then
align ``pred`` to ``gt`` (``align``), by least squares over the points that count:

- ``"none"``: centring only;
- ``"flip"``: per frame, ``pred`` or its depth-negated copy, whichever is nearer (the
  depth ambiguity that the release's MPJPE protocol resolves per view);
- ``"sequence"``: one orthogonal matrix (a rotation, or a rotation and a mirror image) for
  all frames, as Akhter et al. align a reconstruction, which NRSfM recovers up to one
  global rotation and reflection;
- ``"frame"``: one orthogonal matrix per frame (shape error only, the pose ignored).

Definitions (``x_fp`` the centred ground-truth point p of frame f, ``x^_fp`` the aligned
reconstruction, P_f the points that count in frame f, F the frames):

- ``e3d`` (Akhter, Sheikh, Khan and Kanade, "Nonrigid structure from motion in trajectory
  space", NIPS 2008, and the PAMI 2011 version): the mean Euclidean point error divided by
  the ground truth's mean coordinate spread,
    e3D = (1 / sigma) * sum_fp |x^_fp - x_fp| / sum_f P_f,
    sigma = 1 / (3F) * sum_f (sigma_fx + sigma_fy + sigma_fz),
  with sigma_fc the standard deviation (1 / P_f normalisation) of coordinate c of the ground
  truth in frame f. Default alignment: ``"sequence"``.
- ``relative_error``: per frame, the relative Frobenius error
    e_f = ||X^_f - X_f||_F / ||X_f||_F,
  whose mean over frames is the "normalised mean 3D error" that NRSfM tables after Dai, Li
  and He ("A simple prior-free method for non-rigid structure-from-motion factorization",
  CVPR 2012) report. Default alignment: ``"sequence"``.
"""

import numpy as np

ALIGNMENTS = ("none", "flip", "sequence", "frame")


def _orthogonal(cross: np.ndarray) -> np.ndarray:
    """The orthogonal O (..., 3, 3), mirror images allowed, maximising tr(O^T cross), i.e.
    minimising sum |O a - b|^2 for cross = sum b a^T (orthogonal Procrustes)."""
    u, _, vt = np.linalg.svd(cross)
    return u @ vt


def _centre(x: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Each frame minus its masked centroid; points outside the mask set to 0."""
    count = np.maximum(mask.sum(1), 1.0)[:, None]
    mean = np.einsum("mn,mnc->mc", mask, x) / count
    return (x - mean[:, None]) * mask[..., None]


def _check(pred, gt, mask, align: str):
    """float64 arrays and a mask; one-line ValueErrors for shapes or names that do not fit."""
    pred, gt = np.asarray(pred, np.float64), np.asarray(gt, np.float64)
    if gt.ndim != 3 or gt.shape[-1] != 3 or pred.shape != gt.shape:
        raise ValueError(f"pred {pred.shape} and gt {gt.shape} must both be (M, N, 3)")
    mask = np.ones(gt.shape[:2]) if mask is None else np.asarray(mask, np.float64)
    if mask.shape != gt.shape[:2]:
        raise ValueError(f"mask has shape {mask.shape}, expected {gt.shape[:2]}")
    if align not in ALIGNMENTS:
        raise ValueError(f"unknown alignment {align!r}; expected one of {ALIGNMENTS}")
    return pred, gt, (mask > 0).astype(np.float64)


def aligned(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray | None = None,
            align: str = "sequence") -> tuple[np.ndarray, np.ndarray]:
    """``(pred, gt)`` centred per frame, and ``pred`` aligned to ``gt`` (module docstring);
    points outside the mask are set to 0 in both."""
    pred, gt, mask = _check(pred, gt, mask, align)
    pred, gt = _centre(pred, mask), _centre(gt, mask)
    if align == "flip":
        flipped = pred * np.array([1.0, 1.0, -1.0])
        nearer = ((flipped - gt) ** 2).sum((1, 2)) < ((pred - gt) ** 2).sum((1, 2))
        pred = np.where(nearer[:, None, None], flipped, pred)
    elif align == "sequence":
        pred = pred @ _orthogonal(np.einsum("mni,mnj->ij", gt, pred)).T
    elif align == "frame":
        rot = _orthogonal(np.einsum("mni,mnj->mij", gt, pred))
        pred = np.einsum("mij,mnj->mni", rot, pred)
    return pred, gt


def e3d(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray | None = None,
        align: str = "sequence") -> float:
    """Akhter et al.'s normalised mean 3D error (module docstring).

    Args:
      pred: (M, N, 3) reconstruction.
      gt: (M, N, 3) ground truth.
      mask: (M, N) points that count (default: all).
      align: one of ``ALIGNMENTS``.

    Returns:
      e3D, a float (0 for a perfect reconstruction).
    """
    mask = _check(pred, gt, mask, align)[2]
    pred, gt = aligned(pred, gt, mask, align)
    count = np.maximum(mask.sum(1), 1.0)
    # Coordinates are centred on the masked mean, so the std is sqrt(mean of squares).
    spread = np.sqrt(np.einsum("mn,mnc->mc", mask, gt**2) / count[:, None]).sum(1)
    sigma = spread.mean() / 3
    mean_error = (np.linalg.norm(pred - gt, axis=-1) * mask).sum() / max(mask.sum(), 1.0)
    return float(mean_error / max(sigma, np.finfo(np.float64).tiny))


def relative_error(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray | None = None,
                   align: str = "sequence") -> np.ndarray:
    """Per-frame relative Frobenius error ``||X^_f - X_f||_F / ||X_f||_F`` (module docstring).

    Args:
      pred: (M, N, 3) reconstruction.
      gt: (M, N, 3) ground truth.
      mask: (M, N) points that count (default: all).
      align: one of ``ALIGNMENTS``.

    Returns:
      (M,) errors; its mean is the normalised mean 3D error.
    """
    pred, gt = aligned(pred, gt, mask, align)
    norm = np.sqrt((gt**2).sum((1, 2)))
    return np.sqrt(((pred - gt) ** 2).sum((1, 2))) / np.maximum(norm, np.finfo(np.float64).tiny)


def scores(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray | None = None) -> dict:
    """e3D and the mean relative error under the protocol's per-view flip and under one
    alignment for the whole set, as a flat dict of floats."""
    out = {}
    for align in ("flip", "sequence"):
        out[f"e3d/{align}"] = e3d(pred, gt, mask, align)
        out[f"relative_error/{align}"] = float(relative_error(pred, gt, mask, align).mean())
    return out
