"""Training and evaluation: pure step factories and the loop that drives them.

Glossary: B batch, N keypoints, M dataset samples, T steps per compiled call.

- ``make_train_step`` -> ``train_step(state, batch, key)``: one pure, jittable SGD step
  on the objective ``losses.make_loss_fn`` (the per-example forward vmapped over the
  batch, BatchNorm reducing over it; ``LossConfig`` and ``make_loss_fn`` stay importable
  from here).
- ``make_train_chunk`` -> ``chunk(state, data, train_key, n_steps)``: ``lax.scan`` over
  ``n_steps`` steps; each step samples its batch (with replacement, as the release)
  from the device-resident ``data`` with ``fold_in(train_key, step)``, so the data
  order and all augmentations depend only on (seed, step): a resumed run replays an
  uninterrupted one exactly.
- Data parallelism (``device_data.make_mesh`` / ``replicate``): with a mesh, the chunk constrains
  each sampled batch to be split over the mesh's ``"data"`` axis while parameters,
  optimiser state and the training arrays stay replicated; XLA (GSPMD) partitions the
  vmapped step and turns BatchNorm's batch means and the gradient sums into
  all-reduces, so results equal one device's up to float rounding.
- ``RunSpec.from_config(config)``: the frozen description of a run (model, optimiser,
  loss weights, batch size, step counts) that the loop, the benchmark and the
  experiments build their steps from.
- ``train_and_evaluate(config, workdir, hooks)``: the loop (progress bar, the run's records
  of ``run_records``, orbax checkpoints and resume, evaluation every ``eval_every`` steps and
  at the end, with the baselines of ``inference.evaluate_baselines``);
  ``Hooks`` lets experiments observe it and stop it early (e.g. at a time budget).
"""

import dataclasses
import os
import time
from collections.abc import Callable

import jax
import jax.numpy as jnp
import optax
from absl import logging
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from c3dpo_jax import (
    checkpoint,
    device_data,
    evaluation,
    inference,
    lift,
    model,
    progress,
    run_config,
    run_records,
    stops,
    validation,
    workdir_lock,
)
from c3dpo_jax.data import KeypointData, load_splits
from c3dpo_jax.data.dataset import fingerprint
from c3dpo_jax.inference import evaluate_baselines, evaluate_split, with_views_mean
from c3dpo_jax.lift import InferenceConfig
from c3dpo_jax.losses import RAMPED_TERMS, LossConfig, make_loss_fn
from c3dpo_jax.reconstruct import load, split_path
from c3dpo_jax.resolve import resolve_from_data
from c3dpo_jax.state import (
    OptimConfig,
    TrainState,
    create_train_state,
    make_optimizer,
    make_schedule,
)


def make_train_step(model_cfg, loss_cfg, tx: optax.GradientTransformation, schedule=None):
    """``train_step(state, batch, key) -> (state, metrics)``, pure and jittable."""
    grad_fn = jax.value_and_grad(make_loss_fn(model_cfg, loss_cfg), has_aux=True)

    def train_step(state: TrainState, batch, key):
        (_, (stats, metrics)), grads = grad_fn(
            state.params, state.batch_stats, batch, key, state.step
        )
        updates, opt_state = tx.update(grads, state.opt_state, state.params)
        params = optax.apply_updates(state.params, updates)
        metrics = dict(metrics, grad_norm=optax.global_norm(grads))
        if schedule is not None:
            metrics["lr"] = jnp.asarray(schedule(state.step), jnp.float32)
        new_state = TrainState(state.step + 1, params, stats, opt_state)
        return new_state, metrics

    return train_step


def make_train_chunk(train_step, batch_size: int, mesh: Mesh | None = None,
                     views: int = 0):
    """``chunk(state, data, train_key, n_steps)``: ``n_steps`` steps in one ``lax.scan``
    (``views``: with frame tables in ``data``, the views drawn per frame).

    With ``mesh``, pass ``replicate``d state and data: each batch is split over the
    mesh's ``"data"`` axis (``batch_size`` must be a multiple of its size).
    """
    if mesh is not None and batch_size % mesh.size:
        raise ValueError(f"batch_size {batch_size} is not a multiple of {mesh.size} devices")
    if views and batch_size % views:
        raise ValueError(f"batch_size {batch_size} is not a multiple of the {views} views "
                         "drawn per frame (loss.multiview_views)")
    split = None if mesh is None else NamedSharding(mesh, PartitionSpec("data"))

    def chunk(state: TrainState, data, train_key, n_steps: int):
        per_sample = {k: v for k, v in data.items() if k not in device_data.TABLES}

        def body(state, _):
            k_idx, k_step = jax.random.split(jax.random.fold_in(train_key, state.step))
            idx = device_data.sample_indices(data, k_idx, batch_size, views)
            batch = jax.tree.map(lambda a: a[idx], per_sample)
            if split is not None:
                batch = jax.lax.with_sharding_constraint(batch, split)
            return train_step(state, batch, k_step)

        return jax.lax.scan(body, state, None, length=n_steps)

    return chunk


def _scores(record: dict) -> str:
    """An evaluation's scores in one short line (all of them: eval_results.json)."""
    return ", ".join(f"{k} {record[k]:.4g}" for k in evaluation.TABLE_KEYS if k in record)


def _next_stop(step: int, total: int, intervals) -> int:
    """The first step after ``step`` that is a multiple of an interval, or ``total``."""
    stops = [total] + [(step // i + 1) * i for i in intervals if i > 0]
    return min(stops)


@dataclasses.dataclass(frozen=True)
class RunSpec:
    """What a config asks the training loop to do, resolved once (no ml_collections below).

    ``inference`` is how its evaluations lift the test views (a training config's may hold
    what ``resolve.resolve_handedness`` resolves). ``total_steps`` is ``train.num_steps`` or
    ``epochs * steps_per_epoch``; ``eval_every`` is in steps (``train.eval_every_steps``,
    else ``eval_every_epochs`` epochs; 0: only the final evaluation)."""

    model: model.ModelConfig
    inference: InferenceConfig
    optim: OptimConfig
    loss: LossConfig
    batch_size: int
    steps_per_epoch: int
    total_steps: int
    eval_every: int

    @classmethod
    def from_config(cls, config) -> "RunSpec":
        t = config.train
        steps_per_epoch = max(t.samples_per_epoch // t.batch_size, 1)
        eval_every = t.get("eval_every_steps", 0) or t.eval_every_epochs * steps_per_epoch
        return cls(model=model.ModelConfig.from_dict(config.model),
                   inference=InferenceConfig.from_dict(config.get("inference", {})),
                   optim=OptimConfig.from_dict(config.optim), loss=LossConfig(**config.loss),
                   batch_size=t.batch_size, steps_per_epoch=steps_per_epoch,
                   total_steps=t.num_steps or t.epochs * steps_per_epoch,
                   eval_every=eval_every)

    def warnings(self) -> list[str]:
        """Settings that are valid but defeat themselves: schedules cut short by the run's
        length, a shape basis as large as the shapes (``train_and_evaluate`` logs them once,
        before training)."""
        out = []
        k, d = self.model.n_keypoints, self.model.shape_basis_size
        if d >= 3 * k:
            out.append(f"config.model.shape_basis_size={d} is not below 3K = {3 * k}: such a "
                       "basis fits any shape, so the views no longer constrain the depth "
                       "(keep D well below 3K, docs/data.md)")
        for term in RAMPED_TERMS:
            ramp = getattr(self.loss, f"{term}_ramp")
            if ramp and ramp[1] > self.total_steps:
                out.append(f"config.loss.{term}_ramp={ramp} ends after the run's "
                           f"{self.total_steps} steps: the weight never reaches "
                           f"config.loss.w_{term}_final (set a ramp inside the run)")
        if self.optim.warmup_steps > self.total_steps:
            out.append(f"config.optim.warmup_steps={self.optim.warmup_steps} is longer than the "
                       f"run's {self.total_steps} steps: the learning rate never reaches "
                       "config.optim.lr")
        return out

    def optimizer(self) -> optax.GradientTransformation:
        return make_optimizer(self.optim, self.steps_per_epoch)

    def schedule(self) -> optax.Schedule:
        return make_schedule(self.optim, self.steps_per_epoch)

    def train_step(self):
        """The pure ``train_step(state, batch, key)`` of this run (``make_train_step``)."""
        return make_train_step(self.model, self.loss, self.optimizer(), self.schedule())


@dataclasses.dataclass(frozen=True)
class Hooks:
    """Optional host-side callbacks of ``train_and_evaluate`` (experiments, notebooks).

    ``after_chunk(step, state)`` after every compiled chunk (the state is still being
    computed: fetching from it waits); ``after_evaluation(record, state)`` after each test
    evaluation, with the record appended to the history; ``should_stop(step, train_s)``,
    asked after every chunk with the training seconds so far: True ends training early
    (checkpoint and final evaluation at that step; running again resumes to the end);
    ``should_evaluate(step, train_s)``, asked after each chunk that ends before the last
    step and at no ``eval_every`` evaluation: True evaluates the test split there too
    (e.g. at times of a clock)."""

    after_chunk: Callable[[int, TrainState], None] | None = None
    after_evaluation: Callable[[dict, TrainState], None] | None = None
    should_stop: Callable[[int, float], bool] | None = None
    should_evaluate: Callable[[int, float], bool] | None = None


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
    return device_data.make_mesh(n)


def _start_from(state: TrainState, path: str) -> TrainState:
    """``state`` with the parameters and BatchNorm statistics of the model at ``path`` (a
    workdir or one of its checkpoint steps; ``train.init_from``), the optimiser fresh."""
    source = load(path).variables
    for name in ("params", "batch_stats"):
        want = jax.tree.map(jnp.shape, getattr(state, name))
        if jax.tree.map(jnp.shape, source[name]) != want:
            raise ValueError(f"config.train.init_from={path!r} holds a model of another "
                             "architecture (its parameter shapes differ from this config's)")
    logging.info("parameters from %s", path)
    return state.replace(params=source["params"], batch_stats=source["batch_stats"])


@model.single_precision
def train_and_evaluate(config, workdir: str, hooks: Hooks | None = None) -> dict:
    """Trains C3DPO as ``config`` says, resuming from ``workdir`` if it has checkpoints.

    Every evaluation record carries ``train_s``: seconds of training so far (compilation
    and metric logging included; evaluation, checkpoint writing and data loading excluded;
    a resumed run continues the clock of its latest record at or before its checkpoint,
    ``run_records.clock_at``). Returns the final
    ``eval_results.json`` content (also written to ``workdir``). The run holds the workdir's
    lock throughout (``workdir_lock.hold``): a second run there is refused in one line.
    """
    validation.check_config(config)
    validation.check_workdir_is_a_folder(workdir)
    with workdir_lock.hold(workdir):
        return _train_and_evaluate(config, workdir, hooks or Hooks())


def _resolve_run(config, workdir: str, train_data: KeypointData, test_data: KeypointData):
    """``(config, spec, options)``: the run's config resolved from the data, checked against
    the data and the workdir and written to its config.json; its ``RunSpec``; the inference
    options its evaluations use."""
    init_from = config.train.get("init_from") or ""
    # A resumed run keeps its own input scale and handedness; one that starts from another
    # run's parameters takes that run's (only then is the other run read).
    scale_from = (run_config.load_config(workdir) if checkpoint.has_checkpoint(workdir) else
                  run_config.load_config(split_path(init_from)[0]) if init_from else None)
    config = resolve_from_data(config, train_data, scale_from)
    spec = RunSpec.from_config(config)
    options = lift.inference_config(spec.model, spec.inference)
    for warning in spec.warnings():
        logging.warning("%s", warning)
    if spec.batch_size > len(train_data):
        logging.warning("config.train.batch_size=%d is larger than the %d training views: every "
                        "batch repeats views", spec.batch_size, len(train_data))
    # config.json also records what the training split held, so that resuming on a file
    # edited in place under the same path is refused like a change of settings.
    # data_files: the data files' absolute paths, so that the run's pictures find them
    # (visualise.run_style) from any directory, not only the one the run was started in.
    record = dict(config.to_dict(), train_data_sha256=fingerprint(train_data),
                  data_files={k: os.path.abspath(config.data[k])
                              for k in ("train_path", "test_path") if config.data[k]})
    run_config.check_workdir(workdir, record)
    record["software"] = run_config.software_history(workdir)
    if spec.model.projection_type != "perspective" and train_data.intrinsics is not None:
        logging.warning("the training data has intrinsics (K) and the model is orthographic, "
                        "which ignores them (--config.model.projection_type=perspective uses "
                        "them)")
    with_3d = spec.loss.w_supervised > 0  # the 3D truth's term needs the training split's 3D
    validation.check_data(train_data, spec.model, "train", with_3d=with_3d)
    validation.check_data(test_data, spec.model, "test")
    # Written once every check has passed: a refused run leaves no folder behind (the lock
    # removes the workdir it made when nothing was written into it).
    run_config.save_config(workdir, record)
    return config, spec, options


def _initial_state(config, spec: RunSpec, workdir: str, manager, init_key) -> TrainState:
    """The state the run starts from: its latest checkpoint, else a fresh one (with the
    parameters of ``train.init_from`` where that names a model)."""
    init_from = config.train.get("init_from") or ""
    state = checkpoint.restore_or_init(
        manager, create_train_state(init_key, spec.model, spec.optimizer()))
    step, total = int(state.step), spec.total_steps
    if step > total:
        logging.warning("%s holds a checkpoint at step %d, past the %d steps asked for: it is "
                        "scored as it is (a new --workdir trains %d steps)", workdir, step,
                        total, total)
    elif step:
        logging.info("resumed from the checkpoint at step %d in %s", step, workdir)
    elif init_from:
        state = _start_from(state, init_from)
    return state


def _compiled_chunk(config, spec: RunSpec, train_data: KeypointData, state: TrainState):
    """``(chunk, state, data)``: the run's jitted ``make_train_chunk``, the state and the
    device-resident training data it takes (replicated over the devices when data-parallel)."""
    by_frame = spec.loss.w_multiview > 0
    data = device_data.device_train_data(train_data, config.data.class_balanced,
                                         with_3d=spec.loss.w_supervised > 0, by_frame=by_frame)
    mesh = _data_parallel_mesh(config)
    if mesh is not None:
        state, data = device_data.replicate(state, mesh), device_data.replicate(data, mesh)
    chunk = jax.jit(make_train_chunk(spec.train_step(), spec.batch_size, mesh,
                                     spec.loss.multiview_views if by_frame else 0),
                    static_argnames="n_steps", donate_argnums=0)
    return chunk, state, data


def _earlier_evaluations(workdir: str, step: int, total: int) -> tuple[list[dict], float]:
    """The evaluations a resumed run made before its checkpoint at ``step``, and its
    training clock there (none and 0 for a new run)."""
    before = run_records.read_results(workdir)
    history = [h for h in before.get("history", []) if h["step"] <= step]
    last = before.get("final")
    if last and last.get("step") == step < total and all(h["step"] != step for h in history):
        history.append(last)  # a finished run extended: its final evaluation is on the curve
    return history, run_records.clock_at(before, step) or 0.0


def _record_evaluation(workdir: str, history: list[dict], writer, hooks: Hooks,
                       state: TrainState) -> None:
    """Logs and writes the evaluation that ends ``history``, then shows it to the hooks."""
    step = history[-1]["step"]
    logging.info("test at step %d: %s", step, _scores(history[-1]))
    run_records.write_results(workdir, {"history": history})
    writer.scalars(step, history[-1], prefix="test/")
    if hooks.after_evaluation is not None:
        hooks.after_evaluation(history[-1], state)


def _save_views_mean(workdir: str, options: InferenceConfig, used) -> None:
    """With the reference "views_mean", writes the inference of the run's last evaluation
    (``used``: ``inference.with_views_mean``'s options, with their rows or, where its guard
    fell back, the model's own handedness, and the share it weighed) into config.json,
    which loading the model reads, and says which."""
    if options.handedness_reference != "views_mean":
        return
    used, share = used
    run_config.save_inference(workdir, used.to_dict())
    if share is None:  # the guard's share applies to the tetrahedra only
        return
    kept = used.handedness_reference == "views_mean"
    logging.info("handedness at inference: %s (%.1f%% of the training views' shapes reverse "
                 "their mean's small corners; at most %.0f%%: they name a view's handedness)",
                 "each output's, from its small corners" if kept else "the model's own",
                 100 * share, 100 * inference.TETRAHEDRA_TRUST)


def _train_and_evaluate(config, workdir: str, hooks: Hooks) -> dict:
    """``train_and_evaluate``'s run, the workdir locked."""
    train_data, test_data = load_splits(config.data)
    validation.check_split_keypoints(train_data, test_data, config.model.n_keypoints)
    config, spec, options = _resolve_run(config, workdir, train_data, test_data)
    init_key, train_key = jax.random.split(jax.random.key(config.seed))
    manager = checkpoint.make_manager(workdir, config.train.ckpt_every)
    state = _initial_state(config, spec, workdir, manager, init_key)
    step, total = int(state.step), spec.total_steps
    run_records.trim_metrics(workdir, step)
    chunk, state, data = _compiled_chunk(config, spec, train_data, state)
    protocol, eval_bs = config.data.protocol, config.train.eval_batch_size

    used = [(options, None)]  # the latest evaluation's (the views' mean filled in, share)

    def evaluate(state, step):
        used[0] = with_views_mean(options, state.variables, train_data, spec.model)
        res = evaluate_split(state.variables, test_data, spec.model, used[0][0], protocol,
                             eval_bs)
        return dict(step=step, epoch=step // spec.steps_per_epoch, train_s=train_s, **res)

    # A resumed run keeps the evaluations made before its checkpoint and their clock.
    history, train_s = _earlier_evaluations(workdir, step, total)
    pbar = progress.progress_bar(total=total, initial=step, unit="step", dynamic_ncols=True,
                                 disable=not config.train.progress_bar, desc="train")
    writer = run_records.MetricsWriter(workdir, pbar, resumed_from=step)
    if 0 < step < total and spec.eval_every and step % spec.eval_every == 0 and (
            not history or history[-1]["step"] != step):
        # Killed after the checkpoint of an evaluation's step, before the evaluation was
        # recorded: made now, so that the curve has it.
        history.append(evaluate(state, step))
        _record_evaluation(workdir, history, writer, hooks, state)

    def close() -> None:
        """Ends the bar (before any message) and finishes and seals the saves in flight."""
        pbar.close()
        manager.wait_until_finished()
        manager.close()

    tic = time.perf_counter()
    try:
        with stops.StopRequests() as signals:
            while step < total:
                stop = _next_stop(step, total, (config.train.log_every, config.train.ckpt_every,
                                                spec.eval_every))
                state, metrics = chunk(state, data, train_key, n_steps=stop - step)
                writer.push(step, metrics)
                step = stop
                if hooks.after_chunk is not None:
                    hooks.after_chunk(step, state)
                clock = train_s + time.perf_counter() - tic
                stopping = signals.requested or (
                    hooks.should_stop is not None and hooks.should_stop(step, clock))
                evaluating = step < total and not signals.requested and (
                    (spec.eval_every and step % spec.eval_every == 0)
                    or (hooks.should_evaluate is not None and hooks.should_evaluate(step, clock)))
                if evaluating or stopping or step % config.train.ckpt_every == 0 or step == total:
                    # Never checkpoint or score a state whose losses were not checked.
                    writer.flush()
                    train_s += time.perf_counter() - tic
                    if step % config.train.ckpt_every == 0 or step == total or stopping:
                        checkpoint.save(manager, step, state, force=step == total or stopping)
                    if evaluating:
                        history.append(evaluate(state, step))
                        _record_evaluation(workdir, history, writer, hooks, state)
                    tic = time.perf_counter()
                if stopping:  # said after the bar is closed, not drawn around it
                    break
        writer.flush()
    except BaseException:  # a diverged loss (FloatingPointError), a hook's exception, Ctrl-C
        close()
        writer.close()
        raise
    train_s += time.perf_counter() - tic
    close()
    if step < total and not signals.requested:  # a hook's stop (a signal's: Interrupted)
        logging.info("stopped early at step %d of %d", step, total)
    if signals.requested:
        writer.close()
        signals.raise_if_requested(step, total)
    if history and history[-1]["step"] == step:  # stopped at an evaluation: no second one
        final = history[-1]
    else:
        final = evaluate(state, step)
        writer.scalars(step, final, prefix="test/")
        if hooks.after_evaluation is not None:
            hooks.after_evaluation(final, state)
    _save_views_mean(workdir, options, used[0])
    results = {"history": history, "final": final,
               "baselines": evaluate_baselines(train_data, test_data, protocol)}
    run_records.write_results(workdir, results)
    writer.close()
    return results
