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


def _low_rank_views(n_views=60, n_points=15, n_basis=3, seed=6):
    """Views of shapes mean + basis @ coefficients under random rotations (N, 3 GT)."""
    rng = np.random.default_rng(seed)
    mean = rng.normal(size=(n_points, 3)) * [1.0, 0.7, 0.5]
    mean -= mean.mean(0)
    basis = rng.normal(size=(n_basis, n_points, 3))
    # No deformation may be a rotation or translation of the mean: project those out, so the
    # shapes' Procrustes alignment does not mix rotations into the deformations.
    rigid = [np.cross(np.eye(3)[k], mean).ravel() for k in range(3)]
    rigid += [np.tile(np.eye(3)[k], n_points) for k in range(3)]
    q, _ = np.linalg.qr(np.stack(rigid, 1))
    flat = basis.reshape(n_basis, -1)
    basis = 0.1 * (flat - (flat @ q) @ q.T).reshape(basis.shape)
    coef = rng.normal(size=(n_views, n_basis))
    shapes = mean + np.einsum("md,dnc->mnc", coef, basis)
    rots = Rotation.random(n_views, random_state=seed + 1).as_matrix()
    return np.einsum("mij,mnj->mni", rots, shapes), basis


def test_pca_basis_fit_recovers_the_depth_of_low_rank_shapes():
    gt, _ = _low_rank_views()
    model = baselines.pca_shape_basis(gt, n_basis=3)
    assert model.basis.shape == (3, 15, 3)
    assert model.noise_var < 1e-3 * model.variances.min()  # rank 3: little left over
    vis = np.ones(gt.shape[:2])
    vis[:, :3] = np.random.default_rng(7).uniform(size=(len(gt), 3)) > 0.3
    data = KeypointData(kp=gt[..., :2], vis=vis, kp3d=gt)
    fitted = baselines.fit_shape_basis(model, gt[..., :2], vis)
    mean_only = baselines.fit_mean_shape(model.mean, gt[..., :2], vis)
    assert evaluation.evaluate(mean_only, data)["mpjpe"] > 0.1
    assert evaluation.evaluate(fitted, data)["mpjpe"] < 1e-3  # 0.14 for the mean shape
    np.testing.assert_array_equal(fitted[..., :2][vis > 0], gt[..., :2][vis > 0])


def test_pca_basis_fit_shrinks_to_the_mean_shape_under_a_strong_prior():
    gt, _ = _low_rank_views(seed=8)
    model = baselines.pca_shape_basis(gt, n_basis=3)
    vis = np.ones(gt.shape[:2])
    strong = model._replace(noise_var=1e12)  # the prior pins every coefficient at 0
    np.testing.assert_allclose(baselines.fit_shape_basis(strong, gt[..., :2], vis),
                               baselines.fit_mean_shape(model.mean, gt[..., :2], vis), atol=1e-6)
    no_basis = baselines.pca_shape_basis(gt, n_basis=0)
    np.testing.assert_allclose(baselines.fit_shape_basis(no_basis, gt[..., :2], vis),
                               baselines.fit_mean_shape(no_basis.mean, gt[..., :2], vis))


def test_pca_basis_fit_is_the_same_in_chunks_and_with_few_training_shapes():
    gt, _ = _low_rank_views(n_views=50, seed=9)
    model = baselines.pca_shape_basis(gt, n_basis=3)
    vis = np.ones(gt.shape[:2])
    whole = baselines.fit_shape_basis(model, gt[..., :2], vis)
    np.testing.assert_allclose(baselines.fit_shape_basis(model, gt[..., :2], vis, chunk=7), whole)
    few = baselines.pca_shape_basis(gt[:3], n_basis=10)  # 3 shapes: at most 2 modes
    assert len(few.basis) == 2 and np.all(few.variances > 0)
    assert np.all(np.isfinite(baselines.fit_shape_basis(few, gt[..., :2], vis)))


def test_visible_mean_averages_only_visible_points_with_leading_axes():
    rng = np.random.default_rng(0)
    x = rng.normal(size=(4, 3, 6, 2))  # (B, M, N, C)
    vis = (rng.uniform(size=(3, 6)) > 0.4).astype(np.float32)
    vis[1] = 0.0  # a view with nothing visible
    got = baselines.visible_mean(x, vis)
    assert got.shape == (4, 3, 2)
    for b in range(4):
        for m in range(3):
            rows = x[b, m][vis[m] > 0]
            want = rows.mean(0) if len(rows) else np.zeros(2)
            np.testing.assert_allclose(got[b, m], want, atol=1e-12)
