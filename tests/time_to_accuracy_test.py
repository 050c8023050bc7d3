"""experiments/time_to_accuracy: a replayed run on a generated sequence, then the report."""

import json
import os
import subprocess
import sys

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
EXP = os.path.join(ROOT, "experiments", "time_to_accuracy")
TINY = ["model.n_fully_connected=32", "model.canonicalization_n_fully_connected=32",
        "model.n_layers=1", "model.canonicalization_n_layers=1", "train.batch_size=16"]


@pytest.fixture(autouse=True)
def _smoke_sized_subprocesses(monkeypatch, smoke_subprocess_env):
    """Every script here runs smoke-sized networks: compile them as such (conftest)."""
    monkeypatch.setenv("XLA_FLAGS", smoke_subprocess_env()["XLA_FLAGS"])


def _sequence(path: str) -> None:
    rng = np.random.default_rng(0)
    base = rng.normal(size=(3, 9))
    t = np.linspace(0, 4 * np.pi, 60)
    wave = np.sin(t)[:, None, None] * rng.normal(size=(1, 3, 9)) * 0.3
    np.savez(path, X=(base[None] + wave).astype(np.float32))  # (F, 3, K) as in shared/data


def test_replayed_run_evaluates_at_the_calibrated_steps_and_reports(tmp_path):
    seq, out = str(tmp_path / "wave.npz"), str(tmp_path / "results")
    _sequence(seq)
    cmd = [sys.executable, os.path.join(EXP, "run.py"), f"--dataset={seq}", "--recipe=cpu",
           "--budget_s=3", "--eval_every_s=1", "--steps_per_s=10", "--compile_s=1",
           "--chunk_steps=5", "--views_per_frame=2", f"--out_dir={out}",
           f"--save_variables={tmp_path / 'wave.msgpack'}"]
    cmd += [f"--set={s}" for s in TINY]
    subprocess.run(cmd, check=True, capture_output=True, text=True, cwd=str(tmp_path))
    with open(os.path.join(out, "wave__cpu__s0.json")) as f:
        result = json.load(f)
    # Replay: time = compile_s + step / steps_per_s (1 s + 0.1 s per step); evaluations at the
    # first chunk (5 steps) at or past each whole second, and at the end of the budget.
    assert [p["step"] for p in result["curve"]] == [5, 10, 20]
    np.testing.assert_allclose([p["t"] for p in result["curve"]], [1.5, 2.0, 3.0])
    # The run is the library's: its workdir holds the loop's records and the same final.
    with open(os.path.join(out, "runs", "wave__cpu__s0", "eval_results.json")) as f:
        loop = json.load(f)
    assert loop["final"]["step"] == 20 and loop["final"]["mpjpe"] == result["curve"][-1]["mpjpe"]
    assert result["recipe_steps"] > 20 and not result["ended"]  # the budget stopped it
    assert result["config"]["model"]["n_fully_connected"] == 32
    assert result["machine"]["cpu"] and result["machine"]["cores"] >= 1  # how it was made
    assert set(result["baselines"]) == {"zero depth", "fitted mean shape", "oracle mean shape",
                                        "fitted PCA basis", "fitted mean shape, per-view scale"}
    assert all(np.isfinite(p["mpjpe"]) for p in result["curve"])
    # The rigidly fitted mean shape keeps the observed x, y: it beats zero depth here.
    assert result["baselines"]["fitted mean shape"] < result["baselines"]["zero depth"]
    # The wave is one deformation mode (plus what the Procrustes alignment turns into
    # rotations), well inside the 10-dimensional PCA basis: 0.03 against 0.17 here.
    assert result["baselines"]["fitted PCA basis"] < 0.3 * result["baselines"]["fitted mean shape"]

    # Baselines added after the runs (--baselines_only) take precedence in the report.
    only = [f"--dataset={seq}", "--baselines_only", "--views_per_frame=2", f"--out_dir={out}"]
    subprocess.run(cmd[:2] + only, check=True, capture_output=True, cwd=str(tmp_path))
    with open(os.path.join(out, "baselines", "wave.json")) as f:
        added = json.load(f)["baselines"]
    assert added == result["baselines"]  # same views, same numbers
    with open(os.path.join(out, "baselines", "wave.json"), "w") as f:
        json.dump({"dataset": "wave", "baselines": dict(added, **{"fitted PCA basis": 0.123})}, f)

    report = subprocess.run([sys.executable, os.path.join(EXP, "report.py"), f"--results={out}",
                             "--at=2,3"], check=True, capture_output=True, text=True)
    row = next(line for line in report.stdout.splitlines() if line.startswith("| wave"))
    cells = [c.strip() for c in row.strip("|").split("|")]
    assert cells[1:3] == [f"{p['mpjpe']:.3f}" for p in result["curve"][1:]]  # t = 2 s, 3 s
    assert cells[-2] == "0.123"  # the fitted PCA basis column, from baselines/wave.json
    assert os.path.getsize(os.path.join(out, "curves.png")) > 1000

    # diagnose.py on the saved variables scores the network and the baseline as the run did.
    diag = [sys.executable, os.path.join(EXP, "diagnose.py"), f"--dataset={seq}",
            "--views_per_frame=2", f"--variables={tmp_path / 'wave.msgpack'}",
            f"--json={tmp_path / 'diag.json'}"] + [f"--set={s}" for s in TINY]
    subprocess.run(diag, check=True, capture_output=True, cwd=str(tmp_path))
    with open(tmp_path / "diag.json") as f:
        figures = json.load(f)["figures"]
    np.testing.assert_allclose(figures["network"], result["curve"][-1]["mpjpe"], rtol=1e-6)
    np.testing.assert_allclose(figures["fitted mean shape (baseline)"],
                               result["baselines"]["fitted mean shape"], rtol=1e-9)
    assert all(np.isfinite(v) for v in figures.values())


def test_a_recipe_that_ends_before_the_budget_ends_the_run_and_stands_for_the_later_marks(
        tmp_path, load_script):
    seq, out = str(tmp_path / "wave.npz"), str(tmp_path / "results")
    _sequence(seq)
    cmd = [sys.executable, os.path.join(EXP, "run.py"), f"--dataset={seq}", "--recipe=cpu",
           "--budget_s=3", "--eval_every_s=1", "--steps_per_s=10", "--compile_s=1",
           "--chunk_steps=5", "--views_per_frame=2", f"--out_dir={out}",
           "--set=train.num_steps=10"] + [f"--set={s}" for s in TINY]
    subprocess.run(cmd, check=True, capture_output=True, text=True, cwd=str(tmp_path))
    with open(os.path.join(out, "wave__cpu__s0.json")) as f:
        result = json.load(f)
    # The CLI's run ends at step 10 (clock 2 s), before the 3 s budget's 20 steps.
    assert [p["step"] for p in result["curve"]] == [5, 10]
    assert result["recipe_steps"] == 10 and result["ended"]
    report = load_script("experiments/time_to_accuracy/report.py")
    final = result["curve"][-1]["mpjpe"]
    assert report.mpjpe_at(result, 1.5) == result["curve"][0]["mpjpe"]
    assert report.mpjpe_at(result, 3.0) == report.mpjpe_at(result, 600.0) == final
    assert np.isnan(report.mpjpe_at(dict(result, ended=False), 3.0))  # stopped for another reason


def test_timed_run_stops_at_its_budget_and_measures_its_rate(tmp_path):
    seq, out = str(tmp_path / "wave.npz"), str(tmp_path / "results")
    _sequence(seq)
    cmd = [sys.executable, os.path.join(EXP, "run.py"), f"--dataset={seq}", "--recipe=cpu",
           "--budget_s=2", "--eval_every_s=100", "--chunk_steps=5", "--views_per_frame=2",
           f"--out_dir={out}"] + [f"--set={s}" for s in TINY]
    subprocess.run(cmd, check=True, capture_output=True, text=True, cwd=str(tmp_path))
    with open(os.path.join(out, "wave__cpu__s0.json")) as f:
        result = json.load(f)
    (point,) = result["curve"]  # evaluated once, where the clock passed the budget
    assert result["mode"] == "wall" and point["t"] >= 2.0 and point["step"] % 5 == 0
    # The clock is the steps at the measured rate plus the compilation (the first chunk's
    # compilation makes the clock longer than the steps alone).
    assert result["steps_per_s"] > 0 and 0 < result["compile_s"] < point["t"]
    np.testing.assert_allclose(result["compile_s"] + point["step"] / result["steps_per_s"],
                               point["t"], rtol=1e-6)


def test_supervised_reference_trains_the_same_networks_with_the_3d_truth(tmp_path):
    seq, out = str(tmp_path / "wave.npz"), str(tmp_path / "results")
    _sequence(seq)
    common = [sys.executable, os.path.join(EXP, "run.py"), f"--dataset={seq}",
              "--views_per_frame=2", f"--out_dir={out}", "--eval_every_s=1000"]
    tiny = [f"--set={s}" for s in TINY]
    subprocess.run([*common, "--supervised", "--set=train.num_steps=400", *tiny],
                   check=True, capture_output=True, cwd=str(tmp_path))
    subprocess.run([*common, "--set=train.num_steps=10", *tiny], check=True,
                   capture_output=True, cwd=str(tmp_path))
    with open(os.path.join(out, "wave__cpu_supervised__s0.json")) as f:
        result = json.load(f)
    loss, model = result["config"]["loss"], result["config"]["model"]
    assert result["recipe"] == "cpu_supervised" and result["ended"]
    assert (loss["w_supervised"], loss["w_reprojection"], loss["w_canonicalization"]) == (1, 0, 0)
    assert not model["canonicalization"] and model["n_fully_connected"] == 32
    final = result["curve"][-1]["mpjpe"]
    # With 3D ground truth the network is far better than no depth at all.
    assert final < 0.5 * result["baselines"]["zero depth"]

    report = subprocess.run([sys.executable, os.path.join(EXP, "report.py"), f"--results={out}",
                             "--at=1"], check=True, capture_output=True, text=True)
    head, _, row = report.stdout.splitlines()[:3]
    columns = [c.strip() for c in head.strip("|").split("|")]
    cells = [c.strip() for c in row.strip("|").split("|")]
    # A reference, not a recipe: its runs have no columns of their own.
    assert [c for c in columns if c.endswith(" min")] == ["cpu 0.0166667 min"]
    assert cells[columns.index("same network, 3D truth")] == f"{final:.3f}"


def _diagnose_module():
    sys.path.insert(0, EXP)
    try:
        import diagnose
    finally:
        sys.path.remove(EXP)
    return diagnose


def test_diagnostics_recover_exact_cameras_shapes_and_low_rank_models():
    diagnose = _diagnose_module()
    from c3dpo_jax import baselines

    rng = np.random.default_rng(1)
    mean, modes = rng.normal(size=(12, 3)), rng.normal(size=(2, 12, 3))
    mean, modes = mean - mean.mean(0), modes - modes.mean(1, keepdims=True)  # centred
    shapes = mean + np.einsum("md,dnc->mnc", rng.normal(size=(40, 2)) * 0.3, modes)
    rot = Rotation.random(40, random_state=2).as_matrix()
    gt = np.einsum("mij,mnj->mni", rot, shapes) + rng.normal(size=(40, 1, 3))

    # Oracle rotation: exact for rotated copies and for mirrored ones (a reflection is the
    # canonical-frame ambiguity), not for a shape that differs.
    np.testing.assert_allclose(diagnose.oracle_rotation(shapes, gt), gt, atol=1e-9)
    np.testing.assert_allclose(diagnose.oracle_rotation(shapes * [1, -1, 1], gt), gt, atol=1e-9)
    assert np.abs(diagnose.oracle_rotation(shapes[::-1], gt) - gt).max() > 0.1

    # A linear model with both modes fits any of them exactly in 3D; with one it does not.
    q = np.linalg.qr(modes.reshape(2, -1).T)[0].T.reshape(2, 12, 3)
    for d, exact in ((2, True), (1, False)):
        model = baselines.ShapeBasis(mean, q[:d], np.ones(d), 1e-6)
        fit = diagnose.pca_oracle_fit(model, gt, n_iters=30)
        assert np.allclose(fit, gt, atol=1e-6) == exact, d

    # Scaled orthographic views of one rigid shape: zero 2D residual; of deforming ones: not.
    kp = 0.7 * gt[..., :2]
    vis = np.ones(kp.shape[:2])
    rigid = np.einsum("mij,nj->mni", rot, mean)[..., :2] * 0.7
    assert diagnose.rigid_residual_2d(mean, rigid, vis) < 1e-9
    assert diagnose.rigid_residual_2d(mean, kp, vis) > 0.01


def test_learnt_basis_spans_the_shape_layer():
    diagnose = _diagnose_module()
    import jax
    import jax.numpy as jnp

    from c3dpo_jax import model

    cfg = model.ModelConfig(n_keypoints=7, shape_basis_size=3, n_fully_connected=16, n_layers=1,
                            canonicalization_n_fully_connected=16, canonicalization_n_layers=1,
                            weight_init_std=0.5)
    variables = model.init_variables(jax.random.key(0), cfg)
    alpha = np.random.default_rng(0).normal(size=(50, 3))
    basis = diagnose.learnt_basis(variables, cfg, alpha, noise_var=1e-6)
    net = model.make_network(cfg)
    shapes = np.stack([np.asarray(net.apply({"params": variables["params"]}, jnp.asarray(a),
                                            method="shape")) for a in alpha])
    flat = basis.basis.reshape(3, -1)
    np.testing.assert_allclose(flat @ flat.T, np.eye(3), atol=1e-9)  # orthonormal modes
    coefs = (shapes - basis.mean).reshape(len(alpha), -1) @ flat.T
    for shape, coef in zip(shapes[:5], coefs[:5]):
        np.testing.assert_allclose(basis.mean + (coef @ flat).reshape(7, 3), shape, atol=1e-5)
    # Prior variances: those of the coefficients of ``alpha`` in the orthonormal frame.
    np.testing.assert_allclose(basis.variances, coefs.var(0), rtol=1e-4)


def test_compare_pairs_seeds_at_the_budget_and_draws_them(tmp_path):
    def write(name, dataset, seed, mpjpes):  # evaluations at t = 100, 300, 600 s
        curve = [{"t": t, "step": i, "mpjpe": m} for i, (t, m) in enumerate(
            zip((100.0, 300.0, 600.0), mpjpes))]
        run = {"dataset": dataset, "seed": seed, "curve": curve,
               "baselines": {"fitted mean shape": {"a": 0.5, "b": 0.9}[dataset]}}
        (tmp_path / name).write_text(json.dumps(run))

    write("a__x__s0.json", "a", 0, (0.9, 0.30, 0.20))
    write("a__x__s1.json", "a", 1, (0.9, 0.50, 0.40))
    write("b__x__s0.json", "b", 0, (0.9, 0.70, 0.60))
    write("a__y__s0.json", "a", 0, (0.9, 0.15, 0.10))
    write("a__y__s1.json", "a", 1, (0.9, 0.60, 0.50))
    fig = tmp_path / "cmp.png"
    out = subprocess.run(
        [sys.executable, os.path.join(EXP, "compare.py"), f"x={tmp_path}/*__x__*.json",
         f"y={tmp_path}/*__y__*.json", "--at=200", f"--figure={fig}"],
        capture_output=True, text=True, timeout=120, check=True).stdout
    cells = [line.strip("| ").split(" | ") for line in out.splitlines()]
    rows = {c[0]: c for c in cells if c[0] in ("a", "b")}
    # At 200 s every run reports its 300 s evaluation (the first at or after the budget).
    assert rows["a"][1] == "0.3000 / 0.5000 (0.4000)"
    assert rows["a"][2] == "0.1500 / 0.6000 (0.3750)"
    assert rows["a"][3] == f"{100 * np.mean([0.15 / 0.3 - 1, 0.6 / 0.5 - 1]):+.0f}% (2)"
    assert rows["b"][2] == "-" and rows["b"][3] == "-" and rows["b"][4] == "0.9000"
    assert fig.stat().st_size > 10_000
    bad = subprocess.run([sys.executable, os.path.join(EXP, "compare.py"),
                          f"x={tmp_path}/nothing*.json"], capture_output=True, text=True)
    assert bad.returncode != 0 and "no file matches" in bad.stderr
