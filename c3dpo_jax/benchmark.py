"""Throughput benchmark of the compiled training chunk and the eval forward pass.

Run: ``python -m c3dpo_jax.benchmark --config=configs/h36m.py [--json=PATH] [--steps=N]``.

Glossary: B batch, N keypoints, D shape-basis size, S canonicalisation samples, H width.

Measures, on random device-resident data of the config's shapes and through the
same ``make_train_chunk`` path as training: compile time, train steps/s and
samples/s (median over calls after warm-up, of ``--chunk_steps`` steps each, 1 by
default; training's chunks end at the next multiple of ``train.log_every``,
``train.ckpt_every`` or the evaluation interval: at most 50 steps with configs/default.py,
20 with configs/release.py), eval samples/s (the compiled ``inference.forward_batch``, with
the config's ``inference.turns`` passes per sample and its ``inference.refine_iters``
refinement steps), the analytic dense-layer FLOPs of a step and the fraction of this
machine's float32 matmul rate (``jnp.dot`` on the same shapes, measured in the same run)
that the step achieves, and peak memory. Numbers are for reporting, never tests. With
several devices (e.g. ``XLA_FLAGS=--xla_force_host_platform_device_count=2``) the train
step is data parallel over all of them, as in ``train.train_and_evaluate``.
"""

import json
import os
import platform
import resource
import statistics
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np
from absl import flags
from ml_collections import config_flags

from c3dpo_jax import cli, device_data, inference, lift, model, train
from c3dpo_jax.state import create_train_state


def _define_flags():
    """Defined only when run as a script, so importing this module next to
    ``c3dpo_jax.main`` (tests, notebooks) does not clash on ``--config``."""
    return dict(
        config=config_flags.DEFINE_config_file("config", None, "Config file (FILE[:ARGS]).",
                                               lock_config=True),
        json=flags.DEFINE_string("json", None, "Write the results to this JSON file."),
        steps=flags.DEFINE_integer("steps", 10, "Timed train calls (after one warm-up call)."),
        chunk_steps=flags.DEFINE_integer(
            "chunk_steps", 1, "Train steps per compiled call (lax.scan), as training's chunks."),
        eval_batch=flags.DEFINE_integer("eval_batch", 1024, "Batch size of the eval forward pass."),
        repeats=flags.DEFINE_integer("repeats", 5, "Timed calls for eval and the matmul rate."),
        verbose=flags.DEFINE_bool("verbose", False, "On an error, its traceback instead of one "
                                  "line."),
    )


def _trunk_shapes(dim_in: int, width: int, n_layers: int) -> list[tuple[int, int]]:
    """(fan_in, fan_out) of the dense layers of a ``networks.Trunk``."""
    inner = width // 4
    return [(dim_in, width)] + [(width, inner), (inner, inner), (inner, width)] * n_layers


def dense_layers(cfg: model.ModelConfig, batch: int, train_mode: bool = True):
    """``[(rows, fan_in, fan_out)]``: every dense matmul of one forward pass over a batch."""
    n, d = cfg.n_keypoints, cfg.shape_basis_size
    h = cfg.n_fully_connected
    heads = d + 3 + 3 * cfg.camera_translation + cfg.camera_scale
    phi = _trunk_shapes(3 * n, h, cfg.n_layers) + [(h, heads)]
    phi_rows = batch * (2 if train_mode and cfg.z_equivariance else 1)
    layers = [(phi_rows, i, o) for i, o in phi] + [(batch, d, 3 * n)]
    if train_mode and cfg.canonicalization:
        hp = cfg.canonicalization_n_fully_connected
        psi = _trunk_shapes(3 * n, hp, cfg.canonicalization_n_layers) + [(hp, d), (d, 3 * n)]
        layers += [(batch * cfg.n_rand_samples, i, o) for i, o in psi]
    return layers


def flops(layers, train_mode: bool = True) -> float:
    """Dense-layer FLOPs (2 per multiply-add); x3 for forward + backward when training."""
    fwd = sum(2.0 * r * i * o for r, i, o in layers)
    return 3.0 * fwd if train_mode else fwd


def _median_time(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn())
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def matmul_gflops(layers, repeats: int) -> float:
    """Measured float32 rate of plain jitted ``jnp.dot`` over the step's layer shapes."""
    key = jax.random.key(0)
    xs = [jax.random.normal(jax.random.fold_in(key, 2 * j), (r, i)) for j, (r, i, _) in
          enumerate(layers)]
    ws = [jax.random.normal(jax.random.fold_in(key, 2 * j + 1), (i, o)) for j, (_, i, o) in
          enumerate(layers)]
    fn = jax.jit(lambda xs, ws: [jnp.dot(x, w) for x, w in zip(xs, ws)])
    jax.block_until_ready(fn(xs, ws))
    return flops(layers, train_mode=False) / _median_time(lambda: fn(xs, ws), repeats) / 1e9


def random_data(cfg: model.ModelConfig, n_samples: int, seed: int = 0) -> dict[str, np.ndarray]:
    """Random inputs with the config's shapes (about 90% visible points)."""
    rng = np.random.default_rng(seed)
    n = cfg.n_keypoints
    data = {
        "kp": rng.normal(size=(n_samples, n, 2)).astype(np.float32),
        "vis": (rng.random((n_samples, n)) < 0.9).astype(np.float32),
        "class_mask": np.ones((n_samples, n), np.float32),
    }
    if cfg.projection_type == "perspective":
        intr = np.tile(np.eye(3, dtype=np.float32), (n_samples, 1, 1))
        data["kp"] += 5.0  # keep points away from the principal point
        data["intrinsics"] = intr
    return data


def _peak_memory_mb() -> dict[str, float]:
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    out = {"peak_rss_mb": rss / (1024.0 if sys.platform != "darwin" else 1024.0**2)}
    stats = jax.local_devices()[0].memory_stats()
    if stats and "peak_bytes_in_use" in stats:
        out["device_peak_mb"] = stats["peak_bytes_in_use"] / 2**20
    return out


def _time_train(spec: train.RunSpec, data, steps: int,
                chunk_steps: int = 1) -> dict[str, float]:
    mesh = device_data.make_mesh() if jax.device_count() > 1 else None
    chunk = jax.jit(train.make_train_chunk(spec.train_step(), spec.batch_size, mesh),
                    static_argnames="n_steps", donate_argnums=0)
    state = create_train_state(jax.random.key(0), spec.model, spec.optimizer())
    if mesh is not None:  # data parallel over every device, as train_and_evaluate does
        state, data = device_data.replicate(state, mesh), device_data.replicate(data, mesh)
    key = jax.random.key(1)
    t0 = time.perf_counter()
    compiled = chunk.lower(state, data, key, n_steps=chunk_steps).compile()
    compile_s = time.perf_counter() - t0
    state, _ = compiled(state, data, key)  # warm-up
    jax.block_until_ready(state)
    times = []
    for _ in range(steps):
        t0 = time.perf_counter()
        state, metrics = compiled(state, data, key)
        jax.block_until_ready((state, metrics))
        times.append(time.perf_counter() - t0)
    if not np.all(np.isfinite(np.asarray(metrics["loss"]))):
        raise FloatingPointError("non-finite loss in the benchmark")
    step_s = statistics.median(times) / chunk_steps
    return {"compile_s": compile_s, "chunk_steps": chunk_steps, "step_s": step_s,
            "steps_per_s": 1.0 / step_s, "train_samples_per_s": spec.batch_size / step_s}


def _time_eval(model_cfg, options, variables, data, batch: int, repeats: int
               ) -> dict[str, float]:
    eval_fn = jax.jit(inference.forward_batch, static_argnames=("cfg", "options"))
    idx = inference.wrap_indices(0, batch, data["vis"].shape[0])
    inputs = jax.device_put({k: v[idx] for k, v in data.items()})
    args = (variables, inputs["kp"], inputs["vis"], inputs["class_mask"],
            inputs.get("intrinsics"), lift.options_body(options))
    t0 = time.perf_counter()
    compiled = eval_fn.lower(*args, cfg=model_cfg, options=options).compile()
    compile_s = time.perf_counter() - t0
    jax.block_until_ready(compiled(*args))
    sec = _median_time(lambda: compiled(*args), repeats)
    return {"eval_compile_s": compile_s, "eval_samples_per_s": batch / sec}


def run(config, steps: int = 10, eval_batch: int = 1024, repeats: int = 5,
        chunk_steps: int = 1) -> dict:
    """Runs every measurement for ``config``; returns a flat dict (see the module docstring)."""
    for name, value in (("chunk_steps", chunk_steps), ("steps", steps), ("repeats", repeats),
                        ("eval_batch", eval_batch)):
        if value < 1:
            raise ValueError(f"--{name}={value} (must be >= 1)")
    if config.model.keypoint_rescale == 0:  # "from the data": the random inputs' unit scale
        config = config.copy_and_resolve_references()
        config.model.keypoint_rescale = 1.0
    if config.model.get("keypoint_scaling") == "auto":  # random inputs: one input scale
        config = config.copy_and_resolve_references()
        config.model.keypoint_scaling = "global"
    if config.inference.handedness_reference == "auto":  # random inputs fit no body
        config = config.copy_and_resolve_references()
        config.inference.handedness_reference = "mean_shape"
    spec = train.RunSpec.from_config(config)
    model_cfg, tx = spec.model, spec.optimizer()
    options = lift.inference_config(model_cfg, spec.inference)
    batch = config.train.batch_size
    host = random_data(model_cfg, max(4 * batch, eval_batch))
    data = jax.device_put(host)
    res = {"config": config.data.get("name", "?"), "batch_size": batch,
           "device": str(jax.devices()[0].device_kind), "n_devices": jax.device_count(),
           "jax_version": jax.__version__, "platform": platform.platform(),
           "load_avg_1m": os.getloadavg()[0],
           "matmul_precision": model_cfg.matmul_precision,
           "turns": options.turns, "turn_span": options.turn_span,
           "refine_iters": options.refine_iters}
    res.update(_time_train(spec, data, steps, chunk_steps))
    variables = jax.device_put(create_train_state(jax.random.key(0), model_cfg, tx).variables,
                               jax.devices()[0])
    res.update(_time_eval(model_cfg, options, variables, host, eval_batch, repeats))
    layers = dense_layers(model_cfg, batch)
    res["flops_per_step"] = flops(layers)
    res["matmul_gflops"] = matmul_gflops(layers, max(repeats, 10))
    res["achieved_gflops"] = res["flops_per_step"] / res["step_s"] / 1e9
    res["matmul_fraction"] = res["achieved_gflops"] / res["matmul_gflops"]
    res["matmul_limit_samples_per_s"] = res["matmul_gflops"] * 1e9 / res["flops_per_step"] * batch
    res.update(_peak_memory_mb())
    res["load_avg_1m_end"] = os.getloadavg()[0]
    return res


def format_table(res: dict) -> str:
    keys = ["config", "device", "n_devices", "batch_size", "chunk_steps", "compile_s",
            "steps_per_s", "train_samples_per_s", "turns", "turn_span", "refine_iters",
            "eval_samples_per_s",
            "flops_per_step",
            "matmul_gflops", "achieved_gflops", "matmul_fraction", "matmul_limit_samples_per_s",
            "peak_rss_mb", "load_avg_1m", "load_avg_1m_end"]
    lines = []
    for k in keys:
        v = res.get(k)
        lines.append(f"{k:28s} {v:.4g}" if isinstance(v, float) else f"{k:28s} {v}")
    return "\n".join(lines)


def main(argv, fl):
    del argv
    cli.setup_logging()
    res = run(fl["config"].value, fl["steps"].value, fl["eval_batch"].value, fl["repeats"].value,
              fl["chunk_steps"].value)
    print(format_table(res))
    if fl["json"].value:
        with open(fl["json"].value, "w") as f:
            json.dump(res, f, indent=2)
    sys.stdout.flush()


if __name__ == "__main__":
    _flags = _define_flags()
    flags.mark_flags_as_required(["config"])
    # As c3dpo-train: configs/NAME.py from any directory, input errors in one line.
    cli.run(lambda argv: main(argv, _flags), _flags["verbose"])
