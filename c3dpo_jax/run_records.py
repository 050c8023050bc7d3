"""What a run writes as it trains and is scored, beside its checkpoints (``checkpoint``)
and its settings (``run_config``)::

    workdir/metrics.jsonl      one JSON line per logged chunk of steps (``MetricsWriter``;
                               ``trim_metrics`` drops the records a resumed run replays)
    workdir/events.out.tfevents.*  the same curves and the test scores, for TensorBoard
    workdir/eval_results.json  the evaluation history, the final scores and the baselines
                               (written whole or not at all)
"""

import json
import math
import os
import time

import jax
import numpy as np
from absl import logging
from tensorboardX import SummaryWriter

from c3dpo_jax import checkpoint, workdir_lock

# Bookkeeping fields of metrics.jsonl and eval_results.json records, not curves.
_NOT_CURVES = frozenset({"step", "epoch", "n_samples"})


def _curves(values: dict, prefix: str = "") -> dict[str, float]:
    """Finite numbers of ``values`` (nested dicts as ``a/b``), bookkeeping fields left out."""
    out = {}
    for key, value in values.items():
        if key in _NOT_CURVES:
            continue
        if isinstance(value, dict):
            out.update(_curves(value, f"{prefix}{key}/"))
        elif isinstance(value, int | float) and math.isfinite(value):
            out[f"{prefix}{key}"] = float(value)
    return out


class MetricsWriter:
    """Fetches chunk metrics (one chunk late, so the host never waits on the device),
    checks them, logs them and appends them to ``metrics.jsonl`` and TensorBoard events.
    ``resumed_from``: the step of the checkpoint the run resumed from (0: none), which a
    loss that is not finite in the first chunk after it names as the suspect.

    The events go through tensorboardX's ``SummaryWriter`` (no TensorFlow), into a file of
    their own for each run in the workdir, which starts by purging the steps after
    ``resumed_from``: TensorBoard then drops what an earlier run wrote past the checkpoint
    (the resumed run replays those steps), as ``trim_metrics`` does in ``metrics.jsonl``.
    ``close`` (or the end of a ``with`` block) writes the events still queued."""

    def __init__(self, workdir: str, pbar, resumed_from: int = 0):
        self.path = os.path.join(workdir, "metrics.jsonl")
        # A suffix in nanoseconds: the file's name holds the time in whole seconds, and a
        # run resumed within the same second would otherwise overwrite the earlier file.
        self.events = SummaryWriter(workdir, purge_step=resumed_from + 1, flush_secs=10,
                                    filename_suffix=f".{time.time_ns()}")
        self.pbar, self.pending, self.last_time = pbar, None, time.perf_counter()
        self.checkpoints, self.resumed_from = (
            os.path.join(workdir, checkpoint.CHECKPOINT_DIR), resumed_from)

    def push(self, first_step: int, metrics) -> None:
        self.flush()
        self.pending = (first_step, metrics)

    def flush(self) -> None:
        if self.pending is None:
            return
        first_step, metrics = self.pending
        self.pending = None
        metrics = jax.device_get(metrics)
        n = len(metrics["loss"])
        bad = np.flatnonzero(~np.isfinite(metrics["loss"]))
        if bad.size:
            at = first_step + int(bad[0])
            values = {k: float(v[bad[0]]) for k, v in metrics.items()}
            shown = ", ".join(f"{k} {v:.4g}" for k, v in values.items())
            if self.resumed_from and first_step == self.resumed_from:
                raise FloatingPointError(
                    f"loss is not finite at step {at} ({shown}), right after resuming from the "
                    f"checkpoint {self.checkpoints}/{first_step}, the first suspect (damaged "
                    "files can read back as finite numbers); training stopped: move that "
                    "folder aside to resume from the checkpoint before it")
            raise FloatingPointError(
                f"loss is not finite at step {at} ({shown}); training stopped, its last "
                "checkpoint kept: a lower --config.optim.lr, or a look at the data, usually helps")
        now = time.perf_counter()
        record = {k: float(np.mean(v)) for k, v in metrics.items()}
        record.update(step=first_step + n, steps_per_s=n / max(now - self.last_time, 1e-9))
        self.last_time = now
        with open(self.path, "a") as f:
            f.write(json.dumps(record) + "\n")
        self.scalars(record["step"], record)
        self.pbar.update(n)
        self.pbar.set_postfix(
            loss=f"{record['loss']:.4f}",
            repro=f"{record['loss/reprojection']:.4f}",
            canon=f"{record['loss/canonicalisation']:.4f}",
            refresh=False,
        )
        logging.log_every_n_seconds(logging.INFO, "step %d: %s", 30, record["step"], record)

    def scalars(self, step: int, values: dict, prefix: str = "") -> None:
        """TensorBoard curves ``prefix + key`` at ``step`` of the numbers in ``values``."""
        for tag, value in _curves(values, prefix).items():
            self.events.add_scalar(tag, value, step)

    def close(self) -> None:
        self.events.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def write_results(workdir: str, results: dict) -> None:
    """Writes ``eval_results.json``; a workdir it cannot write is an OSError naming it."""
    path = os.path.join(workdir, "eval_results.json")
    try:
        checkpoint.write_json(path, results, indent=2)
    except OSError as err:
        raise OSError(f"cannot write {path}: {err.strerror or err}") from err


def left_unwritten(workdir: str, step: int) -> str | None:
    """Why ``--mode=eval``'s scores of the checkpoint at ``step`` must not replace
    ``eval_results.json`` (None: they may): a run training in ``workdir`` writes that file
    itself, and final scores of a later step (its checkpoint now unreadable) are not
    replaced by an earlier step's."""
    who = workdir_lock.who_trains(workdir)
    if who is not None:
        return f"{who} is training in {workdir} and writes that file"
    final = read_results(workdir).get("final") or {}
    if final.get("step", -1) > step:
        return (f"it holds the final scores of step {final['step']}, whose checkpoint cannot be "
                f"read now (the warnings above say why), and step {step} is an earlier one")
    return None


def read_results(workdir: str) -> dict:
    """The workdir's ``eval_results.json`` ({} when there is none yet, or with a warning
    when it cannot be read: the evaluations so far are lost, not the run)."""
    path = os.path.join(workdir, "eval_results.json")
    if not os.path.exists(path):
        return {}
    try:
        with open(path) as f:
            results = json.load(f)
        if not isinstance(results, dict):
            raise ValueError("not a JSON object")
        return results
    except (ValueError, UnicodeDecodeError) as e:
        logging.warning("%s cannot be read (%s): its evaluation history starts again", path, e)
        return {}


def clock_at(results: dict, step: int) -> float | None:
    """``train_s`` of the latest evaluation record (history or final) of ``results`` at or
    before ``step``: the training clock a run resumed (or re-scored) at ``step`` goes on from;
    None when no record has one."""
    records = [r for r in (*results.get("history", []), results.get("final") or {})
               if r.get("step", step + 1) <= step and "train_s" in r]
    return max(records, key=lambda r: r["step"])["train_s"] if records else None


def trim_metrics(workdir: str, step: int) -> None:
    """Drops ``metrics.jsonl`` records past ``step``: a resumed run replays those steps."""
    trim_records(os.path.join(workdir, "metrics.jsonl"), step)


def trim_records(path: str, step: int) -> None:
    """Drops the records past ``step`` of the JSON-lines file ``path`` (records with a
    ``"step"``; a line cut short by a kill goes too), if the file exists."""
    if not os.path.exists(path):
        return
    with open(path) as f:
        lines = [line for line in f if line.strip()]

    def kept(line: str) -> bool:
        try:
            return json.loads(line).get("step", 0) <= step
        except (ValueError, AttributeError):  # a line cut short by a kill mid-write
            logging.warning("%s: dropped a line that is not a JSON record (%.40s...)", path,
                            line.strip())
            return False

    keep = [line if line.endswith("\n") else line + "\n" for line in lines if kept(line)]
    if len(keep) < len(lines):
        with open(path, "w") as f:
            f.writelines(keep)
