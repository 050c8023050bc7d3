"""Users' own keypoints -> the release's JSON format (numpy only; scipy for .mat).

- 3D sequences (``.npz`` or ``.mat`` with ``X`` (F, 3, K), as the classic NRSfM
  sequences, (F, K, 3), (3F, K), or another axis order named by ``layout``): turned so
  that the ``up`` axis is y, each frame centred, the sequence scaled to unit RMS radius,
  and seen by ``views_per_frame`` random cameras; train and test take different blocks of
  frames, so test poses are unseen.
- BVH motion capture: joint positions by forward kinematics, then views as above.
- COCO-style keypoints (``annotations[i].keypoints`` = [x, y, v] * K, v in {0, 1, 2}):
  a 2D-only set (v >= ``min_v`` is visible), one file or train and test files that take
  the annotations of different images (``image_split``).

The files also say how to draw their samples (docs/data.md): ``y_up`` (true for views
of motion capture by upright cameras, false for COCO's image coordinates) and
``skeleton`` (``--skeleton``, else a BVH file's bones or the COCO category's skeleton).

CLI::

  python -m c3dpo_jax.data.importers sequence clip.npz --out_dir data/ --name clip
  python -m c3dpo_jax.data.importers bvh walk.bvh --out_dir data/ --name walk
  python -m c3dpo_jax.data.importers coco person_keypoints.json --out_dir data/ --name coco

Glossary: F frames, K points, V views per frame.
"""

import argparse
import collections
import json
import os
import re
import sys

import numpy as np
from absl import flags, logging

from c3dpo_jax import cli, skeletons
from c3dpo_jax.data import json_dataset
from c3dpo_jax.data.dataset import KeypointData
from c3dpo_jax.data.rotations import axis_rotation, random_rotations, upright_rotations

# The axis orders of a 3D array a sequence may come in: "F3K" is (frames, xyz, points).
LAYOUTS = ("F3K", "FK3", "K3F", "KF3", "3FK", "3KF")


def _arrays(path: str, names: tuple[str, ...] | None = None) -> dict[str, np.ndarray]:
    """The named arrays of a ``.npz`` or ``.mat`` file: all, or only those of ``names``
    that it holds (the others are not read)."""
    if not path.endswith((".npz", ".mat")):
        raise ValueError(f"{path}: a sequence is read from a .npz or .mat file (an array X of "
                         "shape (F, 3, K), (F, K, 3) or (3F, K))")
    if path.endswith(".npz"):
        with np.load(path, allow_pickle=False) as z:
            return {k: z[k] for k in z.files if names is None or k in names}
    import scipy.io

    try:
        contents = scipy.io.loadmat(path, variable_names=names)
    except NotImplementedError as err:  # MATLAB v7.3 files are HDF5
        raise ValueError(f"{path}: {err} (or save it from MATLAB with -v7)") from None
    return {k: v for k, v in contents.items() if not k.startswith("__")}


def _guess_layout(shape: tuple[int, ...], path: str, key: str) -> str:
    """The layout of a 3D array: the one axis of size 3 is xyz, and F before K
    (``LAYOUTS``); more than one axis of size 3, or xyz first, is ambiguous."""
    threes = [i for i, n in enumerate(shape) if n == 3]
    if len(threes) != 1 or threes[0] == 0:
        raise ValueError(f"{path}: array {key!r} has shape {shape}, which could be several "
                         f"layouts; pass the axis order (--layout: one of {', '.join(LAYOUTS)}, "
                         "F frames, 3 coordinates, K points)")
    return "F3K" if threes[0] == 1 else "FK3"


def load_sequence(path: str, key: str = "X", layout: str | None = None) -> np.ndarray:
    """A 3D point sequence (F, K, 3) from ``.npz`` or ``.mat``: the array ``key`` (or the
    file's only array), whose axis order ``layout`` (one of ``LAYOUTS``) is guessed when
    None: (F, 3, K) or (F, K, 3) for a 3D array (an ambiguous shape is an error), the
    classic NRSfM stacking (3F, K) for a 2D one. The reading is logged (F and K)."""
    arrays = _arrays(path)
    if key not in arrays:
        if len(arrays) != 1:
            raise ValueError(f"{path}: no array {key!r}; it holds {sorted(arrays)} (choose one: "
                             "--key, or key=)")
        key = next(iter(arrays))
    x = np.asarray(arrays[key], np.float64)
    if layout is not None and layout not in LAYOUTS:
        raise ValueError(f"layout={layout!r}: one of {', '.join(LAYOUTS)}")
    if x.ndim == 2 and layout is None and x.shape[0] % 3 == 0:
        # Classic NRSfM stacking: rows x1, y1, z1, x2, ...
        x, layout = np.swapaxes(x.reshape(-1, 3, x.shape[1]), 1, 2), "3F x K"
    elif x.ndim == 3:
        layout = layout or _guess_layout(x.shape, path, key)
        x = np.transpose(x, [layout.index(c) for c in "FK3"])
    elif x.ndim == 2 and layout is not None:
        raise ValueError(f"{path}: array {key!r} is 2D {x.shape}: --layout names the axes of a "
                         "3D array (a 2D one is read as the stacking (3F, K))")
    else:
        raise ValueError(f"{path}: array {key!r} has shape {x.shape}; expected (F, 3, K), "
                         "(F, K, 3) (another order: --layout) or (3F, K)")
    if x.shape[2] != 3:
        raise ValueError(f"{path}: array {key!r} read as {layout} has {x.shape[2]} coordinates "
                         "per point, not 3")
    if x.shape[0] >= x.shape[1]:
        logging.info("%s: array %r read as %s: F=%d frames of K=%d points", path, key, layout,
                     *x.shape[:2])
    else:
        logging.warning("%s: array %r read as %s: F=%d frames of K=%d points, fewer frames than "
                        "points: if the array's axes are the other way round, pass --layout",
                        path, key, layout, *x.shape[:2])
    return x


def _normalise(x: np.ndarray) -> tuple[np.ndarray, float]:
    """Centres each frame; divides by the sequence's mean RMS radius (returned)."""
    x = x - x.mean(1, keepdims=True)
    scale = float(np.sqrt((x**2).sum(-1).mean(-1)).mean())
    if not scale > 0:
        raise ValueError(f"the sequence's {x.shape[1]} point(s) coincide in every frame: there "
                         "is no shape to see (a sequence needs two distinct points or more)")
    return x / scale, scale


def frame_blocks_split(n_frames: int, test_fraction: float, n_blocks: int, seed: int):
    """Boolean test mask: ``n_blocks`` contiguous blocks, a ``test_fraction`` of them test."""
    n_blocks = max(2, min(n_blocks, n_frames))
    block = np.arange(n_frames) * n_blocks // n_frames
    n_test = min(max(1, round(test_fraction * n_blocks)), n_blocks - 1)
    test_blocks = np.random.default_rng(seed).choice(n_blocks, n_test, replace=False)
    return np.isin(block, test_blocks)


def clip_split(clip: np.ndarray, test_fraction: float, n_blocks: int, seed: int,
               hold_out: str = "blocks") -> np.ndarray:
    """Boolean test mask over frames labelled with clip ids ``clip`` (F,).

    ``hold_out="blocks"``: each clip is cut into ``n_blocks`` contiguous blocks and a
    ``test_fraction`` of each clip's blocks are test (unseen stretches of every motion);
    ``"clips"``: a ``test_fraction`` of the clips (at least one, never all) are test
    (unseen motions)."""
    clip = np.asarray(clip)
    ids = np.unique(clip)
    rng = np.random.default_rng(seed)
    if hold_out == "clips":
        if len(ids) < 2:
            raise ValueError("hold_out='clips' needs at least two clips")
        n_test = min(max(1, round(test_fraction * len(ids))), len(ids) - 1)
        return np.isin(clip, rng.choice(ids, n_test, replace=False))
    if hold_out != "blocks":
        raise ValueError(f"hold_out must be 'blocks' or 'clips', got {hold_out!r}")
    test = np.zeros(len(clip), bool)
    for c in ids:
        frames = np.flatnonzero(clip == c)
        if len(frames) >= 2:
            test[frames] = frame_blocks_split(len(frames), test_fraction, n_blocks,
                                              int(rng.integers(2**31)))
    return test


def load_clips(path: str, key: str = "clip") -> np.ndarray | None:
    """The per-frame clip ids (F,) of a ``.npz`` or ``.mat`` sequence, or None when it has
    none."""
    clip = _arrays(path, (key,)).get(key)
    if clip is not None and np.ndim(clip) == 2 and 1 in np.shape(clip):
        clip = np.reshape(clip, -1)  # MATLAB stores a vector as (1, F) or (F, 1)
    return clip


# Proper rotations that bring the named axis of a sequence to y, the up of upright cameras.
_TO_Y_UP = {"y": np.eye(3), "z": np.array([[1.0, 0, 0], [0, 0, 1], [0, -1, 0]]),
            "x": np.array([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]])}


def to_y_up(x: np.ndarray, up: str) -> np.ndarray:
    """A sequence ``x`` (F, K, 3) turned so that its ``up`` axis ("x", "y" or "z") is y, by
    a rotation (the body keeps its handedness)."""
    if up not in _TO_Y_UP:
        raise ValueError(f"up={up!r}: one of x, y, z")
    return x @ _TO_Y_UP[up].T


def _views(x, frames, *, views_per_frame, cameras, max_elevation, occlusion, noise,
           min_visible, rng, name, scale):
    f, k, _ = x.shape
    m = f * views_per_frame
    rots = (random_rotations(rng, m) if cameras == "uniform"
            else upright_rotations(rng, m, max_elevation))
    kp3d = np.einsum("mij,mnj->mni", rots, np.repeat(x, views_per_frame, 0))
    vis = (rng.uniform(size=(m, k)) >= occlusion).astype(np.float32)
    keep = np.argsort(rng.uniform(size=(m, k)), axis=1)[:, :min_visible]
    np.put_along_axis(vis, keep, 1.0, axis=1)
    kp = (kp3d[..., :2] + noise * rng.normal(size=(m, k, 2))) * vis[..., None]
    return KeypointData(kp=kp.astype(np.float32), vis=vis, kp3d=kp3d.astype(np.float32),
                        scale=np.full(m, scale, np.float32), name=name,
                        frame=np.repeat(frames, views_per_frame))


def views_from_sequence(x: np.ndarray, *, views_per_frame: int = 10, cameras: str = "upright",
                        max_elevation: float | int = 0.5, test_fraction: float | int = 0.2,
                        n_blocks: int = 10, occlusion: float | int = 0.0, noise: float | int = 0.0,
                        min_visible: int = 3, normalise: bool = True, seed: int = 0,
                        name: str = "sequence", clip: np.ndarray | None = None,
                        hold_out: str = "blocks") -> tuple[KeypointData, KeypointData]:
    """(train, test) views of a 3D sequence ``x`` (F, K, 3), split by frame blocks.

    With per-frame clip ids ``clip`` (F,) (concatenated clips) the split respects the clips
    (``clip_split``: blocks inside every clip, or whole clips with ``hold_out="clips"``).

    ``scale`` of each sample holds the factor that was divided out, so errors times
    ``scale`` are in the sequence's units. ``noise`` is 2D noise in normalised units.
    ``frame`` of each sample is the index in ``x`` of the frame it shows (the
    ``views_per_frame`` views of a frame share it).
    """
    if x.ndim != 3 or x.shape[2] != 3:
        raise ValueError(f"a sequence must be (F, K, 3), got {x.shape}")
    bad = np.argwhere(~np.isfinite(x).all(-1))
    if bad.size:
        frames = np.unique(bad[:, 0])
        raise ValueError(
            f"the sequence has NaN or inf at {len(bad)} points of {len(frames)} frames (first: "
            f"frame {bad[0, 0]}, point {bad[0, 1]}); a frame needs every point (fill the gaps "
            "or drop those frames)")
    if not 0 < test_fraction < 1:
        raise ValueError(f"test_fraction={test_fraction} (must be between 0 and 1: training "
                         "needs a test split, and at least one block of each is kept)")
    if n_blocks < 2:
        raise ValueError(f"n_blocks={n_blocks} (must be >= 2: one block of test frames and one "
                         "of training frames)")
    x, scale = _normalise(x) if normalise else (x - x.mean(1, keepdims=True), 1.0)
    if clip is None:
        if hold_out != "blocks":
            raise ValueError(f"hold_out={hold_out!r} needs per-frame clip ids (a 'clip' array "
                             "beside the sequence); this sequence has none")
        test = frame_blocks_split(len(x), test_fraction, n_blocks, seed)
    else:
        if np.shape(clip) != (len(x),):
            raise ValueError(f"clip has shape {np.shape(clip)}, expected ({len(x)},)")
        test = clip_split(clip, test_fraction, n_blocks, seed, hold_out)
    if test.all() or not test.any():
        empty = "train" if test.all() else "test"
        raise ValueError(f"the split of {len(x)} frame(s) leaves no {empty} frame (a sequence "
                         "needs two frames, and a clip two frames to be split inside it)")
    if views_per_frame < 1:
        raise ValueError(f"views_per_frame={views_per_frame} (must be >= 1)")
    rng = np.random.default_rng(seed + 1)
    common = dict(views_per_frame=views_per_frame, cameras=cameras, max_elevation=max_elevation,
                  occlusion=occlusion, noise=noise, min_visible=min(min_visible, x.shape[1]),
                  rng=rng, scale=scale)
    return (_views(x[~test], np.flatnonzero(~test), name=f"{name}_train", **common),
            _views(x[test], np.flatnonzero(test), name=f"{name}_test", **common))


def parse_bvh(text: str):
    """BVH -> (joint names, parents, offsets (J, 3), channels per joint, motion (F, C),
    whether each is an End Site (named after its joint: ``JOINT_end``))."""
    tokens = re.findall(r"[^\s{}]+|[{}]", text)
    names, parents, offsets, channels, stack, end_sites = [], [], [], [], [], []
    i = 0
    while i < len(tokens) and tokens[i] != "MOTION":
        tok = tokens[i]
        if tok in ("ROOT", "JOINT", "End"):
            names.append(tokens[i + 1] if tok != "End" else f"{names[stack[-1]]}_end")
            end_sites.append(tok == "End")
            parents.append(stack[-1] if stack else -1)
            channels.append([])
            offsets.append(None)
            i += 2
        elif tok == "{":
            stack.append(len(names) - 1)
            i += 1
        elif tok == "}":
            stack.pop()
            i += 1
        elif tok == "OFFSET":
            offsets[-1] = [float(t) for t in tokens[i + 1 : i + 4]]
            i += 4
        elif tok == "CHANNELS":
            n = int(tokens[i + 1])
            channels[-1] = tokens[i + 2 : i + 2 + n]
            i += 2 + n
        else:
            i += 1
    if not names or any(o is None for o in offsets):
        raise ValueError("not a BVH file: no HIERARCHY with OFFSETs found")
    m = re.search(r"Frames:\s*(\d+)\s*Frame Time:\s*[\d.eE+-]+\s*(.*)", text, re.S)
    if m is None:
        raise ValueError("BVH file has no MOTION section with 'Frames:' and 'Frame Time:'")
    values = np.array(m.group(2).split(), np.float64)
    n_ch, n_frames = sum(len(c) for c in channels), int(m.group(1))
    if values.size != n_frames * n_ch:
        raise ValueError(f"the BVH header says {n_frames} frames of {n_ch} channels, the MOTION "
                         f"section holds {values.size / max(n_ch, 1):.1f} frames' worth of "
                         "numbers: is the file cut short, or its Frames: line wrong?")
    motion = values.reshape(n_frames, n_ch)
    return names, parents, np.array(offsets), channels, motion, end_sites


def bvh_positions(text: str, include_end_sites: bool = False):
    """Global joint positions (F, J, 3) of a BVH file by forward kinematics, and names.

    A joint's position channels are its translation from its parent, in place of its
    OFFSET on that axis (as files that animate every joint's position write them, the
    translation repeated each frame; the root's OFFSET is usually 0).
    """
    names, parents, offsets, channels, motion, end_sites = parse_bvh(text)
    f = len(motion)
    pos, rot = np.zeros((f, len(names), 3)), np.zeros((f, len(names), 3, 3))
    col = 0
    for j, chans in enumerate(channels):
        local_t, local_r = np.broadcast_to(offsets[j], (f, 3)).copy(), np.broadcast_to(
            np.eye(3), (f, 3, 3))
        for ch in chans:  # rotations compose in the listed order (intrinsic)
            value = motion[:, col]
            col += 1
            if ch.endswith("position"):
                local_t[:, "XYZ".index(ch[0])] = value
            else:
                local_r = local_r @ axis_rotation(ch[0], np.deg2rad(value))  # BVH: degrees
        p = parents[j]
        if p < 0:
            pos[:, j], rot[:, j] = local_t, local_r
        else:
            pos[:, j] = pos[:, p] + np.einsum("fij,fj->fi", rot[:, p], local_t)
            rot[:, j] = rot[:, p] @ local_r
    keep = [j for j, end in enumerate(end_sites) if include_end_sites or not end]
    return pos[:, keep], [names[j] for j in keep]


def bvh_bones(text: str, include_end_sites: bool = False) -> list[tuple[int, int]]:
    """(parent, child) index pairs of the joints ``bvh_positions`` returns."""
    _, parents, *_, end_sites = parse_bvh(text)
    keep = [j for j, end in enumerate(end_sites) if include_end_sites or not end]
    new = {j: k for k, j in enumerate(keep)}
    return skeletons.from_parents([new.get(parents[j], -1) for j in keep])


def coco_skeleton(obj: dict, category_id=None) -> list[tuple[int, int]] | None:
    """The (0-based) skeleton of the COCO category (COCO's pairs count from 1), if any:
    ``category_id``'s, else that of the one category the keypoint annotations belong to
    (annotations that name none: the file's only category; none when they name several)."""
    categories = obj.get("categories", [])
    if category_id is None:
        used = {a.get("category_id") for a in obj.get("annotations", []) if a.get("keypoints")}
        if used == {None} and len(categories) == 1:
            used = {categories[0].get("id")}
        if len(used) != 1:
            return None
        category_id = used.pop()
    for cat in categories:
        if cat.get("skeleton") and cat.get("id") == category_id:
            return [(int(a) - 1, int(b) - 1) for a, b in cat["skeleton"]]
    return None


def save(data: KeypointData, path: str, *, y_up: bool, skeleton=None, unit: str = "") -> None:
    """``json_dataset.save`` with the picture settings ``y_up``, ``skeleton`` (pairs,
    checked against the data's K) and ``unit`` in the file's wrapper."""
    style = {"y_up": bool(y_up), **({"unit": unit} if unit else {})}
    if skeleton:
        style["skeleton"] = [list(e) for e in skeletons.skeleton(skeleton, data.n_keypoints)]
    with open(path, "w") as f:
        json.dump({"dataset": data.name, **style, "data": json_dataset.to_json_entries(data)}, f)


def warn_skipped(label: str, skipped: np.ndarray, total: int, items: str, why: str) -> None:
    """One warning line: ``LABEL: S of T ITEMS have WHY: skipped (ITEMS [first ten] ...)``."""
    logging.warning("%s: %d of %d %s have %s: skipped (%s %s%s)", label, skipped.size, total,
                    items, why, items, skipped[:10].tolist(), " ..." if skipped.size > 10 else "")


def read_coco(obj: dict, *, min_v: int = 1, min_visible: int = 1, category_id=None,
              name: str = "coco") -> tuple[KeypointData, np.ndarray]:
    """COCO-style keypoint annotations -> 2D-only ``KeypointData`` (no ``kp3d``) and the
    position (M,) of each kept annotation in ``obj["annotations"]``: the one COCO reader
    (``coco_to_data`` for training sets, ``predict`` for inference).

    Annotations without ``keypoints`` (other kinds, or an empty list) and, with
    ``category_id``, of other categories are passed over. A point is visible when its flag
    v >= ``min_v`` (1: labelled, maybe occluded; 2: labelled and visible); annotations with
    fewer than ``min_visible`` visible points are skipped with one warning line. Malformed
    keypoint lists are a ``ValueError`` naming the annotation.
    """
    images = {im["id"]: im.get("file_name", "") for im in obj.get("images", [])}
    with_kp = [(i, a) for i, a in enumerate(obj.get("annotations", [])) if a.get("keypoints")]
    picked = [(i, a) for i, a in with_kp
              if category_id is None or a.get("category_id") == category_id]
    if not picked:
        ids = sorted({str(a.get("category_id")) for _, a in with_kp})
        raise ValueError("no annotations with 'keypoints' found" + (
            f" of category_id {category_id} (the keypoint annotations' categories: "
            f"{', '.join(ids)})" if with_kp else ""))
    rows = []
    for i, ann in picked:
        try:
            flat = np.asarray(ann["keypoints"], np.float32).reshape(-1)
        except (TypeError, ValueError):
            raise ValueError(f"annotation {i}: 'keypoints' is not a list of numbers, "
                             "[x, y, v] * N") from None
        if flat.size == 0 or flat.size % 3:
            raise ValueError(f"annotation {i}: 'keypoints' has {flat.size} numbers; expected "
                             "one length 3K for all annotations, [x, y, v] * N")
        rows.append(flat)
    sizes = [r.size for r in rows]
    common = collections.Counter(sizes).most_common(1)[0][0]  # ties: the first annotation's
    odd = [(i, size) for (i, _), size in zip(picked, sizes, strict=True) if size != common]
    if odd:
        i, size = odd[0]
        cats = {a.get("category_id") for _, a in picked}
        hint = (f"; they hold {len(cats)} categories: keep one with category_id (--category_id)"
                if category_id is None and len(cats) > 1 else "")
        raise ValueError(f"annotation {i} has {size // 3} keypoints, most others "
                         f"{common // 3} ({len(odd)} of {len(rows)} annotations differ); "
                         f"expected one length 3K for all annotations{hint}")
    kpv = np.stack(rows).reshape(len(rows), -1, 3)
    vis = (kpv[..., 2] >= min_v).astype(np.float32)
    keep = vis.sum(1) >= min_visible
    index = np.array([i for i, _ in picked])
    what = ("no visible keypoint" if min_visible <= 1
            else f"fewer than {min_visible} visible points")
    if not keep.any():
        raise ValueError(f"every COCO annotation with keypoints has {what}")
    if not keep.all():
        warn_skipped("coco", index[~keep], len(picked), "annotations", what)
    paths = np.array([images.get(a.get("image_id"), "") for _, a in picked])[keep]
    data = KeypointData(kp=(kpv[..., :2] * vis[..., None])[keep], vis=vis[keep],
                        image_path=paths, name=name)
    return data, index[keep]


def coco_to_data(obj: dict, *, min_v: int = 1, min_visible: int = 2, category_id=None,
                 name: str = "coco") -> KeypointData:
    """COCO-style keypoint annotations -> a 2D-only training set (``read_coco``; by
    default annotations need two visible points, the least that has a shape)."""
    data, _ = read_coco(obj, min_v=min_v, min_visible=min_visible, category_id=category_id,
                        name=name)
    return data


def image_split(images: np.ndarray, test_fraction: float, seed: int) -> np.ndarray:
    """Boolean test mask over annotations of the images ``images`` (M,) (file names; all
    empty: each annotation is its own): a ``test_fraction`` of the images, at least one and
    never all, with all their annotations, so test people are in unseen pictures."""
    images = np.asarray(images)
    groups = np.arange(len(images)) if not any(images) else images
    ids = np.unique(groups)
    if len(ids) < 2:
        raise ValueError("the annotations are all of one image: there is no other image to "
                         "test on (--out writes them to one file)")
    n_test = min(max(1, round(test_fraction * len(ids))), len(ids) - 1)
    return np.isin(groups, np.random.default_rng(seed).choice(ids, n_test, replace=False))


def _write_pair(train: KeypointData, test: KeypointData, out_dir: str, name: str, **style):
    os.makedirs(out_dir, exist_ok=True)
    paths = [os.path.join(out_dir, f"{name}_{s}.json") for s in ("train", "test")]
    for data, path in zip((train, test), paths, strict=True):
        save(data, path, **style)
    print(f"wrote {paths[0]} ({len(train)} views) and {paths[1]} ({len(test)} views); "
          f"K={train.n_keypoints}: --config.model.n_keypoints={train.n_keypoints}")
    if train.scale is not None and not np.allclose(train.scale, 1.0):
        print(f"units: the sequence was divided by {float(train.scale[0]):.6g} (its RMS radius) "
              "so that its errors read as fractions of the body's size; times that factor "
              "they are in the sequence's own units")


_SKELETON_HELP = ("lines for the pictures, stored in the files: a built-in name (h36m, "
                  "cub_birds, ...) or index pairs such as 0-1,1-2,2-3")


def main(argv=None, prog: str = "c3dpo-import") -> None:
    parser = argparse.ArgumentParser(prog=prog, description=__doc__.split("\n\n")[0])
    parser.add_argument("--verbose", action="store_true",
                        help="on an error, its traceback instead of one line")
    sub = parser.add_subparsers(dest="kind", required=True)
    for kind in ("sequence", "bvh"):
        p = sub.add_parser(kind, help="views of a 3D point sequence" if kind == "sequence"
                           else "views of the joints of a BVH motion capture")
        p.add_argument("path", help=".npz or .mat holding X: (F, 3, K), (F, K, 3) or (3F, K)"
                       if kind == "sequence" else "BVH motion capture file")
        p.add_argument("--out_dir", required=True,
                       help="writes OUT_DIR/NAME_train.json and OUT_DIR/NAME_test.json")
        p.add_argument("--name", default=None, help="dataset name (default: the file's stem)")
        p.add_argument("--views_per_frame", type=int, default=10,
                       help="random cameras per frame (default: %(default)s)")
        p.add_argument("--cameras", choices=("upright", "uniform"), default="upright",
                       help="upright: any azimuth, limited elevation and roll (y is up); "
                            "uniform: any rotation (default: %(default)s)")
        p.add_argument("--max_elevation", type=float, default=0.5,
                       help="upright cameras: elevation within +- this (radians), roll "
                            "within half of it (default: %(default)s)")
        p.add_argument("--test_fraction", type=float, default=0.2,
                       help="fraction of the frame blocks (--hold_out=clips: of the clips) "
                            "held out as test frames (default: %(default)s)")
        p.add_argument("--n_blocks", type=int, default=10,
                       help="contiguous frame blocks the sequence (or each clip) is cut into "
                            "for the split (default: %(default)s)")
        p.add_argument("--occlusion", type=float, default=0.0,
                       help="probability that a point is hidden in a view; 3 points stay "
                            "visible (default: %(default)s)")
        p.add_argument("--noise", type=float, default=0.0,
                       help="std of 2D noise, in units of the sequence scaled to RMS radius 1 "
                            "(default: %(default)s)")
        p.add_argument("--seed", type=int, default=0,
                       help="seed of the split, cameras, occlusion and noise (default: "
                            "%(default)s)")
        p.add_argument("--hold_out", choices=("blocks", "clips"), default="blocks",
                       help="test blocks inside every clip, or whole clips (clips: needs a "
                            "per-frame clip array beside the sequence; default: %(default)s)")
        p.add_argument("--up", choices=("x", "y", "z"), default="y",
                       help="the sequence's up axis; upright cameras keep it vertical (z-up "
                            "data is turned to y-up first; default: %(default)s)")
        p.add_argument("--skeleton", default=None, help=_SKELETON_HELP + (
            " (default: the BVH file's bones)" if kind == "bvh" else " (default: none)"))
        if kind == "sequence":
            p.add_argument("--key", default="X",
                           help="the array that holds the points (default: %(default)s, or the "
                                "file's only array)")
            p.add_argument("--clip_key", default="clip",
                           help="the array of per-frame clip ids, if any (default: %(default)s)")
            p.add_argument("--layout", choices=LAYOUTS, default=None,
                           help="the array's axis order, F frames, 3 coordinates, K points "
                                "(default: guessed, (F, 3, K) or (F, K, 3); a 2D array is "
                                "(3F, K))")
        else:
            p.add_argument("--end_sites", action="store_true",
                           help="keep the End Sites (head top, toe tips, ...) as points too")
    p = sub.add_parser("coco", help="2D-only data from COCO-style keypoint annotations")
    p.add_argument("path", help="COCO-style keypoint annotations (.json)")
    out = p.add_mutually_exclusive_group(required=True)
    out.add_argument("--out", help="the JSON file to write (all annotations)")
    out.add_argument("--out_dir", help="writes OUT_DIR/NAME_train.json and NAME_test.json, "
                     "the test file with the annotations of a --test_fraction of the images")
    p.add_argument("--name", default=None, help="with --out_dir: the dataset name (default: "
                   "the file's stem)")
    p.add_argument("--test_fraction", type=float, default=0.2,
                   help="with --out_dir: fraction of the images held out (default: %(default)s)")
    p.add_argument("--seed", type=int, default=0,
                   help="with --out_dir: seed of the split (default: %(default)s)")
    p.add_argument("--min_v", type=int, default=1,
                   help="a point is visible when its flag v >= this (1: labelled, 2: labelled "
                        "and visible; default: %(default)s)")
    p.add_argument("--category_id", type=int, default=None,
                   help="keep only annotations of this category (default: all)")
    p.add_argument("--skeleton", default=None,
                   help=_SKELETON_HELP + " (default: the category's 'skeleton', if any)")
    args = parser.parse_args(argv)
    if args.kind == "coco":
        obj = json_dataset.read_json(args.path)
        name = args.name or os.path.splitext(os.path.basename(args.path))[0]
        data = coco_to_data(obj, min_v=args.min_v, category_id=args.category_id,
                            name=name if args.out_dir else "coco")
        style = dict(y_up=False, unit="px",
                     skeleton=args.skeleton or coco_skeleton(obj, args.category_id))
        if args.out_dir:
            test = image_split(data.image_path, args.test_fraction, args.seed)
            _write_pair(data.subset(~test), data.subset(test), args.out_dir, name, **style)
            print("2D only: --config.data.protocol=none")
            return
        save(data, args.out, **style)
        print(f"wrote {args.out} ({len(data)} samples, K={data.n_keypoints}): "
              f"--config.model.n_keypoints={data.n_keypoints} --config.data.protocol=none "
              "(2D only)")
        return
    name = args.name or os.path.splitext(os.path.basename(args.path))[0]
    bones = None
    if args.kind == "bvh":
        with open(args.path) as f:
            text = f.read()
        x, _ = bvh_positions(text, args.end_sites)
        bones = bvh_bones(text, args.end_sites)
        clip = None
    else:
        x = load_sequence(args.path, args.key, args.layout)
        clip = load_clips(args.path, args.clip_key)
    x = to_y_up(x, args.up)
    train, test = views_from_sequence(
        x, views_per_frame=args.views_per_frame, cameras=args.cameras,
        max_elevation=args.max_elevation, test_fraction=args.test_fraction,
        n_blocks=args.n_blocks, occlusion=args.occlusion, noise=args.noise, seed=args.seed,
        name=name, clip=clip, hold_out=args.hold_out)
    # Upright cameras keep the sequence's y axis up in every view; uniform ones have no up.
    _write_pair(train, test, args.out_dir, name, y_up=args.cameras == "upright",
                skeleton=args.skeleton or bones)


def cli_main() -> None:
    """The ``c3dpo-import`` console script: ``main`` with errors in the input (files, their
    contents, argument values) as one line ``error: ...`` and exit status 2, as the other
    commands print them (``--verbose``: the traceback instead)."""
    argv = sys.argv[1:]
    verbose = "--verbose" in argv
    # What was read (F, K, layout) is logged as by the other commands, whose absl.app sets
    # this up: argparse reads these arguments, so absl's own flags keep their defaults.
    flags.FLAGS.mark_as_parsed()
    logging.use_absl_handler()
    logging.set_verbosity(logging.INFO)
    cli.setup_logging()
    # The command's name as it was typed: the console script's, or "python -m ..." for this file.
    prog = os.path.basename(sys.argv[0])
    if prog.endswith(".py"):
        prog = "python -m c3dpo_jax.data.importers"
    try:
        main([a for a in argv if a != "--verbose"], prog=prog)
    except cli.USER_ERRORS as err:
        if verbose:
            raise
        cli.fail(err)


if __name__ == "__main__":
    cli_main()
