"""A tiny model, a batch of its views and model variables with known outputs, shared by the
tests of the forward passes (model_test) and of lifting at inference (lift_test)."""

from functools import partial

import jax
import jax.numpy as jnp

from c3dpo_jax import lift, model
from c3dpo_jax.data import synthetic

CFG = model.ModelConfig(
    n_keypoints=8, shape_basis_size=3, n_fully_connected=16, n_layers=1,
    canonicalization_n_fully_connected=16, canonicalization_n_layers=1, n_rand_samples=3,
    argmin_translation=True,
)
ONE_PASS = lift.InferenceConfig()  # the release's inference


def views(n=6, seed=0):
    """``(data, arrays)``: ``n`` generated views of ``CFG``'s points and their model inputs."""
    data = synthetic.make_split(n, n_keypoints=8, n_modes=2, deformation=0.3, occlusion=0.3,
                                noise=0.0, perspective=False, shape_seed=0, seed=seed)
    return data, {k: jnp.asarray(v) for k, v in data.model_inputs().items()}


def perfect_variables(cfg, shape):
    """Heads zeroed: alpha = 0, theta = 0 (R = I) and the mean shape = ``shape``."""
    variables = model.init_variables(jax.random.key(0), cfg)
    params = jax.tree_util.tree_map_with_path(
        lambda path, p: jnp.zeros_like(p) if any(
            getattr(k, "key", "").endswith(("_layer", "_layer_psi")) for k in path) else p,
        variables["params"])
    params["shape_layer"]["bias"] = jnp.asarray(shape.T.reshape(-1))
    return dict(variables, params=params)


def input_dependent_variables(cfg):
    """Heads scaled up: a freshly initialised model barely depends on its input."""
    variables = model.init_variables(jax.random.key(4), cfg)
    variables["params"] = jax.tree_util.tree_map_with_path(
        lambda path, p: p * 1000.0 if any(
            getattr(k, "key", "") in ("alpha_layer", "rot_layer") for k in path) else p,
        variables["params"])
    return variables


def eval_pass(cfg, variables, kp, vis, options=ONE_PASS):
    """The jitted eval pass of ``cfg`` with ``options`` on a batch (every point in the
    class), with the body the options name."""
    fn = partial(lift.forward_eval, variables, cfg=cfg, options=options)
    return jax.jit(jax.vmap(fn, in_axes=(0, 0, 0, None, None)))(
        kp, vis, jnp.ones_like(vis), None, lift.options_body(options))
