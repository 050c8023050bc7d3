"""Checkpoints and their integrity: the only module that imports orbax.

``workdir/checkpoints/<step>/`` holds an orbax StandardSave of the TrainState pytree (or of
the variables alone: ``save_variables``) and ``c3dpo_sha256.json``, the sha256 of each of
its files. The rest of the workdir (``config.json``, ``metrics.jsonl``,
``eval_results.json``, the TensorBoard events) is the run's records, ``run_records``.

A checkpoint proves itself before it is used: orbax does not check that its data files
hold what was written (flipped bytes can decode into wrong numbers), so once a save has
finished the manager records the sha256 of every file of the step, and a restore first
compares them; a checkpoint that is incomplete, fails its checksums, cannot be read or
holds NaN/inf is skipped with a one-line warning for the newest intact one. A step
without the record (a kill between the save and the record, or an older workdir) is
checked for readability and finite values only.
"""

import contextlib
import hashlib
import json
import logging as py_logging
import os
from typing import Any

import jax
import numpy as np
import orbax.checkpoint as ocp
from absl import logging
from etils import epath

CHECKPOINT_DIR = "checkpoints"
CHECKSUM_FILE = "c3dpo_sha256.json"


def _file_hashes(step_dir: str) -> dict[str, str]:
    """``{path relative to step_dir: sha256}`` of every file but the checksum record."""
    out = {}
    for folder, _, files in os.walk(step_dir):
        for name in files:
            path = os.path.join(folder, name)
            rel = os.path.relpath(path, step_dir)
            if rel == CHECKSUM_FILE:
                continue
            h = hashlib.sha256()
            with open(path, "rb") as f:
                for block in iter(lambda f=f: f.read(1 << 20), b""):
                    h.update(block)
            out[rel] = h.hexdigest()
    return out


class _NotOrbax(py_logging.Filter):
    def filter(self, record):
        return f"{os.sep}orbax{os.sep}" not in record.pathname


@contextlib.contextmanager
def _orbax_quiet():
    """Drops orbax's own log records (its warnings about a damaged step's missing files,
    several lines each) while steps are listed and read: ``_restore`` reports the damage in
    one line. Also a decorator."""
    logger, quiet = py_logging.getLogger("absl"), _NotOrbax()
    logger.addFilter(quiet)
    try:
        yield
    finally:
        logger.removeFilter(quiet)


def write_json(path: str, obj: Any, **dump_kw) -> None:
    """Writes ``obj`` as JSON whole or not at all: a kill mid-write leaves the old file."""
    with open(path + ".tmp", "w") as f:
        json.dump(obj, f, **dump_kw)
    os.replace(path + ".tmp", path)


def _write_checksums(step_dir: str) -> None:
    write_json(os.path.join(step_dir, CHECKSUM_FILE), _file_hashes(step_dir), indent=0,
               sort_keys=True)


def _checksum_problem(step_dir: str) -> str | None:
    """What is wrong with ``step_dir``'s files against its record (None: nothing, or
    no record to check against)."""
    path = os.path.join(step_dir, CHECKSUM_FILE)
    if not os.path.exists(path):
        return None
    try:
        with open(path) as f:
            recorded = json.load(f)
    except (OSError, ValueError):
        return f"its {CHECKSUM_FILE} is unreadable"
    if not isinstance(recorded, dict):
        return f"its {CHECKSUM_FILE} is unreadable (not a JSON object)"
    actual = _file_hashes(step_dir)
    for rel, digest in sorted(recorded.items()):
        if rel not in actual:
            return f"{rel} is missing"
        if actual[rel] != digest:
            return f"{rel} fails its sha256 checksum"
    return None


class _Manager(ocp.CheckpointManager):
    """An orbax manager that records the checksums of the steps it saved once their
    asynchronous saves have finished (orbax waits for them before each save and on
    ``wait_until_finished``/``close``)."""

    def __init__(self, *args, **kwargs):
        self._unsealed: list[int] = []
        super().__init__(*args, **kwargs)

    def save(self, step: int, *args, **kwargs) -> bool:
        saved = super().save(step, *args, **kwargs)  # finishes (and seals) earlier saves
        if saved:
            self._unsealed.append(step)
        return saved

    def wait_until_finished(self) -> None:
        super().wait_until_finished()
        for step in self._unsealed:
            step_dir = os.path.join(str(self.directory), str(step))
            if os.path.isdir(step_dir):  # not yet removed by max_to_keep
                _write_checksums(step_dir)
        self._unsealed = []


@_orbax_quiet()
def make_manager(workdir: str, save_every: int, max_to_keep: int = 3) -> ocp.CheckpointManager:
    """The training run's manager. It first removes the ``<step>.orbax-checkpoint-tmp``
    folders that a killed run's uncommitted saves left (orbax never reads them)."""
    options = ocp.CheckpointManagerOptions(
        max_to_keep=max_to_keep, save_interval_steps=max(int(save_every), 1), create=True,
        cleanup_tmp_directories=True,
    )
    return _Manager(os.path.abspath(os.path.join(workdir, CHECKPOINT_DIR)), options=options)


def _restore_args(template, subtree: bool) -> ocp.args.CheckpointArgs:
    """Orbax's restore arguments: the whole saved tree onto ``template``, or with
    ``subtree`` only the entries ``template`` names (e.g. ``params`` and ``batch_stats``
    of a saved TrainState, without its optimiser state), onto the default device."""
    if not subtree:
        return ocp.args.StandardRestore(template)
    device = jax.sharding.SingleDeviceSharding(jax.devices()[0])
    restore_args = jax.tree.map(lambda _: ocp.ArrayRestoreArgs(sharding=device), template)
    return ocp.args.PyTreeRestore(item=template, restore_args=restore_args,
                                  partial_restore=True)


def _path_names(path) -> str:
    """A pytree path as ``params/phi_trunk/...``, alike for dicts and dataclass fields."""
    return "/".join(str(getattr(k, "key", getattr(k, "name", getattr(k, "idx", k))))
                    for k in path)


def _network_shape_problem(step_dir: str, template) -> str | None:
    """How the network (``params``, ``batch_stats``) saved in ``step_dir`` differs in
    shape from ``template``'s, from orbax's metadata alone (None when it does not, or when
    the metadata cannot be read: the restore then reports the damage)."""
    handler = ocp.StandardCheckpointHandler()
    try:
        stored = handler.metadata(epath.Path(step_dir) / "default")
    except Exception:  # noqa: BLE001 (a damaged step: the restore names it)
        return None
    finally:
        handler.close()
    stored = getattr(stored, "tree", stored)
    have = {_path_names(p): tuple(leaf.shape) for p, leaf
            in jax.tree_util.tree_leaves_with_path(stored) if hasattr(leaf, "shape")}
    diffs = []
    for p, leaf in jax.tree_util.tree_leaves_with_path(template):
        name = _path_names(p)
        if name.split("/")[0] not in ("params", "batch_stats"):
            continue
        want = tuple(np.shape(leaf))
        if have.get(name, want) != want:
            diffs.append(f"{name}: {have[name]} stored, {want} expected")
        elif name not in have:
            diffs.append(f"{name}: not stored")
    if not diffs:
        return None
    more = f"; and {len(diffs) - 2} more" if len(diffs) > 2 else ""
    return f"{'; '.join(diffs[:2])}{more}"


def _restore(manager: ocp.CheckpointManager, step: int, template, subtree: bool = False):
    """The state saved at ``step`` (``_restore_args``), or None (with a warning naming it)
    when its files fail their checksums, cannot be read or hold non-finite numbers: a
    half-written or half-deleted directory (a kill during a save or the ``max_to_keep``
    clean-up), a truncated, missing, damaged or altered file. The checksums cover every
    file of the step, also when only a subtree is read."""
    step_dir = os.path.join(str(manager.directory), str(step))
    problem = _checksum_problem(step_dir)
    if problem is None and not os.path.isdir(os.path.join(step_dir, "default")):
        problem = "its saved state is missing: an empty or partly deleted step folder"
    if problem is not None:
        logging.warning("checkpoint %s/%d cannot be read (%s)", manager.directory, step, problem)
        return None
    # Not damage but another network: no older step would do, so it is an error.
    problem = _network_shape_problem(step_dir, template)
    if problem is not None:
        workdir = os.path.dirname(os.path.abspath(str(manager.directory)))
        raise ValueError(f"checkpoint {manager.directory}/{step} holds a network of other shapes "
                         f"than {os.path.join(workdir, 'config.json')}'s model section describes "
                         f"({problem}): that config.json is not the one it was saved with")
    # A reader of its own for each step: orbax's manager fixes how it reads its steps
    # (one item or several) from the first one it reads, so a damaged step folder read
    # first would make every intact one after it unreadable to the same manager.
    reader = ocp.CheckpointManager(manager.directory,
                                   options=ocp.CheckpointManagerOptions(create=False))
    try:
        state = reader.restore(step, args=_restore_args(template, subtree))
    except Exception as err:  # noqa: BLE001 (orbax raises many types for damaged files)
        problem = (str(err).strip().splitlines() or [type(err).__name__])[0][:200]
        logging.warning("checkpoint %s/%d cannot be read (%s)", manager.directory, step, problem)
        return None
    finally:
        reader.close()
    leaves = [np.asarray(x) for x in jax.tree.leaves(state)]
    if not all(np.all(np.isfinite(x)) for x in leaves if np.issubdtype(x.dtype, np.floating)):
        logging.warning("checkpoint %s/%d holds NaN or inf", manager.directory, step)
        return None
    return state


def _restore_newest(manager: ocp.CheckpointManager, template, subtree: bool = False):
    """``(state, step)`` of the newest checkpoint that restores intact (broken ones are
    skipped with a warning); ``(None, None)`` when there is none at all. Raises when
    checkpoints exist but none can be read."""
    steps = sorted(manager.all_steps(), reverse=True)
    for step in steps:
        state = _restore(manager, step, template, subtree)
        if state is not None:
            if step != steps[0]:
                logging.warning("using checkpoint %d, the newest intact one", step)
            return state, step
    if steps:
        raise ValueError(f"no checkpoint under {manager.directory} can be read (steps "
                         f"{steps}); delete that folder to start again")
    return None, None


@_orbax_quiet()
def restore_or_init(manager: ocp.CheckpointManager, state):
    """The newest intact saved state if there is one (restored onto ``state``'s structure),
    else ``state``. Newer steps that could not be read are moved aside (to
    ``<step>.unreadable``, with a warning): the training that replays their steps saves
    them again, which a step folder of the same name would refuse."""
    restored, step = _restore_newest(manager, state)
    if restored is None:
        return state
    newer = [s for s in manager.all_steps() if s > step]
    for bad in newer:
        source = os.path.join(str(manager.directory), str(bad))
        target, n = source + ".unreadable", 1
        while os.path.exists(target):
            n += 1
            target = f"{source}.unreadable{n}"
        os.rename(source, target)
        logging.warning("moved the unreadable checkpoint %s aside to %s", source, target)
    if newer:
        manager.reload()
    return restored


def save(manager: ocp.CheckpointManager, step: int, state, force: bool = False) -> bool:
    """Saves if the manager's interval says so (or ``force``); returns whether it did."""
    return manager.save(step, args=ocp.args.StandardSave(state), force=force)


def has_checkpoint(workdir: str) -> bool:
    """Whether ``workdir/checkpoints`` holds a step directory (intact or not)."""
    directory = os.path.join(workdir, CHECKPOINT_DIR)
    return os.path.isdir(directory) and any(n.isdigit() for n in os.listdir(directory))


@_orbax_quiet()
def restore_latest(workdir: str, template, step: int | None = None, subtree: bool = False):
    """Restores ``template``-shaped state from ``workdir``: ``step``, or by default the newest
    checkpoint that reads back intact. With ``subtree``, only the entries that ``template``
    names are read (``restore_variables``)."""
    directory = os.path.abspath(os.path.join(workdir, CHECKPOINT_DIR))
    if not os.path.isdir(directory):  # a read makes no folder
        raise FileNotFoundError(f"no checkpoint found under {workdir}/{CHECKPOINT_DIR}")
    manager = ocp.CheckpointManager(directory,
                                    options=ocp.CheckpointManagerOptions(create=False))
    try:
        if step is None:
            state, step = _restore_newest(manager, template, subtree)
            if state is None:
                raise FileNotFoundError(f"no checkpoint found under {workdir}/{CHECKPOINT_DIR}")
        else:
            steps = sorted(manager.all_steps())
            if step not in steps:
                raise FileNotFoundError(f"no checkpoint {step} under {workdir}/{CHECKPOINT_DIR} "
                                        f"(its steps: {steps})")
            state = _restore(manager, step, template, subtree)
            if state is None:
                raise ValueError(f"checkpoint {step} under {workdir}/{CHECKPOINT_DIR} cannot be "
                                 "read (see the warning above)")
    finally:
        manager.close()
    return state, step


def restore_variables(workdir: str, template: dict[str, Any], step: int | None = None):
    """``(variables, step)``: the ``{"params", "batch_stats"}`` of a checkpoint, whether it
    holds a whole TrainState (a training run) or the variables alone (``save_variables``),
    shaped like ``template`` (e.g. ``jax.eval_shape`` of ``model.init_variables``). No
    optimiser is built and its state is not read: inference needs neither."""
    template = {"params": template["params"], "batch_stats": template["batch_stats"]}
    return restore_latest(workdir, template, step, subtree=True)


def save_variables(workdir: str, variables: dict[str, Any], step: int = 0) -> None:
    """Writes ``variables`` (``{"params", "batch_stats"}``) as the checkpoint ``step`` of
    ``workdir``, with its checksums: a workdir that ``restore_variables`` (``load``,
    ``--mode=eval``) reads. It holds no optimiser state, so training cannot resume it."""
    manager = make_manager(workdir, save_every=1)
    try:
        variables = {"params": variables["params"], "batch_stats": variables["batch_stats"]}
        save(manager, step, variables, force=True)
        manager.wait_until_finished()
    finally:
        manager.close()
