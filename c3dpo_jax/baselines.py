"""Trivial 3D-lifting baselines that any learned NRSfM method must beat (numpy only).

Glossary: M samples, N keypoints. ``mean_shape (N, 3)`` is the Procrustes mean of the
training ground truth. Baselines produce ``(M, N, 3)`` predictions in the input's
units, scored with the same protocol as the model:

- ``fitted mean shape``: the best rigid fit of the mean training shape to each view: the
  scaled orthographic camera (rotation, least-squares scale, translation) with the least
  2D error on the visible points, found by refining the one-shot affine fit (``fit_camera``;
  the shape's mirror image projects no differently, so it is covered; a view with fewer
  than 4 visible points keeps the one-shot fit); observed x, y are kept for visible points
  and the depth is the fitted shape's.
- ``zero depth``: the same x, y with depth 0 (what a method learns if it learns nothing).
- ``oracle mean shape`` (``oracle_mean_shape``, needs the test split's 3D ground truth):
  the mean shape rotated and translated onto each ground-truth shape (best rotation,
  Kabsch); its error is the part of the shapes that no rigid model explains.
- ``fitted PCA basis`` (``pca_shape_basis`` + ``fit_shape_basis``, needs the training
  split's 3D ground truth): the probabilistic PCA of the aligned training shapes with
  C3DPO's basis size, its coefficients and camera fitted to each view's visible points
  (MAP under the PCA's Gaussian prior); observed x, y kept. A linear shape model learnt
  *with* 3D supervision and fitted per view by optimisation: a reference for what C3DPO's
  linear basis could reach, not a baseline it is expected to beat.
"""

from typing import NamedTuple

import numpy as np


def kabsch(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """(M, 3, 3) rotations minimising ||R src_m - dst_m||, no reflections.

    ``src`` is (M, N, 3); ``dst`` is (N, 3) or (M, N, 3)."""
    h = np.einsum("mni,mnj->mij", src, np.broadcast_to(dst, src.shape))
    u, _, vt = np.linalg.svd(h)
    d = np.sign(np.linalg.det(np.einsum("mij,mjk->mik", u, vt)))
    u[:, :, 2] *= d[:, None]
    return np.einsum("mij,mjk->mki", u, vt)


def procrustes_mean_shape(kp3d: np.ndarray, iters: int = 5, max_samples: int = 5000) -> np.ndarray:
    """Mean of the shapes after rotating each onto a common reference (GPA)."""
    x = kp3d[:max_samples].astype(np.float64)
    x = x - x.mean(1, keepdims=True)
    ref = x[0]
    for _ in range(iters):
        rot = kabsch(x, ref)
        aligned = np.einsum("mij,mnj->mni", rot, x)
        ref = aligned.mean(0)
    return ref


def _lift(shapes: np.ndarray, kp: np.ndarray, vis: np.ndarray, n_iters: int = 0,
          refit=None, camera_iters: int = 10) -> np.ndarray:
    """Fits ``s R2 S_m + t`` to the visible points of each view; returns 3D predictions.

    ``shapes`` is (N, 3) or (M, N, 3). ``refit(proj)``, if given, is called ``n_iters``
    times with the current per-view scaled 2x3 projections (M, 2, 3) of the one-shot
    camera and returns new (M, N, 3) shapes (alternation between camera and shape). The
    final shapes get the refined camera (``fit_camera`` with ``camera_iters``), which can
    only lower their 2D error."""
    shapes = np.broadcast_to(shapes, kp.shape[:2] + (3,))
    for _ in range(n_iters):
        scale, rows, _, _ = fit_camera(shapes, kp, vis, n_iters=0)
        shapes = refit(scale[:, None, None] * rows)
    camera = scale, rows, centred, _ = fit_camera(shapes, kp, vis, camera_iters)
    xy = np.where(vis[..., None] > 0, kp, project(*camera))
    depth = scale[:, None] * np.einsum("mnj,mj->mn", centred, np.cross(rows[:, 0], rows[:, 1]))
    return np.concatenate([xy, depth[..., None]], axis=-1)


def visible_mean(x: np.ndarray, vis: np.ndarray) -> np.ndarray:
    """(..., M, C) mean of each view's visible points of ``x`` (..., M, N, C); views with no
    visible point get 0."""
    w = np.asarray(vis, np.float64)
    return np.einsum("mn,...mnc->...mc", w, x) / np.maximum(w.sum(1), 1.0)[:, None]


def reprojection_residual(xy: np.ndarray, kp: np.ndarray, vis: np.ndarray) -> np.ndarray:
    """(M,) mean squared 2D distance between ``xy`` and ``kp`` (M, N, 2) over each view's
    visible points (0 for a view with none)."""
    return visible_mean(((xy - kp) ** 2).sum(-1, keepdims=True), vis)[:, 0]


def project(scale: np.ndarray, rows: np.ndarray, centred: np.ndarray,
            kp_mean: np.ndarray) -> np.ndarray:
    """(M, N, 2) image points of every shape point under a camera returned by ``fit_camera``."""
    return scale[:, None, None] * np.einsum("mij,mnj->mni", rows, centred) + kp_mean[:, None]


_TINY = np.finfo(np.float64).tiny
# The fewest visible points for which fit_camera refines the camera (see there).
MIN_REFINED = 4


def _sphere_argmax(quad: np.ndarray, lin: np.ndarray, n_bisect: int = 60) -> np.ndarray:
    """(M, 3) global maximisers over unit vectors a of ``a quad a + 2 lin a`` (quad (M, 3, 3)
    symmetric, lin (M, 3)): a = (mu - quad)^-1 lin with mu >= quad's top eigenvalue and
    |a| = 1 (the trust-region secular equation, solved by bisection)."""
    lam, vec = np.linalg.eigh(quad)  # ascending: lam[:, 2] is the top eigenvalue
    c = np.einsum("mij,mi->mj", vec, lin)
    lo, hi = lam[:, 2] + np.abs(c[:, 2]), lam[:, 2] + np.linalg.norm(c, axis=-1)  # |a| >=, <= 1
    for _ in range(n_bisect):
        mid = (lo + hi) / 2
        with np.errstate(over="ignore"):  # |a| = inf as mid reaches an eigenvalue: too long
            long = ((c / np.maximum(mid[:, None] - lam, _TINY)) ** 2).sum(-1) > 1
        lo, hi = np.where(long, mid, lo), np.where(long, hi, mid)
    a = c / np.maximum(hi[:, None] - lam, _TINY)  # |a| <= 1 at hi
    # The top component from |a| = 1 instead: also right when c[:, 2] = 0 (the "hard case").
    a[:, 2] = np.where(c[:, 2] < 0, -1.0, 1.0) * np.sqrt(np.maximum(1 - (a[:, :2] ** 2).sum(-1), 0))
    a = np.einsum("mij,mj->mi", vec, a)
    return a / np.linalg.norm(a, axis=-1, keepdims=True)


def _axis_camera(axis: np.ndarray, yx: np.ndarray, xx: np.ndarray):
    """The least-squares camera ``(scale (M,), rows (M, 2, 3))`` of optical axis ``axis``
    (M, 3), for centred shapes x_n and image points y_n (the visible ones) given by
    ``yx = sum_n y_n x_n^T`` (M, 2, 3) and ``xx = sum_n x_n x_n^T`` (M, 3, 3).

    The rows are r1 and r2 = axis x r1 (so rows[0] x rows[1] = axis), r1 normal to the
    axis; with b1, b2 the rows of ``yx`` the summed 2D error is |y|^2 - 2 s (r1 g) + s^2 D,
    g = b1 - (axis b1) axis + b2 x axis, D = tr(xx) - axis xx axis: r1 = g / |g|, s = |g| / D
    and the error is |y|^2 - |g|^2 / D."""
    b1, b2 = yx[:, 0], yx[:, 1]
    g = b1 - (axis * b1).sum(-1, keepdims=True) * axis + np.cross(b2, axis)
    total = np.trace(xx, axis1=1, axis2=2)
    spread = total - np.einsum("mi,mij,mj->m", axis, xx, axis)
    norm = np.linalg.norm(g, axis=-1)
    r1 = g / np.maximum(norm, _TINY)[:, None]
    seen = spread > 1e-12 * total  # else the points lie along the axis (or coincide): s = 0
    scale = np.where(seen, norm, 0.0) / np.where(seen, spread, 1.0)
    return scale, np.stack([r1, np.cross(axis, r1)], 1)


def _refine_camera(axis: np.ndarray, x: np.ndarray, y: np.ndarray, n_iters: int):
    """The camera ``(scale (M,), rows (M, 2, 3))`` with the least 2D error seen in ``n_iters``
    Dinkelbach steps from the optical axis ``axis`` (M, 3) (the start's camera included),
    for shapes ``x`` (M, N, 3) and image points ``y`` (M, N, 2), both centred on the visible
    points and with hidden points zeroed.

    The summed error of axis a is |y|^2 - N(a) / D(a) (``_axis_camera``), N = |g|^2 =
    |yx|^2 - a yx^T yx a + 2 a (b1 x b2) and D = tr(xx) - a xx a, both quadratic in a. Each
    step takes the a maximising N(a) - h D(a), h = N / D of the best axis so far, over the
    unit sphere (globally, ``_sphere_argmax``): that maximum is >= 0 (the best axis scores
    0), so the new axis has N / D >= h and cannot raise the error. The steps are Newton's
    method on the convex, decreasing h -> max_a N(a) - h D(a), whose root is the largest
    N / D: from any start they converge (superlinearly) to the best camera of all."""
    yx, xx = np.einsum("mni,mnj->mij", y, x), np.einsum("mni,mnj->mij", x, x)
    quad, lin = np.einsum("mki,mkj->mij", yx, yx), np.cross(yx[:, 0], yx[:, 1])

    def fit(axis):  # the axis' camera and its error, point by point (no cancellation)
        scale, rows = _axis_camera(axis, yx, xx)
        xy = scale[:, None, None] * x @ rows.transpose(0, 2, 1)
        return scale, rows, ((xy - y) ** 2).sum((1, 2))

    best = fit(axis)
    for _ in range(n_iters):
        gain = (y**2).sum((1, 2)) - best[2]  # N / D of the best axis so far
        new = fit(_sphere_argmax(gain[:, None, None] * xx - quad, lin))
        take = new[2] < best[2]
        best = [np.where(take.reshape((-1,) + (1,) * (b.ndim - 1)), n, b)
                for n, b in zip(new, best)]
    return best[0], best[1]


def fit_camera(shapes: np.ndarray, kp: np.ndarray, vis: np.ndarray, n_iters: int = 10,
               start_axis: np.ndarray | None = None):
    """The scaled orthographic camera of each view fitted to the shapes' visible points.

    One-shot (``n_iters=0``): least-squares 2x3 projection onto ``kp``, then the nearest
    scaled orthonormal rows. Refined (default): ``n_iters`` steps of ``_refine_camera`` from
    that camera's optical axis (or from ``start_axis`` (M, 3)), which cannot raise the 2D
    error and converge from any start to the camera (rotation, least-squares scale,
    translation) with the least 2D error; per view, whichever of it and the one-shot camera
    has the lower error (the one-shot one only where the fit is degenerate, e.g. all visible
    points coincide). Views with fewer than ``MIN_REFINED`` visible points keep the one-shot
    camera: three points give as many equations as the camera has unknowns (rotation and
    scale), and the least-error camera is then often a near edge-on view with a scale
    hundreds of times the true one, which puts the hidden points and the depth far off. A
    mirror image of the shapes needs no separate fit: it projects as the shapes under
    another rotation (the same rows, the depth negated).

    ``shapes`` is (N, 3) or (M, N, 3). Returns ``(scale (M,), rows (M, 2, 3), centred
    shapes (M, N, 3), kp_mean (M, 2))``: the projection of point n of view m is
    ``scale[m] * rows[m] @ centred[m, n] + kp_mean[m]`` (``project``; both means over the
    visible points), its depth ``scale[m] * (rows[m, 0] x rows[m, 1]) @ centred[m, n]``."""
    w = vis.astype(np.float64)
    kp_mean = visible_mean(kp, w)
    y = (kp - kp_mean[:, None]) * w[..., None]
    shapes = np.broadcast_to(shapes, kp.shape[:2] + (3,))
    centred = shapes - visible_mean(shapes, w)[:, None]
    s = centred * w[..., None]
    sts = np.einsum("mni,mnj->mij", s, s)
    yts = np.einsum("mni,mnj->mij", y, s)
    cam = np.einsum("mij,mjk->mik", yts, np.linalg.inv(sts + 1e-9 * np.eye(3)))
    u, sig, vt = np.linalg.svd(cam, full_matrices=False)
    camera = sig.mean(1), np.einsum("mij,mjk->mik", u, vt), centred, kp_mean
    if n_iters == 0:
        return camera
    axis = np.cross(camera[1][:, 0], camera[1][:, 1]) if start_axis is None else start_axis
    best = _refine_camera(axis, s, y, n_iters) + camera[2:]
    better = ((reprojection_residual(project(*best), kp, w)
               < reprojection_residual(project(*camera), kp, w))
              & (w.sum(1) >= MIN_REFINED))
    return (np.where(better, best[0], camera[0]),
            np.where(better[:, None, None], best[1], camera[1]), centred, kp_mean)


def one_scale_cameras(shapes: np.ndarray, kp: np.ndarray, vis: np.ndarray, n_iters: int = 10,
                      rounds: int = 5, rotation_steps: int = 10):
    """``fit_camera``'s cameras with one scale shared by every view (the shapes are in the
    data's units, so the views differ in rotation and translation only): from each view's
    own least-2D-error camera, ``rounds`` of the least-squares scale of all views together
    (their rows fixed), then ``rotation_steps`` steps per view of the rotation at that scale
    (the depths as unknowns: given the rotation each point's depth is its shape's, given the
    depths the rotation is the Procrustes fit of (x, y, depth) onto the scaled shape). No
    step raises the summed 2D error. Returns ``fit_camera``'s ``(scale, rows, centred,
    kp_mean)``, the scale repeated per view."""
    _, rows, centred, kp_mean = fit_camera(shapes, kp, vis, n_iters)
    w = vis.astype(np.float64)[..., None]
    y = (kp - kp_mean[:, None]) * w
    x = centred * w
    scale = 1.0
    for _ in range(rounds):
        proj = np.einsum("mij,mnj->mni", rows, x)
        scale = float((y * proj).sum() / max((proj**2).sum(), _TINY))
        for _ in range(rotation_steps):
            depth = scale * np.einsum("mnj,mj->mn", x, np.cross(rows[:, 0], rows[:, 1]))
            target = np.concatenate([y, depth[..., None]], -1)  # (M, N, 3), camera frame
            rot = kabsch(scale * x, target)  # camera = rot @ shape
            rows = rot[:, :2]
    return np.full(len(kp), scale), rows, centred, kp_mean


def fit_mean_shape(mean_shape: np.ndarray, kp: np.ndarray, vis: np.ndarray, n_iters: int = 10,
                   chunk: int = 4096) -> np.ndarray:
    """The best rigid fit ``s R2 S + t`` of the shape to the visible points of each view
    (``fit_camera``; ``n_iters=0``: the one-shot fit); returns 3D predictions. Views are
    processed ``chunk`` at a time.

    ``mean_shape`` is one shape (N, 3) for every view, or one per view (M, N, 3)."""
    shapes = np.broadcast_to(mean_shape, kp.shape[:2] + (3,))
    return np.concatenate([
        _lift(shapes[i:i + chunk], kp[i:i + chunk], vis[i:i + chunk], camera_iters=n_iters)
        for i in range(0, max(len(kp), 1), chunk)])


class ShapeBasis(NamedTuple):
    """Probabilistic PCA of aligned 3D shapes: ``S = mean + sum_d a_d basis_d + noise``,
    ``a_d ~ N(0, variances_d)``, noise ~ N(0, noise_var) per coordinate."""

    mean: np.ndarray  # (N, 3)
    basis: np.ndarray  # (D, N, 3), orthonormal when flattened
    variances: np.ndarray  # (D,)
    noise_var: float


def pca_shape_basis(kp3d: np.ndarray, n_basis: int, max_samples: int = 5000) -> ShapeBasis:
    """PPCA (Tipping and Bishop's maximum-likelihood solution) of the training shapes,
    each rotated onto their Procrustes mean."""
    mean = procrustes_mean_shape(kp3d, max_samples=max_samples)
    x = kp3d[:max_samples].astype(np.float64)
    x = x - x.mean(1, keepdims=True)
    aligned = np.einsum("mij,mnj->mni", kabsch(x, mean), x)
    dev = (aligned - mean).reshape(len(x), -1)
    _, sing, vt = np.linalg.svd(dev, full_matrices=False)
    eig = np.zeros(dev.shape[1])
    eig[: len(sing)] = sing**2 / len(x)
    n_basis = min(n_basis, len(sing) - 1, dev.shape[1] - 1)  # fewer shapes than D: fewer
    noise_var = max(float(eig[n_basis:].mean()), 1e-12)
    basis = vt[:n_basis].reshape(n_basis, *mean.shape)
    return ShapeBasis(mean, basis, np.maximum(eig[:n_basis], 1e-12), noise_var)


def fit_shape_basis(model: ShapeBasis, kp: np.ndarray, vis: np.ndarray, n_iters: int = 20,
                    chunk: int = 1024) -> np.ndarray:
    """The PPCA shape model fitted to each view (MAP coefficients under the Gaussian prior,
    alternating with the one-shot scaled orthographic camera, from the mean shape's); observed
    x, y kept, depth from the fitted shape under its best camera (as ``fit_mean_shape``).
    Views are processed ``chunk`` at a time (the per-view design matrices are (N * 2, D))."""
    if len(model.basis) == 0:
        return _lift(model.mean, kp, vis)
    if len(kp) > chunk:
        return np.concatenate([
            fit_shape_basis(model, kp[i:i + chunk], vis[i:i + chunk], n_iters, chunk)
            for i in range(0, len(kp), chunk)])
    w = vis.astype(np.float64)

    def centre(x):  # (..., M, N, C): minus each view's visible-point mean, hidden points 0
        return (x - visible_mean(x, w)[..., None, :]) * w[..., None]

    m_c = centre(np.broadcast_to(model.mean, kp.shape[:2] + (3,)))
    b_c = centre(np.broadcast_to(model.basis[:, None], (len(model.basis),) + m_c.shape))
    y = centre(kp)
    prior = model.noise_var / model.variances  # ridge per coefficient, in shape units

    def refit(proj):
        # Residual of the projected mean shape, linear in the coefficients; the image-space
        # ridge is the shape-space one times the camera scale squared.
        a_mat = np.einsum("mij,dmnj->mnid", proj, b_c).reshape(len(kp), -1, len(model.basis))
        r = (y - np.einsum("mij,mnj->mni", proj, m_c)).reshape(len(kp), -1)
        scale2 = (np.linalg.norm(proj, axis=(1, 2)) ** 2 / 2)[:, None, None]
        ata = np.einsum("mkd,mke->mde", a_mat, a_mat) + scale2 * np.diag(prior)
        coef = np.linalg.solve(ata, np.einsum("mkd,mk->md", a_mat, r)[..., None])[..., 0]
        return model.mean + np.einsum("md,dnc->mnc", coef, model.basis)

    return _lift(model.mean, kp, vis, n_iters, refit)


def oracle_mean_shape(mean_shape: np.ndarray, kp3d: np.ndarray, vis: np.ndarray) -> np.ndarray:
    """The mean shape under each sample's best rotation onto ``kp3d`` (visible points)."""
    w = vis.astype(np.float64)[..., None]
    count = np.maximum(w.sum(1, keepdims=True), 1.0)
    gt_mean = (kp3d * w).sum(1, keepdims=True) / count
    src_mean = (mean_shape[None] * w).sum(1, keepdims=True) / count
    src = (mean_shape[None] - src_mean) * w
    dst = (kp3d - gt_mean) * w
    rot = kabsch(src, dst)
    return np.einsum("mij,mnj->mni", rot, mean_shape[None] - src_mean) + gt_mean


def fit_mean_shape_one_scale(mean_shape: np.ndarray, kp: np.ndarray, vis: np.ndarray,
                             n_iters: int = 10) -> np.ndarray:
    """The rigid fit of the shape (N, 3) to every view with one scale for all of them
    (``one_scale_cameras``); 3D predictions as ``fit_mean_shape``'s (observed x, y kept)."""
    camera = scale, rows, centred, _ = one_scale_cameras(mean_shape, kp, vis, n_iters)
    xy = np.where(vis[..., None] > 0, kp, project(*camera))
    depth = scale[:, None] * np.einsum("mnj,mj->mn", centred, np.cross(rows[:, 0], rows[:, 1]))
    return np.concatenate([xy, depth[..., None]], axis=-1)


def predict(mean_shape: np.ndarray, kp: np.ndarray, vis: np.ndarray) -> dict[str, np.ndarray]:
    """Predictions of every baseline, by name: ``fitted mean shape`` (one scale for the
    split), ``fitted mean shape, per-view scale`` (each view's own least-squares scale) and
    ``zero depth``."""
    fitted = fit_mean_shape_one_scale(mean_shape, kp, vis)
    return {"fitted mean shape": fitted,
            "fitted mean shape, per-view scale": fit_mean_shape(mean_shape, kp, vis),
            "zero depth": fitted * np.array([1.0, 1.0, 0.0])}
