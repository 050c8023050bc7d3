"""A fully supervised lifter: the reference for what one view's 2D points say about 3D.

C3DPO learns from 2D keypoints alone. This script trains the same kind of network with
the 3D ground truth instead: Phi's trunk (``networks.Trunk``: the cpu recipe's 256-wide
3-block trunk by default) followed by a dense head that outputs the N x 3 shape in the
camera frame, trained with the mean point distance to the ground truth (Adam, the cpu
recipe's learning rate, batch size and x0.1 decay at 80% of the steps). Evaluated like
C3DPO (observed x, y of visible points kept; test MPJPE with the C3DPO protocol), on the
same views as run.py (same importer, same data seed), so its numbers sit beside the
time-to-accuracy table: a weakly supervised method should not be expected to beat it.

  python experiments/time_to_accuracy/supervised.py --dataset=face --steps=10000

writes ``OUT_DIR/supervised/DATASET__sSEED.json`` (curve of test MPJPE against steps and
wall time, the final value, the settings).
"""

import json
import os
import sys
import time

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import optax
from absl import app, flags, logging

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import run  # noqa: E402  (load_dataset and its flags: --dataset, --set, --data_seed, ...)

from c3dpo_jax import baselines, evaluation, networks  # noqa: E402

FLAGS = flags.FLAGS
flags.DEFINE_integer("steps", 10_000, "training steps, rounded up to a multiple of 20 (default: "
                     "the cpu recipe's, configs.default.cpu_recipe)")
flags.DEFINE_integer("width", 256, "trunk width")
flags.DEFINE_integer("blocks", 3, "residual blocks")
flags.DEFINE_integer("batch_size", 256, "batch size")
flags.DEFINE_float("lr", 3e-3, "Adam learning rate (x0.1 after 80% of the steps)")
flags.DEFINE_integer("evals", 10, "evaluations of the test split during training")


class Lifter(nn.Module):
    """(N, 2) centred visible points and (N,) visibility -> (N, 3) centred shape."""

    n_keypoints: int
    width: int
    blocks: int

    @nn.compact
    def __call__(self, kp, vis, train: bool):
        x = jnp.concatenate([(kp * vis[:, None]).T.reshape(-1), vis])
        feats = networks.Trunk(self.width, self.blocks, "batch")(x, train)
        return nn.Dense(3 * self.n_keypoints)(feats).reshape(3, self.n_keypoints).T


def _centred(kp, vis):
    """Points minus the mean of the visible ones (per view): the lifter's origin in x, y."""
    return kp - baselines.visible_mean(kp, vis)[:, None]


def _targets(data):
    """Ground truth in the lifter's frame: x, y minus the visible kp mean, depth centred."""
    gt = data.kp3d.astype(np.float64)
    xy = gt[..., :2] - baselines.visible_mean(data.kp, data.vis)[:, None]
    z = gt[..., 2:] - gt[..., 2:].mean(1, keepdims=True)
    return np.concatenate([xy, z], -1).astype(np.float32)


def train_and_evaluate() -> dict:
    train_data, test_data, protocol = run.load_dataset(
        FLAGS.dataset, FLAGS.views_per_frame, FLAGS.cameras, FLAGS.data_seed)
    n = train_data.n_keypoints
    net = Lifter(n, FLAGS.width, FLAGS.blocks)
    kp_tr = jnp.asarray(_centred(train_data.kp, train_data.vis), jnp.float32)
    vis_tr = jnp.asarray(train_data.vis, jnp.float32)
    y_tr = jnp.asarray(_targets(train_data))
    kp_te = jnp.asarray(_centred(test_data.kp, test_data.vis), jnp.float32)
    vis_te = jnp.asarray(test_data.vis, jnp.float32)

    key = jax.random.key(FLAGS.seed)
    batched = jax.vmap(net.apply, in_axes=(None, 0, 0, None), axis_name="batch")
    variables = jax.vmap(net.init, in_axes=(None, 0, 0, None), axis_name="batch")(
        key, kp_tr[:2], vis_tr[:2], False)
    variables = jax.tree.map(lambda a: a[0], variables)
    schedule = optax.piecewise_constant_schedule(FLAGS.lr, {int(0.8 * FLAGS.steps): 0.1})
    tx = optax.adam(schedule)
    opt_state = tx.init(variables["params"])

    def loss_fn(params, stats, idx):
        pred, upd = jax.vmap(
            lambda k, v: net.apply({"params": params, "batch_stats": stats}, k, v, True,
                                   mutable=["batch_stats"]),
            axis_name="batch")(kp_tr[idx], vis_tr[idx])
        loss = jnp.linalg.norm(pred - y_tr[idx], axis=-1).mean()
        return loss, jax.tree.map(lambda a: a[0], upd["batch_stats"])

    @jax.jit
    def step(carry, i):
        params, stats, opt_state = carry
        idx = jax.random.randint(jax.random.fold_in(key, i), (FLAGS.batch_size,), 0, len(kp_tr))
        (loss, stats), grads = jax.value_and_grad(loss_fn, has_aux=True)(params, stats, idx)
        updates, opt_state = tx.update(grads, opt_state, params)
        return (optax.apply_updates(params, updates), stats, opt_state), loss

    @jax.jit
    def predict(params, stats):
        return batched({"params": params, "batch_stats": stats}, kp_te, vis_te, False)

    def score(params, stats):
        out = np.asarray(predict(params, stats), np.float64)
        kp_mean = baselines.visible_mean(test_data.kp, test_data.vis)[:, None]
        xy = np.where(test_data.vis[..., None] > 0, test_data.kp, out[..., :2] + kp_mean)
        pred = np.concatenate([xy, out[..., 2:]], -1)
        return evaluation.evaluate(pred, test_data, protocol)["mpjpe"]

    chunk = jax.jit(lambda carry, start: jax.lax.scan(step, carry, start + jnp.arange(20)))
    carry = (variables["params"], variables["batch_stats"], opt_state)
    every = max(FLAGS.steps // FLAGS.evals // 20, 1) * 20
    curve, done, t_train = [], 0, 0.0
    while done < FLAGS.steps:
        tic = time.perf_counter()
        carry, loss = chunk(carry, done)
        loss = float(loss.mean())
        t_train += time.perf_counter() - tic
        done += 20
        if not np.isfinite(loss):
            raise FloatingPointError(f"supervised loss is not finite near step {done}")
        if done % every == 0 or done >= FLAGS.steps:
            curve.append(dict(step=done, wall_s=t_train, loss=loss, mpjpe=score(*carry[:2])))
            logging.info("%s", curve[-1])
    return dict(dataset=run.dataset_name(FLAGS.dataset), seed=FLAGS.seed,
                data_seed=FLAGS.data_seed, steps=done, width=FLAGS.width,
                blocks=FLAGS.blocks, batch_size=FLAGS.batch_size, lr=FLAGS.lr,
                n_train=len(train_data), n_test=len(test_data), protocol=protocol,
                mpjpe=curve[-1]["mpjpe"], curve=curve)


def main(argv):
    del argv
    result = train_and_evaluate()
    out = os.path.join(FLAGS.out_dir, "supervised")
    os.makedirs(out, exist_ok=True)
    path = os.path.join(out, f"{result['dataset']}__s{FLAGS.seed}.json")
    with open(path, "w") as f:
        json.dump(result, f, indent=1)
    print(f"{result['dataset']} supervised lifter seed {FLAGS.seed}: {result['steps']} steps, "
          f"{result['curve'][-1]['wall_s']:.0f} s, test MPJPE {result['mpjpe']:.4f} -> {path}")


if __name__ == "__main__":
    app.run(main)
