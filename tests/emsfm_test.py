"""EM-SfM: recovers known low-rank shapes, never lowers the likelihood, exact on rigid views,
handles hidden points; its likelihood and posterior checked against dense Gaussians."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from scipy.stats import multivariate_normal

from c3dpo_jax import baselines, emsfm


def _low_rank_views(n_views=150, n_points=15, n_modes=2, hidden=0.15, noise=0.01, seed=0):
    """Camera-frame shapes mean + sum_d z_d V_d (z ~ N(0, I)) under random rotations, scales
    and offsets, their noisy 2D projections and a visibility mask."""
    rng = np.random.default_rng(seed)
    mean = rng.normal(size=(n_points, 3)) * [1.0, 0.7, 0.5]
    modes = 0.15 * rng.normal(size=(n_modes, n_points, 3))  # deformation ~30% of the shape
    shapes = mean + np.einsum("md,dnc->mnc", rng.normal(size=(n_views, n_modes)), modes)
    rots = Rotation.random(n_views, random_state=seed + 1).as_matrix()
    scale = rng.uniform(0.5, 2.0, n_views)[:, None, None]
    gt = scale * np.einsum("mij,mnj->mni", rots, shapes) + rng.normal(size=(n_views, 1, 3))
    kp = gt[..., :2] + noise * rng.normal(size=gt[..., :2].shape)
    vis = (rng.uniform(size=gt.shape[:2]) > hidden).astype(float)
    vis[:, :3] = 1
    return gt, kp, vis


def _point_errors(pred, gt):
    """(M, N) distances after removing each view's mean depth, per view the depth sign with
    the lower mean distance (the paper's protocol, written out here)."""
    pred = pred - [0, 0, 1] * pred[..., 2:].mean(1, keepdims=True)
    gt = gt - [0, 0, 1] * gt[..., 2:].mean(1, keepdims=True)
    errs = [np.linalg.norm(p - gt, axis=-1) for p in (pred, pred * [1, 1, -1])]
    return np.where((errs[0].mean(1) <= errs[1].mean(1))[:, None], errs[0], errs[1])


@pytest.fixture(scope="module")
def fitted():
    gt, kp, vis = _low_rank_views()
    return gt, kp, vis, emsfm.em_sfm(kp, vis, n_basis=2, n_iters=60)


def test_recovers_low_rank_shapes_to_within_noise_and_beats_the_rigid_fit(fitted):
    gt, kp, vis, res = fitted
    err = _point_errors(res.shapes, gt)
    assert err.mean() < 0.025  # 2D noise 0.01 per coordinate
    assert err[vis == 0].mean() < 0.03  # hidden points: from the model alone
    # The best rigid fit of the true shapes' own Procrustes mean is an order worse.
    rigid = baselines.fit_mean_shape(baselines.procrustes_mean_shape(gt), kp, vis)
    assert _point_errors(rigid, gt).mean() > 10 * err.mean()
    np.testing.assert_array_equal(res.shapes[..., :2][vis > 0], kp[vis > 0])


def test_cameras_are_scaled_rotations_that_reproject_the_canonical_shapes(fitted):
    _, kp, vis, res = fitted
    rot = res.rotations
    np.testing.assert_allclose(rot @ rot.transpose(0, 2, 1), np.broadcast_to(np.eye(3), rot.shape),
                               atol=1e-10)
    np.testing.assert_allclose(np.linalg.det(rot), 1.0, atol=1e-10)
    xy = res.scales[:, None, None] * res.canonical @ rot[:, :2].transpose(0, 2, 1)
    xy += res.translations[:, None]
    assert np.abs(xy - kp)[vis > 0].mean() < 0.02
    np.testing.assert_allclose(res.shapes[..., :2][vis == 0], xy[vis == 0], atol=1e-10)
    np.testing.assert_allclose(res.canonical, res.mean_shape + np.einsum(
        "md,dnc->mnc", res.coefficients, res.basis), atol=1e-10)


def test_likelihood_and_posterior_match_dense_gaussians(fitted):
    """The final log-likelihood and posterior means, recomputed per view from the covariance
    sigma^2 I + A A^T of the visible coordinates (no Woodbury, no moments)."""
    _, kp, vis, res = fitted
    total = 0.0
    for m in range(len(kp)):
        on = vis[m] > 0
        cam = res.scales[m] * res.rotations[m, :2]
        a = np.einsum("ij,dnj->nid", cam, res.basis[:, on]).reshape(-1, len(res.basis))
        mu = (res.mean_shape[on] @ cam.T + res.translations[m]).ravel()
        cov = res.noise_var * np.eye(len(mu)) + a @ a.T
        total += multivariate_normal(mu, cov).logpdf(kp[m, on].ravel())
        post = a.T @ np.linalg.solve(cov, kp[m, on].ravel() - mu)  # E[z | w] = A^T C^-1 r
        np.testing.assert_allclose(res.coefficients[m], post, rtol=1e-6, atol=1e-8)
    np.testing.assert_allclose(res.log_likelihood[-1], total, rtol=1e-9)


def test_log_likelihood_never_decreases():
    _, kp, vis = _low_rank_views(n_views=80, n_points=12, n_modes=3, hidden=0.25, seed=4)
    ll = emsfm.em_sfm(kp, vis, n_basis=3, n_iters=40, tol=0.0, seed=1).log_likelihood
    assert len(ll) == 41
    assert np.all(np.diff(ll) >= -1e-9 * np.abs(ll[1:]))
    assert ll[-1] > ll[0] + 100


def test_exact_rigid_views_give_zero_error_with_hidden_points():
    gt, kp, vis = _low_rank_views(n_views=60, n_points=12, n_modes=0, hidden=0.2, noise=0.0,
                                  seed=2)
    res = emsfm.em_sfm(kp, vis, n_basis=0)
    err = _point_errors(res.shapes, gt)
    assert err.max() < 1e-5 and err[vis == 0].size > 50
    assert res.basis.shape == (0, 12, 3) and res.coefficients.shape == (60, 0)


def test_hidden_values_change_nothing_and_the_seed_is_the_only_randomness():
    _, kp, vis = _low_rank_views(n_views=40, n_points=10, seed=3)
    first = emsfm.em_sfm(kp, vis, n_basis=2, n_iters=5, seed=7)
    junk = np.where(vis[..., None] > 0, kp, np.nan)
    junk[0, vis[0] == 0] = 1e20
    again = emsfm.em_sfm(junk, vis, n_basis=2, n_iters=5, seed=7)
    np.testing.assert_array_equal(first.shapes, again.shapes)
    other = emsfm.em_sfm(kp, vis, n_basis=2, n_iters=5, seed=8)
    assert not np.array_equal(first.basis, other.basis)


@pytest.mark.parametrize("change, message", [
    (dict(kp=np.zeros((5, 6, 3))), r"kp has shape \(5, 6, 3\), expected \(M, N, 2\)"),
    (dict(vis=np.ones((5, 7))), r"vis has shape \(5, 7\), expected \(5, 6\)"),
    (dict(n_basis=-1), "must be >= 0"),
    (dict(kp=np.ones((1, 6, 2)), vis=np.ones((1, 6))), "at least 2 views"),
    (dict(vis=np.eye(5, 6) + np.eye(5, 6, 1)), "5 views have fewer than 3 visible points"),
    (dict(vis=np.ones((5, 6)) * [1, 1, 1, 1, 1, 0]), "1 keypoints are visible in fewer than 2"),
    (dict(kp=np.full((5, 6, 2), np.inf)), "NaN or inf"),
])
def test_bad_inputs_are_one_line_errors(change, message):
    args = dict(kp=np.random.default_rng(0).normal(size=(5, 6, 2)), vis=np.ones((5, 6)))
    args.update(change)
    with pytest.raises(ValueError, match=message):
        emsfm.em_sfm(**args)
