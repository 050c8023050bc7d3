"""Trivial baselines: exact on rigid data, Procrustes mean undoes rotations."""

import numpy as np
from scipy.spatial.transform import Rotation

from c3dpo_jax import baselines, evaluation
from c3dpo_jax.data import KeypointData


def test_fitted_mean_shape_is_exact_on_rigid_orthographic_views():
    rng = np.random.default_rng(0)
    shape = rng.normal(size=(12, 3)) * [1.0, 0.6, 0.3]
    rots = Rotation.random(50, random_state=1).as_matrix()
    gt = np.einsum("mij,nj->mni", rots, shape) * 2.0 + [3.0, -1.0, 0.0]  # scaled, shifted
    vis = (rng.uniform(size=(50, 12)) > 0.2).astype(float)
    vis[:, :4] = 1
    mean = baselines.procrustes_mean_shape(gt)
    pred = baselines.fit_mean_shape(mean, gt[..., :2], vis)
    data = KeypointData(kp=gt[..., :2], vis=vis, kp3d=gt)
    assert evaluation.evaluate(pred, data)["mpjpe"] < 1e-6


def test_procrustes_mean_recovers_the_shape_up_to_rotation():
    rng = np.random.default_rng(2)
    shape = rng.normal(size=(10, 3))
    shape -= shape.mean(0)
    rots = Rotation.random(30, random_state=3).as_matrix()
    shapes = np.einsum("mij,nj->mni", rots, shape)
    mean = baselines.procrustes_mean_shape(shapes)
    d_mean = np.linalg.norm(mean[:, None] - mean[None], axis=-1)
    d_true = np.linalg.norm(shape[:, None] - shape[None], axis=-1)
    np.testing.assert_allclose(d_mean, d_true, atol=1e-8)


def test_oracle_mean_shape_matches_scipy_alignment_on_deformed_shapes():
    rng = np.random.default_rng(4)
    mean = rng.normal(size=(9, 3))
    rots = Rotation.random(20, random_state=5).as_matrix()
    deformed = mean[None] + 0.2 * rng.normal(size=(20, 9, 3))
    gt = np.einsum("mij,mnj->mni", rots, deformed) + rng.normal(size=(20, 1, 3))
    vis = np.ones((20, 9))
    vis[:, 6:] = rng.uniform(size=(20, 3)) > 0.5  # hidden points do not steer the fit
    pred = baselines.oracle_mean_shape(mean, gt, vis)
    for m in range(20):
        on = vis[m] > 0
        src = mean[on] - mean[on].mean(0)
        dst = gt[m, on] - gt[m, on].mean(0)
        rot, _ = Rotation.align_vectors(dst, src)
        expected = rot.apply(mean - mean[on].mean(0)) + gt[m, on].mean(0)
        np.testing.assert_allclose(pred[m], expected, atol=1e-9)
