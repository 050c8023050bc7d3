"""Robustness to 2D noise and occlusion, for several keypoint counts (the paper's
supplementary "Analysis of robustness", on the built-in humans).

For each keypoint count (the 17 joints, plus ``--dense`` surface points), each noise level
sigma and each occlusion probability p, the built-in humans' views are corrupted (train and
test inputs alike: Gaussian noise of standard deviation sigma times the views' median RMS
radius added to every 2D point, then each point hidden with probability p; the 3D ground
truth stays clean), C3DPO is trained on them with the CLI, and the test MPJPE is measured
on the 17 joints, whatever the model was trained on (the paper's "representative" points)::

  python experiments/robustness/run.py                      # the grid, then table + figure
  python experiments/robustness/run.py --report_only        # table + figure of the runs made
  python experiments/robustness/run.py --dense=0,80 --grid_seeds=0,1   # two seeds a cell
  python experiments/robustness/run.py --report_only --rescore_rigid   # rigid fits again

Runs go to ``OUT/runs/kK_sSIGMA_pP`` (seeds other than 0: ``..._seedN``; a finished run is
not run again), ``--jobs`` at a time, one core each; a cell reports the mean over the seeds
asked for (± their standard deviation with more than one); ``OUT/robustness.md`` and
``OUT/robustness.png`` are the table and the heat maps. Each cell also scores the rigid
baseline (the training mean shape of the joints, best rigid fit to each corrupted view) on
the same joints.
"""

import json
import os
import sys

import numpy as np
from absl import flags

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.normpath(os.path.join(HERE, "..", ".."))
sys.path.insert(0, ROOT)
sys.path.insert(0, os.path.join(ROOT, "experiments"))

from runner import check_steps, is_finished, repo_path, run_all, run_main  # noqa: E402

FLAGS = flags.FLAGS
flags.DEFINE_list("sigmas", ["0", "0.05", "0.1"], "2D noise std, in median RMS radii")
flags.DEFINE_list("occlusions", ["0", "0.2", "0.4"], "probability of hiding a point")
flags.DEFINE_list("dense", ["0", "80", "500"], "surface points added to the 17 joints")
flags.DEFINE_integer("steps", 3000, "training steps of every run")
flags.DEFINE_list("grid_seeds", ["0"], "seeds of the training and of the corruption; a cell "
                  "reports their mean (and spread, with several)")
flags.DEFINE_string("grid_out", os.path.join(HERE, "results"), "data, runs, table, figure")
flags.DEFINE_integer("jobs", 2, "runs at a time (each pinned to one core)")
flags.DEFINE_bool("report_only", False, "only the table and figure of the runs made")
flags.DEFINE_bool("rescore_rigid", False, "score the rigid baseline of every finished run "
                  "again (views remade in memory) before the report")

N_JOINTS = 17


def cell_name(dense: int, sigma: float, p: float, seed: int = 0) -> str:
    """A cell's name; seeds other than 0 add ``_seedN`` (seed 0's runs keep the plain name)."""
    return f"k{N_JOINTS + dense}_s{sigma:g}_p{p:g}" + (f"_seed{seed}" if seed else "")


def corrupt(data, sigma: float, p: float, radius: float, rng: np.random.Generator):
    """``data`` with noise (std ``sigma * radius``) on every 2D point, then each point
    hidden with probability ``p`` (at least 2 visible kept per view); 3D unchanged."""
    from c3dpo_jax.data import KeypointData

    kp = data.kp + sigma * radius * rng.normal(size=data.kp.shape)
    vis = data.vis * (rng.random(data.vis.shape) >= p)
    few = vis.sum(1) < 2  # a view needs 2 visible points; show its first two again
    vis[few, :2] = 1.0
    return KeypointData(kp=(kp * vis[..., None]).astype(np.float32),
                        vis=vis.astype(np.float32), kp3d=data.kp3d, name=data.name)


def joints(data):
    """The 17 joints of a split (the points every model is scored on)."""
    from c3dpo_jax.data import KeypointData

    return KeypointData(kp=data.kp[:, :N_JOINTS], vis=data.vis[:, :N_JOINTS],
                        kp3d=data.kp3d[:, :N_JOINTS], name=data.name)


def cell_views(dense: int, sigma: float, p: float, seed: int):
    """A cell's corrupted (train, test) views, made the same way every time."""
    from c3dpo_jax.data import humans

    train, test = humans.make_splits(dense_points=dense, self_occlusion=False, seed=0)
    centred = train.kp[:, :N_JOINTS] - train.kp[:, :N_JOINTS].mean(1, keepdims=True)
    radius = float(np.median(np.sqrt((centred**2).sum(-1).mean(1))))
    rng = np.random.default_rng([seed, dense, round(sigma * 1e4), round(p * 1e4)])
    return tuple(corrupt(data, sigma, p, radius, rng) for data in (train, test))


def make_cell(dense: int, sigma: float, p: float, out: str, seed: int) -> dict:
    """Writes a cell's corrupted train/test JSON once; returns their paths and K."""
    from c3dpo_jax.data import json_dataset

    name = cell_name(dense, sigma, p, seed)
    paths = {s: os.path.join(out, "data", f"{name}_{s}.json") for s in ("train", "test")}
    if not all(os.path.exists(q) for q in paths.values()):
        os.makedirs(os.path.join(out, "data"), exist_ok=True)
        for split, data in zip(("train", "test"), cell_views(dense, sigma, p, seed)):
            json_dataset.save(data, paths[split])
    return dict(paths, n_keypoints=N_JOINTS + dense)


def rigid_mpjpe(train, test) -> float:
    """Test MPJPE on the 17 joints of the rigid baseline: the training mean shape of the
    joints (from the clean 3D) under the best rigid fit to each test view's visible joints."""
    from c3dpo_jax import baselines, evaluation

    tj = joints(test)
    rigid = baselines.fit_mean_shape(baselines.procrustes_mean_shape(joints(train).kp3d),
                                     tj.kp, tj.vis)
    return evaluation.evaluate(rigid, tj, "up3d")["mpjpe"]


def command(cell: dict, workdir: str, seed: int) -> list[str]:
    """The CLI call of one cell: the built-in humans' recipe with the paper's objective
    (configs/humans.py:paper) on the cell's files, ``--steps`` steps with the learning rate
    x0.1 for the last 20%, Phi's single pass at inference."""
    steps = FLAGS.steps
    return [sys.executable, "-m", "c3dpo_jax.main", "--config=configs/humans.py:paper",
            f"--workdir={workdir}", "--nofigures",
            f"--config.data.train_path={repo_path(cell['train'])}",
            f"--config.data.test_path={repo_path(cell['test'])}",
            f"--config.model.n_keypoints={cell['n_keypoints']}",
            f"--config.seed={seed}", "--config.train.progress_bar=False",
            f"--config.train.num_steps={steps}",
            f"--config.train.samples_per_epoch={256 * steps // 5}",
            "--config.train.epochs=5", "--config.optim.lr_milestones=(4,)",
            "--config.train.eval_every_steps=0", "--config.train.eval_every_epochs=0",
            "--config.inference.refine_iters=0"]  # Phi's single pass, as the tables


def score(workdir: str, make) -> dict:
    """Test MPJPE on the 17 joints of the run in ``workdir`` and of the rigid baseline
    (kept in ``workdir/joints.json``; ``make()`` gives the cell's files when not yet)."""
    from c3dpo_jax import evaluation, load, reconstruct
    from c3dpo_jax.data import json_dataset

    path = os.path.join(workdir, "joints.json")
    if os.path.exists(path):
        with open(path) as f:
            return json.load(f)
    cell = make()
    train, test = json_dataset.load(cell["train"]), json_dataset.load(cell["test"])
    pred = reconstruct(load(workdir), test.kp, test.vis)
    res = evaluation.evaluate(pred.shape_3d[:, :N_JOINTS], joints(test), "up3d")
    out = dict(mpjpe=res["mpjpe"], rigid=rigid_mpjpe(train, test),
               visible=float(test.vis.mean()))
    with open(path, "w") as f:
        json.dump(out, f)
    return out


def rescore_rigid(workdir: str, dense: int, sigma: float, p: float, seed: int) -> None:
    """Scores the rigid baseline of a scored run again (views remade in memory), replacing
    the one in its ``joints.json``; the model's score is kept (checkpoints are not kept)."""
    path = os.path.join(workdir, "joints.json")
    if not os.path.exists(path):
        return
    with open(path) as f:
        scores = json.load(f)
    old = scores["rigid"]
    scores["rigid"] = rigid_mpjpe(*cell_views(dense, sigma, p, seed))
    with open(path, "w") as f:
        json.dump(scores, f)
    print(f"{os.path.basename(workdir)}: rigid baseline {old:.4f} -> {scores['rigid']:.4f}")


def report(out: str, grid: list[tuple[int, float, float]], seeds=(0,)) -> str:
    """The table of every cell of ``grid``: the mean over the finished runs of ``seeds``
    ("± std" with more than one, and how many when fewer than asked), the rigid baseline's
    mean in brackets."""
    scores = {}
    for dense, sigma, p in grid:
        runs = []
        for seed in seeds:
            workdir = os.path.join(out, "runs", cell_name(dense, sigma, p, seed))
            if is_finished(workdir):
                runs.append(score(workdir, lambda d=dense, s=sigma, q=p, r=seed:
                                  make_cell(d, s, q, out, r)))
        if runs:
            scores[(dense, sigma, p)] = {
                "mpjpe": float(np.mean([r["mpjpe"] for r in runs])),
                "std": float(np.std([r["mpjpe"] for r in runs])),
                "rigid": float(np.mean([r["rigid"] for r in runs])), "n": len(runs)}
    sigmas = sorted({g[1] for g in grid})
    occl = sorted({g[2] for g in grid})
    lines = []
    for dense in sorted({g[0] for g in grid}):
        lines += [f"**{N_JOINTS + dense} keypoints** (test MPJPE on the 17 joints; in brackets "
                  "the rigid baseline on the same views)", "",
                  "| sigma \\ p | " + " | ".join(f"{p:g}" for p in occl) + " |",
                  "|---|" + "---|" * len(occl)]
        for sigma in sigmas:
            cells = [_entry(scores[k], len(seeds)) if (k := (dense, sigma, p)) in scores
                     else "-" for p in occl]
            lines.append(f"| {sigma:g} | " + " | ".join(cells) + " |")
        lines.append("")
    _figure(out, scores, sigmas, occl)
    return "\n".join(lines)


def _entry(cell: dict, n_seeds: int) -> str:
    text = f"{cell['mpjpe']:.3f}"
    if cell["n"] > 1:
        text += f" ± {cell['std']:.3f}"
    if cell["n"] < n_seeds:
        text += f" (n={cell['n']})"
    return text + f" ({cell['rigid']:.3f})"


def _figure(out: str, scores: dict, sigmas: list[float], occl: list[float]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    counts = sorted({k[0] for k in scores})
    if not counts:
        return
    values = [v["mpjpe"] for v in scores.values()]
    fig, axes = plt.subplots(1, len(counts), figsize=(3.8 * len(counts), 3.4), squeeze=False,
                             gridspec_kw={"wspace": 0.3})
    for ax, dense in zip(axes[0], counts):
        grid = np.full((len(sigmas), len(occl)), np.nan)
        for i, s in enumerate(sigmas):
            for j, p in enumerate(occl):
                if (dense, s, p) in scores:
                    grid[i, j] = scores[(dense, s, p)]["mpjpe"]
        im = ax.imshow(grid, cmap="viridis", vmin=min(values), vmax=max(values), origin="upper")
        for (i, j), v in np.ndenumerate(grid):
            if np.isfinite(v):
                ax.text(j, i, f"{v:.3f}", ha="center", va="center", color="w", fontsize=9)
        ax.set_xticks(range(len(occl)), [f"{p:g}" for p in occl])
        ax.set_yticks(range(len(sigmas)), [f"{s:g}" for s in sigmas])
        ax.set_xlabel("occlusion probability p")
        if ax is axes[0][0]:
            ax.set_ylabel("2D noise sigma (RMS radii)")
        ax.set_title(f"{N_JOINTS + dense} keypoints")
    fig.colorbar(im, ax=axes[0].tolist(), label="test MPJPE, 17 joints")
    fig.savefig(os.path.join(out, "robustness.png"), dpi=120, bbox_inches="tight")
    plt.close(fig)


def main(argv):
    del argv
    out = FLAGS.grid_out
    grid = [(int(d), float(s), float(p)) for d in FLAGS.dense for s in FLAGS.sigmas
            for p in FLAGS.occlusions]
    seeds = [int(s) for s in FLAGS.grid_seeds]
    if not FLAGS.report_only:
        jobs = []
        for seed in seeds:
            for dense, sigma, p in sorted(grid, key=lambda g: -g[0]):  # the slowest first
                workdir = os.path.join(out, "runs", cell_name(dense, sigma, p, seed))
                check_steps(workdir, FLAGS.steps)
                if not is_finished(workdir):
                    cell = make_cell(dense, sigma, p, out, seed)
                    jobs.append((workdir, command(cell, workdir, seed)))
        run_all(jobs, FLAGS.jobs, out)
    if FLAGS.rescore_rigid:
        for seed in seeds:
            for dense, sigma, p in grid:
                rescore_rigid(os.path.join(out, "runs", cell_name(dense, sigma, p, seed)),
                              dense, sigma, p, seed)
    text = report(out, grid, seeds)
    with open(os.path.join(out, "robustness.md"), "w") as f:
        f.write(text)
    print(text)


if __name__ == "__main__":
    run_main(main)
