"""The release's JSON dataset format -> ``KeypointData`` (numpy only).

A file is a JSON list of entries, or ``{"dataset": name, "data": [...]}``. Each entry
has ``kp_loc`` (2 x N) and ``kp_vis`` (N,), and optionally ``kp_loc_3d`` (3 x N),
``class_mask`` (N,), ``kp_defined`` (N,), ``K`` (3 x 3 intrinsics), ``h36m_info``
(``scale``, ``action_name``) and ``p3d_info`` (``p3d_class``, ``bbox`` [x, y, w, h]).
The ``2 x N`` layout is transposed here, once, to points-on-the-last-axis.
PASCAL3D+ rule (as in the release): keypoints outside the bbox enlarged by 10% on
each side are made invisible.
"""

import json
import os

import numpy as np

from c3dpo_jax.data.dataset import KeypointData


def _array(entry: dict, field: str, index: int, shape: tuple[int, ...]) -> np.ndarray:
    try:
        value = np.asarray(entry[field], dtype=np.float32)
    except (ValueError, TypeError) as err:
        raise ValueError(f"entry {index}: field {field!r} is not a numeric array ({err})") from None
    if value.shape != shape:
        raise ValueError(f"entry {index}: field {field!r} has shape {value.shape}, expected {shape}")
    if not np.all(np.isfinite(value)):
        raise ValueError(f"entry {index}: field {field!r} contains NaN or inf")
    return value


def _stack_optional(entries, field, shape, transpose=False):
    present = [field in e for e in entries]
    if not any(present):
        return None
    if not all(present):
        missing = present.index(False)
        raise ValueError(f"entry {missing}: field {field!r} is missing (other entries have it)")
    values = [_array(e, field, i, shape) for i, e in enumerate(entries)]
    return np.stack([v.T if transpose else v for v in values])


def _bbox_visibility(kp: np.ndarray, bboxes: np.ndarray) -> np.ndarray:
    """1 where a point lies inside its bbox enlarged by 10% on each side."""
    x, y, w, h = (bboxes[:, i : i + 1] for i in range(4))
    x0, x1 = x - 0.1 * w, x + 1.1 * w
    y0, y1 = y - 0.1 * h, y + 1.1 * h
    inside = (kp[..., 0] >= x0) & (kp[..., 0] <= x1) & (kp[..., 1] >= y0) & (kp[..., 1] <= y1)
    return inside.astype(np.float32)


def _groups(names: list[str]) -> tuple[np.ndarray, tuple[str, ...]]:
    unique = tuple(sorted(set(names)))
    lookup = {name: i for i, name in enumerate(unique)}
    return np.array([lookup[n] for n in names], np.int32), unique


def parse(obj, name: str = "") -> KeypointData:
    """Parses the decoded JSON (a list, or the ``{"dataset", "data"}`` wrapper)."""
    if isinstance(obj, dict):
        if "data" not in obj:
            raise ValueError("a JSON object dataset needs a 'data' list")
        name = obj.get("dataset", name)
        obj = obj["data"]
    if not isinstance(obj, list) or not obj:
        raise ValueError("a dataset must be a non-empty list of entries")
    for i, entry in enumerate(obj):
        for field in ("kp_loc", "kp_vis"):
            if field not in entry:
                raise ValueError(f"entry {i}: required field {field!r} is missing")
    n = len(obj[0]["kp_vis"])
    kp = np.stack([_array(e, "kp_loc", i, (2, n)).T for i, e in enumerate(obj)])
    vis = np.stack([_array(e, "kp_vis", i, (n,)) for i, e in enumerate(obj)])
    bad = np.argwhere((vis != 0) & (vis != 1))
    if bad.size:
        i, k = bad[0]
        raise ValueError(f"entry {i}: field 'kp_vis' has value {vis[i, k]} at point {k} (not 0 or 1)")
    fields = dict(
        kp3d=_stack_optional(obj, "kp_loc_3d", (3, n), transpose=True),
        class_mask=_stack_optional(obj, "class_mask", (n,)),
        kp_defined=_stack_optional(obj, "kp_defined", (n,)),
        intrinsics=_stack_optional(obj, "K", (3, 3)),
    )
    if all("h36m_info" in e for e in obj):
        fields["scale"] = np.array([e["h36m_info"].get("scale", 1.0) for e in obj], np.float32)
        actions = [str(e["h36m_info"].get("action_name", "")) for e in obj]
        fields["group"], fields["group_names"] = _groups(actions)
    if all("p3d_info" in e for e in obj):
        classes = [str(e["p3d_info"].get("p3d_class", "")) for e in obj]
        fields["group"], fields["group_names"] = _groups(classes)
        if all("bbox" in e["p3d_info"] for e in obj):
            bboxes = np.array([e["p3d_info"]["bbox"] for e in obj], np.float32)
            vis = vis * _bbox_visibility(kp, bboxes)
    return KeypointData(kp=kp, vis=vis, name=name, **fields)


def load(path: str) -> KeypointData:
    """Reads one JSON file of the release's format."""
    path = os.path.expanduser(path)
    if not os.path.exists(path):
        raise FileNotFoundError(f"dataset file {path!r} does not exist")
    with open(path) as f:
        obj = json.load(f)
    return parse(obj, name=os.path.basename(path).removesuffix(".json"))


def to_json_entries(data: KeypointData) -> list[dict]:
    """``KeypointData`` -> entries of the release's format (inverse of ``parse``)."""
    entries = []
    for i in range(len(data)):
        entry = {"kp_loc": data.kp[i].T.tolist(), "kp_vis": data.vis[i].tolist()}
        if data.kp3d is not None:
            entry["kp_loc_3d"] = data.kp3d[i].T.tolist()
        if data.class_mask is not None:
            entry["class_mask"] = data.class_mask[i].tolist()
        if data.kp_defined is not None:
            entry["kp_defined"] = data.kp_defined[i].tolist()
        if data.intrinsics is not None:
            entry["K"] = data.intrinsics[i].tolist()
        entries.append(entry)
    return entries


def save(data: KeypointData, path: str) -> None:
    """Writes ``data`` as a JSON file of the release's format."""
    with open(path, "w") as f:
        json.dump({"dataset": data.name, "data": to_json_entries(data)}, f)
