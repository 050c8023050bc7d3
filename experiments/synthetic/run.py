"""The README's table on the built-in dataset: C3DPO and the paper's two ablations trained by
the main job, ``python -m c3dpo_jax.main --config=configs/synthetic.py[:equiv|:base]``.

  python experiments/synthetic/run.py                  # trains what is missing, then tabulates
  python experiments/synthetic/run.py --report_only    # the table of the runs made

Each run is the README's quick-start command with ``--config.seed=S`` and ``--nofigures``
(``--jobs`` at a time, each pinned to one core; a finished run is not run again). Each
finished checkpoint is then scored again with two other inference options, without
retraining (``evaluate_workdir.evaluate_checkpoint``; kept in ``WORKDIR/inference.json``):
Phi's single pass (``inference.refine_iters=0``, the release's inference) and one
handedness for every view (``inference.one_handedness=True``). The table goes to
``--synthetic_out``/synthetic.md, with the command, the CPU and the jax version.
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

from runner import cpu_model, is_finished, literal, override, run_all, run_main  # noqa: E402

# Row name -> the config's variant (configs/default.py's apply_variants).
METHODS = {"C3DPO": "", "C3DPO, the paper's objective": "paper", "C3DPO-equiv": "equiv",
           "C3DPO-base": "base"}
# Inference options scored again on each checkpoint: name -> config overrides.
INFERENCE = {"one_pass": {"refine_iters": 0},
             "one_handedness": {"one_handedness": True}}


def run_name(method: str, seed: int) -> str:
    return f"{METHODS[method] or 'c3dpo'}__s{seed}"


def config_spec(method: str) -> str:
    variant = METHODS[method]
    return "configs/synthetic.py" + (f":{variant}" if variant else "")


def command(method: str, seed: int, workdir: str, extra: list[str]) -> list[str]:
    return [sys.executable, "-m", "c3dpo_jax.main", f"--config={config_spec(method)}",
            f"--workdir={workdir}", "--nofigures", f"--config.seed={seed}",
            "--config.train.progress_bar=False", *extra]


def _overrides(extra: list[str]) -> dict:
    """``--config.KEY=VALUE`` flags as a flattened dict (values as Python literals, else
    strings); other flags are not config fields."""
    out = {}
    for flag in extra:
        key, _, value = flag.partition("=")
        if key.startswith("--config."):
            out[key[len("--config."):]] = literal(value)
    return out


def other_inference(method: str, seed: int, workdir: str, extra: list[str]) -> dict:
    """The run's checkpoint scored with each of ``INFERENCE``'s options, with the config the
    run was made with (its ``eval_results.json`` is left as training wrote it); cached in
    ``inference.json``."""
    path = os.path.join(workdir, "inference.json")
    if os.path.exists(path):
        with open(path) as f:
            return json.load(f)
    from c3dpo_jax import cli, evaluate_workdir

    scores = {}
    for name, options in INFERENCE.items():
        config = cli.get_config(config_spec(method))
        config.unlock()
        override(config, {**_overrides(extra), "seed": seed,
                          **{f"inference.{k}": v for k, v in options.items()}})
        scores[name] = evaluate_workdir.evaluate_checkpoint(config, workdir, save=False)["final"]
    with open(path, "w") as f:
        json.dump(scores, f, indent=1)
    return scores


def _mean_std(values, digits: int = 3) -> str:
    return f"{np.mean(values):.{digits}f} ± {np.std(values):.{digits}f}"


def report(out: str, seeds: list[int], jobs: int, extra: list[str], argv: list[str]) -> str:
    """The markdown table of the runs made: mean ± std over the seeds (population std)."""
    import jax

    lines = [
        "# C3DPO and its ablations on the built-in dataset",
        "",
        f"`python {' '.join(['experiments/synthetic/run.py', *argv])}`; {cpu_model()}, jax "
        f"{jax.__version__}, {jobs} run(s) at a time, one core each. Test split ({{n}} views), "
        "protocol `default`; mean ± std over the seeds; minutes: each run's training clock.",
        "",
        "| method | seeds | up to one mirror (mpjpe_global) | per-view flip (the paper's mpjpe) "
        "| one pass (the paper's mpjpe) | as it is | stress | 2D reprojection | mirrored "
        "| one handedness: as it is / mirrored | steps, train min |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    n_views, baselines, per_seed = None, None, []
    for method in METHODS:
        rows = []
        for seed in seeds:
            workdir = os.path.join(out, "runs", run_name(method, seed))
            if not is_finished(workdir):
                continue
            with open(os.path.join(workdir, "eval_results.json")) as f:
                results = json.load(f)
            rows.append((seed, results["final"], other_inference(method, seed, workdir, extra)))
            n_views, baselines = results["final"]["n_samples"], results["baselines"]
        if not rows:
            continue
        finals = [r[1] for r in rows]
        one_pass = [r[2]["one_pass"]["mpjpe"] for r in rows]
        hand = [r[2]["one_handedness"] for r in rows]
        lines.append(
            f"| {method} (`{config_spec(method)}`) | {len(rows)} | "
            f"{_mean_std([f['mpjpe_global'] for f in finals])} | "
            f"{_mean_std([f['mpjpe'] for f in finals])} | {_mean_std(one_pass)} | "
            f"{_mean_std([f['mpjpe_orig'] for f in finals])} | "
            f"{_mean_std([f['stress'] for f in finals])} | "
            f"{_mean_std([f['reprojection'] for f in finals])} | "
            f"{_mean_std([f['mirrored'] for f in finals], 2)} | "
            f"{_mean_std([h['mpjpe_orig'] for h in hand])} / "
            f"{_mean_std([h['mirrored'] for h in hand], 2)} | "
            f"{finals[0]['step']}, {np.mean([f['train_s'] for f in finals]) / 60:.1f} |")
        per_seed.append(f"- {method}, seeds {', '.join(str(r[0]) for r in rows)}: "
                        "mpjpe_global "
                        + ", ".join(f"{r[1]['mpjpe_global']:.3f}" for r in rows) + "; mpjpe "
                        + ", ".join(f"{r[1]['mpjpe']:.3f}" for r in rows) + "; one pass "
                        + ", ".join(f"{p:.3f}" for p in one_pass) + "; as it is "
                        + ", ".join(f"{r[1]['mpjpe_orig']:.3f}" for r in rows) + "; mirrored "
                        + ", ".join(f"{r[1]['mirrored']:.2f}" for r in rows)
                        + "; with one handedness: as it is "
                        + ", ".join(f"{h['mpjpe_orig']:.3f}" for h in hand) + ", mirrored "
                        + ", ".join(f"{h['mirrored']:.2f}" for h in hand))
    if baselines is None:
        return "no finished runs yet\n"
    for name, res in baselines.items():
        lines.append(f"| {name} | - | {res.get('mpjpe_global', res['mpjpe_orig']):.3f} | "
                     f"{res['mpjpe']:.3f} | - | {res['mpjpe_orig']:.3f} | "
                     f"{res['stress']:.3f} | - | - | - | - |")
    lines[2] = lines[2].replace("{n}", f"{n_views:,}")
    return "\n".join([*lines, "", "Per seed:", "", *per_seed]) + "\n"


def main(argv):
    del argv
    from c3dpo_jax import cli

    cli.setup_logging(hidden=("input scale",))  # not orbax's lines, nor one per scoring
    fl = flags.FLAGS
    out, seeds = fl.synthetic_out, [int(s) for s in fl.seeds]
    if not fl.report_only:
        jobs = [(w, command(m, s, w, fl.extra)) for m in METHODS for s in seeds
                if not is_finished(w := os.path.join(out, "runs", run_name(m, s)))]
        run_all(jobs, fl.jobs, out)
    shown = [a for a in sys.argv[1:] if not a.startswith("--report_only")]
    text = report(out, seeds, fl.jobs, fl.extra, shown)
    if not fl.report_only:
        with open(os.path.join(out, "synthetic.md"), "w") as f:
            f.write(text)
    print(text)


def _define_flags() -> None:
    """Defined only when run as a script, so that tests can import this module."""
    flags.DEFINE_list("seeds", ["0", "1", "2"], "training seeds")
    flags.DEFINE_string("synthetic_out", os.path.join(HERE, "results"), "runs and table")
    flags.DEFINE_integer("jobs", 2, "runs at a time (each pinned to one core)")
    flags.DEFINE_bool("report_only", False,
                      "print the table of the runs made (synthetic.md is not written)")
    flags.DEFINE_multi_string("extra", [], "a further CLI flag for every run (e.g. "
                              "--extra=--config.train.num_steps=40, for a quick check)")


if __name__ == "__main__":
    _define_flags()
    run_main(main)
