"""Training and evaluation: pure step factories and the loop that drives them.

Glossary: B batch, N keypoints, M dataset samples, T steps per compiled call.

- ``make_train_step`` -> ``train_step(state, batch, key)``: one pure, jittable SGD step;
  the per-example forward is vmapped over the batch (BatchNorm reduces over it).
- ``make_train_chunk`` -> ``chunk(state, data, train_key, n_steps)``: ``lax.scan`` over
  ``n_steps`` steps; each step samples its batch (with replacement, as the release)
  from the device-resident ``data`` with ``fold_in(train_key, step)``, so the data
  order and all augmentations depend only on (seed, step): a resumed run replays an
  uninterrupted one exactly.
- ``make_mesh`` / ``replicate``: data parallelism. With a mesh, the chunk constrains
  each sampled batch to be split over the mesh's ``"data"`` axis while parameters,
  optimiser state and the training arrays stay replicated; XLA (GSPMD) partitions the
  vmapped step and turns BatchNorm's batch means and the gradient sums into
  all-reduces, so results equal one device's up to float rounding.
- ``train_and_evaluate(config, workdir)``: the loop (progress bar, metrics.jsonl,
  orbax checkpoints and resume, evaluation at epoch ends and at the end).
"""

import dataclasses
import json
import os
import time
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
import optax
from absl import logging
from jax.sharding import Mesh, NamedSharding, PartitionSpec
from tqdm.auto import tqdm

from c3dpo_jax import baselines, checkpoint, evaluation, losses, model
from c3dpo_jax.data import KeypointData, load_splits
from c3dpo_jax.state import (
    OptimConfig,
    TrainState,
    create_train_state,
    make_optimizer,
    make_schedule,
)


@dataclasses.dataclass(frozen=True)
class LossConfig:
    """Weights of the objective ``w_reprojection * l_repro + w_canonicalization * l_canon``."""

    w_reprojection: float = 1.0
    w_canonicalization: float = 1.0


def make_loss_fn(model_cfg: model.ModelConfig, loss_cfg: LossConfig):
    """``loss_fn(params, batch_stats, batch, key) -> (objective, (batch_stats, metrics))``."""

    def loss_fn(params, batch_stats, batch, key):
        variables = {"params": params, "batch_stats": batch_stats}
        keys = jax.random.split(key, batch["vis"].shape[0])
        intrinsics = batch.get("intrinsics")
        per_example = partial(model.forward_train, cfg=model_cfg)
        terms, stats = jax.vmap(
            per_example, in_axes=(None, 0, 0, 0, None if intrinsics is None else 0, 0),
            axis_name="batch",
        )(variables, batch["kp"], batch["vis"], batch["class_mask"], intrinsics, keys)
        stats = jax.tree.map(lambda a: a[0], stats)
        l_repro = losses.reprojection(
            terms["repro"], batch["vis"], model_cfg.reprojection_normalization
        )
        l_canon = losses.canonicalisation(terms["canon"])
        objective = loss_cfg.w_reprojection * l_repro + loss_cfg.w_canonicalization * l_canon
        metrics = {
            "loss": objective,
            "loss/reprojection": l_repro,
            "loss/canonicalisation": l_canon,
        }
        return objective, (stats, metrics)

    return loss_fn


def make_train_step(model_cfg, loss_cfg, tx: optax.GradientTransformation, schedule=None):
    """``train_step(state, batch, key) -> (state, metrics)``, pure and jittable."""
    grad_fn = jax.value_and_grad(make_loss_fn(model_cfg, loss_cfg), has_aux=True)

    def train_step(state: TrainState, batch, key):
        (_, (stats, metrics)), grads = grad_fn(state.params, state.batch_stats, batch, key)
        updates, opt_state = tx.update(grads, state.opt_state, state.params)
        params = optax.apply_updates(state.params, updates)
        metrics = dict(metrics, grad_norm=optax.global_norm(grads))
        if schedule is not None:
            metrics["lr"] = jnp.asarray(schedule(state.step), jnp.float32)
        new_state = TrainState(state.step + 1, params, stats, opt_state)
        return new_state, metrics

    return train_step


def sample_indices(data, key, batch_size: int):
    """Indices drawn with replacement; class-balanced when ``data`` has class tables."""
    n = data["vis"].shape[0]
    if "class_start" not in data:
        return jax.random.randint(key, (batch_size,), 0, n)
    k_class, k_item = jax.random.split(key)
    cls = jax.random.randint(k_class, (batch_size,), 0, data["class_start"].shape[0])
    offset = jax.random.randint(k_item, (batch_size,), 0, data["class_count"][cls])
    return data["class_start"][cls] + offset


def make_mesh(n_devices: int | None = None) -> Mesh:
    """A 1D mesh with axis ``"data"`` over the first ``n_devices`` devices (default all)."""
    devices = jax.devices()[: n_devices or jax.device_count()]
    return Mesh(np.array(devices), ("data",))


def replicate(tree, mesh: Mesh):
    """Copies every array of ``tree`` onto every device of ``mesh``."""
    return jax.device_put(tree, NamedSharding(mesh, PartitionSpec()))


def make_train_chunk(train_step, batch_size: int, mesh: Mesh | None = None):
    """``chunk(state, data, train_key, n_steps)``: ``n_steps`` steps in one ``lax.scan``.

    With ``mesh``, pass ``replicate``d state and data: each batch is split over the
    mesh's ``"data"`` axis (``batch_size`` must be a multiple of its size).
    """
    if mesh is not None and batch_size % mesh.size:
        raise ValueError(f"batch_size {batch_size} is not a multiple of {mesh.size} devices")
    split = None if mesh is None else NamedSharding(mesh, PartitionSpec("data"))

    def chunk(state: TrainState, data, train_key, n_steps: int):
        per_sample = {k: v for k, v in data.items() if k not in ("class_start", "class_count")}

        def body(state, _):
            k_idx, k_step = jax.random.split(jax.random.fold_in(train_key, state.step))
            idx = sample_indices(data, k_idx, batch_size)
            batch = jax.tree.map(lambda a: a[idx], per_sample)
            if split is not None:
                batch = jax.lax.with_sharding_constraint(batch, split)
            return train_step(state, batch, k_step)

        return jax.lax.scan(body, state, None, length=n_steps)

    return chunk


def make_eval_fn(model_cfg: model.ModelConfig):
    """``eval_fn(variables, batch) -> dict of (B, ...)`` eval-mode outputs."""

    def eval_fn(variables, batch):
        intrinsics = batch.get("intrinsics")
        fn = partial(model.forward_eval, variables, cfg=model_cfg)
        return jax.vmap(fn, in_axes=(0, 0, 0, None if intrinsics is None else 0))(
            batch["kp"], batch["vis"], batch["class_mask"], intrinsics
        )

    return eval_fn


def predict(variables, data: KeypointData, model_cfg, batch_size: int = 1024, eval_fn=None):
    """Eval-mode outputs for a whole split, in compiled fixed-size batches (numpy out)."""
    eval_fn = eval_fn or jax.jit(make_eval_fn(model_cfg))
    inputs = data.model_inputs()
    m = len(data)
    batch_size = min(batch_size, m)
    outputs = []
    for start in range(0, m, batch_size):
        idx = np.arange(start, start + batch_size) % m  # pad the tail by wrapping around
        out = eval_fn(variables, {k: v[idx] for k, v in inputs.items()})
        outputs.append(jax.device_get(out))
    return {k: np.concatenate([o[k] for o in outputs])[:m] for k in outputs[0]}


def evaluate_split(variables, data, model_cfg, protocol, eval_fn=None, batch_size=1024) -> dict:
    """Test metrics: MPJPE/stress when the split has 3D ground truth, and always the
    2D reprojection error of the visible points (the only score for 2D-only data)."""
    pred = predict(variables, data, model_cfg, batch_size, eval_fn)
    # kp_reprojected is in the input's units (pixels for perspective models too).
    reproj = evaluation.reprojection_error(pred["kp_reprojected"], data)
    out = {"n_samples": len(data), "reprojection": reproj}
    if data.kp3d is not None and protocol != "none":
        out.update(evaluation.evaluate(pred["shape_image_coord"], data, protocol))
    return out


def baseline_results(train: KeypointData, test: KeypointData, protocol: str) -> dict:
    """Scores of the trivial baselines (orthographic data with 3D ground truth only)."""
    if train.kp3d is None or test.kp3d is None or test.intrinsics is not None or protocol == "none":
        return {}
    mean_shape = baselines.procrustes_mean_shape(train.kp3d)
    preds = baselines.predict(mean_shape, test.kp, test.vis)
    return {name: evaluation.evaluate(p, test, protocol) for name, p in preds.items()}


def _check_data(data: KeypointData, model_cfg: model.ModelConfig, split: str) -> None:
    if data.n_keypoints != model_cfg.n_keypoints:
        raise ValueError(
            f"{split} split has {data.n_keypoints} keypoints but config.model.n_keypoints is "
            f"{model_cfg.n_keypoints}; set --config.model.n_keypoints={data.n_keypoints}"
        )
    if model_cfg.projection_type == "perspective" and data.intrinsics is None:
        raise ValueError(f"perspective model but the {split} split has no intrinsics 'K'")


def device_train_data(data: KeypointData, class_balanced: bool):
    """Training arrays for the device; sorted by class with lookup tables if balanced."""
    if class_balanced and data.group is not None:
        data = data.subset(np.argsort(data.group, kind="stable"))
        counts = np.bincount(data.group, minlength=len(data.group_names))
        present = counts > 0
        starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
        tables = {"class_start": starts[present].astype(np.int32),
                  "class_count": counts[present].astype(np.int32)}
        return jax.device_put(dict(data.model_inputs(), **tables))
    return jax.device_put(data.model_inputs())


def _next_stop(step: int, total: int, intervals) -> int:
    """The first step after ``step`` that is a multiple of an interval, or ``total``."""
    stops = [total] + [(step // i + 1) * i for i in intervals if i > 0]
    return min(stops)


class _MetricsWriter:
    """Fetches chunk metrics (one chunk late, so the host never waits on the device),
    checks them, logs them and appends them to ``metrics.jsonl``."""

    def __init__(self, workdir: str, pbar):
        self.path = os.path.join(workdir, "metrics.jsonl")
        self.pbar, self.pending, self.last_time = pbar, None, time.perf_counter()

    def push(self, first_step: int, metrics) -> None:
        self.flush()
        self.pending = (first_step, metrics)

    def flush(self) -> None:
        if self.pending is None:
            return
        first_step, metrics = self.pending
        self.pending = None
        metrics = jax.device_get(metrics)
        n = len(metrics["loss"])
        bad = np.flatnonzero(~np.isfinite(metrics["loss"]))
        if bad.size:
            at = first_step + int(bad[0])
            values = {k: float(v[bad[0]]) for k, v in metrics.items()}
            raise FloatingPointError(f"loss is not finite at step {at}: {values}")
        now = time.perf_counter()
        record = {k: float(np.mean(v)) for k, v in metrics.items()}
        record.update(step=first_step + n, steps_per_s=n / max(now - self.last_time, 1e-9))
        self.last_time = now
        with open(self.path, "a") as f:
            f.write(json.dumps(record) + "\n")
        self.pbar.update(n)
        self.pbar.set_postfix(
            loss=f"{record['loss']:.4f}",
            repro=f"{record['loss/reprojection']:.4f}",
            canon=f"{record['loss/canonicalisation']:.4f}",
            refresh=False,
        )
        logging.log_every_n_seconds(logging.INFO, "step %d: %s", 30, record["step"], record)


def _write_results(workdir: str, results: dict) -> None:
    with open(os.path.join(workdir, "eval_results.json"), "w") as f:
        json.dump(results, f, indent=2)


def _read_results(workdir: str) -> dict:
    """The workdir's ``eval_results.json`` ({} when there is none yet)."""
    path = os.path.join(workdir, "eval_results.json")
    if not os.path.exists(path):
        return {}
    with open(path) as f:
        return json.load(f)


def _setup(config):
    model_cfg = model.ModelConfig.from_dict(config.model)
    optim_cfg = OptimConfig.from_dict(config.optim)
    steps_per_epoch = max(config.train.samples_per_epoch // config.train.batch_size, 1)
    total = config.train.num_steps or config.train.epochs * steps_per_epoch
    tx = make_optimizer(optim_cfg, steps_per_epoch)
    return model_cfg, optim_cfg, steps_per_epoch, total, tx


def _data_parallel_mesh(config) -> Mesh | None:
    """All devices when there are several, unless ``config.train.data_parallel`` is False."""
    n = jax.device_count()
    if n == 1 or not config.train.data_parallel:
        return None
    if config.train.batch_size % n:
        logging.warning("batch_size %d is not a multiple of %d devices: training on one device",
                        config.train.batch_size, n)
        return None
    logging.info("data parallel over %d devices", n)
    return make_mesh(n)


def train_and_evaluate(config, workdir: str) -> dict:
    """Trains C3DPO as ``config`` says, resuming from ``workdir`` if it has checkpoints.

    Returns the final ``eval_results.json`` content (also written to ``workdir``).
    """
    os.makedirs(workdir, exist_ok=True)
    model_cfg, optim_cfg, steps_per_epoch, total, tx = _setup(config)
    saved = checkpoint.load_config(workdir)
    if saved is not None and saved.get("model") != config.model.to_dict():
        raise ValueError(f"{workdir} holds a run with other model settings; use a new --workdir")
    checkpoint.save_config(workdir, config.to_dict())
    train_data, test_data = load_splits(config.data)
    _check_data(train_data, model_cfg, "train")
    _check_data(test_data, model_cfg, "test")
    init_key, train_key = jax.random.split(jax.random.key(config.seed))
    manager = checkpoint.make_manager(workdir, config.train.ckpt_every)
    state = checkpoint.restore_or_init(manager, create_train_state(init_key, model_cfg, tx))
    step = int(state.step)
    if step:
        logging.info("resumed from the checkpoint at step %d in %s", step, workdir)
    data = device_train_data(train_data, config.data.class_balanced)
    mesh = _data_parallel_mesh(config)
    if mesh is not None:
        state, data = replicate(state, mesh), replicate(data, mesh)
    schedule = make_schedule(optim_cfg, steps_per_epoch)
    train_step = make_train_step(model_cfg, LossConfig(**config.loss), tx, schedule)
    chunk = jax.jit(make_train_chunk(train_step, config.train.batch_size, mesh),
                    static_argnames="n_steps", donate_argnums=0)
    eval_fn = jax.jit(make_eval_fn(model_cfg))
    protocol, eval_bs = config.data.protocol, config.train.eval_batch_size
    eval_every = config.train.eval_every_epochs * steps_per_epoch
    # A resumed run keeps the evaluations made before its checkpoint.
    history = [h for h in _read_results(workdir).get("history", []) if h["step"] <= step]
    pbar = tqdm(total=total, initial=step, unit="step", dynamic_ncols=True,
                disable=not config.train.progress_bar, desc="train")
    writer = _MetricsWriter(workdir, pbar)
    while step < total:
        stop = _next_stop(
            step, total, (config.train.log_every, config.train.ckpt_every, eval_every)
        )
        state, metrics = chunk(state, data, train_key, n_steps=stop - step)
        writer.push(step, metrics)
        step = stop
        if step % config.train.ckpt_every == 0 or step == total:
            writer.flush()  # never checkpoint a state whose losses were not checked
            checkpoint.save(manager, step, state, force=step == total)
        if eval_every and step % eval_every == 0 and step < total:
            writer.flush()
            res = evaluate_split(state.variables, test_data, model_cfg, protocol, eval_fn, eval_bs)
            history.append(dict(step=step, epoch=step // steps_per_epoch, **res))
            logging.info("epoch %d: test %s", step // steps_per_epoch,
                         {k: v for k, v in res.items() if k != "per_group"})
            _write_results(workdir, {"history": history})
    writer.flush()
    pbar.close()
    manager.wait_until_finished()
    manager.close()
    final = evaluate_split(state.variables, test_data, model_cfg, protocol, eval_fn, eval_bs)
    results = {"history": history, "final": dict(step=step, **final),
               "baselines": baseline_results(train_data, test_data, protocol)}
    _write_results(workdir, results)
    return results


def evaluate_checkpoint(config, workdir: str) -> dict:
    """``--mode=eval``: scores the latest checkpoint in ``workdir`` on the test split.

    Updates ``final`` and ``baselines`` of ``eval_results.json``; its training history stays.
    """
    model_cfg, _, _, _, tx = _setup(config)
    template = create_train_state(jax.random.key(0), model_cfg, tx)
    state, step = checkpoint.restore_latest(workdir, template)
    train_data, test_data = load_splits(config.data)
    _check_data(test_data, model_cfg, "test")
    final = evaluate_split(state.variables, test_data, model_cfg, config.data.protocol,
                           batch_size=config.train.eval_batch_size)
    results = dict(_read_results(workdir), final=dict(step=step, **final),
                   baselines=baseline_results(train_data, test_data, config.data.protocol))
    _write_results(workdir, results)
    return results
