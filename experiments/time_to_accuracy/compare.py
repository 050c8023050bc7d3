"""Settings compared seed by seed: test MPJPE of each seed at one budget, per dataset.

  python experiments/time_to_accuracy/compare.py \\
      "0.1=results/[!h]*__cpu__s*.json" \\
      "0.3925=results/eq_range/*__cpu_eq03925__s*.json" [--at=600] [--figure=PATH] [--xlabel=..]

Each argument is ``LABEL=GLOB`` (relative paths from this folder): run.py results of one
setting. Prints a markdown table (per setting: the seeds' MPJPE at ``--at`` seconds in
seed order, their mean; the mean change of each later setting against the first, paired
by seed; the fitted mean shape stored in the run files) and, with ``--figure``, draws the
same numbers: one panel per dataset, every seed and the mean per setting, and the 2x
target (half the fitted mean shape's error).
"""

import argparse
import collections
import glob
import json
import os

import numpy as np
from report import HERE, mpjpe_at, panels, save_panels


def load_settings(specs: list[str], at: float) -> tuple[list[str], dict, dict]:
    """``(labels, {(dataset, label): {seed: mpjpe}}, {dataset: fitted mean shape})``."""
    labels, values, fitted = [], collections.defaultdict(dict), {}
    for spec in specs:
        label, sep, pattern = spec.partition("=")
        if not sep or not label:
            raise SystemExit(f"{spec!r}: expected LABEL=GLOB")
        paths = sorted(glob.glob(os.path.join(HERE, pattern)))
        if not paths:
            raise SystemExit(f"{spec!r}: no file matches {os.path.join(HERE, pattern)}")
        labels.append(label)
        for path in paths:
            with open(path) as f:
                run = json.load(f)
            values[(run["dataset"], label)][run["seed"]] = mpjpe_at(run, at)
            fitted.setdefault(run["dataset"], run["baselines"]["fitted mean shape"])
    return labels, values, fitted


def table(labels: list[str], values: dict, fitted: dict) -> str:
    head = ["dataset"] + [f"{lab}: seeds (mean)" for lab in labels]
    head += [f"{lab} vs {labels[0]}" for lab in labels[1:]] + ["fitted mean shape"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for d in sorted(fitted):
        cells = [d]
        for lab in labels:
            seeds = values.get((d, lab), {})
            v = [seeds[s] for s in sorted(seeds)]
            cells.append(" / ".join(f"{x:.4f}" for x in v) + f" ({np.mean(v):.4f})" if v else "-")
        first = values.get((d, labels[0]), {})
        for lab in labels[1:]:
            other = values.get((d, lab), {})
            common = sorted(set(first) & set(other))
            change = [other[s] / first[s] - 1 for s in common]
            cells.append(f"{100 * np.mean(change):+.0f}% ({len(common)})" if common else "-")
        cells.append(f"{fitted[d]:.4f}")
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def figure(labels: list[str], values: dict, fitted: dict, path: str, at: float,
           xlabel: str = "") -> None:
    datasets = sorted(fitted)
    fig, axes = panels(len(datasets), (3.2, 2.8))
    x = np.arange(len(labels))
    for ax, d in zip(axes.flat, datasets):
        means = []
        for i, lab in enumerate(labels):
            v = list(values.get((d, lab), {}).values())
            ax.scatter([i] * len(v), v, color="gray", s=12, zorder=2)
            means.append(np.mean(v) if v else np.nan)
        ax.plot(x, means, "o-", color="C0", zorder=3, label="mean over seeds")
        ax.axhline(fitted[d] / 2, color="C3", linestyle="--", label="target: fitted mean / 2")
        ax.set_xticks(x, labels)
        ax.set_title(d)
        ax.set_xlabel(xlabel)
        ax.set_ylabel(f"test MPJPE at {at / 60:g} min")
    save_panels(fig, axes, len(datasets), path)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("settings", nargs="+", help="LABEL=GLOB, the first is the reference")
    parser.add_argument("--at", type=float, default=600.0, help="budget in seconds")
    parser.add_argument("--figure", default="", help="also draw the table here (.png)")
    parser.add_argument("--xlabel", default="", help="the figure's name for the settings")
    args = parser.parse_args()
    labels, values, fitted = load_settings(args.settings, args.at)
    print(table(labels, values, fitted))
    if args.figure:
        figure(labels, values, fitted, args.figure, args.at, args.xlabel)
        print(f"figure: {args.figure}")


if __name__ == "__main__":
    main()
