"""Reference bodies for the handedness at inference, on the host (numpy only).

A body is one 3D example of a model's points, ``(N, 3)`` rows of (x, y, z) in the model's
order, in any position, orientation and scale: the built-in humans' average body in a
known joint order (``HUMAN_BODIES``), or a user's own, from an array or a file
(``BODY_FILE_SUFFIXES``). ``lift.reference_body`` picks one for an inference config.
"""

import functools
import json
import os

import numpy as np

from c3dpo_jax.data import humans

# The built-in bodies, with the number of points of their joint order (the built-in humans'
# average body, ``humans.mean_pose``): "h36m", a person in Human3.6M's 17-joint order
# (pelvis, right leg, left leg, spine, thorax, neck, head, left arm, right arm, as
# ``skeletons.SKELETONS["h36m"]`` joins them); "coco", in COCO's 17 person keypoints, the
# common 2D detectors' order (nose, eyes, ears, then shoulders, elbows, wrists, hips, knees,
# ankles, left before right; ``humans.coco_from_h36m``).
HUMAN_BODIES = {"h36m": 17, "coco": 17}
# Files a body is read from (``read_body``).
BODY_FILE_SUFFIXES = (".npy", ".json", ".txt", ".csv")
# A body whose centred points' smallest singular value is below this fraction of their
# largest lies near a plane (or a line): its mirror image is nearly itself, so it has no
# handedness to give (the built-in humans' average body: 0.20).
BODY_MIN_THICKNESS = 0.05


@functools.lru_cache
def human_body(name: str) -> np.ndarray:
    """The built-in body ``name`` of ``HUMAN_BODIES``, (17, 3) float32, read-only, made once
    per process (numpy, not jax: a jax array made while a function is traced would be that
    trace's)."""
    body = np.asarray(humans.mean_pose(order=name), np.float32)
    body.setflags(write=False)
    return body


def is_body_file(name) -> bool:
    """Whether ``name`` names a file to read a body from (by its suffix)."""
    return isinstance(name, str) and name.lower().endswith(BODY_FILE_SUFFIXES)


def read_body(path: str) -> np.ndarray:
    """The (N, 3) body in ``path``: a ``.npy`` array, a ``.json`` list of N ``[x, y, z]``,
    or ``.txt`` / ``.csv`` text of N rows of three numbers (spaces or commas). One-line
    ``ValueError`` for a file that cannot be read as that."""
    path = os.path.expanduser(path)
    if not os.path.exists(path):
        raise ValueError(f"body file {path!r} does not exist")
    try:
        if path.lower().endswith(".npy"):
            body = np.load(path, allow_pickle=False)
        elif path.lower().endswith(".json"):
            with open(path, encoding="utf-8-sig") as f:
                body = json.load(f)
        else:
            with open(path, encoding="utf-8-sig") as f:
                body = np.loadtxt(f.read().replace(",", " ").splitlines(), ndmin=2)
        body = np.asarray(body, np.float64)
    except (ValueError, TypeError, OSError) as err:
        raise ValueError(f"body file {path!r} is not N rows of (x, y, z): "
                         f"{str(err).splitlines()[0] if str(err) else type(err).__name__}"
                         ) from None
    if body.ndim != 2 or body.shape[1] != 3:
        raise ValueError(f"body file {path!r} holds an array of shape {body.shape}; a body is "
                         "N rows of (x, y, z)")
    return body


def body_problem(body, n_keypoints: int) -> str:
    """Why ``body`` cannot give the views of a model of ``n_keypoints`` points their
    handedness ('' if it can)."""
    try:
        b = np.asarray(body, np.float64)
    except (TypeError, ValueError):
        return "a body is N rows of (x, y, z)"
    if b.shape != (n_keypoints, 3):
        return (f"a body of the model's {n_keypoints} points, N rows of (x, y, z); "
                f"got shape {b.shape}")
    if not np.isfinite(b).all():
        return "the body has NaN or inf"
    s = np.linalg.svd(b - b.mean(0), compute_uv=False)
    if not s[0] > 0 or s[2] < BODY_MIN_THICKNESS * s[0]:
        return ("the body's points lie near one plane, so its mirror image is nearly itself "
                "and it has no handedness to give")
    return ""
