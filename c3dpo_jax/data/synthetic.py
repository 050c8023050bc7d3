"""Built-in low-rank non-rigid dataset, generated in code (numpy only, seeded).

Each sample is ``X = mean_shape + sum_d c_d B_d`` (N points, a few deformation
modes B_d), seen by a camera with a uniformly random (Haar) rotation, projected
orthographically (or perspectively with per-sample intrinsics), with each point
hidden at random with probability ``occlusion``. Ground truth ``kp3d`` is the
camera-frame shape, in the same units as ``kp``. Train and test use the same shape
space and different random poses and cameras, so test poses are unseen.
"""

import numpy as np

from c3dpo_jax.data.dataset import KeypointData
from c3dpo_jax.data.rotations import random_rotations, upright_rotations


def shape_model(n_keypoints: int, n_modes: int, deformation: float, seed: int):
    """Mean shape (N, 3) with unequal principal extents, and modes (n_modes, N, 3)."""
    rng = np.random.default_rng(seed)
    mean = rng.normal(size=(n_keypoints, 3)) * np.array([1.0, 0.6, 0.35])
    mean -= mean.mean(0)
    modes = rng.normal(size=(n_modes, n_keypoints, 3))
    modes -= modes.mean(1, keepdims=True)
    # Decreasing mode strengths, like a PCA spectrum.
    strengths = deformation / np.arange(1, n_modes + 1)
    modes *= strengths[:, None, None] / np.sqrt((modes**2).sum((1, 2)) / n_keypoints)[:, None, None]
    return mean.astype(np.float32), modes.astype(np.float32)


def make_split(
    n_samples: int,
    *,
    n_keypoints: int,
    n_modes: int,
    deformation: float,
    occlusion: float,
    noise: float,
    perspective: bool,
    shape_seed: int,
    seed: int,
    cameras: str = "uniform",
    max_elevation: float = 0.5,
) -> KeypointData:
    """One split of ``n_samples`` views of the shape space made by ``shape_seed``."""
    mean, modes = shape_model(n_keypoints, n_modes, deformation, shape_seed)
    rng = np.random.default_rng(seed)
    coeffs = rng.normal(size=(n_samples, n_modes)).astype(np.float32)
    shapes = mean + np.einsum("md,dnc->mnc", coeffs, modes)
    if cameras == "uniform":
        rots = random_rotations(rng, n_samples)
    elif cameras == "upright":
        rots = upright_rotations(rng, n_samples, max_elevation)
    else:
        raise ValueError(f"unknown cameras {cameras!r}: 'uniform' or 'upright'")
    rots = rots.astype(np.float32)
    kp3d = np.einsum("mij,mnj->mni", rots, shapes)
    vis = (rng.uniform(size=(n_samples, n_keypoints)) >= occlusion).astype(np.float32)
    # Keep at least three visible points per view, the least a rotation can be fit to.
    first = np.argsort(rng.uniform(size=(n_samples, n_keypoints)), axis=1)[:, :3]
    np.put_along_axis(vis, first, 1.0, axis=1)
    intrinsics = None
    if perspective:
        kp3d = kp3d + np.array([0.0, 0.0, 6.0], np.float32)
        focal = rng.uniform(400, 600, size=n_samples).astype(np.float32)
        centre = rng.uniform(200, 300, size=(n_samples, 2)).astype(np.float32)
        intrinsics = np.zeros((n_samples, 3, 3), np.float32)
        intrinsics[:, 0, 0] = intrinsics[:, 1, 1] = focal
        intrinsics[:, :2, 2] = centre
        intrinsics[:, 2, 2] = 1.0
        kp = kp3d[..., :2] / kp3d[..., 2:3] * focal[:, None, None] + centre[:, None, :]
    else:
        kp = kp3d[..., :2].copy()
    kp = kp + noise * rng.normal(size=kp.shape).astype(np.float32)
    kp = kp * vis[..., None]  # the release's files zero invisible points
    return KeypointData(
        kp=kp.astype(np.float32), vis=vis, kp3d=kp3d.astype(np.float32),
        intrinsics=intrinsics, name="synthetic",
    )


def make_splits(
    n_keypoints: int = 20,
    n_modes: int = 3,
    deformation: float = 0.35,
    occlusion: float = 0.1,
    noise: float = 0.0,
    perspective: bool = False,
    n_train: int = 5000,
    n_test: int = 1000,
    cameras: str = "uniform",
    max_elevation: float = 0.5,
    seed: int = 0,
) -> tuple[KeypointData, KeypointData]:
    """Train and test splits of one shape space; reproducible from ``seed``.

    ``cameras``: ``"uniform"`` (Haar-random rotations) or ``"upright"`` (any azimuth,
    elevation within ``max_elevation`` radians and roll within half of it).
    """
    common = dict(
        n_keypoints=n_keypoints, n_modes=n_modes, deformation=deformation,
        occlusion=occlusion, noise=noise, perspective=perspective, shape_seed=seed,
        cameras=cameras, max_elevation=max_elevation,
    )
    train = make_split(n_train, seed=seed + 1, **common)
    test = make_split(n_test, seed=seed + 2, **common)
    return train, test
