"""experiments/time_to_accuracy: a replayed run on a generated sequence, then the report."""

import json
import os
import subprocess
import sys

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
EXP = os.path.join(ROOT, "experiments", "time_to_accuracy")
TINY = ["model.n_fully_connected=32", "model.canonicalization_n_fully_connected=32",
        "model.n_layers=1", "model.canonicalization_n_layers=1", "train.batch_size=16"]


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
           "--chunk_steps=5", "--views_per_frame=2", f"--out_dir={out}"]
    cmd += [f"--set={s}" for s in TINY]
    subprocess.run(cmd, check=True, capture_output=True, text=True, cwd=str(tmp_path))
    with open(os.path.join(out, "wave__cpu__s0.json")) as f:
        result = json.load(f)
    # Replay: time = compile_s + step / steps_per_s (1 s + 0.1 s per step); evaluations at the
    # first chunk (5 steps) at or past each whole second, and at the end of the budget.
    assert [p["step"] for p in result["curve"]] == [5, 10, 20]
    np.testing.assert_allclose([p["t"] for p in result["curve"]], [1.5, 2.0, 3.0])
    assert result["config"]["model"]["n_fully_connected"] == 32
    assert set(result["baselines"]) == {"zero depth", "fitted mean shape", "oracle mean shape",
                                        "fitted PCA basis"}
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


def test_supervised_lifter_learns_depth_from_3d_ground_truth(tmp_path):
    seq, out = str(tmp_path / "wave.npz"), str(tmp_path / "results")
    _sequence(seq)
    common = [f"--dataset={seq}", "--views_per_frame=2", f"--out_dir={out}"]
    subprocess.run([sys.executable, os.path.join(EXP, "supervised.py"), *common, "--width=32",
                    "--blocks=1", "--batch_size=16", "--steps=400", "--evals=2"],
                   check=True, capture_output=True, cwd=str(tmp_path))
    subprocess.run([sys.executable, os.path.join(EXP, "run.py"), *common, "--baselines_only"],
                   check=True, capture_output=True, cwd=str(tmp_path))
    with open(os.path.join(out, "supervised", "wave__s0.json")) as f:
        result = json.load(f)
    with open(os.path.join(out, "baselines", "wave.json")) as f:
        base = json.load(f)["baselines"]
    assert [p["step"] for p in result["curve"]] == [200, 400]
    assert result["mpjpe"] == result["curve"][-1]["mpjpe"]
    # With 3D ground truth the lifter is far better than no depth at all.
    assert result["mpjpe"] < 0.5 * base["zero depth"]
