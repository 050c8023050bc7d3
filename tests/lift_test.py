"""Lifting one view at inference (``lift``): the turned copies, the refinement and the
handedness against numpy and scipy re-implementations; the inference config's checks."""

import dataclasses
import json
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from numpy_reference import procrustes_evidence
from tiny_model import CFG, ONE_PASS, eval_pass, input_dependent_variables, perfect_variables, views

from c3dpo_jax import evaluation, inference, lift, model
from c3dpo_jax.data import KeypointData, synthetic


def _turned_numpy(cfg, options, variables, kp, vis, turns, span="augmentation", keep_ratio=1.1):
    """Independent of ``lift._turned_depth``: each view turned in numpy about its visible
    centroid, one single-copy pass per angle, signs matched and the median taken in numpy
    over the copies kept: every one ("augmentation"), those whose mean 2D distance to their
    turned input is within ``keep_ratio`` of the view's lowest ("circle"), or those and the
    copies turned by at most ``z_augment_rot_angle`` ("circle_and_range")."""
    one = dataclasses.replace(options, turns=1)
    k = (turns - 1) // 2
    angles = [0.0] + [sign * cfg.z_augment_rot_angle * i / k for sign in (1, -1)
                      for i in range(1, k + 1)]
    if span != "augmentation":
        angles = [2 * np.pi * i / turns for i in range(turns)]
    kp, vis = np.asarray(kp, np.float64), np.asarray(vis, np.float64)
    centre = (kp * vis[..., None]).sum(1, keepdims=True) / vis.sum(1)[:, None, None]
    depths, fits = [], []
    for a in angles:
        turn = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
        turned = (kp - centre) @ turn.T + centre
        out = eval_pass(cfg, variables, jnp.asarray(turned, jnp.float32), jnp.asarray(vis), one)
        depths.append(np.asarray(out["shape_camera"][..., 2], np.float64))
        dist = np.linalg.norm(np.asarray(out["kp_reprojected"], np.float64) - turned, axis=-1)
        fits.append((dist * vis).sum(1) / vis.sum(1))
    means = [(d * vis).sum(1, keepdims=True) / vis.sum(1, keepdims=True) for d in depths]
    centred = np.array([d - m for d, m in zip(depths, means)])
    agree = np.einsum("amn,mn->am", centred * vis, centred[0])
    matched = np.where(agree[..., None] < 0, -centred, centred)
    in_range = np.array([min(a, 2 * np.pi - a) <= cfg.z_augment_rot_angle + 1e-3
                         for a in np.abs(angles)])
    keep = {"augmentation": np.ones_like(agree, bool),
            "circle": np.array(fits) <= keep_ratio * np.min(fits, 0),
            "circle_and_range": (np.array(fits) <= keep_ratio * np.min(fits, 0))
            | in_range[:, None]}[span]
    median = np.nanmedian(np.where(keep[..., None], matched, np.nan), 0)
    return median + means[0], centred, agree, keep


def _evaluated(cfg, options, seed):
    """``(variables, data, out)``: input-dependent variables, a batch's data and the jitted
    eval pass of ``cfg`` with ``options`` on the batch."""
    variables = input_dependent_variables(cfg)
    data, batch = views(seed=seed)
    return variables, data, eval_pass(cfg, variables, batch["kp"], batch["vis"], options)


def test_turns_give_the_median_depth_of_copies_turned_in_plane():
    cfg = dataclasses.replace(CFG, z_augment=True, z_augment_rot_angle=0.4)
    options = lift.InferenceConfig(turns=5)
    variables = input_dependent_variables(cfg)
    data, batch = views(seed=5)
    turned = eval_pass(cfg, variables, batch["kp"], batch["vis"], options)
    want, copies, agree, _ = _turned_numpy(cfg, options, variables, data.kp, data.vis, 5)
    # The copies differ (so the median matters), some with the other depth sign.
    assert np.abs(copies - copies[0]).max() > 0.3 * np.abs(copies).max()
    assert np.any(agree < 0)
    np.testing.assert_allclose(turned["shape_camera"][..., 2], want, atol=2e-4)
    np.testing.assert_allclose(turned["shape_3d"][..., 2], want / cfg.keypoint_rescale,
                               atol=2e-4)
    # Only the depth changes: the image x, y, the reprojection and the camera are the view's.
    single = eval_pass(cfg, variables, batch["kp"], batch["vis"])
    for name in ("kp_reprojected", "rotation", "alpha", "shape_canonical", "dist_sq"):
        np.testing.assert_allclose(turned[name], single[name], atol=1e-5, err_msg=name)
    np.testing.assert_allclose(turned["shape_3d"][..., :2],
                               single["shape_3d"][..., :2], atol=1e-5)


def test_turns_round_the_circle_keep_the_copies_that_fit_their_2d_input_best():
    # Even turns and no in-plane augmentation are fine round the circle.
    cfg = dataclasses.replace(CFG, z_augment=False)
    options = lift.InferenceConfig(turns=8, turn_span="circle")
    variables, data, out = _evaluated(cfg, options, seed=6)
    want, _, _, keep = _turned_numpy(cfg, options, variables, data.kp, data.vis, 8,
                                     span="circle")
    # The choice matters: copies are left out, several are kept in some view, and the
    # median of all the copies is another depth.
    assert not keep.all() and keep.sum(0).max() > 1
    every = _turned_numpy(cfg, options, variables, data.kp, data.vis, 8, span="circle",
                          keep_ratio=np.inf)
    assert np.abs(every[0] - want).max() > 1e-2
    np.testing.assert_allclose(out["shape_camera"][..., 2], want, atol=2e-4)


def test_turns_round_the_circle_and_range_also_keep_every_copy_within_the_augmentation():
    # 16 copies 22.5 degrees apart, range 0.4 rad: the unturned copy and +-22.5 degrees are
    # always kept, beside the copies that fit their 2D input within 1.1x of the best.
    cfg = dataclasses.replace(CFG, z_augment=True, z_augment_rot_angle=0.4)
    options = lift.InferenceConfig(turns=16, turn_span="circle_and_range")
    variables, data, out = _evaluated(cfg, options, seed=6)
    want, _, _, keep = _turned_numpy(cfg, options, variables, data.kp, data.vis, 16,
                                     span="circle_and_range")
    fit_only, _, _, fit_keep = _turned_numpy(cfg, options, variables, data.kp, data.vis, 16,
                                             span="circle")
    # The in-range copies matter: "circle" leaves some of them out, and its depth differs.
    assert keep[[0, 1, 15]].all() and not fit_keep[[0, 1, 15]].all()
    assert not keep.all() and np.abs(fit_only - want).max() > 1e-2
    np.testing.assert_allclose(out["shape_camera"][..., 2], want, atol=2e-4)


def _canonical_numpy(variables, alpha):
    """The canonical shape (N, 3) of coefficients ``alpha``, from the shape layer's arrays."""
    layer = variables["params"]["shape_layer"]
    flat = np.asarray(layer["bias"], np.float64) + np.asarray(alpha, np.float64) @ np.asarray(
        layer["kernel"], np.float64)
    return flat.reshape(3, -1).T


def _refinement_residuals_numpy(variables, kp_norm, vis, alpha_phi, prior, p):
    """Independent of ``lift.refine_camera_and_shape``: for one view, the residuals whose
    squares sum to the refinement's cost at ``p = (theta, alpha)``, in numpy and scipy: the
    visible points' 2D distances (orthographic, shifted by the least-squares translation),
    weighted to a mean, and the canonical points' distances to Phi's shape, weighted to
    ``prior`` times a mean."""
    from scipy.spatial.transform import Rotation

    kp, vis = np.asarray(kp_norm, np.float64), np.asarray(vis, np.float64)
    shape = _canonical_numpy(variables, p[3:])
    proj = (shape @ Rotation.from_rotvec(p[:3]).as_matrix().T)[:, :2]
    proj = proj + ((kp - proj) * vis[:, None]).sum(0) / vis.sum()  # argmin_translation
    fit = (proj - kp) * np.sqrt(vis / vis.sum())[:, None]
    shift = (shape - _canonical_numpy(variables, alpha_phi)) * np.sqrt(prior / len(vis))
    return np.concatenate([fit.ravel(), shift.ravel()])


def _basis_views(cfg, n=4, seed=0):
    """``(variables, kp, vis)``: a freshly initialised model (Phi's outputs near 0) whose
    shape layer is a synthetic shape model (mean and D modes), and ``n`` views of shapes of
    that model under rotations whose axis-angle components have std 0.35 rad, a quarter of
    the points hidden."""
    mean, modes = synthetic.shape_model(cfg.n_keypoints, cfg.shape_basis_size, 0.3, seed=0)
    variables = model.init_variables(jax.random.key(1), cfg)
    variables["params"]["shape_layer"] = {
        "bias": jnp.asarray(mean.T.reshape(-1)),
        "kernel": jnp.asarray(modes.transpose(0, 2, 1).reshape(len(modes), -1))}
    rng = np.random.default_rng(seed)
    from scipy.spatial.transform import Rotation

    rots = Rotation.from_rotvec(rng.normal(size=(n, 3)) * 0.35).as_matrix()
    shapes = mean + np.einsum("bd,dnc->bnc", rng.normal(size=(n, len(modes))), modes)
    kp = np.einsum("bij,bnj->bni", rots, shapes)[..., :2] + rng.normal(size=(n, 1, 2))
    vis = (rng.uniform(size=(n, cfg.n_keypoints)) > 0.25).astype(np.float32)
    vis[:, :4] = 1.0
    return variables, jnp.asarray(kp, jnp.float32), jnp.asarray(vis)


def test_refinement_reaches_the_minimum_scipy_finds_from_phi_s_output():
    from scipy.optimize import least_squares
    from scipy.spatial.transform import Rotation

    cfg = CFG
    variables, kp, vis = _basis_views(cfg)
    phi = eval_pass(cfg, variables, kp, vis)
    refined = lift.InferenceConfig(refine_iters=20, refine_prior=0.3)
    out = eval_pass(cfg, variables, kp, vis, refined)
    for i in range(len(kp)):
        def residuals(p, i=i):
            return _refinement_residuals_numpy(variables, phi["kp_norm"][i], vis[i],
                                               phi["alpha"][i], 0.3, p)

        def cost(p):
            return np.sum(residuals(p) ** 2)

        start = np.concatenate([phi["theta"][i], phi["alpha"][i]]).astype(np.float64)
        best = least_squares(residuals, start, method="lm").x
        got = np.concatenate([out["theta"][i], out["alpha"][i]]).astype(np.float64)
        assert cost(got) < 0.5 * cost(start)  # Phi's camera was far off: the fit moved
        np.testing.assert_allclose(cost(got), cost(best), rtol=1e-3, atol=1e-7)
        # The reconstruction is the refined camera's and shape's.
        shape = _canonical_numpy(variables, got[3:])
        np.testing.assert_allclose(out["shape_canonical"][i], shape, atol=1e-4)
        depth = (shape @ Rotation.from_rotvec(got[:3]).as_matrix().T)[:, 2]
        np.testing.assert_allclose(out["shape_camera"][i, :, 2], depth, atol=1e-4)


@pytest.mark.parametrize("margin", [1.0, 0.5])
def test_the_refinement_s_handedness_term_keeps_phi_s_evidence_and_reaches_scipy_s_minimum(
        margin):
    from scipy.optimize import least_squares

    cfg, weight = CFG, 30.0
    variables, kp, vis = _basis_views(cfg, n=8, seed=3)
    mean = _canonical_numpy(variables, np.zeros(cfg.shape_basis_size))
    phi = eval_pass(cfg, variables, kp, vis)
    free = eval_pass(cfg, variables, kp, vis, lift.InferenceConfig(refine_iters=20))
    kept = eval_pass(cfg, variables, kp, vis, lift.InferenceConfig(
        refine_iters=20, refine_handedness=weight, refine_handedness_margin=margin))
    lost_free, lost_kept = [], []  # per view: the fall below the lower of Phi's and the margin
    for i in range(len(kp)):
        def evidence(alpha):
            return procrustes_evidence(_canonical_numpy(variables, alpha), mean)

        floor = min(evidence(phi["alpha"][i]), margin)

        def residuals(p, i=i, floor=floor):
            fit = _refinement_residuals_numpy(variables, phi["kp_norm"][i], vis[i],
                                              phi["alpha"][i], 0.3, p)
            return np.concatenate([fit, [np.sqrt(weight) * max(floor - evidence(p[3:]), 0.0)]])

        start = np.concatenate([phi["theta"][i], phi["alpha"][i]]).astype(np.float64)
        got = np.concatenate([kept["theta"][i], kept["alpha"][i]]).astype(np.float64)
        best = least_squares(residuals, start).x
        cost = lambda p: np.sum(residuals(p) ** 2)  # noqa: E731
        # The hinge's kink slows Levenberg-Marquardt: near, not at, the minimum in 20 steps.
        assert cost(got) <= cost(start) and cost(got) <= 1.1 * cost(best) + 1e-7
        lost_free.append(floor - evidence(free["alpha"][i]))
        lost_kept.append(floor - evidence(kept["alpha"][i]))
    lost_free, lost_kept = np.array(lost_free), np.array(lost_kept)
    # Phi (untrained here) is far off: without the term the fit takes views' handedness
    # evidence far below the lower of Phi's and the margin; with it, next to none.
    fell = lost_free > 0.1
    assert fell.sum() >= 2 and lost_kept[fell].max() < 0.02
    if margin < 1.0:  # a view the fit leaves well above the margin moves as without the term
        above = lost_free < -0.05
        assert above.any()
        np.testing.assert_allclose(kept["alpha"][above], free["alpha"][above], atol=1e-4)


def test_refinement_recovers_the_camera_of_a_view_of_the_model_s_own_shape():
    # Phi says "no rotation" for every view; the views are its mean shape under other
    # rotations. With the shape exact, the refined camera is the true one, and so the depth.
    from scipy.spatial.transform import Rotation

    cfg = dataclasses.replace(CFG, z_equivariance=False, z_augment=False)
    shape = synthetic.shape_model(8, 2, 0.3, seed=0)[0]
    shape = shape - shape.mean(0)
    variables = perfect_variables(cfg, shape)
    truth = Rotation.from_rotvec([[0.4, -0.2, 0.1], [-0.3, 0.0, 0.35], [0.1, 0.4, -0.2]])
    cams = np.einsum("bij,nj->bni", truth.as_matrix(), shape)
    out = eval_pass(cfg, variables, jnp.asarray(cams[..., :2] + 2.0, jnp.float32),
                jnp.ones((3, 8)), lift.InferenceConfig(refine_iters=30))
    np.testing.assert_allclose(out["rotation"], truth.as_matrix(), atol=1e-4)
    depth = out["shape_camera"][..., 2] - np.mean(out["shape_camera"][..., 2], 1, keepdims=True)
    np.testing.assert_allclose(depth, cams[..., 2] - cams[..., 2].mean(1, keepdims=True),
                               atol=1e-4)


def test_every_turned_copy_is_refined():
    cfg = dataclasses.replace(CFG, z_augment=True, z_augment_rot_angle=0.4)
    options = lift.InferenceConfig(turns=5, refine_iters=20)
    variables, kp, vis = _basis_views(cfg, n=6, seed=2)
    rot = variables["params"]["rot_layer"]  # Phi's camera depends on the turned input
    variables["params"]["rot_layer"] = dict(rot, kernel=rot["kernel"] * 30.0)
    want, _, _, _ = _turned_numpy(cfg, options, variables, kp, vis, 5)  # each copy refined
    unrefined, _, _, _ = _turned_numpy(cfg, dataclasses.replace(options, refine_iters=0),
                                       variables, kp, vis, 5)
    assert np.abs(unrefined - want).max() > 1e-2
    np.testing.assert_allclose(eval_pass(cfg, variables, kp, vis, options)["shape_camera"][..., 2],
                               want, atol=2e-4)


def _rotation_residual_numpy(x, ref):
    """RMS distance of ``x`` to ``ref`` (both centred) after the best proper rotation
    (scipy's Rotation.align_vectors, weighted Kabsch)."""
    from scipy.spatial.transform import Rotation

    rot, _ = Rotation.align_vectors(ref, x)
    return np.sqrt(np.mean(np.sum((rot.apply(x) - ref) ** 2, axis=-1)))


def test_one_handedness_gives_every_view_the_mean_shape_s_handedness_and_keeps_its_2d():
    from scipy.spatial.transform import Rotation

    # Canonical shapes near the model's mean shape, half of them mirrored, under rotations.
    cfg = CFG
    variables, _, _ = _basis_views(cfg)
    mean = _canonical_numpy(variables, np.zeros(cfg.shape_basis_size))
    rng = np.random.default_rng(4)
    flip = np.array([1.0, 1.0, -1.0])
    n = 8
    truth_mirrored = np.arange(n) % 2 == 1
    shapes = mean + 0.05 * rng.normal(size=(n, *mean.shape))
    shapes = np.where(truth_mirrored[:, None, None], shapes * flip, shapes)
    rots = Rotation.random(n, random_state=5)
    thetas = rots.as_rotvec()
    t = np.array([0.5, -1.0, 3.0])
    x_cam = np.einsum("bij,bnj->bni", rots.as_matrix(), shapes) + t
    net = model.make_network(cfg)
    fn = jax.jit(jax.vmap(partial(lift.one_handedness, net, variables["params"]),
                          in_axes=(0, None, 0, 0, 0, None)))
    got = fn(jnp.asarray(x_cam, jnp.float32), jnp.asarray(t, jnp.float32),
             *(jnp.asarray(a, jnp.float32) for a in (shapes, rots.as_matrix(), thetas)),
             jnp.ones(cfg.n_keypoints))
    centred_mean = mean - mean.mean(0)
    for i in range(n):
        x = shapes[i] - shapes[i].mean(0)
        # Independently (scipy's best rotation): is the mirror image nearer to the mean?
        mirrored = (_rotation_residual_numpy(x * flip, centred_mean)
                    < _rotation_residual_numpy(x, centred_mean))
        assert mirrored == truth_mirrored[i]
        f = flip if mirrored else np.ones(3)
        assert float(got[4][i]) == float(mirrored)  # the flag says which views were mirrored
        np.testing.assert_allclose(got[1][i], shapes[i] * f, atol=1e-5)
        np.testing.assert_allclose(got[2][i], f[:, None] * rots[i].as_matrix() * f, atol=1e-5)
        np.testing.assert_allclose(Rotation.from_rotvec(got[3][i]).as_matrix(), got[2][i],
                                   atol=1e-5)
        depth = x_cam[i, :, 2]
        want = 2 * t[2] - depth if mirrored else depth
        np.testing.assert_allclose(got[0][i, :, 2], want, atol=1e-4)
        np.testing.assert_allclose(got[0][i, :, :2], x_cam[i, :, :2], atol=1e-5)
        # The mirrored canonical shape under the conjugated rotation is the reflected view.
        np.testing.assert_allclose(
            np.asarray(got[1][i], np.float64) @ np.asarray(got[2][i], np.float64).T + t,
            got[0][i], atol=1e-4)


def test_a_body_reference_gives_every_view_the_body_s_handedness():
    """With ``reference`` (here the built-in humans' average body, "h36m"), a view is
    mirrored when its shape is nearer, up to a rotation, to the body's mirror image than to
    the body, whatever the model's own mean shape is; and in the eval pass every view's
    reconstruction then has the body's handedness, its 2D fit unchanged."""
    from scipy.spatial.transform import Rotation

    from c3dpo_jax.data import humans

    cfg = dataclasses.replace(CFG, n_keypoints=17)
    variables = model.init_variables(jax.random.key(2), cfg)
    body = humans.mean_pose()
    assert body.shape == (17, 3) and lift.reference_body("h36m").shape == (17, 3)
    assert lift.reference_body("mean_shape") is None
    rng = np.random.default_rng(6)
    flip = np.array([1.0, 1.0, -1.0])
    n = 8
    truth_mirrored = np.arange(n) % 2 == 0
    shapes = body + 0.03 * rng.normal(size=(n, 17, 3))
    shapes = np.where(truth_mirrored[:, None, None], shapes * flip, shapes)
    rots = Rotation.random(n, random_state=7)
    t = np.array([0.2, 0.1, 2.0])
    x_cam = np.einsum("bij,bnj->bni", rots.as_matrix(), shapes) + t
    net = model.make_network(cfg)
    fn = jax.jit(jax.vmap(partial(lift.one_handedness, net, variables["params"]),
                          in_axes=(0, None, 0, 0, 0, None, None)))
    got = fn(*(jnp.asarray(a, jnp.float32) for a in (x_cam, t, shapes, rots.as_matrix(),
                                                      rots.as_rotvec())),
             jnp.ones(17), jnp.asarray(body, jnp.float32))
    centred = body - body.mean(0)
    for i in range(n):
        x = np.asarray(got[1][i], np.float64)
        x = x - x.mean(0)
        assert _rotation_residual_numpy(x, centred) < _rotation_residual_numpy(x * flip, centred)
        np.testing.assert_allclose(got[1][i], shapes[i] * (flip if truth_mirrored[i] else 1),
                                   atol=1e-5)
        np.testing.assert_allclose(got[0][i, :, :2], x_cam[i, :, :2], atol=1e-5)
    # The eval pass with the setting: the camera-frame shapes have the body's handedness.
    kp = jnp.asarray(rng.normal(size=(6, 17, 2)), jnp.float32)
    vis = jnp.ones((6, 17), jnp.float32)
    h36m = lift.InferenceConfig(one_handedness=True, handedness_reference="h36m")
    on = eval_pass(cfg, variables, kp, vis, h36m)
    off = eval_pass(cfg, variables, kp, vis)
    np.testing.assert_allclose(on["kp_reprojected"], off["kp_reprojected"], atol=1e-5)
    for x in np.asarray(on["shape_camera"], np.float64):
        x = x - x.mean(0)
        assert _rotation_residual_numpy(x, centred) < _rotation_residual_numpy(x * flip, centred)
    # handedness_flipped names the views given their mirror image; own_handedness undoes it,
    # so the results' "mirrored" is the model's own mix of handednesses either way.
    flipped = np.asarray(on["handedness_flipped"])
    assert set(flipped.tolist()) == {0.0, 1.0} and not np.asarray(off["handedness_flipped"]).any()
    for i in range(len(kp)):
        a, b = (np.asarray(p["shape_camera"][i, :, 2]) for p in (on, off))
        np.testing.assert_allclose(a - a.mean(), (b - b.mean()) * (1 - 2 * flipped[i]), atol=1e-5)
    np.testing.assert_allclose(lift.own_handedness(on["shape_canonical"], flipped),
                               off["shape_canonical"], atol=1e-6)
    data = KeypointData(kp=np.asarray(kp), vis=np.asarray(vis))
    scores = [inference.evaluate_split(variables, data, cfg, o, "none")["mirrored"]
              for o in (h36m, ONE_PASS)]
    own = evaluation.mirrored_fraction(np.asarray(off["shape_canonical"]))
    as_given = evaluation.mirrored_fraction(np.asarray(on["shape_canonical"]))
    assert scores[0] == scores[1] == own != as_given  # the views as the model made them


def test_one_handedness_in_the_eval_pass_leaves_the_2d_fit_and_flip_resolved_depth():
    variables, data, off = _evaluated(CFG, ONE_PASS, seed=3)
    on = eval_pass(CFG, variables, jnp.asarray(data.kp, jnp.float32),
               jnp.asarray(data.vis, jnp.float32), lift.InferenceConfig(one_handedness=True))
    np.testing.assert_allclose(on["kp_reprojected"], off["kp_reprojected"], atol=1e-5)
    for i in range(len(data.kp)):
        a = np.asarray(on["shape_camera"][i, :, 2])
        b = np.asarray(off["shape_camera"][i, :, 2])
        a, b = a - a.mean(), b - b.mean()
        assert np.allclose(a, b, atol=1e-5) or np.allclose(a, -b, atol=1e-5)


def _maker(**fields):
    """``lift.inference_config`` for a model of 8 points trained with in-plane augmentation."""
    return lift.inference_config(dataclasses.replace(CFG, z_augment=True), **fields)


@pytest.mark.parametrize("make, message", [
    (lambda: _maker(turns=4), r"^turns=4 \(must be an odd number\)$"),
    (lambda: lift.InferenceConfig(turns=0), r"turns=0 \(must be an integer >= 1\)"),
    (lambda: lift.InferenceConfig(turn_span="bogus"),
     r"turn_span='bogus' \(must be one of 'augmentation', 'circle', 'circle_and_range'\)"),
    (lambda: lift.InferenceConfig(refine_iters=-1), r"refine_iters=-1 \(must be an integer >= 0\)"),
    (lambda: lift.InferenceConfig(refine_prior=float("nan")),
     r"refine_prior=nan \(must be a finite number >= 0\)"),
    (lambda: lift.InferenceConfig(refine_handedness=-1.0),
     r"refine_handedness=-1.0 \(must be a finite number >= 0\)"),
    (lambda: lift.inference_config(dataclasses.replace(CFG, projection_type="perspective"),
                                   one_handedness=True),
     r"one_handedness=True \(must be False for a perspective model"),
    (lambda: lift.inference_config(
        dataclasses.replace(CFG, n_keypoints=17, projection_type="perspective"),
        handedness_reference="h36m", one_handedness=False),
     r"handedness_reference='h36m' \(must be 'mean_shape' for a perspective model"),
    (lambda: lift.inference_config(dataclasses.replace(CFG, n_keypoints=18),
                                   handedness_reference="h36m", one_handedness=True),
     r"handedness_reference='h36m' \(a body of 17 points in its joint order; the model has 18"),
])
def test_inference_options_that_would_change_inference_silently_are_refused(make, message):
    """However they are made (``InferenceConfig(...)``, ``dataclasses.replace``, a
    hand-edited config.json, ``inference_config`` against a model): an even number of turns
    had used one copy less, an unknown span the circle's, a negative prior Phi's output."""
    with pytest.raises(ValueError, match=message):
        make()


def test_every_rule_is_said_once_for_every_surface():
    """``inference_config`` (reconstruct, c3dpo-predict, --mode=eval) and ``problems`` say
    the same lines; field checks come first, then the ones against the model."""
    cfg = dataclasses.replace(CFG, projection_type="perspective")
    options = lift.InferenceConfig(refine_iters=3, turns=3)
    found = lift.problems(options, cfg)
    assert found == ["turns=3 (must be used with model.projection_type='orthographic' only and "
                     "used with model.z_augment=True and model.z_augment_rot_angle > 0 only "
                     "(turn_span 'augmentation' uses the training augmentation's range; "
                     "turn_span='circle' does not))",
                     "refine_iters=3 (must be 0 (no refinement) for a perspective model: "
                     "orthographic models only)"]
    with pytest.raises(ValueError) as err:
        lift.inference_config(cfg, options)
    assert str(err.value) == "; ".join(found)
    with pytest.raises(ValueError, match=r"^unknown inference option\(s\) \['turnz'\]"):
        lift.inference_config(cfg, turnz=3)
    with pytest.raises(ValueError, match=r"^handedness_reference='auto' \(a training setting"):
        lift.inference_config(CFG, handedness_reference="auto")
    assert lift.problems(lift.InferenceConfig(handedness_reference="auto"), CFG,
                         resolved=False) == []


def test_an_inference_config_goes_through_json_and_reads_a_model_section():
    """``to_dict``/``from_dict`` through JSON give the same, hashable config; a saved config
    whose model section holds the options (``model.MOVED_TO_INFERENCE``) gives them under
    their names, and a model config made from that section leaves them out."""
    options = lift.InferenceConfig(refine_iters=5, one_handedness=True,
                                   handedness_reference="body",
                                   handedness_body=((0.0, 1.0, 2.0), (3.0, 4.0, 5.0)))
    again = lift.InferenceConfig.from_dict(json.loads(json.dumps(options.to_dict())))
    assert again == options and hash(again) == hash(options)
    # every field but those added after the move had an old name in the model section
    assert set(model.MOVED_TO_INFERENCE.values()) == set(lift.FIELDS) - {
        "handedness_evidence", "handedness_from_output", "refine_handedness",
        "refine_handedness_margin"}
    saved = {"model": {**CFG.to_dict(), "test_time_turns": 3, "test_time_refine_iters": 20,
                       "replace_keypoints_with_input": False}}
    assert lift.saved_options(saved) == {"turns": 3, "refine_iters": 20,
                                         "replace_keypoints_with_input": False}
    assert model.ModelConfig.from_dict(saved["model"]) == CFG
    assert lift.saved_options({"inference": options.to_dict(), **saved}) == options.to_dict()
    with pytest.raises(ValueError, match=r"unknown inference option\(s\) \['turnz'\]"):
        lift.InferenceConfig.from_dict({"turnz": 3})


def test_a_body_without_one_handedness_gives_the_whole_model_one_mirror_decision():
    """``one_handedness=False`` with a body reference: every view is mirrored, as
    ``one_handedness`` mirrors one, exactly when the model's mean shape is nearer, up to a
    proper rotation, to the body's mirror image than to the body (scipy's orthogonal
    Procrustes: the best orthogonal map's determinant), the same decision for every view; the
    2D reprojection is unchanged; with "mean_shape" nothing changes."""
    from scipy.linalg import orthogonal_procrustes

    from c3dpo_jax import C3DPOParams, reconstruct

    k = 9
    cfg = dataclasses.replace(CFG, n_keypoints=k)
    rng = np.random.default_rng(11)
    body = rng.normal(size=(k, 3)) * [1.0, 0.8, 0.5]
    mean = body + 0.3 * rng.normal(size=(k, 3))
    variables = input_dependent_variables(cfg)  # coefficients far from 0
    layer = variables["params"]["shape_layer"]
    layer["bias"] = jnp.asarray(mean.T.reshape(-1), jnp.float32)
    # Basis vectors that put the views' own shapes on both sides of the body.
    layer["kernel"] = 0.1 * jax.random.normal(jax.random.key(6), layer["kernel"].shape)
    net = model.make_network(cfg)
    np.testing.assert_allclose(model.mean_shape(net, variables["params"], jnp.ones(k)), mean,
                               atol=1e-6)
    kp = jnp.asarray(rng.normal(size=(10, k, 2)), jnp.float32)
    vis = jnp.ones((10, k), jnp.float32)

    def lifted(options=ONE_PASS):
        return {n: np.asarray(a) for n, a in eval_pass(cfg, variables, kp, vis, options).items()}

    off = lifted()

    def nearer_mirror(x, ref):
        rot, _ = orthogonal_procrustes(x - x.mean(0), ref - ref.mean(0))
        return bool(np.linalg.det(rot) < 0)

    decisions = []
    for reference in (body, body * [1.0, 1.0, -1.0]):
        options = lift.InferenceConfig(handedness_reference="body",
                                       handedness_body=tuple(map(tuple, reference)))
        on = lifted(options)
        mirrored = nearer_mirror(mean, reference)
        decisions.append(mirrored)
        assert on["handedness_flipped"].tolist() == [float(mirrored)] * len(kp)
        f = np.array([1.0, 1.0, -1.0]) if mirrored else np.ones(3)
        np.testing.assert_allclose(on["shape_canonical"], off["shape_canonical"] * f, atol=1e-5)
        np.testing.assert_allclose(on["rotation"], f[:, None] * off["rotation"] * f, atol=1e-5)
        np.testing.assert_allclose(on["kp_reprojected"], off["kp_reprojected"], atol=1e-5)
        np.testing.assert_allclose(on["shape_3d"][..., :2], off["shape_3d"][..., :2], atol=1e-5)
        depth_on, depth_off = (p["shape_camera"][..., 2].astype(np.float64) for p in (on, off))
        np.testing.assert_allclose(depth_on - depth_on.mean(1, keepdims=True),
                                   (depth_off - depth_off.mean(1, keepdims=True)) * f[2],
                                   atol=1e-4)
        got = reconstruct(C3DPOParams(variables, cfg), kp, vis, handedness_reference=reference,
                          one_handedness=False)  # the same through reconstruct
        np.testing.assert_allclose(got.shape_canonical, off["shape_canonical"] * f, rtol=1e-5,
                                   atol=1e-5)
    assert decisions == [False, True]  # the mean shape is the body's side, not its mirror's
    # The views' own shapes take both sides of the body: the decision above is the model's.
    assert {nearer_mirror(x, body) for x in off["shape_canonical"].astype(np.float64)} == {
        False, True}
    plain = lifted(lift.InferenceConfig(one_handedness=False))
    for name in ("shape_3d", "shape_canonical", "rotation", "handedness_flipped"):
        np.testing.assert_array_equal(plain[name], off[name], err_msg=name)


def test_one_handedness_on_tetrahedra_mirrors_the_views_whose_corners_are_mirrored():
    """``handedness_evidence="tetrahedra"``: a view is mirrored when its small tetrahedra
    (each point with its three nearest in the mean shape) take the chirality of the mean
    shape's mirror image: numpy's determinants decide independently."""
    from scipy.spatial import cKDTree
    from scipy.spatial.transform import Rotation

    variables, _, _ = _basis_views(CFG)
    mean = _canonical_numpy(variables, np.zeros(CFG.shape_basis_size))
    rng = np.random.default_rng(6)
    n = 8
    shapes = mean + 0.01 * np.abs(mean).mean() * rng.normal(size=(n, *mean.shape))
    shapes[n // 2:] *= np.array([1.0, 1.0, -1.0])
    rots = Rotation.random(n, random_state=7)
    t = np.zeros(3)
    x_cam = np.einsum("bij,bnj->bni", rots.as_matrix(), shapes)
    corners = cKDTree(mean).query(mean, k=4)[1]

    def chirality(y):
        edges = y[corners[:, 1:]] - y[corners[:, :1]]
        return np.linalg.det(edges) / np.prod(np.linalg.norm(edges, axis=-1), -1)

    want = np.array([np.sum(chirality(mean) * chirality(x)) < 0 for x in shapes])
    assert want.tolist() == [False] * (n // 2) + [True] * (n // 2)
    fn = jax.jit(jax.vmap(partial(lift.one_handedness, net := model.make_network(CFG),
                                  variables["params"], kind="tetrahedra"),
                          in_axes=(0, None, 0, 0, 0, None)))
    got = fn(jnp.asarray(x_cam, jnp.float32), jnp.asarray(t, jnp.float32),
             *(jnp.asarray(a, jnp.float32) for a in (shapes, rots.as_matrix(),
                                                      rots.as_rotvec())),
             jnp.ones(CFG.n_keypoints))
    assert net is not None
    np.testing.assert_array_equal(np.asarray(got[4]), want.astype(np.float32))
    with pytest.raises(ValueError, match=r"handedness_evidence='volume' \(must be one of "
                                         r"'procrustes', 'tetrahedra'\)"):
        lift.InferenceConfig(handedness_evidence="volume")
