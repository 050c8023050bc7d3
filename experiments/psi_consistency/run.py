"""Does Psi make the predicted canonical shape independent of the viewpoint? (paper Fig. 3)

Trains C3DPO (with the canonicalisation network Psi) and C3DPO-equiv (the same without
Psi) on the built-in synthetic humans with the library's loop, then turns test poses about
the camera's vertical axis, projects each turned pose orthographically with every point
visible, reconstructs every view and measures how much each model's canonical shape
changes with the view (``consistency.py``: the canonical spread, 0 = view-invariant)::

  python experiments/psi_consistency/run.py                  # 10,000 steps per model
  python experiments/psi_consistency/run.py --seed=1         # -> results/seed1
  python experiments/psi_consistency/run.py --num_steps=2000 --out=runs/psi_2000
  python experiments/psi_consistency/run.py --smoke          # a tiny run in a temp dir

Writes ``OUT/runs/{full,equiv}`` (the workdirs; a finished one is not trained again),
``OUT/consistency.json`` and ``OUT/consistency.png``. With two free cores the two models
train at the same time in two subprocesses, one core each (``--noparallel``: one after the
other in this process).
"""

import json
import os
import subprocess
import sys
import tempfile
import time

import numpy as np
from absl import app, flags

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.normpath(os.path.join(HERE, "..", ".."))
sys.path.insert(0, HERE)
sys.path.insert(0, ROOT)
sys.path.insert(0, os.path.join(ROOT, "experiments"))

import consistency  # noqa: E402
from runner import machine, run_main  # noqa: E402

# label, config spec, workdir name
MODELS = (("C3DPO", "configs/humans.py:paper", "full"),
          ("C3DPO-equiv (no Psi)", "configs/humans.py:equiv,paper", "equiv"))

FLAGS = flags.FLAGS
flags.DEFINE_string("out", None, "output directory (default: results/seedSEED beside this "
                    "script; --smoke: a new temp dir)")
flags.DEFINE_integer("num_steps", 0, "training steps per model (0: the config's, 10,000)")
flags.DEFINE_integer("seed", 0, "training seed of both models (the data stay the same)")
flags.DEFINE_integer("n_poses", 100, "test samples (poses seen from their test camera) to turn")
flags.DEFINE_integer("n_angles", 36, "rotation angles, evenly over the full circle")
flags.DEFINE_integer("n_shown_angles", 6, "angles overlaid in the figure's shape panels")
flags.DEFINE_list("example_poses", ["0", "37"], "indices (into the turned poses) to draw")
flags.DEFINE_bool("parallel", True, "train the two models at once, one core each, when the "
                  "process may use two or more cores")
flags.DEFINE_bool("smoke", False, "tiny networks, 20 steps, a few poses and angles")
flags.DEFINE_string("train_only", "", "internal: train this workdir name (full or equiv)")


def model_config(spec: str):
    """The config of one model: ``spec`` (+ ``smoke``), the step count, no progress bar."""
    from c3dpo_jax.cli import get_config

    if FLAGS.smoke:
        spec += ",smoke" if ":" in spec else ":smoke"
    config = get_config(spec)
    if FLAGS.num_steps:
        config.train.num_steps = FLAGS.num_steps
    config.seed = FLAGS.seed
    config.train.progress_bar = False
    config.inference.refine_iters = 0  # Phi's single pass: what Psi is measured against
    return config


def total_steps(config) -> int:
    from c3dpo_jax.train import RunSpec

    return RunSpec.from_config(config).total_steps


def finished(config, workdir: str) -> bool:
    """Whether ``workdir`` holds a finished run of ``config`` (its final evaluation and a
    checkpoint); a finished run of another length is an error."""
    path = os.path.join(workdir, "eval_results.json")
    has_checkpoint = os.path.isdir(os.path.join(workdir, "checkpoints"))
    if not (os.path.exists(path) and has_checkpoint):
        return False
    with open(path) as f:
        final = json.load(f).get("final")
    if final is None:
        return False
    if final["step"] != total_steps(config):
        raise app.UsageError(f"{workdir} holds a finished run of {final['step']} steps, not "
                             f"{total_steps(config)}: give another --out")
    return True


def train_one(name: str) -> None:
    """Trains the model ``name`` into its workdir, recording the wall time."""
    from c3dpo_jax.train import train_and_evaluate

    _, spec, _ = next(m for m in MODELS if m[2] == name)
    config = model_config(spec)
    workdir = os.path.join(FLAGS.out, "runs", name)
    if finished(config, workdir):
        print(f"{name}: finished run in {workdir}, not trained again", flush=True)
        return
    start = time.perf_counter()
    train_and_evaluate(config, workdir)
    wall = {"wall_s": time.perf_counter() - start, "steps": total_steps(config),
            "cpus": sorted(os.sched_getaffinity(0))}
    with open(os.path.join(workdir, "train_wall.json"), "w") as f:
        json.dump(wall, f, indent=2)
    print(f"{name}: trained in {wall['wall_s']:.0f} s", flush=True)


def train_all() -> None:
    """Both models: two subprocesses pinned to one core each, or one after the other."""
    cores = sorted(os.sched_getaffinity(0))
    if not (FLAGS.parallel and len(cores) >= 2):
        for _, _, name in MODELS:
            train_one(name)
        return
    args = [f"--out={FLAGS.out}", f"--num_steps={FLAGS.num_steps}", f"--seed={FLAGS.seed}",
            "--smoke" if FLAGS.smoke else "--nosmoke"]
    procs = []
    for core, (_, _, name) in zip(cores, MODELS, strict=False):
        os.makedirs(os.path.join(FLAGS.out, "runs"), exist_ok=True)
        log = open(os.path.join(FLAGS.out, "runs", f"{name}.log"), "w")
        cmd = [sys.executable, os.path.abspath(__file__), f"--train_only={name}", *args]
        procs.append((name, log, subprocess.Popen(
            cmd, cwd=ROOT, stdout=log, stderr=subprocess.STDOUT,
            preexec_fn=lambda c=core: os.sched_setaffinity(0, {c}))))
        print(f"training {name} on core {core} (log: {log.name})", flush=True)
    failed = []
    for name, log, proc in procs:
        if proc.wait() != 0:
            failed.append(f"{name} (see {log.name})")
        log.close()
    if failed:
        raise RuntimeError("training failed: " + ", ".join(failed))


def sample_indices(n_available: int, n: int) -> np.ndarray:
    """``n`` indices spread evenly over the split (the test views are pose-major, so they
    cover the poses evenly), or all of them when there are fewer."""
    if n >= n_available:
        return np.arange(n_available)
    return np.unique(np.linspace(0, n_available - 1, n).round().astype(int))


def analyse(test, angles: np.ndarray) -> dict:
    """Every model's reconstructions of the turned test poses and the scores."""
    import c3dpo_jax

    idx = sample_indices(len(test), FLAGS.n_poses)
    truth = consistency.rotate_about_y(test.kp3d[idx], angles)  # (P, A, N, 3)
    p, a, n, _ = truth.shape
    kp = truth[..., :2].reshape(p * a, n, 2)
    vis = np.ones((p * a, n))
    results = {"test_indices": idx.tolist(), "models": {}, "reference": {
        "label": "camera-frame truth (a 'canonical' shape that turns with the view)",
        "canonical_spread": float(consistency.canonical_spread(truth).mean()),
        "curve": consistency.deviation_per_angle(truth).mean(0).tolist()}}
    canonical_shapes = {}
    for label, _, name in MODELS:
        workdir = os.path.join(FLAGS.out, "runs", name)
        params = c3dpo_jax.load(workdir)
        rec = c3dpo_jax.reconstruct(params, kp, vis)
        canonical = rec.shape_canonical.reshape(p, a, n, 3)
        canonical_shapes[label] = canonical
        with open(os.path.join(workdir, "eval_results.json")) as f:
            final = json.load(f)["final"]
        test_rec = c3dpo_jax.reconstruct(params, test.kp, test.vis)
        spread = consistency.canonical_spread(canonical)
        wall_path = os.path.join(workdir, "train_wall.json")
        wall = {}
        if os.path.exists(wall_path):
            with open(wall_path) as f:
                wall = json.load(f)
        results["models"][label] = {
            "workdir": os.path.relpath(workdir, ROOT),
            "steps": final["step"],
            "train_wall_s": wall.get("wall_s"),
            "train_s": final.get("train_s"),
            "test_mpjpe": final["mpjpe"],
            "test_sign_agreement": consistency.sign_agreement(test_rec.shape_3d, test.kp3d),
            "canonical_spread": float(spread.mean()),
            "canonical_spread_median": float(np.median(spread)),
            "canonical_spread_own_radius": float(
                consistency.spread_own_radius(canonical).mean()),
            "turned_views_mpjpe": consistency.mpjpe(rec.shape_3d, truth.reshape(p * a, n, 3)),
            "turned_views_sign_agreement": consistency.sign_agreement(
                rec.shape_3d, truth.reshape(p * a, n, 3)),
            "curve": consistency.deviation_per_angle(canonical).mean(0).tolist(),
            "spread_per_pose": spread.tolist(),
        }
    return results, canonical_shapes


def write_figure(results: dict, canonical_shapes: dict, angles_deg: np.ndarray,
                 path: str) -> None:
    from c3dpo_jax import skeletons
    from c3dpo_jax.visualise import save_figure

    n_poses = len(results["test_indices"])
    examples = [int(i) for i in FLAGS.example_poses if int(i) < n_poses] or [0]
    shown = np.unique(np.linspace(0, len(angles_deg), FLAGS.n_shown_angles, endpoint=False)
                      .astype(int)).tolist()
    models = {label: dict(canonical=canonical_shapes[label], curve=info["curve"],
                          spread=info["canonical_spread"])
              for label, info in results["models"].items()}
    n = next(iter(canonical_shapes.values())).shape[-2]
    fig = consistency.plot_consistency(models, angles_deg, examples, shown,
                                       skeletons.skeleton("h36m", n),
                                       np.asarray(results["reference"]["curve"]))
    save_figure(fig, path)


def main(argv):
    if len(argv) > 1:
        raise app.UsageError(f"unexpected arguments {argv[1:]}")
    if FLAGS.out is None:
        FLAGS.out = (tempfile.mkdtemp(prefix="psi_consistency_smoke_") if FLAGS.smoke
                     else os.path.join(HERE, "results", f"seed{FLAGS.seed}"))
    if FLAGS.smoke and not FLAGS["n_poses"].present:
        FLAGS.n_poses = 6
    if FLAGS.smoke and not FLAGS["n_angles"].present:
        FLAGS.n_angles = 8
    FLAGS.out = os.path.abspath(FLAGS.out)
    if FLAGS.train_only:
        train_one(FLAGS.train_only)
        return
    from c3dpo_jax.cli import setup_logging
    from c3dpo_jax.data import load_splits

    setup_logging()
    start = time.perf_counter()
    train_all()
    trained = time.perf_counter()
    _, test = load_splits(model_config(MODELS[0][1]).data)
    angles_deg = np.arange(FLAGS.n_angles) * 360.0 / FLAGS.n_angles
    results, canonical_shapes = analyse(test, np.deg2rad(angles_deg))
    results = {
        "question": "does Psi make the predicted canonical shape independent of the viewpoint?",
        "settings": {"smoke": FLAGS.smoke, "seed": FLAGS.seed,
                     "num_steps": FLAGS.num_steps or "config default",
                     "n_poses": len(results["test_indices"]), "n_angles": FLAGS.n_angles,
                     "angles_deg": angles_deg.tolist(), "parallel": FLAGS.parallel,
                     "configs": {label: spec for label, spec, _ in MODELS}},
        **results,
        "wall_s": {"training": trained - start, "analysis": time.perf_counter() - trained},
        "machine": machine(),
    }
    os.makedirs(FLAGS.out, exist_ok=True)
    write_figure(results, canonical_shapes, angles_deg,
                 os.path.join(FLAGS.out, "consistency.png"))
    results["wall_s"]["total"] = time.perf_counter() - start
    with open(os.path.join(FLAGS.out, "consistency.json"), "w") as f:
        json.dump(results, f, indent=2)
    print("| model | test MPJPE [m] | canonical spread | sign agreement (turned views) |")
    print("|---|---|---|---|")
    for label, info in results["models"].items():
        print(f"| {label} | {info['test_mpjpe']:.4f} | {info['canonical_spread']:.3f} | "
              f"{info['turned_views_sign_agreement']:.2f} |")
    print(f"reference, camera-frame truth: canonical spread "
          f"{results['reference']['canonical_spread']:.3f}")
    print(f"wrote {FLAGS.out}/consistency.json and consistency.png in "
          f"{results['wall_s']['total']:.0f} s")


if __name__ == "__main__":
    run_main(main)
