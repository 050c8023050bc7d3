"""The per-example forward passes: wiring, masking, zero loss at a perfect fit (the eval
pass's inference options: lift_test)."""

import dataclasses
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from tiny_model import CFG, ONE_PASS, eval_pass, input_dependent_variables, perfect_variables, views

from c3dpo_jax import lift, losses, model
from c3dpo_jax.data import synthetic


@partial(jax.jit, static_argnums=0)  # one compile per config instead of op-by-op dispatch
def _train_terms(cfg, variables, batch, key):
    keys = jax.random.split(key, batch["vis"].shape[0])
    rotations = jax.vmap(partial(losses.draw_rotations, cfg=cfg))(keys)
    fn = partial(model.forward_train, cfg=cfg)
    return jax.vmap(fn, in_axes=(None, 0, 0, 0, None, 0), axis_name="batch")(
        variables, batch["kp"], batch["vis"], batch["class_mask"], None, rotations)


def test_losses_are_zero_when_the_model_explains_the_view_exactly(key):
    cfg = dataclasses.replace(CFG, z_equivariance=False, z_augment=False)
    shape = synthetic.shape_model(8, 2, 0.3, seed=0)[0]
    variables = perfect_variables(cfg, shape)
    vis = (
        jnp.asarray(np.random.default_rng(1).uniform(size=(4, 8)) > 0.3, jnp.float32)
        .at[:, :3]
        .set(1)
    )
    kp = jnp.broadcast_to(jnp.asarray(shape[:, :2]) + 5.0, (4, 8, 2)) * vis[..., None]
    batch = {"kp": kp, "vis": vis, "class_mask": jnp.ones((4, 8))}
    terms, _ = _train_terms(cfg, variables, batch, key)
    np.testing.assert_allclose(terms["dist_sq"] * vis, 0.0, atol=1e-5)
    np.testing.assert_allclose(terms["canon_dist_sq"], 0.0, atol=1e-6)  # Psi undoes any rotation
    out = lift.forward_eval(variables, kp[0], vis[0], jnp.ones(8), None, None, cfg, ONE_PASS)
    np.testing.assert_allclose(out["shape_3d"][:, 2], shape[:, 2] - 0.0, atol=1e-5)


@pytest.mark.parametrize("variant", [
    {}, {"z_equivariance": False}, {"canonicalization": False}, {"independent_phi_for_aug": False},
    {"z_augment": True}, {"camera_translation": True, "camera_scale": True},
])
def test_invisible_coordinates_change_nothing_in_training(key, variant):
    cfg = dataclasses.replace(CFG, **variant)
    variables = model.init_variables(jax.random.key(1), cfg)
    _, batch = views()
    moved = dict(batch, kp=jnp.where(batch["vis"][..., None] > 0, batch["kp"], 123.0))
    terms, stats = _train_terms(cfg, variables, batch, key)
    terms2, stats2 = _train_terms(cfg, variables, moved, key)
    vis = batch["vis"]
    np.testing.assert_allclose(terms["dist_sq"] * vis, terms2["dist_sq"] * vis, atol=1e-6)
    np.testing.assert_allclose(terms["canon_dist_sq"], terms2["canon_dist_sq"], atol=1e-6)
    assert terms["canon_dist_sq"].shape == ((6, 3, 8) if cfg.canonicalization else (6, 0, 8))
    assert np.all(np.isfinite(terms["dist_sq"]))


def test_eval_keeps_visible_input_points_and_is_batch_independent():
    variables = model.init_variables(jax.random.key(2), CFG)
    data, batch = views(seed=3)
    outs = jax.vmap(partial(lift.forward_eval, variables, body=None, cfg=CFG, options=ONE_PASS),
                    in_axes=(0, 0, 0, None))(batch["kp"], batch["vis"], batch["class_mask"], None)
    vis = data.vis > 0
    np.testing.assert_allclose(
        np.asarray(outs["shape_3d"])[..., :2][vis], data.kp[vis], atol=1e-5
    )
    single = jax.jit(lift.forward_eval, static_argnums=(6, 7))(
        variables, batch["kp"][2], batch["vis"][2], batch["class_mask"][2], None, None, CFG,
        ONE_PASS)
    np.testing.assert_allclose(single["shape_3d"], outs["shape_3d"][2], atol=1e-5)
    assert outs["rotation"].shape == (6, 3, 3) and outs["alpha"].shape == (6, 3)


def test_perspective_model_requires_intrinsics():
    cfg = dataclasses.replace(CFG, projection_type="perspective")
    variables = model.init_variables(jax.random.key(0), cfg)
    with pytest.raises(ValueError, match="intrinsics"):
        lift.forward_eval(variables, jnp.zeros((8, 2)), jnp.ones(8), jnp.ones(8), None, None,
                          cfg, ONE_PASS)


def test_an_unresolved_input_scale_is_refused_not_trained_on_zeros():
    # keypoint_rescale=0 is the configs' "from the training data"; train_and_evaluate
    # resolves it, a hand-made step must too.
    cfg = dataclasses.replace(CFG, keypoint_rescale=0.0)
    variables = model.init_variables(jax.random.key(0), cfg)
    with pytest.raises(ValueError, match=r"keypoint_rescale=0 .*\(resolve\.resolve_input_scale"):
        lift.forward_eval(variables, jnp.ones((8, 2)), jnp.ones(8), jnp.ones(8), None, None,
                          cfg, ONE_PASS)


def test_unknown_model_options_are_rejected():
    with pytest.raises(ValueError, match="n_keypoint"):
        model.ModelConfig.from_dict({"n_keypoint": 3})


def test_both_forward_passes_trace_under_the_configured_matmul_precision(monkeypatch):
    """The precision context is entered with the pass's own config, positional or keyword."""
    seen = []
    real = model._precision

    def recording(cfg):
        seen.append(cfg.matmul_precision)
        return real(cfg)

    monkeypatch.setattr(model, "_precision", recording)
    cfg = dataclasses.replace(CFG, matmul_precision="highest")
    variables = model.init_variables(jax.random.key(0), cfg)
    _, batch = views()
    jax.jit(lift.forward_eval, static_argnums=(6, 7))(  # the configs passed positionally
        variables, batch["kp"][0], batch["vis"][0], batch["class_mask"][0], None, None, cfg,
        ONE_PASS)
    fn = partial(model.forward_train, variables, cfg=cfg)
    keys = jax.random.split(jax.random.key(1), 6)
    rotations = jax.vmap(partial(losses.draw_rotations, cfg=cfg))(keys)
    jax.jit(jax.vmap(fn, in_axes=(0, 0, 0, None, 0), axis_name="batch"))(
        batch["kp"], batch["vis"], batch["class_mask"], None, rotations)
    assert seen == ["highest", "highest"]


def test_per_view_scaling_makes_the_reconstruction_scale_with_the_view(key):
    """``keypoint_scaling="per_view"``: a view scaled by s and shifted gives the same
    canonical shape and normalised visible points and the 3D output scaled by s (depth too)
    and shifted in x, y, and the visible points' training terms are unchanged; with
    "global" the network sees s (its output differs); what hidden points hold and the
    global input scale change nothing; a view whose points coincide stays finite; an
    unknown, unresolved or perspective setting is refused."""
    cfg = dataclasses.replace(CFG, keypoint_scaling="per_view", keypoint_rescale=0.3)
    variables = input_dependent_variables(cfg)
    data, batch = views(seed=3)
    kp, vis = batch["kp"], batch["vis"]
    s = jnp.asarray([0.5, 2.0, 1.0, 3.0, 0.25, 1.5])[:, None, None]
    shift = jnp.asarray([[[4.0, -2.0]]])
    a, b = eval_pass(cfg, variables, kp, vis), eval_pass(cfg, variables, kp * s + shift, vis)
    np.testing.assert_allclose(b["shape_canonical"], a["shape_canonical"], atol=1e-5)
    np.testing.assert_allclose(b["kp_scale"], a["kp_scale"] / np.asarray(s)[:, 0, 0], rtol=1e-5)
    shown = np.asarray(vis)[..., None]  # hidden points' values are masked by the network
    np.testing.assert_allclose(b["kp_norm"] * shown, a["kp_norm"] * shown, atol=1e-5)
    expected = np.asarray(a["shape_3d"]) * np.asarray(s)
    expected[..., :2] += np.asarray(shift)
    np.testing.assert_allclose(b["shape_3d"], expected, rtol=1e-4, atol=1e-4)
    hidden = jnp.where(vis[..., None] > 0, kp, 1e6)
    np.testing.assert_allclose(eval_pass(cfg, variables, hidden, vis)["shape_3d"],
                               a["shape_3d"], atol=1e-5)
    other_rescale = dataclasses.replace(cfg, keypoint_rescale=3.0)
    np.testing.assert_allclose(eval_pass(other_rescale, variables, kp, vis)["shape_3d"],
                               a["shape_3d"], rtol=1e-4, atol=1e-5)
    terms_a, _ = _train_terms(cfg, variables, batch, key)
    terms_b, _ = _train_terms(cfg, variables, dict(batch, kp=kp * s + shift), key)
    np.testing.assert_allclose(terms_b["dist_sq"] * vis, terms_a["dist_sq"] * vis, rtol=1e-3,
                               atol=1e-6)
    plain = dataclasses.replace(cfg, keypoint_scaling="global")
    assert not np.allclose(eval_pass(plain, variables, kp * s, vis)["shape_canonical"],
                           eval_pass(plain, variables, kp, vis)["shape_canonical"], atol=1e-3)
    point = jnp.broadcast_to(kp[:1, :1], kp[:1].shape)
    assert np.isfinite(np.asarray(eval_pass(cfg, variables, point, vis[:1])["shape_3d"])).all()
    with pytest.raises(ValueError, match=r"keypoint_scaling='per_view' \(must be 'global' or "
                       r"'auto' for a perspective model"):
        dataclasses.replace(cfg, projection_type="perspective")
    with pytest.raises(ValueError, match=r"keypoint_scaling='each' \(known: global, per_view, "
                       r"auto\)"):
        dataclasses.replace(cfg, keypoint_scaling="each")
    with pytest.raises(ValueError, match=r"keypoint_scaling='auto' means 'from the training"):
        eval_pass(dataclasses.replace(cfg, keypoint_scaling="auto"), variables, kp, vis)
