"""One training run per workdir: a second one is refused in one line naming the first's
pid, ``--mode=eval`` beside a run scores a committed checkpoint, and the lock goes with its
process however it ends (the kill -9 case: tests/stop_test.py)."""

import json
import os
import re
import subprocess
import sys
import time

import pytest

from c3dpo_jax import train, workdir_lock
from configs import default

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
STEPS = 60
ARGS = ["--config=configs/synthetic.py:smoke", "--nofigures", f"--config.train.num_steps={STEPS}",
        "--config.train.ckpt_every=10", "--config.train.progress_bar=False"]

# The command, paused while its second checkpoint (step 20) is written and not yet
# committed (orbax's post_finalization_callback, as in tests/stop_test.py) until the test
# creates MARKER.go: the run holds its lock, step 10 is committed, step 20 half-written.
_PAUSING_MAIN = """
import os, sys, time

import orbax.checkpoint as ocp

from c3dpo_jax import main

marker, saves = os.environ["PAUSE_MARKER"], []


def before_commit():
    saves.append(1)
    if len(saves) == 2:
        open(marker, "w").close()
        deadline = time.time() + 300
        while not os.path.exists(marker + ".go") and time.time() < deadline:
            time.sleep(0.02)


options = ocp.CheckpointManagerOptions
ocp.CheckpointManagerOptions = lambda **kw: options(
    **kw, async_options=ocp.AsyncOptions(post_finalization_callback=before_commit))
sys.argv[0] = "c3dpo_jax.main"
main.cli_main()
"""


def _env():
    flags = [os.environ.get("XLA_FLAGS", ""), "--xla_backend_optimization_level=0"]
    return dict(os.environ, XLA_FLAGS=" ".join(f for f in flags if f),
                JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS="0")


def _command(workdir, *extra):
    return subprocess.run([sys.executable, "-m", "c3dpo_jax.main", *ARGS, f"--workdir={workdir}",
                           *extra], cwd=ROOT, env=_env(), capture_output=True, text=True,
                          timeout=600)


def _steps(workdir) -> list[int]:
    with open(os.path.join(workdir, "metrics.jsonl")) as f:
        return [json.loads(line)["step"] for line in f]


@pytest.fixture(scope="module")
def beside_a_run(tmp_path_factory):
    """A run paused half-way through writing its step-20 checkpoint; meanwhile a second
    training command and an evaluation on its workdir. Returns what each did."""
    workdir = str(tmp_path_factory.mktemp("lock") / "run")
    marker = workdir + ".paused"
    first = subprocess.Popen([sys.executable, "-c", _PAUSING_MAIN, *ARGS, f"--workdir={workdir}"],
                             cwd=ROOT, env=dict(_env(), PAUSE_MARKER=marker), text=True,
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        deadline = time.time() + 300
        while not os.path.exists(marker):
            if first.poll() is not None or time.time() > deadline:
                pytest.fail(f"the first run never paused: {first.communicate()[1][-3000:]}")
            time.sleep(0.05)
        with open(os.path.join(workdir, "metrics.jsonl")) as f:
            metrics_then = f.read()
        second = _command(workdir)
        evaluation = _command(workdir, "--mode=eval")
        open(marker + ".go", "w").close()
        _, first_err = first.communicate(timeout=300)
    finally:
        if first.poll() is None:
            first.kill()
            first.communicate()
    return {"workdir": workdir, "pid": first.pid, "first": first, "first_err": first_err,
            "metrics_then": metrics_then, "second": second, "evaluation": evaluation}


def test_a_second_training_run_in_a_workdir_is_refused_in_one_line(beside_a_run):
    workdir, second = beside_a_run["workdir"], beside_a_run["second"]
    assert second.returncode == 2, second.stderr[-3000:]
    assert second.stderr.splitlines() == [
        f"error: another process (pid {beside_a_run['pid']}) is training in {workdir}; wait "
        "for it to end (or stop it) before training there, or use another --workdir "
        "(--mode=eval may score its checkpoints meanwhile)"]
    # The first run goes on to its end as if alone: one metrics record per logged step.
    assert beside_a_run["first"].returncode == 0, beside_a_run["first_err"][-3000:]
    with open(os.path.join(workdir, "metrics.jsonl")) as f:
        assert f.read().startswith(beside_a_run["metrics_then"])
    assert _steps(workdir) == list(range(5, STEPS + 1, 5))
    assert not os.path.exists(os.path.join(workdir, workdir_lock.LOCK_FILE))  # released


def test_an_evaluation_beside_a_training_run_scores_a_committed_checkpoint(beside_a_run):
    workdir, evaluation = beside_a_run["workdir"], beside_a_run["evaluation"]
    assert evaluation.returncode == 0, evaluation.stderr[-3000:]
    # Step 20 was half-written (not yet committed): the evaluation scores step 10, leaves
    # eval_results.json to the run, which writes it, and says so.
    assert "), step 10:\n" in evaluation.stdout
    assert "cannot be read" not in evaluation.stderr, evaluation.stderr[-3000:]
    assert evaluation.stdout.rstrip().splitlines()[-1] == (
        f"scores not written to {workdir}/eval_results.json: another process (pid "
        f"{beside_a_run['pid']}) is training in {workdir} and writes that file")
    with open(os.path.join(workdir, "eval_results.json")) as f:
        assert json.load(f)["final"]["step"] == STEPS


def test_the_lock_names_its_holder_and_goes_with_the_block(tmp_path):
    workdir = str(tmp_path / "made" / "run")
    me = f"another process (pid {os.getpid()})"
    with workdir_lock.hold(workdir):
        assert workdir_lock.who_trains(workdir) == me
        busy = re.escape(f"{me} is training in {workdir}; ")
        with pytest.raises(workdir_lock.WorkdirBusy, match=f"^{busy}"):
            with workdir_lock.hold(workdir):
                pass
    assert workdir_lock.who_trains(workdir) is None
    assert not (tmp_path / "made").exists()  # the folders it made, left empty, go too
    with pytest.raises(RuntimeError), workdir_lock.hold(workdir):
        (tmp_path / "made" / "run" / "kept").write_text("")
        raise RuntimeError
    assert os.listdir(workdir) == ["kept"]  # released, and a folder written into stays
    with workdir_lock.hold(workdir):
        pass


def test_a_lock_file_left_by_a_dead_process_locks_nothing(tmp_path):
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"],
                          capture_output=True, text=True, check=True).stdout.strip()
    (tmp_path / workdir_lock.LOCK_FILE).write_text(f"{dead}\n")
    assert workdir_lock.who_trains(str(tmp_path)) is None
    with workdir_lock.hold(str(tmp_path)):
        assert (tmp_path / workdir_lock.LOCK_FILE).read_text() == f"{os.getpid()}\n"


def test_training_takes_the_lock_before_it_reads_anything(tmp_path):
    config = default.apply_variants(default.get_config(), "smoke")
    config.data.train_path = str(tmp_path / "missing.json")  # never read: refused before
    config.data.test_path = config.data.train_path
    with workdir_lock.hold(str(tmp_path / "run")):
        with pytest.raises(workdir_lock.WorkdirBusy, match="is training in"):
            train.train_and_evaluate(config, str(tmp_path / "run"))
