"""A run's settings in its workdir, ``config.json``, and which checkpoints they may resume.

``config.json`` holds the resolved config (the model settings that ``load`` rebuilds the
network from), the training split's fingerprint, the data files' absolute paths
(``data_files``) and the software that trained the run (``software_record``, one record per
resumption by other software); the training loop writes it before training. It also says
which run the workdir's checkpoints belong to: ``check_workdir`` refuses, in one line, a
run whose settings would make other checkpoints (``_run_identity``).
"""

import importlib.metadata
import json
import os
import platform
import subprocess
from typing import Any

from absl import logging

from c3dpo_jax import checkpoint
from c3dpo_jax.model import MOVED_TO_INFERENCE

CONFIG_FILE = "config.json"


def check_workdir(workdir: str, config: dict[str, Any]) -> None:
    """Refuses, in one line and before anything is written, to resume checkpoints made
    with another run identity (``_run_identity``) than ``config`` asks for. A workdir
    without checkpoints (e.g. left by a run that failed before its first one) may be
    reused by any run; checkpoints without a ``config.json`` are refused (their run is
    unknown); fields that only one of the two configs has are not compared."""
    if not checkpoint.has_checkpoint(workdir):
        return
    saved, checkpoints = load_config(workdir), os.path.join(workdir, checkpoint.CHECKPOINT_DIR)
    if saved is None:
        raise ValueError(f"{workdir} holds checkpoints but no {CONFIG_FILE}, so which run they "
                         f"belong to is unknown; put its {CONFIG_FILE} back, use a new "
                         f"--workdir, or delete {checkpoints}")
    diffs = differences(_run_identity(saved), _run_identity(config))
    if diffs:
        more = f"; and {len(diffs) - 3} more" if len(diffs) > 3 else ""
        raise ValueError(
            f"{workdir} holds checkpoints of another run ({'; '.join(diffs[:3])}{more}); "
            f"use a new --workdir, or delete {checkpoints} to start again there")


# What makes a checkpoint another run's: the network (model; a saved model section's
# inference options, ``model.MOVED_TO_INFERENCE``, are not the network's), the optimiser and
# its state (optim), the objective (loss), the seed, the batches and the epoch length that
# the schedule counts in, and what the run learns from. The evaluation protocol, the test
# file, the inference options (``inference``) and the step counts may change between a run
# and its resumption.
_RUN_DATA_FIELDS = ("train_path", "source", "min_visible", "drop_invalid", "class_balanced")
_RUN_TRAIN_FIELDS = ("batch_size", "samples_per_epoch")


def _run_identity(config: dict[str, Any]) -> dict[str, Any]:
    data, train = config.get("data", {}), config.get("train", {})
    ident = {"model": {k: v for k, v in config.get("model", {}).items()
                       if k not in MOVED_TO_INFERENCE},
             "optim": config.get("optim", {}),
             "train": {k: train[k] for k in _RUN_TRAIN_FIELDS if k in train},
             "data": {k: data[k] for k in _RUN_DATA_FIELDS if k in data}}
    for key in ("loss", "seed"):
        if key in config:
            ident[key] = config[key]
    if "train_data_sha256" in config:  # what was read, so a file edited in place counts
        ident["train_data_sha256"] = config["train_data_sha256"][:12]
        ident["data"].pop("train_path", None)  # and the same file under another path does not
    if data.get("train_path"):  # the files win over the source (data.load_splits)
        ident["data"].pop("source", None)
    elif data.get("source") == "release":
        ident["data"]["name"] = data.get("name")
    elif data.get("source") in data:  # a generator's parameters
        ident["data"][data["source"]] = data[data["source"]]
    return json.loads(json.dumps(ident, default=list))  # tuples as JSON lists


def differences(saved: Any, new: Any, path: str = "") -> list[str]:
    """``section.field: A in the checkpoint's run, B now`` for every field both have."""
    if isinstance(saved, dict) and isinstance(new, dict):
        return [d for k in sorted(set(saved) & set(new))
                for d in differences(saved[k], new[k], f"{path}.{k}" if path else k)]
    return [] if saved == new else [f"{path}: {saved!r} in the checkpoint's run, {new!r} now"]


def load_config(workdir: str) -> dict[str, Any] | None:
    """The run's saved ``config.json``, None when there is none; a damaged one (e.g. cut
    short by a full disk) is a one-line ValueError naming the file."""
    path = os.path.join(workdir, CONFIG_FILE)
    if not os.path.exists(path):
        return None
    with open(path) as f:
        try:
            return json.load(f)
        except json.JSONDecodeError as err:
            raise ValueError(f"{path} is not valid JSON ({err}): it holds the run's settings, "
                             "which loading and resuming the run need") from None


def save_config(workdir: str, config: dict[str, Any]) -> None:
    """Writes ``config.json`` whole or not at all (a kill mid-write leaves the old one)."""
    checkpoint.write_json(os.path.join(workdir, CONFIG_FILE), config, indent=2, sort_keys=True)


def save_inference(workdir: str, inference: dict[str, Any]) -> None:
    """Writes ``inference`` as config.json's ``inference`` section: a run that ends with
    the training views' mean filled in (``inference.with_views_mean``), which loading the
    model reads."""
    config = load_config(workdir)
    config["inference"] = json.loads(json.dumps(inference))  # tuples as JSON lists
    save_config(workdir, config)


def _git(*args: str) -> str | None:
    """Output of ``git ARGS`` run in this package's directory, or None (no git, no repo)."""
    try:
        out = subprocess.run(["git", "-C", os.path.dirname(os.path.abspath(__file__)), *args],
                             capture_output=True, text=True, timeout=10, check=False)
    except (OSError, subprocess.SubprocessError):
        return None
    return out.stdout.strip() if out.returncode == 0 else None


def software_record() -> dict[str, Any]:
    """The software a run is made with: the package's version, the git commit of its source
    when it runs from a git checkout that tracks it (``git_dirty``: the package's tracked
    files differ from that commit), and the versions of Python and the numerical stack."""
    record: dict[str, Any] = {}
    for name in ("c3dpo_jax", "jax", "jaxlib", "flax", "optax", "orbax-checkpoint"):
        try:
            record[name] = importlib.metadata.version(name)
        except importlib.metadata.PackageNotFoundError:
            record[name] = None
    record["python"] = platform.python_version()
    tracked = _git("ls-files", "--error-unmatch", os.path.basename(__file__)) is not None
    commit = _git("rev-parse", "HEAD") if tracked else None
    record["git_commit"] = commit
    record["git_dirty"] = None if commit is None else bool(
        _git("status", "--porcelain", "--untracked-files=no", "--", "."))
    return record


def software_history(workdir: str) -> list[dict[str, Any]]:
    """The software records of a run: those of the workdir's checkpoints' run, plus this
    process's when it differs from the last (a resumption by other software is warned
    about in one line). A workdir without checkpoints starts a new history."""
    saved = load_config(workdir) if checkpoint.has_checkpoint(workdir) else None
    history = list((saved or {}).get("software", []))
    current = software_record()
    if history and history[-1] == current:
        return history
    if history:
        changed = [f"{k} {history[-1].get(k)} -> {v}" for k, v in current.items()
                   if history[-1].get(k) != v]
        logging.warning("resuming a run begun with other software: %s", "; ".join(changed))
    return [*history, current]
