"""Numerics of the training objective: hidden coordinates never reach the arithmetic,
and odd but legal inputs give finite losses and gradients."""

import dataclasses
import functools
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from c3dpo_jax import geometry, lift, losses, model, train
from c3dpo_jax.data import synthetic

CFG = model.ModelConfig(
    n_keypoints=8,
    shape_basis_size=3,
    n_fully_connected=16,
    n_layers=1,
    canonicalization_n_fully_connected=16,
    canonicalization_n_layers=1,
    n_rand_samples=2,
    argmin_translation=True,
    z_augment=True,
)
B = 6
# The eval pass as users run it, compiled (op by op it compiles hundreds of programs); the
# configs are static, the release's inference.
_forward_eval = jax.jit(partial(lift.forward_eval, body=None, options=lift.InferenceConfig()),
                        static_argnames="cfg")


@functools.cache
def _loss_and_grad():
    loss_fn = train.make_loss_fn(CFG, train.LossConfig())
    return jax.jit(jax.value_and_grad(loss_fn, has_aux=True))


@functools.cache
def _variables():
    return model.init_variables(jax.random.key(1), CFG)


def _batch(seed=0):
    data = synthetic.make_split(
        B,
        n_keypoints=8,
        n_modes=2,
        deformation=0.3,
        occlusion=0.3,
        noise=0.0,
        perspective=False,
        shape_seed=0,
        seed=seed,
    )
    inputs = data.model_inputs()
    inputs["vis"][:, :2] = 1  # every sample keeps two visible points
    return {k: np.array(v) for k, v in inputs.items()}


def _run(batch):
    v = _variables()
    (loss, (_, metrics)), grads = _loss_and_grad()(
        v["params"], v["batch_stats"], jax.device_put(batch), jax.random.key(5)
    )
    return float(loss), metrics, grads


def _all_finite(tree) -> bool:
    return all(bool(jnp.all(jnp.isfinite(x))) for x in jax.tree.leaves(tree))


@pytest.mark.parametrize("junk", [1e20, -3e38, np.inf, -np.inf, np.nan])
def test_hidden_values_change_nothing_in_the_loss_or_its_gradient(junk):
    batch = _batch()
    assert (batch["vis"] == 0).any()
    dirty = dict(batch, kp=np.where(batch["vis"][..., None] > 0, batch["kp"], np.float32(junk)))
    loss, metrics, grads = _run(batch)
    loss2, metrics2, grads2 = _run(dirty)
    assert np.isfinite(loss2) and _all_finite(grads2)
    assert loss2 == loss
    same = jax.tree.map(lambda a, b: bool(jnp.array_equal(a, b)), grads, grads2)
    assert all(jax.tree.leaves(same))


@pytest.mark.parametrize("junk", [1e20, np.inf, np.nan])
def test_eval_outputs_ignore_hidden_values(junk):
    batch = _batch(seed=2)
    i = int(np.flatnonzero((batch["vis"] == 0).any(1))[0])
    kp, vis = jnp.asarray(batch["kp"][i]), jnp.asarray(batch["vis"][i])
    dirty = jnp.where(vis[:, None] > 0, kp, np.float32(junk))
    ones = jnp.ones(8)
    clean_out = _forward_eval(_variables(), kp, vis, ones, None, cfg=CFG)
    dirty_out = _forward_eval(_variables(), dirty, vis, ones, None, cfg=CFG)
    for k in clean_out:
        np.testing.assert_array_equal(dirty_out[k], clean_out[k], err_msg=k)


def _odd_batches():
    """Legal but extreme inputs, each a (B, N) batch of the one compiled shape."""
    base = _batch(seed=1)
    rng = np.random.default_rng(0)
    out = {}
    for scale in (1e-6, 1e6):
        out[f"scale {scale:g}"] = dict(base, kp=base["kp"] * np.float32(scale))
    out["offset 1e6"] = dict(base, kp=base["kp"] + np.float32(1e6))
    out["coincident points"] = dict(base, kp=np.zeros_like(base["kp"]) + 3.0)
    one = base["vis"].copy()
    one[0] = 0
    one[0, 4] = 1
    out["one visible point"] = dict(base, vis=one)
    none = base["vis"].copy()
    none[1] = 0
    out["nothing visible in a sample"] = dict(base, vis=none)
    out["random"] = dict(base, kp=rng.normal(size=base["kp"].shape).astype(np.float32) * 1e3)
    return out


@pytest.mark.parametrize("name", sorted(_odd_batches()))
def test_extreme_but_legal_batches_give_finite_losses_and_gradients(name):
    batch = _odd_batches()[name]
    batch["kp"] = np.where(batch["vis"][..., None] > 0, batch["kp"], 0.0).astype(np.float32)
    loss, metrics, grads = _run(batch)
    assert np.isfinite(loss) and _all_finite(metrics) and _all_finite(grads), name


def test_masked_reductions_select_rather_than_multiply():
    x = jnp.array([[1.0, 2.0], [jnp.inf, jnp.nan], [3.0, 4.0]])
    mask = jnp.array([1.0, 0.0, 1.0])
    np.testing.assert_array_equal(geometry.masked_mean(x, mask), [2.0, 3.0])
    repro = jnp.array([[1.0, jnp.inf, 3.0]])
    for norm in ("kp_total_count", "kp_count_per_image"):
        assert float(losses.reprojection(repro, mask[None], norm)) == 2.0
    # d/dx of the masked mean is finite even where the hidden value is inf.
    grad = jax.grad(lambda x: geometry.masked_mean(x, mask).sum())(x)
    assert _all_finite(grad) and float(grad[1].sum()) == 0.0


def test_perspective_hidden_values_are_ignored_too():
    cfg = dataclasses.replace(CFG, projection_type="perspective", argmin_translation=False)
    variables = model.init_variables(jax.random.key(0), cfg)
    batch = _batch(seed=3)
    i = int(np.flatnonzero((batch["vis"] == 0).any(1))[0])
    kp, vis = jnp.asarray(batch["kp"][i] * 100 + 300), jnp.asarray(batch["vis"][i])
    K = jnp.array([[500.0, 0, 300], [0, 500, 300], [0, 0, 1]])
    clean = _forward_eval(variables, kp, vis, jnp.ones(8), K, cfg=cfg)
    dirty = _forward_eval(
        variables, jnp.where(vis[:, None] > 0, kp, np.nan), vis, jnp.ones(8), K, cfg=cfg
    )
    np.testing.assert_array_equal(dirty["shape_3d"], clean["shape_3d"])
