"""Skeletons for pictures: index pairs of keypoints joined by a line (pure Python).

A skeleton is given as a built-in name (``SKELETONS``), as text ``"0-1,1-2,2-3"``, or as
a sequence of index pairs; ``skeleton(spec, n_keypoints)`` turns any of them into a checked
list of pairs. A data file may carry its own (``"skeleton"`` in the JSON wrapper, see
docs/data.md), and the BVH importer writes the file's bone hierarchy there
(``from_parents``). Glossary: N keypoints.
"""

from collections.abc import Sequence

# Keypoint index pairs of the release's plots.
SKELETONS: dict[str, list[tuple[int, int]]] = {
    "h36m": [(10, 9), (9, 8), (8, 14), (14, 15), (15, 16), (8, 11), (11, 12), (12, 13), (8, 7),
             (7, 0), (1, 0), (1, 2), (2, 3), (0, 4), (4, 5), (5, 6)],
    # COCO's person skeleton (its 1-based pairs less one): COCO's 17 keypoints, the order of
    # the common 2D detectors (``data.humans.COCO_JOINT_NAMES``).
    "coco": [(15, 13), (13, 11), (16, 14), (14, 12), (11, 12), (5, 11), (6, 12), (5, 6), (5, 7),
             (6, 8), (7, 9), (8, 10), (1, 2), (0, 1), (0, 2), (1, 3), (2, 4), (3, 5), (4, 6)],
    "cub_birds": [(1, 5), (5, 4), (4, 9), (9, 0), (0, 13), (0, 12), (0, 8), (12, 13), (1, 14),
                  (14, 3), (3, 2), (2, 7), (1, 10), (1, 6), (2, 11), (2, 7), (8, 13)],
    "pascal3d/car": [(0, 8), (0, 4), (4, 10), (8, 10), (10, 9), (9, 11), (8, 11), (11, 6), (9, 2),
                     (2, 6), (4, 1), (5, 1), (0, 5), (5, 7), (1, 3), (7, 3), (3, 2), (7, 6)],
    "pascal3d/aeroplane": [(2, 5), (1, 4), (5, 3), (3, 7), (7, 0), (0, 5), (5, 7), (5, 6), (6, 0),
                           (6, 3), (2, 4), (2, 1)],
    "pascal3d/motorbike": [(6, 2), (2, 9), (2, 3), (3, 8), (5, 8), (3, 5), (2, 1), (1, 0), (0, 7),
                           (0, 4), (4, 7), (1, 4), (1, 7), (1, 5), (1, 8)],
    "pascal3d/sofa": [(1, 5), (5, 4), (4, 6), (6, 2), (2, 0), (1, 0), (0, 4), (1, 3), (7, 5),
                      (2, 3), (3, 7), (9, 7), (7, 6), (6, 8), (8, 9)],
    "pascal3d/chair": [(7, 3), (6, 2), (9, 5), (8, 4), (7, 9), (8, 6), (6, 7), (9, 8), (9, 1),
                       (8, 0), (1, 0)],
}

Spec = str | Sequence[Sequence[int]] | None


def _parse_pairs(text: str) -> list[tuple[int, int]]:
    """``"0-1,1-2"`` (commas or spaces between pairs) -> [(0, 1), (1, 2)]."""
    pairs = []
    for item in text.replace(",", " ").split():
        a, sep, b = item.partition("-")
        if not (sep and a.strip().isdigit() and b.strip().isdigit()):
            raise ValueError(f"skeleton pair {item!r} is not of the form I-J (e.g. 0-1)")
        pairs.append((int(a), int(b)))
    return pairs


def skeleton(spec: Spec, n_keypoints: int) -> list[tuple[int, int]]:
    """The index pairs of ``spec`` for data with ``n_keypoints`` points.

    Args:
      spec: None or "" (no lines), a name in ``SKELETONS``, text ``"0-1,1-2"``, or pairs.
      n_keypoints: N of the data the lines are drawn on.

    Returns:
      The pairs, each index in [0, N).

    Raises:
      ValueError: an unknown name, a malformed pair, or an index outside [0, N).
    """
    if spec is None or (isinstance(spec, str) and not spec.strip()):
        return []
    if isinstance(spec, str):
        if spec in SKELETONS:
            pairs = SKELETONS[spec]
        elif spec[:1].isdigit():
            pairs = _parse_pairs(spec)
        else:
            raise ValueError(f"unknown skeleton {spec!r}: one of {', '.join(SKELETONS)}, or index "
                             "pairs such as '0-1,1-2'")
    else:
        pairs = [tuple(int(i) for i in pair) for pair in spec]
        if any(len(pair) != 2 for pair in pairs):
            raise ValueError(f"a skeleton is a list of index pairs, got {list(spec)!r}")
    bad = [p for p in pairs if min(p) < 0 or max(p) >= n_keypoints]
    if bad:
        name = f"skeleton {spec!r}" if isinstance(spec, str) and spec in SKELETONS else "skeleton"
        raise ValueError(f"{name} joins keypoints {bad[:3]} but the data has {n_keypoints} "
                         f"(indices 0-{n_keypoints - 1})")
    return [(int(a), int(b)) for a, b in pairs]


def from_parents(parents: Sequence[int]) -> list[tuple[int, int]]:
    """Bones of a kinematic tree (``parents[j]`` is j's parent, -1 for a root)."""
    return [(int(p), j) for j, p in enumerate(parents) if p >= 0]
