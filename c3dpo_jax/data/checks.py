"""Checks of the entries of a keypoint data file, each problem named by entry and field.

Shapes: M entries, N keypoints, C coordinates (2 in ``kp_loc``, 3 in ``kp_loc_3d``).

``Problems`` collects one message per entry (the first found); ``raise_or_drop`` turns
them into one ``ValueError`` line or drops and logs those entries. The checks: a
missing required field (``check_required``), a ragged, non-numeric or misshaped list
(``stack``), a keypoint count N that differs from the file's (``n_keypoints``), NaN/inf
(``check_finite``; in ``kp_loc`` at visible points only: ``check_keypoints``), a
visibility not in {0, 1} or fewer than ``min_visible`` visible points
(``check_keypoints``), and coordinates far outside the file's other points
(``check_magnitude``): more than ``OUTLIER_FACTOR`` times the file's typical distance of
a point from its entry's median point, coordinate-wise, or beyond ``MAX_ABS`` (a corrupt
value, which float32 squares would overflow). Numpy only.
"""

import collections

import numpy as np
from absl import logging

_MAX_LISTED = 5
OUTLIER_FACTOR = 1e4
MAX_ABS = 1e12


class Problems:
    """Per-entry problems, in entry order; the first one per entry is kept."""

    def __init__(self):
        self.by_entry: dict[int, str] = {}

    def add(self, i, message: str) -> None:
        self.by_entry.setdefault(int(i), f"entry {int(i)}: {message}")

    def raise_or_drop(self, n_entries: int, drop_invalid: bool, label: str) -> np.ndarray:
        """Indices of the entries to keep (raises unless ``drop_invalid``)."""
        if not self.by_entry:
            return np.arange(n_entries)
        msgs = [self.by_entry[i] for i in sorted(self.by_entry)]
        if not drop_invalid:
            more = len(msgs) - _MAX_LISTED
            tail = f"; ... and {more} more" if more > 0 else ""
            raise ValueError(
                f"{label}: {len(msgs)} invalid of {n_entries} entries: "
                + "; ".join(msgs[:_MAX_LISTED]) + tail
                + " (fix them, or drop them: json_dataset.load(..., drop_invalid=True); "
                "in training, --config.data.drop_invalid=True)"
            )
        logging.warning("%s: dropped %d of %d invalid entries; first: %s",
                        label, len(msgs), n_entries, msgs[0])
        keep = np.ones(n_entries, bool)
        keep[sorted(self.by_entry)] = False
        return np.flatnonzero(keep)


_NUMBERS = "biuf"  # JSON numbers and booleans (0 / 1), not strings or null


def _null_as_nan(value):
    """Nested lists with JSON null (None) read as NaN; anything else but numbers raises."""
    if isinstance(value, list):
        return [_null_as_nan(v) for v in value]
    if value is None:
        return np.nan
    if isinstance(value, bool | int | float):
        return value
    raise TypeError(type(value).__name__)


def stack(entries, field: str, shape: tuple, problems: Problems, *, null: bool = False,
          dtype=np.float32) -> np.ndarray:
    """(M, *shape) of ``dtype``; ragged, non-numeric (strings; null unless ``null``: then it
    reads as NaN, which the caller's checks judge by point) or misshaped entries become
    problems (NaN)."""
    try:  # Fast path: one conversion for the whole file.
        arr = np.asarray([e[field] for e in entries])
        if arr.dtype.kind in _NUMBERS and arr.shape[1:] == shape:
            return arr.astype(dtype)
    except (ValueError, TypeError):
        pass
    out = np.full((len(entries), *shape), np.nan, dtype)
    for i, e in enumerate(entries):
        try:
            value = np.asarray(_null_as_nan(e[field]) if null else e[field])
            if value.dtype.kind not in _NUMBERS:
                raise TypeError(value.dtype)
        except (ValueError, TypeError):
            problems.add(i, f"field {field!r} is a ragged or non-numeric list")
            continue
        if value.shape != shape:
            problems.add(i, f"field {field!r} has shape {value.shape}, expected {shape}")
            continue
        out[i] = value
    return out


def check_finite(i_bad: np.ndarray, field: str, problems: Problems) -> None:
    """Each entry index in ``i_bad`` is a problem: ``field`` holds NaN or inf."""
    for i in i_bad:
        problems.add(i, f"field {field!r} contains NaN or inf")


def _masked_median(x: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Median over axis 1 of ``x (M, N, ...)`` where ``mask (M, N)``; NaN for none."""
    m = mask.reshape(mask.shape + (1,) * (x.ndim - 2))
    srt = np.sort(np.where(m, x, np.inf), axis=1)  # selected values first
    count = np.broadcast_to(m.sum(1, keepdims=True), srt[:, :1].shape)
    lo = np.take_along_axis(srt, np.maximum(count - 1, 0) // 2, axis=1)
    hi = np.take_along_axis(srt, count // 2, axis=1)  # count < N unless all are selected
    with np.errstate(invalid="ignore"):
        return np.where(count > 0, (lo + hi) / 2, np.nan)[:, 0]


def check_magnitude(points: np.ndarray, mask: np.ndarray, field: str, what: str,
                     problems: Problems) -> None:
    """Coordinates of ``points (M, N, C)`` at ``mask (M, N)`` that lie more than
    ``OUTLIER_FACTOR`` times the file's typical point-to-median distance from their
    entry's median point (coordinate-wise), or beyond ``MAX_ABS``, are problems."""
    if points.size == 0:  # no entry holds a point: nothing to compare
        return
    mask = mask & np.isfinite(points).all(-1)
    pts = points.astype(np.float64)
    with np.errstate(invalid="ignore", over="ignore"):
        dist = np.abs(pts - _masked_median(pts, mask)[:, None]).max(-1)
        typical = _masked_median(dist, mask)
    typical = typical[np.isfinite(typical) & (typical > 0)]
    scale = float(np.median(typical)) if typical.size else np.inf
    bad = mask & ((np.abs(pts).max(-1) > MAX_ABS) | (dist > OUTLIER_FACTOR * scale))
    if not bad.any():
        return
    # Named per entry: the flagged point farthest from the file's median point (with two
    # visible points both lie far from their entry's median).
    centre = np.median(pts[mask], axis=0)
    with np.errstate(invalid="ignore", over="ignore"):
        far = np.where(bad, np.abs(pts - centre).max(-1), -1.0)
    for i in np.flatnonzero(bad.any(1)):
        k = int(np.argmax(far[i]))
        value = pts[i, k][np.argmax(np.abs(pts[i, k]))]
        problems.add(i, f"field {field!r} has {value:.3g} at {what} {k}, far outside the "
                        f"file's other points (typical distance from an entry's median point: "
                        f"{scale:.3g}; limit {OUTLIER_FACTOR:g} times that or {MAX_ABS:g})")


def n_keypoints(entries, problems: Problems) -> int:
    """The most common length of ``kp_vis``; entries with another length are problems."""
    lengths = [len(e["kp_vis"]) if isinstance(e.get("kp_vis"), list) else -1 for e in entries]
    n = collections.Counter(x for x in lengths if x >= 0).most_common(1)
    n = n[0][0] if n else 0
    for i, length in enumerate(lengths):
        if length != n:
            what = "is not a list" if length < 0 else f"has {length} keypoints"
            problems.add(i, f"field 'kp_vis' {what} but the dataset has {n} keypoints "
                            "(K must be the same in every entry)")
    return n


def check_required(entries, problems: Problems) -> None:
    """Entries that are not objects, or lack ``kp_loc`` or ``kp_vis``, are problems."""
    for i, e in enumerate(entries):
        if not isinstance(e, dict):
            problems.add(i, f"is a {type(e).__name__}, not an object with 'kp_loc' and 'kp_vis'")
            continue
        for field in ("kp_loc", "kp_vis"):
            if field not in e:
                problems.add(i, f"required field {field!r} is missing")


def check_keypoints(kp: np.ndarray, vis: np.ndarray, min_visible: int, problems: Problems
                    ) -> None:
    """``kp_loc`` as ``kp (M, N, 2)`` and ``kp_vis`` as ``vis (M, N)``: visible points
    finite and not far outside the file's others (``check_magnitude``; hidden points are
    not looked at), visibilities 0 or 1, at least ``min_visible`` visible points."""
    for i, k in zip(*np.nonzero((vis != 0) & ~np.isfinite(kp).all(-1)), strict=True):
        problems.add(i, f"field 'kp_loc' contains NaN or inf at visible point {k} (or null)")
    check_magnitude(kp, vis == 1, "kp_loc", "visible point", problems)
    bad_vis = ~((vis == 0) | (vis == 1))  # NaN too (a list that stack refused is named)
    for i, k in zip(*np.nonzero(bad_vis), strict=True):
        problems.add(i, f"field 'kp_vis' has value {vis[i, k]:g} at point {k} (must be 0 or 1)")
    counts = np.nansum(vis, axis=1)
    for i in np.flatnonzero(counts < min_visible):
        problems.add(i, f"field 'kp_vis' has {int(counts[i])} visible points, fewer than "
                        f"min_visible={min_visible}")
