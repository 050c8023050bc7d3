"""Trivial baselines: exact on rigid data, optimal rigid fits, Procrustes mean undoes
rotations."""

import numpy as np
from scipy.optimize import minimize
from scipy.spatial.transform import Rotation

from c3dpo_jax import baselines, evaluation
from c3dpo_jax.data import KeypointData


def _residual(camera, kp, vis):
    """Per view, the mean squared 2D distance of the visible points to the camera's projection
    (written out here, independently of ``baselines.project``/``reprojection_residual``)."""
    scale, rows, centred, kp_mean = camera
    out = []
    for m in range(len(kp)):
        on = vis[m] > 0
        xy = scale[m] * centred[m, on] @ rows[m].T + kp_mean[m]
        out.append(((xy - kp[m, on]) ** 2).sum(1).mean() if on.any() else 0.0)
    return np.array(out)


def _deformed_views(n_views, n_points=12, seed=0):
    """A shape, and views of it deformed per view (anisotropic, non-rigid), occluded."""
    rng = np.random.default_rng(seed)
    shape = rng.normal(size=(n_points, 3)) * [1.0, 0.6, 0.3]
    deformed = shape + rng.normal(size=(n_views, n_points, 3)) * [0.05, 0.1, 0.4]
    rots = Rotation.random(n_views, random_state=seed + 1).as_matrix()
    kp = 1.5 * np.einsum("mij,mnj->mni", rots[:, :2], deformed) + rng.normal(size=(n_views, 1, 2))
    vis = (rng.uniform(size=(n_views, n_points)) > 0.2).astype(float)
    vis[:, :4] = 1
    return shape, kp, vis


def test_fitted_mean_shape_is_exact_on_rigid_orthographic_views():
    rng = np.random.default_rng(0)
    shape = rng.normal(size=(12, 3)) * [1.0, 0.6, 0.3]
    flip = np.ones((50, 3))
    flip[::3, 2] = -1  # every third view sees the mirror image of the shape (z negated)
    cams = Rotation.random(50, random_state=1).as_matrix() * flip[:, None]
    scale = rng.uniform(0.5, 3.0, 50)
    gt = scale[:, None, None] * np.einsum("mij,nj->mni", cams, shape) + rng.normal(size=(50, 1, 3))
    vis = (rng.uniform(size=(50, 12)) > 0.2).astype(float)
    vis[:, :4] = 1
    mean = baselines.procrustes_mean_shape(gt[1::3])  # only views of the shape, not its mirror
    pred = baselines.fit_mean_shape(mean, gt[..., :2], vis)
    data = KeypointData(kp=gt[..., :2], vis=vis, kp3d=gt)
    assert evaluation.evaluate(pred, data)["mpjpe"] < 1e-6
    # The true camera itself, from the one-shot start and from random ones, to rounding (the
    # one-shot camera alone is only good to ~1e-8 here).
    for start in (None, Rotation.random(50, random_state=2).as_matrix()[:, 2]):
        got_scale, got_rows, _, _ = baselines.fit_camera(shape, gt[..., :2], vis, start_axis=start)
        np.testing.assert_allclose(got_scale, scale, rtol=1e-12)
        np.testing.assert_allclose(got_rows, cams[:, :2], atol=1e-12)


def test_best_rigid_fit_is_never_worse_and_clearly_better_than_the_one_shot_fit():
    shape, kp, vis = _deformed_views(200)
    one_shot = _residual(baselines.fit_camera(shape, kp, vis, n_iters=0), kp, vis)
    camera = baselines.fit_camera(shape, kp, vis)
    refined = _residual(camera, kp, vis)
    assert np.all(refined <= one_shot * (1 + 1e-12))
    assert refined.mean() < 0.8 * one_shot.mean()
    np.testing.assert_allclose(baselines.reprojection_residual(baselines.project(*camera), kp, vis),
                               refined, rtol=1e-12)
    rows = camera[1]
    np.testing.assert_allclose(np.einsum("mij,mkj->mik", rows, rows), np.broadcast_to(
        np.eye(2), rows.shape[:1] + (2, 2)), atol=1e-12)
    # fit_mean_shape: observed x, y where visible, else the camera's; depth along the axis.
    pred = baselines.fit_mean_shape(shape, kp, vis, chunk=7)
    scale, _, centred, kp_mean = camera
    xy = scale[:, None, None] * np.einsum("mij,mnj->mni", rows, centred) + kp_mean[:, None]
    np.testing.assert_allclose(pred[..., :2], np.where(vis[..., None] > 0, kp, xy), atol=1e-12)
    depth = scale[:, None] * np.einsum("mnj,mj->mn", centred, np.cross(rows[:, 0], rows[:, 1]))
    np.testing.assert_allclose(pred[..., 2], depth, atol=1e-12)


def test_best_rigid_fit_matches_a_brute_force_optimiser_from_any_start():
    shape, kp, vis = _deformed_views(5, seed=3)
    brute = []
    for m in range(len(kp)):
        on = vis[m] > 0

        def error(p, m=m, on=on):  # axis-angle rotation, scale, translation
            xy = p[3] * shape[on] @ Rotation.from_rotvec(p[:3]).as_matrix()[:2].T + p[4:]
            return ((xy - kp[m, on]) ** 2).sum(1).mean()

        brute.append(min(
            minimize(error, np.r_[r, 1.0, kp[m, on].mean(0)], method="BFGS",
                     options={"gtol": 1e-12}).fun
            for r in Rotation.random(20, random_state=m).as_rotvec()))
    one_shot = _residual(baselines.fit_camera(shape, kp, vis, n_iters=0), kp, vis)
    assert np.all(one_shot > np.array(brute) * 1.01)  # the one-shot fit is not optimal here
    for start in (None, Rotation.random(len(kp), random_state=9).as_matrix()[:, 2]):
        got = _residual(baselines.fit_camera(shape, kp, vis, start_axis=start), kp, vis)
        np.testing.assert_allclose(got, brute, rtol=1e-6)


def test_degenerate_views_give_finite_fits():
    rng = np.random.default_rng(5)
    shape = rng.normal(size=(6, 3))
    kp = rng.normal(size=(6, 6, 2))
    vis = np.zeros((6, 6))
    for m, n in enumerate([0, 1, 2, 3, 6, 6]):
        vis[m, :n] = 1  # 0, 1, 2 visible points, then enough
    shapes = np.broadcast_to(shape, (6, 6, 3)).copy()
    shapes[4] = shape[0]  # all points coincide
    shapes[5] = np.outer(np.arange(6.0), [1.0, 2.0, 0.5])  # all on a line
    for n_iters in (0, 20):
        pred = baselines.fit_mean_shape(shapes, kp, vis, n_iters=n_iters)
        assert np.all(np.isfinite(pred))
        np.testing.assert_array_equal(pred[..., :2][vis > 0], kp[vis > 0])
    camera = baselines.fit_camera(shapes, kp, vis)
    assert all(np.all(np.isfinite(x)) for x in camera)
    one_shot = _residual(baselines.fit_camera(shapes, kp, vis, n_iters=0), kp, vis)
    got = _residual(camera, kp, vis)
    assert np.all(got <= one_shot + 1e-12)
    np.testing.assert_array_equal(got[:4], one_shot[:4])  # < 4 points: the one-shot camera


def test_views_with_three_points_keep_the_one_shot_scale():
    # The built-in humans' mean shape (limbs: nearly collinear triples), views of it deformed
    # a little, three visible points each: the least-2D-error camera of some views is a near
    # edge-on one with a scale hundreds of times the true 1, which fit_camera must not return.
    from c3dpo_jax.data import humans

    shape = baselines.procrustes_mean_shape(humans.make_split(20, views_per_pose=10, seed=1).kp3d)
    rng = np.random.default_rng(0)
    n_views = 4000
    rots = Rotation.random(n_views, random_state=1).as_matrix()
    kp = np.einsum("mij,mnj->mni", rots[:, :2], shape + 0.05 * rng.normal(size=(n_views, 17, 3)))
    vis = np.zeros((n_views, 17))
    for m in range(n_views):
        vis[m, rng.choice(17, 3, replace=False)] = 1
    y = (kp - baselines.visible_mean(kp, vis)[:, None]) * vis[..., None]
    x = (shape - baselines.visible_mean(np.broadcast_to(shape, (n_views, 17, 3)), vis)[:, None])
    least_error_scale, _ = baselines._refine_camera(rots[:, 2], x * vis[..., None], y, 10)
    assert least_error_scale.max() > 300 and np.mean(least_error_scale > 3) > 0.01
    scale = baselines.fit_camera(shape, kp, vis)[0]
    np.testing.assert_array_equal(scale, baselines.fit_camera(shape, kp, vis, n_iters=0)[0])
    assert scale.max() < 100 and np.mean(scale > 3) < 0.005 and 0.5 < np.median(scale) < 1.5


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


def test_one_scale_rigid_fit_finds_the_common_scale_and_each_view_rotation():
    rng = np.random.default_rng(4)
    shape = rng.normal(size=(12, 3)) * [1.0, 0.6, 0.3]
    cams = Rotation.random(40, random_state=5).as_matrix()
    gt = np.einsum("mij,nj->mni", cams, shape) + rng.normal(size=(40, 1, 3))
    vis = (rng.uniform(size=(40, 12)) > 0.2).astype(float)
    vis[:, :4] = 1
    data = KeypointData(kp=gt[..., :2], vis=vis, kp3d=gt)
    assert evaluation.evaluate(baselines.fit_mean_shape_one_scale(shape, gt[..., :2], vis),
                               data)["mpjpe"] < 1e-6
    # The 2D in other units (pixels): the least-squares scale is theirs.
    scale, rows, _, _ = baselines.one_scale_cameras(shape, 3.0 * gt[..., :2], vis)
    np.testing.assert_allclose(scale, 3.0, rtol=1e-8)
    np.testing.assert_allclose(rows, cams[:, :2], atol=1e-7)


def test_one_scale_rotations_match_a_brute_force_optimiser_at_that_scale():
    shape, kp, vis = _deformed_views(6, seed=7)
    scale, rows, centred, kp_mean = camera = baselines.one_scale_cameras(shape, kp, vis)
    assert np.all(scale == scale[0])
    brute = []
    for m in range(len(kp)):
        on = vis[m] > 0

        def error(p, m=m, on=on):  # rotation only: the scale is the split's, the mean fixed
            xy = scale[0] * centred[m, on] @ Rotation.from_rotvec(p).as_matrix()[:2].T
            return ((xy + kp_mean[m] - kp[m, on]) ** 2).sum(1).mean()

        brute.append(min(minimize(error, r, method="BFGS", options={"gtol": 1e-12}).fun
                         for r in Rotation.random(20, random_state=m).as_rotvec()))
    np.testing.assert_allclose(_residual(camera, kp, vis), brute, rtol=1e-4)
    # Per-view scales fit the 2D points at least as closely: one scale is a constraint.
    per_view = _residual(baselines.fit_camera(shape, kp, vis), kp, vis)
    assert np.all(per_view <= _residual(camera, kp, vis) * (1 + 1e-9))
