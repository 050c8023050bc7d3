"""Evaluation protocol of the release: MPJPE (orig / depth-flipped / best) and stress.

Glossary: M samples, N keypoints; ``pred`` and ``gt`` are ``(M, N, 3)`` in the
camera frame; ``mask (M, N)`` selects the points that count. numpy only.

Protocols (``protocol`` argument):
- ``"default"`` / ``"up3d"``: mean depth of pred and gt set to 0, plain averages.
- ``"h36m"``: pred and gt made relative to joint 0, errors times ``scale``, averaged
  per action (``group``) first, then over actions.
- ``"pascal3d"``: masked mean depth set to 0, averaged per class (``group``) first, then
  over classes.
In every protocol only the points that ``class_mask`` and ``kp_defined`` keep (where the
data has them) count.
Paper Sec. 4.2: MPJPE is evaluated for the prediction and its depth-flipped copy and
the better of the two is kept (per sample); stress is invariant to the flip.
"""

import math

import numpy as np
from scipy.spatial.distance import pdist

from c3dpo_jax import baselines
from c3dpo_jax.data.dataset import KeypointData


def _masked_mean(x: np.ndarray, mask: np.ndarray, axis: int) -> np.ndarray:
    return (x * mask).sum(axis) / np.maximum(mask.sum(axis), 1e-9)


def center_depth(x: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Subtracts the (masked) mean depth of each sample."""
    depth = _masked_mean(x[..., 2], mask, axis=1)
    return x - np.stack([np.zeros_like(depth), np.zeros_like(depth), depth], -1)[:, None, :]


def mpjpe(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray) -> dict[str, np.ndarray]:
    """Per-sample MPJPE of ``pred``, of ``pred`` with depth negated, and their min."""
    flipped = pred * np.array([1.0, 1.0, -1.0])
    orig = _masked_mean(np.linalg.norm(pred - gt, axis=-1), mask, axis=1)
    flip = _masked_mean(np.linalg.norm(flipped - gt, axis=-1), mask, axis=1)
    return {"mpjpe_orig": orig, "mpjpe_flip": flip, "mpjpe": np.minimum(orig, flip)}


def stress(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Per-sample mean over pairs i < j of points that ``mask`` keeps (0/1, both 1) of
    | ||X_i - X_j|| - ||X*_i - X*_j|| |; 0 for a sample with fewer than two kept points.

    One sample at a time with scipy's ``pdist`` (compiled pair distances): dense points
    have N(N-1)/2 pairs per sample, and building them for blocks of samples with numpy
    took ~25x longer at 2,017 points (all samples at once would not fit in memory)."""
    out = np.zeros(len(pred))
    keep_all = (mask > 0).all(1)
    for s, every in enumerate(keep_all):
        keep = slice(None) if every else mask[s] > 0
        x, y = pred[s, keep], gt[s, keep]
        if len(x) >= 2:
            out[s] = np.abs(pdist(x) - pdist(y)).mean()
    return out


def _aggregate(per_sample: np.ndarray, data: KeypointData) -> tuple[float, dict]:
    """Mean over groups of per-group means (plain mean when there are no groups)."""
    if data.group is None or not data.group_names:
        return float(per_sample.mean()), {}
    per_group = {
        name: float(per_sample[data.group == g].mean())
        for g, name in enumerate(data.group_names)
        if np.any(data.group == g)
    }
    return float(np.mean(list(per_group.values()))), per_group


def evaluate(pred: np.ndarray, data: KeypointData, protocol: str = "default") -> dict:
    """Scores predictions ``pred (M, N, 3)`` against ``data.kp3d`` under ``protocol``.

    Returns:
      ``{"mpjpe", "mpjpe_global", "mpjpe_orig", "mpjpe_flip", "stress", "n_samples",
      "per_group"}`` where ``mpjpe`` is the flip-resolved MPJPE (the paper's protocol: per
      view the better of the prediction and its depth mirror image), ``mpjpe_orig`` the
      prediction's as it is, ``mpjpe_flip`` that of every view mirrored, and
      ``mpjpe_global`` the lower of those two: what a user gets, up to one mirror flip of the
      whole split.
    """
    if data.kp3d is None:
        raise ValueError("this split has no 3D ground truth (kp_loc_3d); cannot compute MPJPE")
    pred = np.asarray(pred, np.float64)
    gt = data.kp3d.astype(np.float64)
    mask = np.ones(gt.shape[:2])  # points outside the class or without ground truth: none
    for extra in (data.class_mask, data.kp_defined):
        if extra is not None:
            mask = mask * extra
    if protocol == "h36m":
        pred, gt = pred - pred[:, :1], gt - gt[:, :1]
        scale = data.scale if data.scale is not None else np.ones(len(data))
    elif protocol in ("default", "up3d", "pascal3d"):
        pred, gt = center_depth(pred, mask), center_depth(gt, mask)
        scale = np.ones(len(data))
    else:
        raise ValueError(f"unknown evaluation protocol {protocol!r}")
    errors = {k: v * scale for k, v in mpjpe(pred, gt, mask).items()}
    errors["stress"] = stress(pred, gt, mask) * scale
    out = {"n_samples": len(data)}
    for key, values in errors.items():
        out[key], per_group = _aggregate(values, data)
        if key == "mpjpe" and per_group:
            out["per_group"] = per_group
    # What a user gets up to one bit: the prediction as it is or every view mirrored.
    out["mpjpe_global"] = min(out["mpjpe_orig"], out["mpjpe_flip"])
    return out


def mpjpe_by_visibility(pred: np.ndarray, data: KeypointData) -> dict:
    """Mean point error of the visible and of the hidden points, pooled over samples.

    As the ``default``/``up3d`` protocol: mean depth removed over all points, and per
    sample the prediction or its depth flip, whichever has the lower MPJPE over all
    points. ``{}`` when no point is hidden. A diagnostic for occluded data: are the
    errors in what was seen or in what was guessed?
    """
    if data.kp3d is None:
        raise ValueError("this split has no 3D ground truth (kp_loc_3d); cannot compute MPJPE")
    hidden = data.vis < 0.5
    if not hidden.any():
        return {}
    every = np.ones(hidden.shape)
    pred = center_depth(np.asarray(pred, np.float64), every)
    gt = center_depth(data.kp3d.astype(np.float64), every)
    per_sample = mpjpe(pred, gt, every)
    flip = per_sample["mpjpe_flip"] < per_sample["mpjpe_orig"]
    pred = np.where(flip[:, None, None], pred * np.array([1.0, 1.0, -1.0]), pred)
    err = np.linalg.norm(pred - gt, axis=-1)
    out = {"mpjpe_hidden": float(err[hidden].mean())}
    if (~hidden).any():
        out["mpjpe_visible"] = float(err[~hidden].mean())
    return out


def reprojection_error(kp_reprojected: np.ndarray, data: KeypointData) -> float:
    """Mean 2D distance between reprojected and input visible points (input units).

    The only score for 2D-only data (e.g. CUB birds, COCO imports).
    """
    dist = np.linalg.norm(np.asarray(kp_reprojected, np.float64) - data.kp, axis=-1)
    return float((dist * data.vis).sum() / max(data.vis.sum(), 1.0))


def mirrored_fraction(shape_canonical: np.ndarray, max_samples: int = 5000) -> float:
    """Fraction of views whose canonical shape is, up to a rotation, closer to the mirror
    image of the views' mean shape than to the mean shape itself. Needs no 3D ground truth.

    A view and its depth mirror image fit the same 2D points; a model that gives every view
    one handedness scores 0, one that tosses a coin per view about 0.5 (shapes with a mirror
    symmetry score near 0.5 whatever the model does). On human bodies a coin toss signals a
    degenerate factorisation (evidence: experiments/dev_suite/diagnostics.md).
    ``shape_canonical (M, N, 3)``; the first ``max_samples`` count.
    """
    x = np.asarray(shape_canonical[:max_samples], np.float64)
    x = x - x.mean(1, keepdims=True)
    mean = baselines.procrustes_mean_shape(x, max_samples=max_samples)

    def fit(shapes):  # RMS distance to the mean after the best proper rotation
        rot = baselines.kabsch(shapes, mean)
        return np.sqrt(((np.einsum("mij,mnj->mni", rot, shapes) - mean) ** 2).sum(-1).mean(-1))

    return float(np.mean(fit(x * np.array([1.0, 1.0, -1.0])) < fit(x)))


# The scores a results table shows, in its column order.
TABLE_KEYS = ("mpjpe_global", "mpjpe", "mpjpe_orig", "stress", "reprojection", "mirrored")


def format_table(rows: dict[str, dict], keys=TABLE_KEYS) -> str:
    """Plain-text table: one row per method, one column per metric ("-" where absent).

    Four decimals, or four significant digits in exponent form for values that four
    decimals would show as 0.0000 or that would not fit the column (data in other units)."""
    keys = [k for k in keys if any(k in res for res in rows.values())]
    width = max(len(name) for name in [*rows, "method"]) + 2

    def cell(value) -> str:
        value = float(value)
        plain = 1e-3 <= abs(value) < 1e6 or value == 0 or not math.isfinite(value)
        return f"{value:13.4f}" if plain else f"{value:13.3e}"

    lines = ["method".ljust(width) + "".join(k.rjust(13) for k in keys)]
    for name, res in rows.items():
        cells = [cell(res[k]) if k in res else "-".rjust(13) for k in keys]
        lines.append(name.ljust(width) + "".join(cells))
    return "\n".join(lines)
