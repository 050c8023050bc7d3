"""Benchmark CLI on a tiny config: JSON keys and sane (positive, finite) numbers, not speed."""

import json
import math
import os
import subprocess
import sys
from functools import partial

from c3dpo_jax import benchmark, lift, model

TINY = [
    "--config.model.n_keypoints=8", "--config.model.shape_basis_size=3",
    "--config.model.n_fully_connected=32", "--config.model.n_layers=1",
    "--config.model.canonicalization_n_fully_connected=32",
    "--config.model.canonicalization_n_layers=1", "--config.model.n_rand_samples=2",
    "--config.train.batch_size=16",
]


def test_benchmark_cli_writes_sane_json(tmp_path, smoke_subprocess_env):
    out = tmp_path / "bench.json"
    cmd = [sys.executable, "-m", "c3dpo_jax.benchmark", "--config=configs/default.py", *TINY,
           "--steps=2", "--chunk_steps=3", "--repeats=2", "--eval_batch=32", f"--json={out}"]
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    proc = subprocess.run(cmd, cwd=root, capture_output=True, text=True, timeout=300,
                          env=smoke_subprocess_env())  # its numbers are not under test
    assert proc.returncode == 0, proc.stderr[-3000:]
    res = json.loads(out.read_text())
    for k in ("train_samples_per_s", "eval_samples_per_s", "compile_s", "matmul_fraction",
              "flops_per_step", "matmul_gflops", "steps_per_s", "peak_rss_mb"):
        assert isinstance(res[k], float) and math.isfinite(res[k]) and res[k] > 0, k
    for k in ("config", "device", "jax_version"):
        assert isinstance(res[k], str) and res[k]
    assert res["batch_size"] == 16
    assert res["chunk_steps"] == 3
    # steps_per_s counts training steps, not compiled calls of 3 steps each.
    assert math.isclose(res["steps_per_s"], 1.0 / res["step_s"])
    assert math.isclose(res["train_samples_per_s"], 16 * res["steps_per_s"])
    assert "train_samples_per_s" in proc.stdout


def test_benchmark_cli_finds_the_bundled_configs_and_reports_errors_in_one_line(tmp_path):
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    proc = subprocess.run([sys.executable, "-m", "c3dpo_jax.benchmark", "--config=configs/nope.py"],
                          cwd=tmp_path, capture_output=True, text=True, timeout=300,
                          env=dict(os.environ, PYTHONPATH=root))
    assert proc.returncode == 2
    assert proc.stderr.startswith("error: config file 'configs/nope.py' not found; the bundled "
                                  "configs are ") and proc.stderr.count("\n") == 1, proc.stderr


def test_the_own_data_config_benchmarks_with_its_data_driven_settings_fixed():
    """configs/own_json.py leaves the input scale, the per-view scaling and the handedness
    reference to the training data, which random inputs do not have: the benchmark fixes
    them (one unit scale, one input scale, the mean shape) instead of refusing."""
    from configs import own_json

    c = own_json.get_config("smoke")
    c.model.n_keypoints = 8
    assert c.model.keypoint_scaling == "auto" and c.inference.handedness_reference == "auto"
    res = benchmark.run(c, steps=1, repeats=1, eval_batch=8)
    assert res["eval_samples_per_s"] > 0 and res["batch_size"] == c.train.batch_size


def test_chunk_steps_below_one_is_a_clear_error():
    import pytest

    from configs import default

    c = default.get_config("smoke")  # the configs' own tiny variant
    with pytest.raises(ValueError, match=r"--chunk_steps=0 \(must be >= 1\)"):
        benchmark.run(c, steps=1, eval_batch=16, repeats=1, chunk_steps=0)
    for name in ("steps", "repeats", "eval_batch"):
        kwargs = {**dict(steps=1, eval_batch=16, repeats=1, chunk_steps=1), name: 0}
        with pytest.raises(ValueError, match=rf"--{name}=0 \(must be >= 1\)"):
            benchmark.run(c, **kwargs)


def test_flops_count_matches_a_hand_count():
    cfg = model.ModelConfig(n_keypoints=2, shape_basis_size=1, n_fully_connected=8, n_layers=1,
                            canonicalization_n_fully_connected=4, canonicalization_n_layers=0,
                            n_rand_samples=3)
    # Phi on 2B rows: 6*8 + (8*2 + 2*2 + 2*8) + 8*(1+3); shape layer on B rows: 1*6;
    # Psi on 3B rows: 6*4 + 4*1 + 1*6.
    fwd_macs = 2 * (48 + 36 + 32) + 6 + 3 * (24 + 4 + 6)
    assert benchmark.flops(benchmark.dense_layers(cfg, batch=1)) == 3 * 2 * fwd_macs
    assert benchmark.flops(benchmark.dense_layers(cfg, 1, False), False) == 2 * (116 + 6)


def test_matmul_precision_option_runs_and_stays_close():
    import dataclasses

    import jax
    import numpy as np
    import pytest

    cfg = model.ModelConfig(n_keypoints=8, shape_basis_size=3, n_fully_connected=32, n_layers=1,
                            canonicalization_n_fully_connected=32, canonicalization_n_layers=1)
    variables = model.init_variables(jax.random.key(0), cfg)
    data = jax.device_put(benchmark.random_data(cfg, 4))
    args = (data["kp"][0], data["vis"][0], data["class_mask"][0], None)
    forward_eval = partial(lift.forward_eval, body=None, options=lift.InferenceConfig())
    ref = jax.jit(forward_eval, static_argnames="cfg")(variables, *args, cfg=cfg)
    low = dataclasses.replace(cfg, matmul_precision="bfloat16")
    out = jax.jit(forward_eval, static_argnames="cfg")(variables, *args, cfg=low)
    ref, out = ref["shape_canonical"], out["shape_canonical"]
    # The trunks' products take bfloat16 operands on every backend (CPU included), so
    # the result moves, a little; the output and the parameters stay float32.
    assert out.dtype == ref.dtype == np.float32
    assert not np.array_equal(out, ref)
    np.testing.assert_allclose(out, ref, rtol=0.05, atol=1e-3)
    jaxpr = str(jax.make_jaxpr(lambda v: forward_eval(v, *args, cfg=low))(variables))
    assert "bf16" in jaxpr and "bf16" not in str(jax.make_jaxpr(
        lambda v: forward_eval(v, *args, cfg=cfg))(variables))
    with pytest.raises(ValueError, match="matmul_precision"):
        forward_eval(variables, *args, cfg=dataclasses.replace(cfg, matmul_precision="x"))
