"""A run's training curves: the losses and the test error against the step (matplotlib).

Reads what training writes into a workdir: ``metrics.jsonl`` (one record of mean losses
per logging interval) and ``eval_results.json`` (``history``: the test scores at each
evaluation, ``final``, and ``baselines``: the trivial methods' scores on the same split).
matplotlib is imported lazily, as in ``c3dpo_jax.visualise``.
"""

import json
import os

import numpy as np

_LOSSES = ("loss", "loss/reprojection", "loss/canonicalisation")


def pyplot():
    """``matplotlib.pyplot`` with the Agg backend (files only, no window), imported now."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def read_records(path: str) -> list[dict]:
    """The records of a ``metrics.jsonl`` file (blank lines skipped)."""
    with open(path) as f:
        return [json.loads(line) for line in f if line.strip()]


def _test_points(results: dict, key: str) -> tuple[list[int], list[float]]:
    """(steps, values) of ``key`` over the evaluations, the final one included once."""
    records = list(results.get("history", []))
    final = results.get("final")
    if final and not any(r.get("step") == final.get("step") for r in records):
        records.append(final)
    points = sorted((r["step"], r[key]) for r in records if key in r and "step" in r)
    return [s for s, _ in points], [v for _, v in points]


# The test score drawn: the 3D error, else (2D-only data, protocol "none") the 2D one.
_TEST_LABELS = {"mpjpe": "test MPJPE", "reprojection": "test 2D reprojection error"}


def _plot_test_error(ax, results: dict, key: str = "mpjpe", unit: str = "") -> None:
    steps, values = _test_points(results, key)
    ax.plot(steps, values, marker="o", color="tab:blue", label=f"C3DPO ({values[-1]:.3g})")
    styles = iter(("--", ":", "-.", (0, (5, 1, 1, 1))))
    for name, scores in results.get("baselines", {}).items():
        if key in scores:
            ax.axhline(scores[key], color="0.35", ls=next(styles, "--"), lw=1.2,
                       label=f"{name} ({scores[key]:.3g})")
    ax.set_xlabel("step")
    ax.set_ylabel(_TEST_LABELS[key] + (f" [{unit}]" if unit and key == "reprojection" else ""))
    tops = [*values, *(s[key] for s in results.get("baselines", {}).values() if key in s)]
    ax.set_ylim(0, 1.08 * max(tops))
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    ax.set_title("test error (lower is better)", fontsize=10)


def plot_training_curves(path: str, unit: str = ""):
    """The losses (log scale) and, when the run was evaluated, the test MPJPE (2D-only
    data: the test 2D reprojection error) with the baselines' as horizontal lines; ``path``
    is a workdir or its ``metrics.jsonl``; ``unit``: the data's 2D unit (e.g. "px"), which
    the 2D reprojection error is in."""
    workdir = path if os.path.isdir(path) else os.path.dirname(path)
    metrics = os.path.join(path, "metrics.jsonl") if os.path.isdir(path) else path
    records = read_records(metrics)
    if not records:
        raise ValueError(f"{metrics} has no records")
    results_path = os.path.join(workdir, "eval_results.json")
    results = {}
    if os.path.exists(results_path):
        with open(results_path) as f:
            results = json.load(f)
    key = next((k for k in _TEST_LABELS if _test_points(results, k)[0]), None)
    evaluated = key is not None
    fig, axes = pyplot().subplots(1, 1 + evaluated, figsize=(6 + 5 * evaluated, 4), squeeze=False)
    ax = axes[0, 0]
    steps = [r["step"] for r in records]
    for name in _LOSSES:
        values = np.asarray([r.get(name, np.nan) for r in records], np.float64)
        if np.any(values > 0):
            ax.plot(steps, values, label=name, lw=1.2)
    ax.set_yscale("log")
    ax.set_xlabel("step")
    ax.set_ylabel("training loss")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    ax.set_title("training losses (means over each logging interval)", fontsize=10)
    if evaluated:
        _plot_test_error(axes[0, 1], results, key, unit)
    fig.tight_layout()
    return fig
