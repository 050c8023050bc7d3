"""The release's JSON dataset format -> ``KeypointData`` (numpy only), validated and cached.

A file is a JSON list of entries, or ``{"dataset": name, "data": [...]}``. Each entry
has ``kp_loc`` (2 x N) and ``kp_vis`` (N,), and optionally ``kp_loc_3d`` (3 x N),
``class_mask`` (N,), ``kp_defined`` (N,), ``K`` (3 x 3 intrinsics), ``image_path``,
``frame_id`` (an integer shared by the views of one pose filmed at one instant: not in the
release's files, the importer writes it), ``h36m_info`` (``scale``, ``action_name``) and
``p3d_info`` (``p3d_class``, ``bbox`` [x, y, w, h]). The ``2 x N`` layout is transposed
here, once, to points-on-the-last-axis. PASCAL3D+ rule (as in the release): keypoints
outside the bbox enlarged by 10% on each side are made invisible.

Validation (``checks``) names the entry index and field of every problem: a missing
field, a ragged list, a keypoint count N that differs from the other entries, NaN/inf
(in ``kp_loc`` at visible points only), a coordinate far outside the file's other
points, visibility not in {0, 1}, and fewer than ``min_visible`` visible points.
Problems raise one ``ValueError`` line naming the file unless ``drop_invalid=True``,
which drops (and logs) the entries. The coordinates of hidden points carry no data:
they are stored as 0, whatever the file holds there.

``load`` converts a file once and caches the arrays next to it
(``FILE.json`` -> ``FILE.c3dpo_cache.npz``), keyed by the file's size, mtime, an md5
of its first and last MiB, the parse options and ``CACHE_VERSION``; a stale or
unreadable cache is rebuilt, never trusted.
"""

import hashlib
import json
import os
import tempfile

import numpy as np
from absl import logging

from c3dpo_jax.data import checks
from c3dpo_jax.data.dataset import KeypointData

CACHE_VERSION = 5
_OPTIONAL = (("kp_loc_3d", 3, True), ("class_mask", None, False), ("kp_defined", None, False))


def _bbox_visibility(kp: np.ndarray, bboxes: np.ndarray) -> np.ndarray:
    """1 where a point lies inside its bbox enlarged by 10% on each side."""
    x, y, w, h = (bboxes[:, i : i + 1] for i in range(4))
    inside = ((kp[..., 0] >= x - 0.1 * w) & (kp[..., 0] <= x + 1.1 * w)
              & (kp[..., 1] >= y - 0.1 * h) & (kp[..., 1] <= y + 1.1 * h))
    return inside.astype(np.float32)


def _groups(names: list[str]) -> tuple[np.ndarray, tuple[str, ...]]:
    unique = tuple(sorted(set(names)))
    lookup = {name: i for i, name in enumerate(unique)}
    return np.array([lookup[n] for n in names], np.int32), unique


def _unwrap(obj, name: str, source: str):
    if isinstance(obj, dict):
        if "data" not in obj:
            raise ValueError(f"{source or f'dataset {name!r}'}: a JSON object dataset needs "
                             "a 'data' list")
        name = obj.get("dataset", name) or name
        obj = obj["data"]
    if not isinstance(obj, list) or not obj:
        raise ValueError(f"{source or f'dataset {name!r}'}: a dataset must be a non-empty "
                         "list of entries")
    return obj, name


def _optional_fields(entries, n: int, problems: checks.Problems) -> dict:
    out = {}
    specs = [(f, (rows, n) if rows else (n,), t) for f, rows, t in _OPTIONAL]
    specs.append(("K", (3, 3), False))
    for field, shape, transpose in specs:
        present = [field in e for e in entries]
        if not any(present):
            continue
        for i in np.flatnonzero(~np.asarray(present)):
            problems.add(i, f"field {field!r} is missing (other entries have it)")
        filled = [e if field in e else {field: np.zeros(shape).tolist()} for e in entries]
        value = checks.stack(filled, field, shape, problems, null=field == "kp_loc_3d")
        out[field] = np.swapaxes(value, 1, 2) if transpose else value
    for field in out:
        if field != "kp_loc_3d":
            checks.check_finite(np.flatnonzero(
                ~np.isfinite(out[field]).reshape(len(entries), -1).all(1)), field, problems)
    if "K" in out:  # a perspective model divides by them
        with np.errstate(invalid="ignore"):
            cond = np.linalg.cond(np.nan_to_num(out["K"].astype(np.float64)))
        for i in np.flatnonzero(~(cond < 1e12)):
            problems.add(i, "field 'K' is singular (the intrinsics must be invertible)")
    if "kp_loc_3d" in out:
        # A 3D point counts in the evaluation unless kp_defined or class_mask says not; the
        # others may hold anything (null, NaN, a placeholder) and are stored as 0.
        points = out["kp_loc_3d"]
        counts = np.ones(points.shape[:2], bool)
        for mask in ("kp_defined", "class_mask"):
            if mask in out:
                counts &= np.nan_to_num(out[mask]) != 0
        checks.check_finite(np.flatnonzero((counts & ~np.isfinite(points).all(-1)).any(1)),
                            "kp_loc_3d", problems)
        checks.check_magnitude(points, counts, "kp_loc_3d", "point", problems)
        out["kp_loc_3d"] = np.where(counts[..., None], points, np.float32(0))
    return out


def _frame_ids(entries, problems: checks.Problems) -> dict:
    """``{"frame": (M,) int64}`` when the entries carry ``frame_id`` (an integer each)."""
    present = ["frame_id" in e for e in entries]
    if not any(present):
        return {}
    ids = np.zeros(len(entries), np.int64)
    for i, e in enumerate(entries):
        value = e.get("frame_id")
        if not present[i]:
            problems.add(i, "field 'frame_id' is missing (other entries have it)")
        elif isinstance(value, bool) or not isinstance(value, int):
            problems.add(i, f"field 'frame_id' must be an integer, not {value!r}")
        else:
            ids[i] = value
    return {"frame": ids}


def _info_fields(entries) -> dict:
    out = {}
    if all("image_path" in e for e in entries):
        out["image_path"] = np.array([str(e["image_path"]) for e in entries])
    if all(isinstance(e.get("h36m_info"), dict) for e in entries):
        out["scale"] = np.array([e["h36m_info"].get("scale", 1.0) for e in entries], np.float32)
        if any("action_name" in e["h36m_info"] for e in entries):
            out["group"], out["group_names"] = _groups(
                [str(e["h36m_info"].get("action_name", "")) for e in entries])
    if all(isinstance(e.get("p3d_info"), dict) for e in entries):
        out["group"], out["group_names"] = _groups(
            [str(e["p3d_info"].get("p3d_class", "")) for e in entries])
        if all("bbox" in e["p3d_info"] for e in entries):
            out["bbox"] = np.array([e["p3d_info"]["bbox"] for e in entries], np.float32)
    return out


def parse(obj, name: str = "", *, min_visible: int = 2, drop_invalid: bool = False,
          source: str = "", kp_dtype=np.float32) -> KeypointData:
    """Parses and validates decoded JSON (a list, or the ``{"dataset", "data"}`` wrapper).

    Args:
      obj: the decoded JSON.
      name: dataset name (the wrapper's ``dataset`` wins).
      min_visible: entries with fewer visible points are invalid.
      drop_invalid: drop invalid entries (logged with their count) instead of raising.
      source: what messages call the data (e.g. its file); default: ``dataset NAME``.
      kp_dtype: the 2D points' dtype (float64 keeps coordinates far from 0 exact for
        inference; training takes float32).
    Returns:
      the valid entries as ``KeypointData``.
    """
    entries, name = _unwrap(obj, name, source)
    label = source or f"dataset {name!r}"
    problems = checks.Problems()
    checks.check_required(entries, problems)
    ok = [e if i not in problems.by_entry else {"kp_loc": [[]], "kp_vis": []}
          for i, e in enumerate(entries)]
    n = checks.n_keypoints(ok, problems)
    kp = np.swapaxes(checks.stack(ok, "kp_loc", (2, n), problems, null=True, dtype=kp_dtype),
                     1, 2)
    vis = checks.stack(ok, "kp_vis", (n,), problems)
    checks.check_keypoints(kp, vis, min_visible, problems)
    fields = _optional_fields(ok, n, problems)
    fields.update(_info_fields(ok))
    fields.update(_frame_ids(ok, problems))
    keep = problems.raise_or_drop(len(entries), drop_invalid, label)
    if len(keep) == 0:
        raise ValueError(f"{label}: every entry is invalid")
    fields = {k: (v[keep] if isinstance(v, np.ndarray) else v) for k, v in fields.items()}
    kp, vis = kp[keep], vis[keep]
    if "bbox" in fields:
        vis = vis * _bbox_visibility(kp, fields.pop("bbox"))
    kp = np.where(vis[..., None] > 0, kp, kp.dtype.type(0))
    if "kp_loc_3d" in fields:
        fields["kp3d"] = fields.pop("kp_loc_3d")
    if "K" in fields:
        fields["intrinsics"] = fields.pop("K")
    return KeypointData(kp=kp, vis=vis, name=name, **fields)


def check_n_keypoints(data: KeypointData, n_keypoints: int) -> None:
    """Raises a ``ValueError`` that says how to fix a model/dataset keypoint mismatch."""
    if data.n_keypoints != n_keypoints:
        raise ValueError(
            f"dataset {data.name!r} has K={data.n_keypoints} keypoints but the model expects "
            f"{n_keypoints}; set --config.model.n_keypoints={data.n_keypoints}"
        )


def cache_path(path: str) -> str:
    """``FILE.json`` -> ``FILE.c3dpo_cache.npz``."""
    return path.removesuffix(".json") + ".c3dpo_cache.npz"


def _fingerprint(path: str, options: dict) -> str:
    st = os.stat(path)
    h = hashlib.md5()
    with open(path, "rb") as f:
        h.update(f.read(1 << 20))
        if st.st_size > 1 << 20:
            f.seek(max(st.st_size - (1 << 20), 1 << 20))
            h.update(f.read())
    return json.dumps(dict(version=CACHE_VERSION, size=st.st_size, mtime_ns=st.st_mtime_ns,
                           md5_ends=h.hexdigest(), **options), sort_keys=True)


def _read_cache(cpath: str, key: str) -> KeypointData | None:
    try:
        with np.load(cpath, allow_pickle=False) as z:
            if str(z["__key__"]) != key:
                logging.info("cache %s is stale; rebuilding it", cpath)
                return None
            fields = {k: z[k] for k in z.files if not k.startswith("__")}
            return KeypointData(**fields, name=str(z["__name__"]),
                                group_names=tuple(str(g) for g in z["__group_names__"]))
    except FileNotFoundError:
        return None
    except Exception as err:  # A corrupt or foreign file is rebuilt, never trusted.
        logging.warning("cache %s is unreadable (%s); rebuilding it", cpath, err)
        return None


def _write_cache(cpath: str, key: str, data: KeypointData) -> None:
    arrays = {k: v for k, v in vars(data).items() if isinstance(v, np.ndarray)}
    arrays.update(__key__=np.array(key), __name__=np.array(data.name),
                  __group_names__=np.array(list(data.group_names), dtype=str))
    try:
        fd, tmp = tempfile.mkstemp(dir=os.path.dirname(cpath) or ".", suffix=".tmp.npz")
        with os.fdopen(fd, "wb") as f:
            np.savez(f, **arrays)
        os.replace(tmp, cpath)
    except OSError as err:
        logging.warning("could not write the cache %s (%s); continuing without it", cpath, err)


def read_json(path: str):
    """The content of the JSON file ``path`` as every reader of the release's format reads
    it (data, styles for the pictures, inputs to ``predict``, COCO annotations): UTF-8, a
    byte-order mark (Windows tools write one) skipped; one-line ValueError naming the file
    when it is not JSON."""
    with open(path, encoding="utf-8-sig") as f:
        try:
            return json.load(f)
        except json.JSONDecodeError as err:
            raise ValueError(f"{path} is not valid JSON: {err}") from None
        except UnicodeDecodeError as err:
            raise ValueError(f"{path} is not a UTF-8 text (JSON) file: byte {err.start} "
                             f"is {err.object[err.start:err.start + 1]!r}") from None


def load(path: str, *, min_visible: int = 2, drop_invalid: bool = False, cache: bool = True
         ) -> KeypointData:
    """Reads one JSON file of the release's format (through its ``.c3dpo_cache.npz``)."""
    path = os.path.expanduser(path)
    if not os.path.exists(path):
        raise FileNotFoundError(f"dataset file {path!r} does not exist")
    name = os.path.basename(path).removesuffix(".json")
    key = _fingerprint(path, dict(min_visible=min_visible, drop_invalid=drop_invalid))
    cpath = cache_path(path)
    if cache and (data := _read_cache(cpath, key)) is not None:
        return data
    data = parse(read_json(path), name=name, min_visible=min_visible, drop_invalid=drop_invalid,
                 source=path)
    if cache:
        _write_cache(cpath, key, data)
    return data


def _json_numbers(a: np.ndarray | np.generic) -> list | float:
    """``a.tolist()``, float32 numbers as their shortest decimals: 362.79 where float64 would
    write the same float32 as 362.7900085449219 (both read back as that float32)."""
    a = np.asarray(a)
    return (a.astype(str).astype(np.float64) if a.dtype == np.float32 else a).tolist()


def to_json_entries(data: KeypointData) -> list[dict]:
    """``KeypointData`` -> entries of the release's format (inverse of ``parse``)."""
    arrays = {"kp_loc": np.swapaxes(data.kp, 1, 2), "kp_vis": data.vis}
    for field, key in (("kp3d", "kp_loc_3d"), ("class_mask", "class_mask"),
                       ("kp_defined", "kp_defined"), ("intrinsics", "K")):
        value = getattr(data, field)
        if value is not None:
            arrays[key] = np.swapaxes(value, 1, 2) if field == "kp3d" else value
    lists = {key: _json_numbers(value) for key, value in arrays.items()}
    entries = []
    for i in range(len(data)):
        entry = {key: values[i] for key, values in lists.items()}
        if data.image_path is not None:
            entry["image_path"] = str(data.image_path[i])
        if data.frame is not None:
            entry["frame_id"] = int(data.frame[i])
        if data.class_mask is not None and data.group is not None and data.group_names:
            entry["p3d_info"] = {"p3d_class": data.group_names[data.group[i]]}
        elif data.scale is not None or (data.group is not None and data.group_names):
            entry["h36m_info"] = {}
            if data.scale is not None:
                entry["h36m_info"]["scale"] = _json_numbers(data.scale[i])
            if data.group is not None and data.group_names:
                entry["h36m_info"]["action_name"] = data.group_names[data.group[i]]
        entries.append(entry)
    return entries


def save(data: KeypointData, path: str) -> None:
    """Writes ``data`` as a JSON file of the release's format (groups as ``p3d_info`` classes
    when there is a class mask, else as ``h36m_info`` actions)."""
    with open(path, "w") as f:
        json.dump({"dataset": data.name, "data": to_json_entries(data)}, f)
