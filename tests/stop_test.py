"""Stopping a training run from outside, as a user, a scheduler or a crash does.

SIGTERM and SIGINT stop with a checkpoint at the step reached and one line on stderr;
SIGKILL at the worst moments (before the first checkpoint, while a save is in flight,
half-way through deleting an old step for ``max_to_keep``) loses at most the steps since
the last committed checkpoint. Either way, running the same command again ends with
parameters bitwise equal to an uninterrupted run, the same test scores, and one
``metrics.jsonl`` record per logged step; the workdir's lock goes with the process (a
killed run's lock file locks nothing).

Every run is a real ``c3dpo_jax.main`` process. The moments inside orbax's background
threads are hit deterministically: the process runs under ``_PAUSING_MAIN``, which
pauses one save after its files are written and before its folder is committed (orbax's
public ``post_finalization_callback``), or one ``max_to_keep`` deletion after its first
two files are gone (orbax's internal ``PathDeleter``: the orbax pin keeps it there),
creates a marker file and waits until the test has signalled or killed the process.
"""

import json
import os
import signal
import subprocess
import sys
import time

import jax
import numpy as np
import pytest

from c3dpo_jax import checkpoint, workdir_lock

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
STEPS = 60
# Chunks of 5 steps (log_every), checkpoints at 10, 20, ... (3 kept), evaluations at
# every epoch end (10 steps): the smoke config's.
ARGS = ["--config=configs/synthetic.py:smoke", "--nofigures", f"--config.train.num_steps={STEPS}",
        "--config.train.ckpt_every=10", "--config.train.progress_bar=False"]

_PAUSING_MAIN = """
import os, sys, threading, time

import orbax.checkpoint as ocp
from orbax.checkpoint._src.path import deleter

from c3dpo_jax import main

phase, at = os.environ["PAUSE"].split(":")
marker = os.environ["PAUSE_MARKER"]
calls = {"save": 0, "cleanup": 0}
deleting = threading.local()


def pause():
    open(marker, "w").close()
    deadline = time.time() + 300
    while not os.path.exists(marker + ".go") and time.time() < deadline:
        time.sleep(0.02)


def reached(name):
    calls[name] += 1
    return name == phase and calls[name] == int(at)


def before_commit():
    if reached("save"):
        pause()


def delete(self, path, **kwargs):
    deleting.left = 2 if reached("cleanup") else 0
    delete_path(self, path, **kwargs)


def counting_unlink(*args, **kwargs):
    unlink(*args, **kwargs)
    if getattr(deleting, "left", 0):
        deleting.left -= 1
        if not deleting.left:
            pause()


options = ocp.CheckpointManagerOptions
ocp.CheckpointManagerOptions = lambda **kw: options(
    **kw, async_options=ocp.AsyncOptions(post_finalization_callback=before_commit))
delete_path, unlink = deleter.PathDeleter.delete, os.unlink
deleter.PathDeleter.delete, os.unlink = delete, counting_unlink
sys.argv[0] = "c3dpo_jax.main"
main.cli_main()
"""


def _env():
    # As conftest's smoke_subprocess_env (module-scoped here), caching every compilation:
    # these processes all compile the same small programs.
    flags = [os.environ.get("XLA_FLAGS", ""), "--xla_backend_optimization_level=0"]
    return dict(os.environ, XLA_FLAGS=" ".join(f for f in flags if f),
                JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS="0")


def _run(workdir):
    """The command, to the end (a fresh run or a resumption)."""
    out = subprocess.run([sys.executable, "-m", "c3dpo_jax.main", *ARGS, f"--workdir={workdir}"],
                         cwd=ROOT, env=_env(), capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr[-3000:]
    return out


def _start_paused(workdir, pause: str):
    """The command, paused at ``pause`` ("save:K" or "cleanup:K", the K-th of either):
    ``(process, marker)`` once it waits there; creating ``marker + ".go"`` lets it go on."""
    marker = f"{workdir}.paused"
    proc = subprocess.Popen([sys.executable, "-c", _PAUSING_MAIN, *ARGS, f"--workdir={workdir}"],
                            cwd=ROOT, env=dict(_env(), PAUSE=pause, PAUSE_MARKER=marker),
                            text=True, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    deadline = time.time() + 300
    while not os.path.exists(marker):
        if proc.poll() is not None or time.time() > deadline:
            proc.kill()
            pytest.fail(f"never reached {pause}: {proc.communicate()[1][-3000:]}")
        time.sleep(0.05)
    return proc, marker


def _finish(proc) -> str:
    """Its stderr once it has exited (killed if it has not within 5 minutes)."""
    try:
        return proc.communicate(timeout=300)[1]
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()


def _steps(workdir) -> list[int]:
    """The committed checkpoint steps."""
    return sorted(int(n) for n in os.listdir(workdir / "checkpoints") if n.isdigit())


def _tmp_folders(workdir) -> list[str]:
    return [d for d, _, _ in os.walk(workdir) if "orbax-checkpoint-tmp" in d]


def _outcome(workdir) -> dict:
    """What a run leaves that must not depend on its interruptions: the final state's
    leaves, the logged losses and the test scores (times excluded)."""
    state, step = checkpoint.restore_latest(str(workdir), None)
    with open(workdir / "metrics.jsonl") as f:
        records = [json.loads(line) for line in f]
    with open(workdir / "eval_results.json") as f:
        results = json.load(f)
    scores = [{k: v for k, v in h.items() if k != "train_s"}
              for h in [*results["history"], results["final"]]]
    return {"step": step, "leaves": [np.asarray(x) for x in jax.tree.leaves(state)],
            "metrics": [{k: v for k, v in r.items() if k != "steps_per_s"} for r in records],
            "scores": scores}


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """The uninterrupted run."""
    workdir = tmp_path_factory.mktemp("stop") / "whole"
    _run(workdir)
    return _outcome(workdir)


def _assert_same_as(workdir, reference):
    got = _outcome(workdir)
    assert got["step"] == reference["step"] == STEPS
    assert len(got["leaves"]) == len(reference["leaves"])
    for a, b in zip(got["leaves"], reference["leaves"], strict=True):
        assert a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()
    # One record per logged step (5, 10, ..., 60), each with the uninterrupted run's losses.
    assert [r["step"] for r in got["metrics"]] == list(range(5, STEPS + 1, 5))
    assert got["metrics"] == reference["metrics"]
    assert got["scores"] == reference["scores"]
    assert not _tmp_folders(workdir)


@pytest.mark.parametrize("sig, pause, times", [
    (signal.SIGTERM, "save:2", 1),  # while the step-20 save is in flight
    # while step 10 is being deleted (after the step-40 save), delivered twice in quick
    # succession as `timeout -s INT` does (to the process, then to its process group)
    (signal.SIGINT, "cleanup:1", 2),
], ids=["SIGTERM_during_a_save", "SIGINT_twice_during_the_clean_up"])
def test_a_stop_signal_checkpoints_the_step_reached_and_the_run_resumes_bitwise(
        tmp_path, reference, sig, pause, times):
    workdir = tmp_path / "run"
    proc, marker = _start_paused(workdir, pause)
    for i in range(times):
        time.sleep(0.3 * i)  # the second after the first has been handled
        proc.send_signal(sig)
    open(marker + ".go", "w").close()
    err = _finish(proc)
    name = signal.Signals(sig).name
    assert proc.returncode == 128 + sig, err[-3000:]
    # One line says what happened and what to do; nothing else is an error.
    last = err.rstrip("\n").splitlines()[-1]
    assert last.startswith(f"{name}: stopped at step ") and last.endswith(
        f" of {STEPS} with a checkpoint; the same command resumes from it"), err[-3000:]
    assert err.count(name) == 1 and "Traceback" not in err and "Error" not in err, err[-3000:]
    stopped = int(last.split()[4])
    assert stopped < STEPS and _steps(workdir)[-1] == stopped
    assert not _tmp_folders(workdir)
    assert not (workdir / workdir_lock.LOCK_FILE).exists()  # the workdir's lock released
    with open(workdir / "metrics.jsonl") as f:  # nothing logged past the checkpoint
        assert json.loads(f.readlines()[-1])["step"] == stopped
    resumed = _run(workdir)
    assert f"resumed from the checkpoint at step {stopped} " in resumed.stderr
    _assert_same_as(workdir, reference)


@pytest.mark.parametrize("pause, committed", [
    ("save:1", []),  # the first checkpoint (step 10) in flight: nothing to resume from
    ("save:3", [10, 20]),  # the step-30 checkpoint in flight
    ("cleanup:1", [10, 20, 30, 40]),  # step 10 half-deleted after the step-40 save
], ids=["during_the_first_save", "during_a_later_save", "during_the_clean_up"])
def test_a_kill_loses_at_most_the_steps_since_the_last_checkpoint(
        tmp_path, reference, pause, committed):
    workdir = tmp_path / "run"
    proc, _ = _start_paused(workdir, pause)
    proc.send_signal(signal.SIGKILL)
    _finish(proc)
    assert proc.returncode == -signal.SIGKILL
    assert _steps(workdir) == committed
    if pause.startswith("save"):
        assert _tmp_folders(workdir), "the kill landed before the save was committed"
    else:  # the deletion had begun: a file of step 10, or its checksum record, is gone
        folder = workdir / "checkpoints" / "10"
        record = folder / checkpoint.CHECKSUM_FILE
        assert not record.exists() or any(
            not (folder / rel).exists() for rel in json.loads(record.read_text()))
    # The lock file stays with the killed run's pid, and locks nothing: the kernel released
    # its lock with the process, and the same command proceeds.
    assert (workdir / workdir_lock.LOCK_FILE).read_text() == f"{proc.pid}\n"
    resumed = _run(workdir)
    assert not (workdir / workdir_lock.LOCK_FILE).exists()
    if committed:
        assert f"resumed from the checkpoint at step {committed[-1]} " in resumed.stderr
    _assert_same_as(workdir, reference)
