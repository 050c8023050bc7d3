"""Runs of the experiments' training jobs: several at a time, each pinned to one core.

Shared by the experiments that train many models through the CLI (``dev_suite/suite.py``,
``robustness/run.py``); it defines no flags, so tests can import it beside the CLI.
"""

import ast
import json
import os
import subprocess
import time

ROOT = os.path.normpath(os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))


def repo_path(path: str) -> str:
    """``path`` relative to the repository root when it lies inside it, else unchanged: the
    runs execute there (``run_all``), so a run's recorded data paths name no machine's
    checkout."""
    rel = os.path.relpath(os.path.abspath(path), ROOT)
    return path if rel == ".." or rel.startswith(".." + os.sep) else rel


def cpu_model() -> str:
    """This machine's CPU model (lscpu's "Model name"), for the records of how a result was
    made."""
    import platform

    try:
        out = subprocess.run(["lscpu"], capture_output=True, text=True, check=True).stdout
    except (OSError, subprocess.CalledProcessError):
        return platform.processor()
    names = [line.split(":", 1)[1].strip() for line in out.splitlines()
             if line.startswith("Model name")]
    return names[0] if names else platform.processor()


def machine() -> dict:
    """How a result was made, for its record: the CPU model, the cores this process may use
    and the jax version (results differ across machines and versions in the last digits)."""
    import jax

    return {"cpu": cpu_model(), "cores": len(os.sched_getaffinity(0)), "jax": jax.__version__}


def run_main(main, positional: bool = False) -> None:
    """Runs an experiment's ``main`` as the library's commands run (``c3dpo_jax.cli.run``):
    an error in the input (a flag's value, a missing file, ``app.UsageError``) as one line
    ``error: ...`` with exit status 2, Ctrl-C as one line with status 130; absl's ``-v 1``
    shows the traceback instead. ``positional``: ``main`` reads arguments that are not flags
    (e.g. a sub-command)."""
    from c3dpo_jax import cli

    cli.run(main, on_interrupt="what has finished is kept; the same command goes on from it",
            positional=positional)


def literal(text: str):
    """A ``KEY=VALUE`` override's value as the CLI reads it: a Python literal (``"1.5"`` ->
    1.5, ``"(8,)"`` -> (8,)), else the string itself (``sgd``)."""
    try:
        return ast.literal_eval(text)
    except (ValueError, SyntaxError):
        return text


def override(config, items: dict) -> None:
    """Sets ``items`` (``{"optim.lr": 1e-3, ...}``, flattened keys) in ``config``, refusing in
    one line a key that names no field of it, as the CLI's ``--config.KEY`` does (a misspelt
    key would otherwise add a field that nothing reads)."""
    from absl import app

    for key in items:
        node = config
        for part in key.split("."):
            if not hasattr(node, "keys") or part not in node:
                raise app.UsageError(f"{key}={items[key]!r}: the config has no field {key}")
            node = node[part]
    with config.unlocked():
        config.update_from_flattened_dict(items)


def check_steps(workdir: str, steps: int) -> None:
    """Refuses, in one line, to reuse a finished run in ``workdir`` that was trained for
    another number of steps than ``steps`` (its table would be labelled with the new one)."""
    path = os.path.join(workdir, "config.json")
    if not os.path.exists(path):
        return
    with open(path) as f:
        saved = json.load(f).get("train", {}).get("num_steps")
    if saved and saved != steps:
        raise ValueError(f"{workdir} holds a run of {saved} steps, not {steps}: give another "
                         "output folder, or the same steps")


def is_finished(workdir: str) -> bool:
    """Whether the run in ``workdir`` has made its final evaluation."""
    path = os.path.join(workdir, "eval_results.json")
    if not os.path.exists(path):
        return False
    with open(path) as f:
        return "final" in json.load(f)


def run_all(jobs: list[tuple[str, list[str]]], n_at_once: int, out: str) -> None:
    """Runs ``(workdir, command)`` pairs from the repository root, ``n_at_once`` at a time,
    each pinned to one core (its output in ``workdir/log.txt``); progress lines name the
    workdirs relative to ``out``."""
    if n_at_once < 1:
        raise ValueError(f"--jobs={n_at_once} (must be >= 1)")
    cores = sorted(os.sched_getaffinity(0))
    running: dict[int, tuple[subprocess.Popen, str, float]] = {}
    pending = list(jobs)
    while pending or running:
        for core in cores[:n_at_once]:
            if core in running or not pending:
                continue
            workdir, cmd = pending.pop(0)
            os.makedirs(workdir, exist_ok=True)
            log = open(os.path.join(workdir, "log.txt"), "a")
            proc = subprocess.Popen(cmd, cwd=ROOT, stdout=log, stderr=subprocess.STDOUT,
                                    preexec_fn=lambda c=core: os.sched_setaffinity(0, {c}))
            running[core] = (proc, workdir, time.time())
            print(f"[core {core}] {os.path.relpath(workdir, out)}", flush=True)
        time.sleep(2)
        for core, (proc, workdir, start) in list(running.items()):
            if proc.poll() is not None:
                del running[core]
                status = "done" if proc.returncode == 0 else f"FAILED ({proc.returncode})"
                print(f"[core {core}] {os.path.relpath(workdir, out)}: {status} in "
                      f"{time.time() - start:.0f} s", flush=True)
