"""``KeypointData``: one split of a dataset as arrays (``splits.load_splits`` makes them
from a config).

Glossary: M samples, N keypoints. Keypoints ``kp (M, N, 2)``, visibility
``vis (M, N)`` in {0, 1}, optional 3D ground truth ``kp3d (M, N, 3)`` in the camera
frame, optional ``class_mask (M, N)``, ``kp_defined (M, N)``, ``intrinsics (M, 3, 3)``,
``scale (M,)`` (h36m's metric scale), ``group (M,)`` integer ids with
``group_names`` (actions for h36m, classes for multi-class data) used by the
evaluation protocol, ``image_path (M,)`` strings when the source names images, and
``frame (M,)`` integer ids when several views show one pose at one instant (cameras filming
together; views with equal ids are that pose's views, ``loss.w_multiview`` links them).
"""

import dataclasses
import hashlib

import numpy as np
from absl import logging


@dataclasses.dataclass(frozen=True)
class KeypointData:
    kp: np.ndarray
    vis: np.ndarray
    kp3d: np.ndarray | None = None
    class_mask: np.ndarray | None = None
    kp_defined: np.ndarray | None = None
    intrinsics: np.ndarray | None = None
    scale: np.ndarray | None = None
    group: np.ndarray | None = None
    group_names: tuple[str, ...] = ()
    name: str = ""
    image_path: np.ndarray | None = None  # (M,) str, when the JSON entries name images
    frame: np.ndarray | None = None  # (M,) int: equal ids, one pose seen by several cameras

    def __post_init__(self):
        m, n = self.vis.shape
        if self.kp.shape != (m, n, 2):
            raise ValueError(f"kp has shape {self.kp.shape}, expected {(m, n, 2)} (from vis)")
        for field, tail in (("kp3d", (n, 3)), ("class_mask", (n,)), ("kp_defined", (n,)),
                            ("intrinsics", (3, 3)), ("scale", ()), ("group", ()),
                            ("image_path", ()), ("frame", ())):
            value = getattr(self, field)
            if value is not None and value.shape != (m, *tail):
                raise ValueError(f"{field} has shape {value.shape}, expected {(m, *tail)}")

    def __len__(self) -> int:
        return self.vis.shape[0]

    @property
    def n_keypoints(self) -> int:
        return self.vis.shape[1]

    def subset(self, idx) -> "KeypointData":
        """Rows ``idx`` of every per-sample array."""
        fields = {}
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            fields[f.name] = value[idx] if isinstance(value, np.ndarray) else value
        return KeypointData(**fields)

    def model_inputs(self) -> dict[str, np.ndarray]:
        """The arrays the compiled step consumes (class mask of ones when absent). Hidden
        points are zeroed: whatever a file holds there never reaches the arithmetic (a huge
        value would overflow in the squared distances before the visibility mask)."""
        out = {
            "kp": np.where(self.vis[..., None] > 0, self.kp, 0.0).astype(np.float32),
            "vis": self.vis.astype(np.float32),
            "class_mask": (
                np.ones_like(self.vis, np.float32)
                if self.class_mask is None
                else self.class_mask.astype(np.float32)
            ),
        }
        if self.intrinsics is not None:
            out["intrinsics"] = self.intrinsics.astype(np.float32)
        return out


def fingerprint(data: KeypointData) -> str:
    """sha256 (hex) of what training reads from a split: ``model_inputs``' arrays (hidden
    points zeroed, so what a file holds there does not count) in a fixed order."""
    digest = hashlib.sha256()
    for name, value in sorted(data.model_inputs().items()):
        array = np.ascontiguousarray(value)
        digest.update(f"{name}{array.dtype.str}{array.shape}".encode())
        digest.update(array.tobytes())
    return digest.hexdigest()


def _centred_views(kp: np.ndarray, vis: np.ndarray):
    """``(centred, radius, usable)``: each view's points (M, N, 2) minus its visible mean,
    hidden points zeroed; the RMS radius (M,) of its visible points about that mean; and
    whether the view has two or more visible points and a finite, positive radius."""
    count = vis.sum(1)
    mean = np.einsum("mn,mnc->mc", vis, kp) / np.maximum(count, 1)[:, None]
    centred = (kp - mean[:, None]) * vis[..., None]
    radius = np.sqrt((centred**2).sum((1, 2)) / np.maximum(count, 1))
    return centred, radius, (count > 1) & np.isfinite(radius) & (radius > 0)


def view_radii(data: KeypointData, calibrate: bool | None = None) -> np.ndarray:
    """The RMS radius of each view's visible 2D points about their mean, for the views with
    two or more visible points and a finite, positive radius. With ``calibrate`` (default:
    when the data has ``intrinsics``) the points are calibrated with them first, as a
    perspective model sees them."""
    kp, vis = np.asarray(data.kp, np.float64), np.asarray(data.vis, np.float64)
    calibrate = data.intrinsics is not None if calibrate is None else calibrate
    if calibrate and data.intrinsics is not None:
        homo = np.concatenate([kp, np.ones_like(kp[..., :1])], -1)
        cal = np.einsum("mij,mnj->mni", np.linalg.inv(data.intrinsics.astype(np.float64)), homo)
        kp = cal[..., :2] / cal[..., 2:]
    _, radius, usable = _centred_views(kp, vis)
    return radius[usable]


def auto_keypoint_rescale(data: KeypointData, target_rms: float = 1.0,
                          calibrate: bool | None = None) -> float:
    """The ``model.keypoint_rescale`` that gives the views' 2D points, centred on their
    visible mean, a median RMS radius of ``target_rms``.

    The paper scales the centred 2D points of a dataset so that their extent is about
    [-1, 1]; the median over views of the RMS radius is a robust form of that rule, the
    same in any units. With ``calibrate`` (default: when the data has ``intrinsics``) the
    points are calibrated with them first, as a perspective model sees them; an
    orthographic model sees the points as they are, whatever intrinsics the data has."""
    radius = view_radii(data, calibrate)
    if radius.size == 0:
        raise ValueError(f"{data.name or 'the training data'}: no view has two distinct visible "
                         "points, so the input scale cannot be set; set model.keypoint_rescale")
    return float(target_rms / np.median(radius))


ALIKE_CHUNK = 4_000_000  # view pairs x points compared at once by alike_view_size_ratio
ALIKE_POINTS = 64  # the most points it compares shapes on (the sizes use every point)


def alike_view_size_ratio(data: KeypointData, n_views: int = 1500, seed: int = 0) -> float:
    """Do views that look alike differ in size? The median over views of the size ratio
    (larger RMS radius over smaller) between a view and the view whose shape, centred and
    scaled to unit RMS radius, is nearest to it (mean squared distance over the points
    visible in both, at least half of them; ``ALIKE_POINTS`` evenly spaced points of larger
    sets), among ``n_views`` views drawn with ``seed``.
    Near 1 for a subject seen at one distance, whose views differ in size only with their
    pose and viewpoint, which also change their shape; well above 1 for people seen at
    different distances (evidence: experiments/dev_suite/data_variants.md, "People at
    different distances"). nan with fewer than 2 usable views."""
    kp, vis = np.asarray(data.kp, np.float64), np.asarray(data.vis, np.float64)
    if len(data) > n_views:
        pick = np.sort(np.random.default_rng(seed).choice(len(data), n_views, replace=False))
        kp, vis = kp[pick], vis[pick]
    centred, radius, usable = _centred_views(kp, vis)
    unit, vis, radius = centred[usable] / radius[usable, None, None], vis[usable], radius[usable]
    if len(unit) < 2:
        return float("nan")
    if unit.shape[1] > ALIKE_POINTS:  # shapes compared on evenly spaced points only
        keep = np.linspace(0, unit.shape[1] - 1, ALIKE_POINTS).round().astype(int)
        unit, vis = unit[:, keep], vis[:, keep]
    nearest = np.zeros(len(unit), int)
    step = max(1, ALIKE_CHUNK // (len(unit) * unit.shape[1]))  # (step, M, K) arrays at a time
    for start in range(0, len(unit), step):
        both = vis[start:start + step, None] * vis[None]
        sq = (((unit[start:start + step, None] - unit[None]) ** 2).sum(-1) * both).sum(-1)
        dist = np.where(both.sum(-1) >= 0.5 * vis.shape[1], sq / np.maximum(both.sum(-1), 1),
                        np.inf)
        rows = np.arange(len(dist))
        dist[rows, start + rows] = np.inf  # not itself
        nearest[start:start + step] = dist.argmin(1)
    return float(np.exp(np.median(np.abs(np.log(radius / radius[nearest])))))


def check_spread(data: KeypointData, split: str) -> None:
    """Degenerate data is refused, not trained on: raises when no view of ``data`` has two
    distinct visible points (all keypoints zero or coincident, or none visible); warns
    with the count when some views' visible points all coincide."""
    vis = data.vis[..., None] > 0
    lo = np.where(vis, data.kp, np.inf).min(1)
    hi = np.where(vis, data.kp, -np.inf).max(1)
    spread = (hi - lo).max(-1)  # -inf for a view with no visible point
    flat = ~(spread > 0)
    what = f"{split} split {data.name!r}" if data.name else f"{split} split"
    if flat.all():
        raise ValueError(f"{what}: no view has two distinct visible points (every view's "
                         "visible keypoints coincide, e.g. all 0, or none is visible): "
                         "nothing to learn from or to score")
    coincident = np.flatnonzero(flat & (data.vis.sum(1) >= 2))
    if coincident.size:
        logging.warning("%s: %d of %d views have visible points that all coincide (entries "
                        "%s%s); they carry no shape", what, coincident.size, len(data),
                        coincident[:5].tolist(), " ..." if coincident.size > 5 else "")
    visible = np.median(data.vis.sum(1))
    if visible < 3 <= data.n_keypoints:
        logging.warning("%s: half of the views show %g point(s) or fewer; a view's depth is "
                        "learnt from how its visible points move together, and two points "
                        "say almost nothing about it", what, visible)
    # Views that are the same: one random projection of each view's visible points and
    # visibilities (equal views give equal numbers; others, almost surely not), ~100x faster
    # than comparing whole rows.
    rng = np.random.default_rng(0)
    seen = np.where(vis, data.kp, np.float32(0))
    key = (np.einsum("mnc,nc->m", seen, rng.normal(size=seen.shape[1:]))
           + data.vis @ rng.normal(size=data.n_keypoints))
    distinct = len(np.unique(key))
    if distinct <= len(data) // 2:
        logging.warning("%s: only %d of its %d views differ from each other; repeated views "
                        "add nothing to learn from", what, distinct, len(data))
