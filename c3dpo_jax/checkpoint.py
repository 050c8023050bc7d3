"""Checkpoints: the only module that imports orbax.

Layout of a workdir::

    workdir/config.json          the resolved config (model settings for ``load``)
    workdir/checkpoints/<step>/  orbax StandardSave of the TrainState pytree
    workdir/metrics.jsonl        one JSON line per logged chunk of steps
    workdir/eval_results.json    evaluation history, final metrics and baselines
"""

import json
import os
from typing import Any

import orbax.checkpoint as ocp

CONFIG_FILE = "config.json"
CHECKPOINT_DIR = "checkpoints"


def make_manager(workdir: str, save_every: int, max_to_keep: int = 3) -> ocp.CheckpointManager:
    options = ocp.CheckpointManagerOptions(
        max_to_keep=max_to_keep, save_interval_steps=max(int(save_every), 1), create=True
    )
    return ocp.CheckpointManager(
        os.path.abspath(os.path.join(workdir, CHECKPOINT_DIR)), options=options
    )


def restore_or_init(manager: ocp.CheckpointManager, state):
    """The latest saved state if there is one (restored onto ``state``'s structure)."""
    step = manager.latest_step()
    if step is None:
        return state
    return manager.restore(step, args=ocp.args.StandardRestore(state))


def save(manager: ocp.CheckpointManager, step: int, state, force: bool = False) -> bool:
    """Saves if the manager's interval says so (or ``force``); returns whether it did."""
    return manager.save(step, args=ocp.args.StandardSave(state), force=force)


def save_config(workdir: str, config: dict[str, Any]) -> None:
    with open(os.path.join(workdir, CONFIG_FILE), "w") as f:
        json.dump(config, f, indent=2, sort_keys=True)


def load_config(workdir: str) -> dict[str, Any] | None:
    path = os.path.join(workdir, CONFIG_FILE)
    if not os.path.exists(path):
        return None
    with open(path) as f:
        return json.load(f)


def restore_latest(workdir: str, template, step: int | None = None):
    """Restores ``template``-shaped state from ``workdir`` (latest step by default)."""
    manager = ocp.CheckpointManager(os.path.abspath(os.path.join(workdir, CHECKPOINT_DIR)))
    step = manager.latest_step() if step is None else step
    if step is None:
        raise FileNotFoundError(f"no checkpoint found under {workdir}/{CHECKPOINT_DIR}")
    state = manager.restore(step, args=ocp.args.StandardRestore(template))
    manager.close()
    return state, step
