"""EM-SfM: non-rigid structure from motion with a Gaussian shape prior, fitted by EM.

Torresani, Hertzmann and Bregler, "Nonrigid Structure-from-Motion: Estimating Shape and
Motion with Hierarchical Priors", PAMI 2008, the probabilistic-PCA model (their EM-PPCA,
without the temporal dynamics): the NRSfM baseline of the C3DPO paper, which ran it
transductively on the test views. numpy only.

Glossary: M views, N keypoints, D shape-basis size. Keypoints ``kp (M, N, 2)``,
visibility ``vis (M, N)`` in {0, 1}; mean shape ``(N, 3)``, basis ``(D, N, 3)``.

Model (per view f, point n, visible points only):
  S_f = S_mean + sum_d z_fd V_d,          z_f ~ N(0, I_D)
  w_fn = G_f S_fn + t_f + e_fn,           e_fn ~ N(0, sigma^2 I_2),  G_f = c_f R_f
with R_f the first two rows of a rotation and c_f >= 0 the scale of a scaled orthographic
camera. Writing B_n = [S_mean,n, V_1n, ..., V_Dn] (3, D + 1) and zh_f = [1, z_f]:
  E-step: the Gaussian posterior of z_f given the visible points,
    Cov = sigma^2 (sigma^2 I + A^T A)^-1,  E[z] = (sigma^2 I + A^T A)^-1 A^T r,
    A (2N_f, D) the projected basis G_f V_dn, r the residual w - G_f S_mean - t_f.
  M-step (conditional steps, each raising or keeping the expected complete log-likelihood
  given the others, so the marginal likelihood never decreases: a generalised EM):
    shape: per point n, linear least squares for B_n with the moments E[zh], E[zh zh^T];
    camera and translation: the scaled orthographic camera minimising
      tr(G Q G^T) - 2 tr(G P^T), P = sum_n (w_n - w_mean) E[s_n]^T,
      Q = sum_n E[s_n s_n^T] - N_f s_mean s_mean^T (the expected shape's centred moments),
      by three of ``baselines.fit_camera``'s steps (which converge to the global optimum)
      on six pseudo-points with those moments, from the current optical axis (so never
      worse); then t_f = w_mean - G_f s_mean, the exact optimum given G_f;
    noise: sigma^2 = the expected squared residual per visible coordinate.
  The shape, translation and noise steps are exact conditional maximisers.
Initialisation: rigid factorisation (Tomasi-Kanade with missing entries imputed by the
rank-3 model, metric upgrade), the best camera per view for that shape, and the basis
from a PCA of the rigid fit's residuals lifted to 3D (plus a small seeded perturbation,
since V = 0 is a fixed point of EM).
EM finds a local optimum. On synthetic low-rank views whose deformations are about a third
of the shape's size it recovers the shapes to within the noise; at half the shape's size
it often stops in a poor optimum (its rigid initial cameras are too far off).
"""

from typing import NamedTuple

import numpy as np

from c3dpo_jax import baselines


class EMSfMResult(NamedTuple):
    """EM-SfM fit of a set of views.

    ``shapes`` (M, N, 3) is the reconstruction in each view's camera frame, in the input's
    units, as the baselines and C3DPO give it (what ``evaluation.evaluate`` scores): x, y
    observed where visible, the fitted model's projection where hidden, depth from the
    posterior mean shape under the view's camera (relative to its visible centroid). The
    camera of view m maps a model-frame point X to ``scales[m] * rotations[m, :2] @ X +
    translations[m]``; ``rotations[m, 2]`` (the optical axis) gives the depth.
    ``log_likelihood`` holds the marginal log-likelihood of the visible points (z integrated
    out) at the start and after each iteration.
    """

    shapes: np.ndarray  # (M, N, 3)
    canonical: np.ndarray  # (M, N, 3) posterior mean shapes S_mean + V E[z_f], model frame
    rotations: np.ndarray  # (M, 3, 3)
    scales: np.ndarray  # (M,)
    translations: np.ndarray  # (M, 2)
    mean_shape: np.ndarray  # (N, 3)
    basis: np.ndarray  # (D, N, 3)
    coefficients: np.ndarray  # (M, D) posterior means E[z_f]
    noise_var: float
    log_likelihood: np.ndarray  # (iterations + 1,)


class _Params(NamedTuple):
    b: np.ndarray  # (N, 3, D + 1): [mean shape, basis] per point
    g: np.ndarray  # (M, 2, 3) scaled camera rows c_f R_f
    t: np.ndarray  # (M, 2)
    noise_var: float


class _Posterior(NamedTuple):
    zh: np.ndarray  # (M, D + 1) E[[1, z]]
    zhzh: np.ndarray  # (M, D + 1, D + 1) E[[1, z] [1, z]^T]
    log_likelihood: float


def _check_inputs(kp, vis, n_basis: int, n_iters: int) -> None:
    """One-line ValueErrors for inputs EM-SfM cannot fit."""
    if kp.ndim != 3 or kp.shape[-1] != 2:
        raise ValueError(f"kp has shape {kp.shape}, expected (M, N, 2)")
    if vis.shape != kp.shape[:2]:
        raise ValueError(f"vis has shape {vis.shape}, expected {kp.shape[:2]} (from kp)")
    if n_basis < 0 or n_iters < 0:
        raise ValueError(f"n_basis={n_basis} and n_iters={n_iters} must be >= 0")
    if len(kp) < 2:
        raise ValueError(f"EM-SfM needs at least 2 views, got {len(kp)}")
    seen = vis > 0
    if not np.isfinite(kp[seen]).all():
        raise ValueError("kp holds NaN or inf at visible points")
    few = np.flatnonzero(seen.sum(1) < 3)
    if few.size:
        raise ValueError(f"{few.size} views have fewer than 3 visible points (first: view "
                         f"{few[0]}); a scaled orthographic camera needs 3")
    unseen = np.flatnonzero(seen.sum(0) < 2)
    if unseen.size:
        raise ValueError(f"{unseen.size} keypoints are visible in fewer than 2 views (first: "
                         f"keypoint {unseen[0]}); their 3D position is undetermined")


def _rigid_factorisation(kp: np.ndarray, w: np.ndarray, n_iters: int = 50) -> np.ndarray:
    """(N, 3) rigid shape from the affine rank-3 factorisation of the views (hidden entries
    imputed by the current rank-3 fit), upgraded to a Euclidean shape (Tomasi-Kanade)."""
    m, n = w.shape
    obs = kp.transpose(0, 2, 1).reshape(2 * m, n)  # rows x_1, y_1, x_2, ...
    on = np.repeat(w > 0, 2, axis=0)
    full = np.where(on, obs, baselines.visible_mean(kp, w).reshape(2 * m, 1))
    for _ in range(n_iters):
        centre = full.mean(1, keepdims=True)
        u, s, vt = np.linalg.svd(full - centre, full_matrices=False)
        full = np.where(on, obs, centre + (u[:, :3] * s[:3]) @ vt[:3])
    motion, shape = u[:, :3] * np.sqrt(s[:3]), np.sqrt(s[:3])[:, None] * vt[:3]
    # Metric upgrade: L = A A^T with rows a, b of every view orthogonal and of equal norm.
    a, b = motion[0::2], motion[1::2]
    iu = np.triu_indices(3)
    weight = np.where(iu[0] == iu[1], 1.0, 2.0)  # x L y = sum_{i<=j} L_ij (x_i y_j + x_j y_i)

    def coeffs(x, y):
        return weight * (x[:, iu[0]] * y[:, iu[1]] + x[:, iu[1]] * y[:, iu[0]]) / 2

    lhs = np.concatenate([coeffs(a, a) - coeffs(b, b), coeffs(a, b),
                          (coeffs(a, a) + coeffs(b, b)).mean(0, keepdims=True) / 2])
    rhs = np.concatenate([np.zeros(2 * m), [1.0]])
    lower = np.zeros((3, 3))
    lower[iu] = np.linalg.lstsq(lhs, rhs, rcond=None)[0]
    lam, vec = np.linalg.eigh(lower + np.triu(lower, 1).T)
    lam = np.maximum(lam, 1e-6 * max(lam.max(), 1e-12))  # non-rigid views: nearest PSD L
    upgrade = vec * np.sqrt(lam)  # A with A A^T = L; the shape is A^-1 S_hat
    return np.linalg.solve(upgrade, shape).T


def _lifted_residual_basis(mean: np.ndarray, g: np.ndarray, t: np.ndarray, kp: np.ndarray,
                           w: np.ndarray, n_basis: int, rng: np.random.Generator) -> np.ndarray:
    """(D, N, 3) initial basis: principal components (scaled to unit-variance coefficients) of
    the rigid fit's visible residuals lifted to 3D by the cameras' pseudo-inverses, plus a
    small random perturbation (V = 0 is a fixed point of EM)."""
    m, n = w.shape
    resid = (kp - np.einsum("mij,nj->mni", g, mean) - t[:, None]) * w[..., None]
    lifted = np.einsum("mij,mni->mnj", np.linalg.pinv(g).transpose(0, 2, 1), resid)
    _, sing, vt = np.linalg.svd(lifted.reshape(m, 3 * n), full_matrices=False)
    k = min(n_basis, len(sing))
    basis = np.zeros((n_basis, 3 * n))
    basis[:k] = vt[:k] * sing[:k, None] / np.sqrt(m)
    spread = np.sqrt(((mean - mean.mean(0)) ** 2).sum(1).mean())
    basis += 1e-3 * spread * rng.normal(size=basis.shape)
    return basis.reshape(n_basis, n, 3)


def _initialise(kp: np.ndarray, w: np.ndarray, n_basis: int,
                rng: np.random.Generator) -> _Params:
    """Rigid factorisation shape, its best camera per view, the lifted-residual basis and
    the rigid fit's mean squared residual as sigma^2."""
    mean = _rigid_factorisation(kp, w)
    scale, rows, _, kp_mean = baselines.fit_camera(mean, kp, w)
    g = scale[:, None, None] * rows
    s_mean = baselines.visible_mean(np.broadcast_to(mean, kp.shape[:2] + (3,)), w)
    t = kp_mean - np.einsum("mij,mj->mi", g, s_mean)
    basis = _lifted_residual_basis(mean, g, t, kp, w, n_basis, rng)
    b = np.concatenate([mean[..., None], basis.transpose(1, 2, 0)], -1)
    resid = (kp - np.einsum("mij,nj->mni", g, mean) - t[:, None]) ** 2 * w[..., None]
    return _Params(b, g, t, float(resid.sum() / (2 * w.sum())))


def _e_step(p: _Params, kp: np.ndarray, w: np.ndarray) -> _Posterior:
    """Posterior moments of [1, z_f] and the marginal log-likelihood of the visible points."""
    d = p.b.shape[-1] - 1
    y = (kp - p.t[:, None] - np.einsum("mij,nj->mni", p.g, p.b[..., 0])) * w[..., None]
    a = np.einsum("mij,njd->mnid", p.g, p.b[..., 1:]) * w[..., None, None]  # (M, N, 2, D)
    ata = np.einsum("mnid,mnie->mde", a, a)
    atr = np.einsum("mnid,mni->md", a, y)
    prec = p.noise_var * np.eye(d) + ata  # sigma^2 times the posterior precision
    ez = np.linalg.solve(prec, atr[..., None])[..., 0]
    cov = p.noise_var * np.linalg.inv(prec)
    zh = np.concatenate([np.ones((len(kp), 1)), ez], 1)
    zhzh = np.einsum("ma,mb->mab", zh, zh)
    zhzh[:, 1:, 1:] += cov
    # log N(y; 0, sigma^2 I + A A^T), by the matrix determinant lemma and Woodbury.
    n_obs = 2 * w.sum(1)
    logdet = (n_obs - d) * np.log(p.noise_var) + np.linalg.slogdet(prec)[1]
    quad = ((y**2).sum((1, 2)) - (atr * ez).sum(1)) / p.noise_var
    ll = -0.5 * (n_obs * np.log(2 * np.pi) + logdet + quad).sum()
    return _Posterior(zh, zhzh, float(ll))


def _update_shape(p: _Params, post: _Posterior, kp: np.ndarray, w: np.ndarray) -> np.ndarray:
    """(N, 3, D + 1) per-point least squares for [S_mean,n, V_n] given the posterior moments:
    sum_f w_fn (G^T G)_ij E[zh zh^T]_ab B_jb = sum_f w_fn (G^T (w_fn - t_f))_i E[zh]_a."""
    n, k = w.shape[1], p.b.shape[-1]
    gtg = np.einsum("mki,mkj->mij", p.g, p.g)
    gty = np.einsum("mki,mnk->mni", p.g, kp - p.t[:, None])
    lhs = np.einsum("mn,mij,mab->niajb", w, gtg, post.zhzh, optimize=True).reshape(n, 3 * k, -1)
    rhs = np.einsum("mn,mni,ma->nia", w, gty, post.zh, optimize=True).reshape(n, 3 * k)
    ridge = 1e-12 * np.trace(lhs, axis1=1, axis2=2)[:, None, None] * np.eye(3 * k)
    return np.linalg.solve(lhs + ridge, rhs[..., None]).reshape(n, 3, k)


def _shape_moments(b: np.ndarray, post: _Posterior, w: np.ndarray):
    """Expected shapes E[s_fn] (M, N, 3), their visible mean per view (M, 3) and
    sum_n w_fn E[s_fn s_fn^T] (M, 3, 3)."""
    es = np.einsum("nia,ma->mni", b, post.zh)
    ss = np.einsum("mn,nia,mab,njb->mij", w, b, post.zhzh, b, optimize=True)
    return es, baselines.visible_mean(es, w), ss


def _update_camera(p: _Params, post: _Posterior, kp: np.ndarray, w: np.ndarray):
    """The expected-loss-optimal scaled orthographic camera and translation of every view."""
    es, s_mean, ss = _shape_moments(p.b, post, w)
    n_vis = w.sum(1)
    kp_mean = baselines.visible_mean(kp, w)
    p_mat = np.einsum("mn,mni,mnj->mij", w, kp - kp_mean[:, None], es)
    q_mat = ss - n_vis[:, None, None] * np.einsum("mi,mj->mij", s_mean, s_mean)
    # Six points +-x_j, +-y_j with sum x x^T = Q and sum y x^T = P have the same loss up to a
    # constant (P's rows lie in Q's range, so Q's pseudo-inverse square root serves).
    lam, vec = np.linalg.eigh(q_mat)
    lam = np.maximum(lam, 0.0)
    inv = np.where(lam > 1e-12 * lam[:, -1:], 1 / np.sqrt(np.where(lam > 0, lam, 1.0)), 0.0)
    x = np.einsum("mij,mj,mkj->mik", vec, np.sqrt(lam), vec) / np.sqrt(2)  # columns x_j
    y = np.einsum("mij,mjk,mk,mlk->mil", p_mat, vec, inv, vec) / np.sqrt(2)
    xs = np.concatenate([x, -x], 2).transpose(0, 2, 1)
    ys = np.concatenate([y, -y], 2).transpose(0, 2, 1)
    axis = np.cross(p.g[:, 0], p.g[:, 1])  # the current optical axis (any where c_f = 0)
    length = np.linalg.norm(axis, axis=1, keepdims=True)
    axis = np.where(length > 0, axis / np.where(length > 0, length, 1.0), [0.0, 0.0, 1.0])
    scale, rows, _, _ = baselines.fit_camera(xs, ys, np.ones(xs.shape[:2]), n_iters=3,
                                             start_axis=axis)
    g = scale[:, None, None] * rows
    return g, kp_mean - np.einsum("mij,mj->mi", g, s_mean)


def _update_noise(p: _Params, post: _Posterior, kp: np.ndarray, w: np.ndarray,
                  floor: float) -> float:
    """Expected squared residual per visible coordinate (at least ``floor``)."""
    es, _, ss = _shape_moments(p.b, post, w)
    y = kp - p.t[:, None]
    total = (w * ((y**2).sum(-1) - 2 * np.einsum("mni,mij,mnj->mn", y, p.g, es))).sum()
    total += np.einsum("mki,mkj,mij->", p.g, p.g, ss)
    return max(float(total / (2 * w.sum())), floor)


def _camera_output(p: _Params, post: _Posterior, kp: np.ndarray, w: np.ndarray):
    """Camera-frame shapes (x, y observed where visible), rotations and scales."""
    es, s_mean, _ = _shape_moments(p.b, post, w)
    scale = np.linalg.norm(p.g, axis=2).mean(1)
    rows = p.g / np.maximum(scale, 1e-300)[:, None, None]
    rot = np.concatenate([rows, np.cross(rows[:, 0], rows[:, 1])[:, None]], 1)
    xy = np.einsum("mij,mnj->mni", p.g, es) + p.t[:, None]
    xy = np.where(w[..., None] > 0, kp, xy)
    depth = scale[:, None] * np.einsum("mnj,mj->mn", es - s_mean[:, None], rot[:, 2])
    return np.concatenate([xy, depth[..., None]], -1), es, rot, scale


def em_sfm(kp: np.ndarray, vis: np.ndarray, n_basis: int = 5, n_iters: int = 200,
           tol: float = 1e-5, seed: int = 0) -> EMSfMResult:
    """Fits the EM-SfM shape model to a set of views, transductively.

    Args:
      kp: (M, N, 2) image points (hidden ones may hold anything).
      vis: (M, N) visibility in {0, 1}; every view needs 3 visible points and every
        keypoint 2 views.
      n_basis: D, the number of deformation modes (0: a rigid shape).
      n_iters: the most EM iterations.
      tol: stop when an iteration raises the log-likelihood by less than ``tol`` per visible
        coordinate (``tol=0``: run all ``n_iters``).
      seed: seeds the perturbation of the initial basis.

    Returns:
      ``EMSfMResult``; ``result.shapes`` is scored like the baselines
      (``evaluation.evaluate(result.shapes, data)``).
    """
    kp, vis = np.asarray(kp, np.float64), np.asarray(vis, np.float64)
    _check_inputs(kp, vis, n_basis, n_iters)
    w = (vis > 0).astype(np.float64)
    kp = np.where(w[..., None] > 0, kp, 0.0)  # hidden values never reach the arithmetic
    p = _initialise(kp, w, n_basis, np.random.default_rng(seed))
    # sigma^2 is kept above 1e-12 of the data's variance: exact data would drive it to 0.
    centred = kp - baselines.visible_mean(kp, w)[:, None]
    floor = 1e-12 * max(float((centred**2 * w[..., None]).sum() / (2 * w.sum())), 1e-300)
    p = p._replace(noise_var=max(p.noise_var, floor))
    post = _e_step(p, kp, w)
    history = [post.log_likelihood]
    for _ in range(n_iters):
        p = p._replace(b=_update_shape(p, post, kp, w))
        g, t = _update_camera(p, post, kp, w)
        p = p._replace(g=g, t=t)
        p = p._replace(noise_var=_update_noise(p, post, kp, w, floor))
        post = _e_step(p, kp, w)
        history.append(post.log_likelihood)
        if history[-1] - history[-2] < tol * 2 * w.sum():
            break
    shapes, canonical, rot, scale = _camera_output(p, post, kp, w)
    return EMSfMResult(shapes, canonical, rot, scale, p.t, p.b[..., 0],
                       p.b[..., 1:].transpose(2, 0, 1), post.zh[:, 1:], p.noise_var,
                       np.array(history))
