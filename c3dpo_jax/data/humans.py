"""Synthetic humans (an S-Up3D analogue), generated in code (numpy only, seeded).

An articulated body in Human3.6M's 17-joint order (0 hip/root, 1-3 right leg, 4-6 left
leg, 7 spine, 8 thorax, 9 neck/nose, 10 head, 11-13 left arm, 14-16 right arm; the
bones are the release's ``h36m`` skeleton pairs) with varied limb proportions, random
poses within joint-angle limits, optionally a dense set of surface points on capsules
around the bones, each pose seen by ``views_per_pose`` random cameras (the paper used
30) and projected orthographically. A point is hidden when the ray from it towards the
camera passes through another body capsule (self-occlusion, computed geometrically).

Body frame: x to the person's left, y up, z forward; metres. Camera frame: the camera
looks along +z (depth grows away from it), ``kp = kp3d[..., :2]``.
Glossary: P poses, V views per pose, M = P V samples, J = 17 joints, N = J + dense.
"""

import numpy as np

from c3dpo_jax.data.dataset import KeypointData
from c3dpo_jax.data.rotations import axis_rotation, random_rotations, upright_rotations

PARENTS = (-1, 0, 1, 2, 0, 4, 5, 0, 7, 8, 9, 8, 11, 12, 8, 14, 15)
JOINT_NAMES = ("hip", "r_hip", "r_knee", "r_ankle", "l_hip", "l_knee", "l_ankle", "spine",
               "thorax", "neck", "head", "l_shoulder", "l_elbow", "l_wrist", "r_shoulder",
               "r_elbow", "r_wrist")
# Rest-pose offset of each joint from its parent (arms hanging down).
REST_OFFSETS = np.array([
    [0, 0, 0], [-0.13, 0, 0], [0, -0.45, 0], [0, -0.42, 0], [0.13, 0, 0], [0, -0.45, 0],
    [0, -0.42, 0], [0, 0.24, 0], [0, 0.26, 0], [0, 0.12, 0.05], [0, 0.14, -0.03],
    [0.18, -0.02, 0], [0, -0.29, 0], [0, -0.26, 0], [-0.18, -0.02, 0], [0, -0.29, 0],
    [0, -0.26, 0]], np.float64)
# Capsule radius of the bone ending at each joint (joint 0 has no bone).
_RADII = np.array([0, 0.1, 0.08, 0.055, 0.1, 0.08, 0.055, 0.12, 0.14, 0.05, 0.1, 0.07,
                   0.05, 0.04, 0.07, 0.05, 0.04])
# Local joint-angle limits (radians): rows = joints, columns = (x flexion, y twist,
# z abduction) ranges. A rotation at joint j moves the bones of j's children.
_LIMITS = np.zeros((17, 3, 2))
_LIMITS[0] = [[-0.25, 0.35], [0, 0], [-0.15, 0.15]]  # whole-body lean
for _j, _s in ((1, -1), (4, 1)):  # hips: leg raised forward (-x) or back, spread out
    _LIMITS[_j] = [[-1.4, 0.4], [-0.4, 0.4], sorted((_s * -0.15, _s * 0.5))]
for _j in (2, 5):  # knees bend backwards only
    _LIMITS[_j] = [[0.0, 1.8], [0, 0], [0, 0]]
_LIMITS[7] = [[-0.3, 0.8], [-0.5, 0.5], [-0.3, 0.3]]  # lower spine
_LIMITS[8] = [[-0.2, 0.4], [-0.4, 0.4], [-0.2, 0.2]]  # thorax
_LIMITS[9] = [[-0.4, 0.6], [-0.8, 0.8], [-0.3, 0.3]]  # neck
for _j, _s in ((11, 1), (14, -1)):  # shoulders: raise forward (-x), sideways (+-z)
    _LIMITS[_j] = [[-2.4, 0.6], [-0.8, 0.8], sorted((_s * -0.2, _s * 2.0))]
for _j in (12, 15):  # elbows: forearm forwards
    _LIMITS[_j] = [[-2.4, 0.0], [-0.5, 0.5], [0, 0]]


def _euler(angles: np.ndarray) -> np.ndarray:
    """(..., 3) angles about x, y, z -> (..., 3, 3) rotations R = Ry Rx Rz."""
    rx, ry, rz = (axis_rotation(a, angles[..., i]) for i, a in enumerate("xyz"))
    return ry @ rx @ rz


def random_proportions(rng: np.random.Generator, p: int, spread: float = 1.0) -> np.ndarray:
    """(P, J, 3) rest offsets: body height (+-15% x spread) and each limb's length
    (+-10% x spread) vary per person; ``spread=0``: everyone has the same body."""
    height = 1 + spread * rng.uniform(-0.15, 0.15, size=(p, 1, 1))
    limb = 1 + spread * rng.uniform(-0.1, 0.1, size=(p, 17, 1))
    for left, right in ((1, 4), (2, 5), (3, 6), (11, 14), (12, 15), (13, 16)):
        limb[:, right] = limb[:, left]  # left and right limbs match
    return REST_OFFSETS[None] * height * limb


def random_joint_angles(rng: np.random.Generator, p: int) -> np.ndarray:
    """(P, J, 3) local joint angles within the limits, triangular between them (extreme
    angles are rarer than middle ones)."""
    lo, hi = _LIMITS[..., 0], _LIMITS[..., 1]
    return lo + (hi - lo) * rng.uniform(size=(2, p, 17, 3)).mean(0)


def forward_kinematics(offsets: np.ndarray, angles: np.ndarray):
    """Joint positions (P, J, 3) and global frames (P, J, 3, 3) from rest offsets and
    local Euler angles (P, J, 3); joint j's frame rotates the bones of its children."""
    local = _euler(angles)
    pos = np.zeros(offsets.shape)
    frames = np.zeros(local.shape)
    frames[:, 0] = local[:, 0]
    for j in range(1, 17):
        parent = PARENTS[j]
        pos[:, j] = pos[:, parent] + np.einsum("pij,pj->pi", frames[:, parent], offsets[:, j])
        frames[:, j] = frames[:, parent] @ local[:, j]
    return pos, frames


# COCO's 17 person keypoints, the order of the common 2D detectors.
COCO_JOINT_NAMES = ("nose", "l_eye", "r_eye", "l_ear", "r_ear", "l_shoulder", "r_shoulder",
                    "l_elbow", "r_elbow", "l_wrist", "r_wrist", "l_hip", "r_hip", "l_knee",
                    "r_knee", "l_ankle", "r_ankle")
# COCO's body joints (5-16) as joints of the Human3.6M order above.
_COCO_BODY = (11, 14, 12, 15, 13, 16, 4, 1, 5, 2, 6, 3)
# COCO's face points (nose, eyes, ears) in a head frame at the neck joint (9): x to the
# left, y along the neck-to-head bone, z forward; metres for a neck-to-head bone of
# _HEAD_BONE, scaled with it. Estimates of an adult's head, not measurements.
_FACE = np.array([[0.0, 0.06, 0.10], [0.032, 0.09, 0.08], [-0.032, 0.09, 0.08],
                  [0.075, 0.07, -0.01], [-0.075, 0.07, -0.01]])
_HEAD_BONE = float(np.linalg.norm(REST_OFFSETS[10]))


def coco_from_h36m(joints: np.ndarray) -> np.ndarray:
    """(..., 17, 3) people in Human3.6M's joint order -> (..., 17, 3) in COCO's
    (``COCO_JOINT_NAMES``): the shoulders, elbows, wrists, hips, knees and ankles are the
    same joints; the nose, eyes and ears are placed on the head (``_FACE``), in a frame
    whose up axis is the neck-to-head bone, whose left axis is the left shoulder's side
    (made perpendicular to it) and whose forward axis completes a right-handed frame (so a
    body's mirror image gets the mirrored face). Rotating or shifting the input does the same
    to the output."""
    joints = np.asarray(joints, np.float64)
    neck, head = joints[..., 9, :], joints[..., 10, :]
    bone = head - neck
    length = np.linalg.norm(bone, axis=-1, keepdims=True)
    up = bone / np.maximum(length, 1e-12)
    side = joints[..., 11, :] - joints[..., 14, :]
    left = side - np.sum(side * up, -1, keepdims=True) * up
    left = left / np.maximum(np.linalg.norm(left, axis=-1, keepdims=True), 1e-12)
    forward = np.cross(left, up)
    frame = np.stack([left, up, forward], axis=-1)  # columns: the head frame's axes
    face = neck[..., None, :] + (length[..., None] / _HEAD_BONE) * np.einsum(
        "...ij,fj->...fi", frame, _FACE)
    return np.concatenate([face, joints[..., list(_COCO_BODY), :]], axis=-2)


def coco_visibility_from_h36m(vis: np.ndarray) -> np.ndarray:
    """(..., 17) visibility flags in Human3.6M's order -> COCO's (``coco_from_h36m``): the
    limbs' joints keep theirs, the nose, eyes and ears take the head's (joint 10)."""
    vis = np.asarray(vis)
    return np.concatenate([np.repeat(vis[..., 10:11], 5, -1), vis[..., list(_COCO_BODY)]], -1)


def mean_pose(n: int = 2000, seed: int = 0, order: str = "h36m") -> np.ndarray:
    """(17, 3) the generator's average body: the mean joint positions of ``n`` random
    people in random poses, each centred (y up, facing +z, the left side at +x; the rest
    pose is nearly flat, the average one has its knees, wrists and head to the front). A
    reference for the handedness of reconstructions in this joint order: ``order`` "h36m"
    (Human3.6M's, the generator's) or "coco" (``coco_from_h36m``)."""
    if order not in ("h36m", "coco"):
        raise ValueError(f"unknown joint order {order!r} (known: h36m, coco)")
    rng = np.random.default_rng(seed)
    pos, _ = forward_kinematics(random_proportions(rng, n), random_joint_angles(rng, n))
    if order == "coco":
        pos = coco_from_h36m(pos)
    return (pos - pos.mean(1, keepdims=True)).mean(0)


def _surface_template(n: int, seed: int):
    """Fixed surface parametrisation: bone (ends at joint), t along it, angle around it."""
    rng = np.random.default_rng(seed + 7919)
    length = np.linalg.norm(REST_OFFSETS, axis=1) * _RADII  # area-like weights per bone
    bone = rng.choice(np.arange(1, 17), size=n, p=length[1:] / length[1:].sum())
    return bone, rng.uniform(0.05, 0.95, n), rng.uniform(-np.pi, np.pi, n)


def _perpendiculars(offset: np.ndarray):
    d = offset / np.linalg.norm(offset)
    helper = np.array([0.0, 0.0, 1.0]) if abs(d[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    u = np.cross(d, helper)
    u /= np.linalg.norm(u)
    return u, np.cross(d, u)


def surface_points(offsets, pos, frames, template):
    """(P, n, 3) points on the capsules, and their outward normals (P, n, 3)."""
    bone, t, phi = template
    parent = np.array(PARENTS)[bone]
    u0, v0 = zip(*(_perpendiculars(REST_OFFSETS[b]) for b in bone), strict=True)
    rest_normal = np.cos(phi)[:, None] * np.array(u0) + np.sin(phi)[:, None] * np.array(v0)
    normal = np.einsum("pnij,nj->pni", frames[:, parent], rest_normal)
    axis = pos[:, parent] + t[None, :, None] * (pos[:, bone] - pos[:, parent])
    return axis + _RADII[bone][None, :, None] * normal, normal


def _spheres(pos: np.ndarray, per_bone: int = 12):
    """Capsules as sphere sweeps: centres (M, S, 3), radii (S,), bone of each (S,)."""
    t = np.linspace(0, 1, per_bone)
    bones = np.arange(1, 17)
    a, b = pos[:, np.array(PARENTS)[bones]], pos[:, bones]
    centres = a[:, :, None] + t[None, None, :, None] * (b - a)[:, :, None]
    return (centres.reshape(len(pos), -1, 3), np.repeat(_RADII[bones], per_bone),
            np.repeat(bones, per_bone))


def occlusion_visibility(points: np.ndarray, centres: np.ndarray, radii: np.ndarray,
                         exclude: np.ndarray, chunk: int = 64) -> np.ndarray:
    """(M, N) 1 where the ray from each point towards the camera (-z) misses every
    sphere not excluded for that point (``exclude`` (N, S) bool) and not containing it
    (a joint lies inside the flesh around it, and that flesh does not hide it)."""
    out = np.ones(points.shape[:2], np.float32)
    for s in range(0, len(points), chunk):
        p = points[s : s + chunk, :, None].astype(np.float32)
        c = centres[s : s + chunk, None].astype(np.float32)
        d2 = ((p[..., :2] - c[..., :2]) ** 2).sum(-1)
        half = np.sqrt(np.maximum(radii**2 - d2, 0.0))
        inside = d2 + (p[..., 2] - c[..., 2]) ** 2 < radii**2  # a point is not hidden by
        hit = (d2 < radii**2) & (c[..., 2] - half < p[..., 2] - 1e-3) & ~exclude & ~inside
        out[s : s + chunk] = ~hit.any(-1)
    return out


def _joint_exclusions(sphere_bone: np.ndarray) -> np.ndarray:
    """(J, S): a joint is never hidden by the capsules of the bones that meet at it."""
    parents = np.array(PARENTS)
    ex = np.zeros((17, len(sphere_bone)), bool)
    for j in range(17):
        touching = (sphere_bone == j) | (parents[sphere_bone] == j)
        ex[j] = touching
    return ex


def make_split(n_poses: int, *, views_per_pose: int = 30, dense_points: int = 0,
               cameras: str = "upright", max_elevation: float | int = 0.5, noise: float | int = 0.0,
               self_occlusion: bool = True, proportions: float | int = 1.0,
               seed: int = 0) -> KeypointData:
    """``n_poses * views_per_pose`` views of ``n_poses`` random people and poses.

    Keypoints are the 17 joints followed by ``dense_points`` surface points (the same
    surface parametrisation for every person, so the points correspond).
    """
    if not 0 <= proportions <= 5:  # beyond ~6.7 some heights would be negative
        raise ValueError(f"humans proportions spread must be in [0, 5], got {proportions}")
    rng = np.random.default_rng(seed)
    offsets = random_proportions(rng, n_poses, proportions)
    angles = random_joint_angles(rng, n_poses)
    pos, frames = forward_kinematics(offsets, angles)
    points, normals = pos, np.zeros_like(pos)
    if dense_points:
        surf, surf_n = surface_points(offsets, pos, frames, _surface_template(dense_points, 0))
        points = np.concatenate([pos, surf], 1)
        normals = np.concatenate([normals, surf_n], 1)
    centroid = pos.mean(1, keepdims=True)
    points, pos = points - centroid, pos - centroid
    m = n_poses * views_per_pose
    rots = (random_rotations(rng, m) if cameras == "uniform"
            else upright_rotations(rng, m, max_elevation))
    rep = np.repeat(np.arange(n_poses), views_per_pose)
    kp3d = np.einsum("mij,mnj->mni", rots, points[rep])
    n = points.shape[1]
    vis = np.ones((m, n), np.float32)
    if self_occlusion:
        centres, radii, sphere_bone = _spheres(np.einsum("mij,mnj->mni", rots, pos[rep]))
        # Surface points start just outside their own capsule, so the back side of a
        # limb hides them; joints ignore the capsules that meet at them.
        start = kp3d + 0.01 * np.einsum("mij,mnj->mni", rots, normals[rep])
        exclude = np.zeros((n, len(radii)), bool)
        exclude[:17] = _joint_exclusions(sphere_bone)
        vis = occlusion_visibility(start, centres, radii, exclude)
    kp = kp3d[..., :2] + noise * rng.normal(size=(m, n, 2))
    kp = kp * vis[..., None]  # the release's files zero invisible points
    return KeypointData(kp=kp.astype(np.float32), vis=vis, kp3d=kp3d.astype(np.float32),
                        name="humans")


def make_splits(n_train_poses: int = 300, n_test_poses: int = 50, views_per_pose: int = 30,
                dense_points: int = 0, cameras: str = "upright", max_elevation: float | int = 0.5,
                noise: float | int = 0.0, self_occlusion: bool = True,
                proportions: float | int = 1.0, seed: int = 0
                ) -> tuple[KeypointData, KeypointData]:
    """Train and test splits with different people and poses; reproducible from ``seed``."""
    common = dict(views_per_pose=views_per_pose, dense_points=dense_points, cameras=cameras,
                  max_elevation=max_elevation, noise=noise, self_occlusion=self_occlusion,
                  proportions=proportions)
    return (make_split(n_train_poses, seed=seed * 2 + 1, **common),
            make_split(n_test_poses, seed=seed * 2 + 2, **common))
