"""Dense points: C3DPO on thousands of surface points of the built-in humans, its cost and
its accuracy on the joints (the paper trains on the 6,890 SMPL vertices of S-Up3D and scores
a representative subset).

Two parts, each a table in ``--dense_out``/dense_points.md and panels of its dense_points.png::

  python experiments/dense_points/run.py --part=cost       # alone on the machine
  python experiments/dense_points/run.py --part=accuracy   # trains, then scores
  python experiments/dense_points/run.py --part=report     # tables + figure of what exists

- **cost**: the library's benchmark (``python -m c3dpo_jax.benchmark``: the compiled
  training step of configs/humans.py on random data of the config's shapes, its median time
  over 10 calls, the eval forward pass at batch 1024, the process's peak memory) at each of
  ``--cost_counts`` keypoints, one process after the other. Run it with nothing else on the
  machine: its numbers are times.
- **accuracy**: configs/humans.py trained through the CLI on the built-in humans with the 17
  joints and ``K - 17`` surface points (self-occlusion on; the same people, poses and
  cameras for every K), ``--steps`` steps with the learning rate x0.1 for the last 20%,
  seeds ``--seeds``, ``--jobs`` runs at a time, one core each (a finished run is not run
  again). Each model is scored on the test views' 17 joints (what every K shares) and on
  all its points, beside the rigid baseline (the training mean shape of the joints, best
  rigid fit to each view's joints). Its time column is the steps at the cost part's rate
  (alone, both cores): the runs themselves share the cores, so their clocks say little.
"""

import json
import os
import subprocess
import sys

import numpy as np
from absl import flags

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.normpath(os.path.join(HERE, "..", ".."))
sys.path.insert(0, ROOT)
sys.path.insert(0, os.path.join(ROOT, "experiments"))

from runner import check_steps, is_finished, run_all, run_main  # noqa: E402

N_JOINTS = 17


def run_name(k: int, seed: int) -> str:
    return f"k{k}_s{seed}"


def command(k: int, seed: int, steps: int, workdir: str) -> list[str]:
    """The CLI call of one run: configs/humans.py:paper (the paper's objective) with
    ``k - 17`` surface points."""
    return [sys.executable, "-m", "c3dpo_jax.main", "--config=configs/humans.py:paper",
            f"--workdir={workdir}", "--nofigures",
            f"--config.data.humans.dense_points={k - N_JOINTS}",
            f"--config.seed={seed}", "--config.train.progress_bar=False",
            f"--config.train.num_steps={steps}",
            f"--config.train.samples_per_epoch={256 * steps // 5}",
            "--config.train.epochs=5", "--config.optim.lr_milestones=(4,)",
            "--config.train.eval_every_steps=0", "--config.train.eval_every_epochs=0",
            "--config.inference.refine_iters=0"]  # Phi's single pass, as the tables


def score(workdir: str) -> dict:
    """Test MPJPE of the run in ``workdir`` on the 17 joints and on all its points, and of
    the rigid baseline on the joints; kept in ``workdir/joints.json``. The test views are
    made again from the run's saved data config (the built-in humans are generated)."""
    path = os.path.join(workdir, "joints.json")
    if os.path.exists(path):
        with open(path) as f:
            return json.load(f)
    import ml_collections

    from c3dpo_jax import baselines, evaluation, load, reconstruct, run_config
    from c3dpo_jax.data import KeypointData, load_splits

    config = run_config.load_config(workdir)
    train, test = load_splits(ml_collections.ConfigDict(config["data"]))
    pred = reconstruct(load(workdir), test.kp, test.vis).shape_3d
    joints = KeypointData(kp=test.kp[:, :N_JOINTS], vis=test.vis[:, :N_JOINTS],
                          kp3d=test.kp3d[:, :N_JOINTS], name=test.name)
    protocol = config["data"]["protocol"]
    mean = baselines.procrustes_mean_shape(train.kp3d[:, :N_JOINTS])
    rigid = baselines.fit_mean_shape(mean, joints.kp, joints.vis)
    out = dict(joints=evaluation.evaluate(pred[:, :N_JOINTS], joints, protocol)["mpjpe"],
               all_points=evaluation.evaluate(pred, test, protocol)["mpjpe"],
               rigid=evaluation.evaluate(rigid, joints, protocol)["mpjpe"],
               visible=float(test.vis.mean()), n_keypoints=int(test.n_keypoints))
    with open(path, "w") as f:
        json.dump(out, f)
    return out


def run_cost(out: str, counts: list[int]) -> None:
    os.makedirs(os.path.join(out, "cost"), exist_ok=True)
    for k in counts:
        path = os.path.join(out, "cost", f"k{k}.json")
        print(f"benchmark, {k} keypoints", flush=True)
        subprocess.run([sys.executable, "-m", "c3dpo_jax.benchmark",
                        "--config=configs/humans.py:paper",
                        f"--config.data.humans.dense_points={k - N_JOINTS}", "--steps=10",
                        "--config.inference.refine_iters=0",  # the eval pass: Phi's
                        f"--json={path}"], cwd=ROOT, check=True, stdout=subprocess.DEVNULL)


def _mean_std(values: list[float], digits: int = 3) -> str:
    if not values:
        return "-"
    text = f"{np.mean(values):.{digits}f}"
    return text + (f" ± {np.std(values):.{digits}f}" if len(values) > 1 else "")


def report(out: str, cost_counts: list[int], counts: list[int], seeds: list[int],
           steps: int) -> str:
    lines = ["**Cost** (`--part=cost`: `python -m c3dpo_jax.benchmark "
             "--config=configs/humans.py --config.data.humans.dense_points=K-17`, batch 256)",
             "", "| keypoints K | train steps/s | train samples/s | compile s | "
             "eval samples/s | peak memory (MB) |", "|---|---|---|---|---|---|"]
    cost = {}
    for k in cost_counts:
        path = os.path.join(out, "cost", f"k{k}.json")
        if os.path.exists(path):
            with open(path) as f:
                cost[k] = r = json.load(f)
            lines.append(f"| {k} | {r['steps_per_s']:.2f} | {r['train_samples_per_s']:.0f} | "
                         f"{r['compile_s']:.1f} | {r['eval_samples_per_s']:.0f} | "
                         f"{r['peak_rss_mb']:.0f} |")
        else:
            lines.append(f"| {k} | - | - | - | - | - |")
    lines += ["", "**Accuracy** (`--part=accuracy`; test MPJPE in metres, mean ± std over "
              f"seeds {', '.join(map(str, seeds))})", "",
              "| keypoints K | runs | MPJPE, 17 joints | MPJPE, all K points | rigid baseline, "
              f"17 joints | rigid / C3DPO (worst seed) | minutes for {steps} steps |",
              "|---|---|---|---|---|---|---|"]
    acc = {}
    for k in counts:
        rows = []
        for s in seeds:
            workdir = os.path.join(out, "runs", run_name(k, s))
            if is_finished(workdir):
                rows.append(score(workdir))
        acc[k] = rows
        if not rows:
            lines.append(f"| {k} | 0 | - | - | - | - | - |")
            continue
        joints = [r["joints"] for r in rows]
        worst = min(r["rigid"] / r["joints"] for r in rows)
        minutes = f"{steps / cost[k]['steps_per_s'] / 60:.1f}" if k in cost else "-"
        lines.append(f"| {k} | {len(rows)} | {_mean_std(joints)} | "
                     f"{_mean_std([r['all_points'] for r in rows])} | "
                     f"{np.mean([r['rigid'] for r in rows]):.3f} | {worst:.2f}x | "
                     f"{minutes} |")
    _figure(out, cost, acc)
    return "\n".join(lines) + "\n"


def _figure(out: str, cost: dict, acc: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(12, 3.4), gridspec_kw={"wspace": 0.35})
    ks = sorted(cost)
    axes[0].loglog(ks, [cost[k]["steps_per_s"] for k in ks], "o-")
    axes[0].set(xlabel="keypoints K", ylabel="train steps/s (batch 256)", title="speed")
    axes[1].loglog(ks, [cost[k]["peak_rss_mb"] for k in ks], "o-", color="C1")
    axes[1].set(xlabel="keypoints K", ylabel="peak memory (MB)", title="memory")
    for k, rows in sorted(acc.items()):
        if rows:
            axes[2].plot([k] * len(rows), [r["joints"] for r in rows], "o", color="C2")
            axes[2].plot([k] * len(rows), [r["rigid"] for r in rows], "_", color="gray", ms=14)
    axes[2].set_xscale("log")
    axes[2].set(xlabel="keypoints K (trained on)", ylabel="test MPJPE, 17 joints (m)",
                title="accuracy (dots: seeds; dash: rigid)")
    fig.savefig(os.path.join(out, "dense_points.png"), dpi=120, bbox_inches="tight")
    plt.close(fig)


def main(argv):
    del argv
    fl = flags.FLAGS
    out = fl.dense_out
    cost_counts = [int(k) for k in fl.cost_counts]
    counts, seeds = [int(k) for k in fl.counts], [int(s) for s in fl.seeds]
    for k in counts:
        for s in seeds:
            check_steps(os.path.join(out, "runs", run_name(k, s)), fl.steps)
    if min(cost_counts + counts) < N_JOINTS:
        raise ValueError(f"keypoint counts start at the {N_JOINTS} joints")
    if fl.part == "cost":
        run_cost(out, cost_counts)
    elif fl.part == "accuracy":
        jobs = [(w, command(k, s, fl.steps, w)) for k in sorted(counts, reverse=True)
                for s in seeds if not is_finished(w := os.path.join(out, "runs", run_name(k, s)))]
        run_all(jobs, fl.jobs, out)  # the slowest first
    text = report(out, cost_counts, counts, seeds, fl.steps)
    with open(os.path.join(out, "dense_points.md"), "w") as f:
        f.write(text)
    print(text)


def _define_flags() -> None:
    """Defined only when run as a script, so that tests can import this module beside
    other experiments' scripts that define flags of the same names."""
    flags.DEFINE_enum("part", "report", ["cost", "accuracy", "report"], "what to run")
    flags.DEFINE_list("cost_counts", ["17", "517", "2017", "6907"], "keypoint counts benchmarked")
    flags.DEFINE_list("counts", ["17", "517", "2017"], "keypoint counts trained")
    flags.DEFINE_list("seeds", ["0", "1", "2"], "training seeds")
    flags.DEFINE_integer("steps", 3000, "training steps of every run")
    flags.DEFINE_string("dense_out", os.path.join(HERE, "results"), "runs, tables, figure")
    flags.DEFINE_integer("jobs", 2, "runs at a time (each pinned to one core)")


if __name__ == "__main__":
    _define_flags()
    run_main(main)
