"""Tables and a figure from ``results/*.json`` of run.py.

  python experiments/time_to_accuracy/report.py [--results=DIR] [--at=120,300,600]

Prints a markdown table (test MPJPE at each budget: mean +- std over seeds, the number
of seeds in brackets when more than one; the baselines, from the runs or from
``DIR/baselines/DATASET.json`` (run.py ``--baselines_only``); the final error of the same
networks trained with the 3D ground truth, when there are ``cpu_supervised`` runs (run.py
``--supervised``); the ratio of the fitted mean shape to the cpu recipe at the last
budget) and writes ``DIR/curves.png`` (MPJPE against wall time, one panel per dataset).
"""

import argparse
import collections
import glob
import json
import os

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
BASELINES = ("zero depth", "fitted mean shape", "oracle mean shape", "fitted PCA basis")


def load(results_dir: str) -> list[dict]:
    runs = []
    for path in sorted(glob.glob(os.path.join(results_dir, "*.json"))):
        with open(path) as f:
            runs.append(json.load(f))
    return runs


def baselines_by_dataset(runs: list[dict], results_dir: str) -> dict[str, dict]:
    """Each dataset's baselines: those of its runs, updated by ``baselines/DATASET.json``
    (run.py ``--baselines_only``: the same data, with baselines added after the runs)."""
    out = collections.defaultdict(dict)
    for r in runs:
        out[r["dataset"]].update(r["baselines"])
    for path in sorted(glob.glob(os.path.join(results_dir, "baselines", "*.json"))):
        with open(path) as f:
            b = json.load(f)
        out[b["dataset"]].update(b["baselines"])
    return out


SUPERVISED = "cpu_supervised"  # run.py --supervised: the cpu recipe's networks, 3D truth
SUPERVISED_LABEL = "same network, 3D truth"


def supervised_by_dataset(runs: list[dict]) -> dict[str, list[float]]:
    """Final test MPJPE of each dataset's ``cpu_supervised`` runs (run.py ``--supervised``)
    that trained their recipe's steps to the end (not stopped by a time budget)."""
    out = collections.defaultdict(list)
    for r in runs:
        if r["recipe"] == SUPERVISED and r.get("ended"):
            out[r["dataset"]].append(r["curve"][-1]["mpjpe"])
    return out


def mpjpe_at(run: dict, t: float) -> float:
    """MPJPE of the evaluation made when the run's time reached ``t`` (the first at or
    after it: runs evaluate at the first chunk boundary past each interval); the final
    model's if the recipe had ended before ``t`` (``ended``); NaN if the run stopped
    earlier for another reason."""
    points = [p for p in run["curve"] if p["t"] >= t - 1e-6]
    if points:
        return points[0]["mpjpe"]
    return run["curve"][-1]["mpjpe"] if run.get("ended") else float("nan")


def _cell(values: list[float]) -> str:
    values = [v for v in values if np.isfinite(v)]
    if not values:
        return "-"
    if len(values) == 1:
        return f"{values[0]:.3f}"
    return f"{np.mean(values):.3f} ± {np.std(values):.3f} ({len(values)})"


def table(runs: list[dict], at: list[float], recipes: list[str], base: dict,
          supervised: dict | None = None) -> str:
    supervised = supervised or {}
    by = collections.defaultdict(list)
    for r in runs:
        by[(r["dataset"], r["recipe"])].append(r)
    datasets = sorted({r["dataset"] for r in runs})
    head = ["dataset"] + [f"{rec} {t / 60:g} min" for rec in recipes for t in at]
    head += list(BASELINES) + [SUPERVISED_LABEL] * bool(supervised)
    head += [f"fitted mean / {recipes[0]} ({at[-1] / 60:g} min)"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for d in datasets:
        cells = [d]
        for rec in recipes:
            cells += [_cell([mpjpe_at(r, t) for r in by[(d, rec)]]) for t in at]
        cells += [f"{base[d][b]:.3f}" if b in base[d] else "-" for b in BASELINES]
        if supervised:
            cells.append(_cell(supervised.get(d, [])))
        last = [mpjpe_at(r, at[-1]) for r in by[(d, recipes[0])]]
        last = [v for v in last if np.isfinite(v)]
        ratio = base[d]["fitted mean shape"] / np.mean(last) if last else float("nan")
        cells.append(f"{ratio:.2f}x")
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def figure(runs: list[dict], path: str, base: dict, supervised: dict | None = None) -> None:
    supervised = supervised or {}
    datasets = sorted({r["dataset"] for r in runs})
    fig, axes = panels(len(datasets), (4, 3.2))
    colours = {}
    for ax, d in zip(axes.flat, datasets):
        labelled = set()  # one legend entry per recipe, however many seeds
        for r in (r for r in runs if r["dataset"] == d and r["recipe"] != SUPERVISED):
            colour = colours.setdefault(r["recipe"], f"C{len(colours)}")
            label = None if r["recipe"] in labelled else r["recipe"]
            labelled.add(r["recipe"])
            t = [p["t"] / 60 for p in r["curve"]]
            ax.plot(t, [p["mpjpe"] for p in r["curve"]], color=colour, alpha=0.8, label=label)
        for name, style in zip(BASELINES, (":", "--", "-.", ":")):
            if name in base[d]:  # gray: baselines; green: the 3D-supervised references
                colour = "C2" if name == "fitted PCA basis" else "gray"
                ax.axhline(base[d][name], color=colour, linestyle=style, label=name)
        if supervised.get(d):
            ax.axhline(np.mean(supervised[d]), color="C2", linestyle="--",
                       label=SUPERVISED_LABEL)
        ax.set_title(d)
        ax.set_yscale("log")
        ax.set_xlabel("training wall time (min)")
        ax.set_ylabel("test MPJPE")
    save_panels(fig, axes, len(datasets), path)


def panels(n: int, size: tuple[float, float]):
    """A figure of ``n`` panels, at most 4 a row, each ``size`` inches (matplotlib is
    imported here, off-screen, so that the tables need no plotting library)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cols = min(4, n)
    rows = -(-n // cols)
    return plt.subplots(rows, cols, figsize=(size[0] * cols, size[1] * rows), squeeze=False)


def save_panels(fig, axes, n: int, path: str) -> None:
    """Hides the unused panels, puts the legend on the first and writes ``path``."""
    for ax in axes.flat[n:]:
        ax.axis("off")
    axes.flat[0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    import matplotlib.pyplot as plt

    plt.close(fig)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--results", default=os.path.join(HERE, "results"))
    parser.add_argument("--at", default="120,300,600", help="budgets in seconds")
    parser.add_argument("--recipes", default="cpu,official")
    args = parser.parse_args()
    runs = load(args.results)
    if not runs:
        raise SystemExit(f"no results in {args.results}; run run.py first")
    at = [float(t) for t in args.at.split(",")]
    recipes = [r for r in args.recipes.split(",") if any(x["recipe"] == r for x in runs)]
    base = baselines_by_dataset(runs, args.results)
    supervised = supervised_by_dataset(runs)
    print(table(runs, at, recipes, base, supervised))
    figure(runs, os.path.join(args.results, "curves.png"), base, supervised)
    print(f"figure: {os.path.join(args.results, 'curves.png')}")


if __name__ == "__main__":
    main()
