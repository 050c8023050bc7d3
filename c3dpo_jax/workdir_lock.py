"""One training run per workdir: ``hold(workdir)`` locks it for as long as a run trains.

The lock is ``fcntl.flock`` on ``WORKDIR/train.lock``, a file that holds the pid of the
process that took it. The kernel releases such a lock when its process ends, however it
ends (an exception, Ctrl-C, SIGTERM, kill -9, a crash), so a lock file left behind by a
dead process locks nothing: the next run takes it. A run that finds the lock taken is
refused in one line naming the other process (``WorkdirBusy``), before it reads or writes
anything there. Readers take no lock: ``--mode=eval``, ``load`` and ``c3dpo-predict`` read
only committed checkpoints (orbax writes each into a temporary folder and renames it once
it is whole), and ``who_trains`` tells them whether a run is training there.
"""

import contextlib
import os
import time

try:
    import fcntl
except ImportError:  # not a POSIX system: runs are not locked (hold says so)
    fcntl = None
from absl import logging

LOCK_FILE = "train.lock"


class WorkdirBusy(ValueError):
    """Another process holds the workdir's lock (a user error: the command's one line)."""


def _folders_to_make(workdir: str) -> list[str]:
    """``workdir`` and those of its parents that do not exist, deepest first."""
    missing, path = [], os.path.abspath(workdir)
    while not os.path.exists(path):
        missing.append(path)
        path = os.path.dirname(path)
    return missing


def _read_pid(path: str) -> int | None:
    """The pid in a lock file (None while its holder has not written it yet)."""
    for _ in range(20):
        try:
            with open(path) as f:
                return int(f.read().strip())
        except (OSError, ValueError):
            time.sleep(0.05)
    return None


def _who(path: str) -> str:
    pid = _read_pid(path)
    return "another process" if pid is None else f"another process (pid {pid})"


def who_trains(workdir: str) -> str | None:
    """Who trains in ``workdir`` ("another process (pid N)"), None when no run does. Takes
    the lock shared for a moment only (``hold`` tries again a few times before it refuses)."""
    path = os.path.join(workdir, LOCK_FILE)
    if fcntl is None or not os.path.exists(path):
        return None
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:  # removed by its holder as it ended
        return None
    try:
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
    except BlockingIOError:
        return _who(path)
    finally:
        os.close(fd)  # and with it the shared lock, if it was taken
    return None


def _lock(fd: int) -> bool:
    """Whether the exclusive lock was taken within half a second (a reader's momentary
    shared lock, ``who_trains``, is not a run)."""
    for _ in range(5):
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            return True
        except BlockingIOError:
            time.sleep(0.1)
    return False


def _acquire(workdir: str, path: str) -> int:
    """An open descriptor of ``path`` holding its lock, with this process's pid written."""
    while True:
        os.makedirs(workdir, exist_ok=True)
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        if not _lock(fd):
            os.close(fd)
            raise WorkdirBusy(f"{_who(path)} is training in {workdir}; wait for it to end (or "
                              "stop it) before training there, or use another --workdir "
                              "(--mode=eval may score its checkpoints meanwhile)")
        try:  # the lock of a file its holder removed as it finished locks nothing: again
            if os.path.samestat(os.fstat(fd), os.stat(path)):
                break
        except FileNotFoundError:
            pass
        os.close(fd)
    os.ftruncate(fd, 0)
    os.write(fd, f"{os.getpid()}\n".encode())
    return fd


@contextlib.contextmanager
def hold(workdir: str):
    """Holds ``workdir``'s lock while the block runs (raises ``WorkdirBusy`` when another
    process holds it). The workdir is made if missing; on leaving, the lock file is removed,
    and so are the folders made here if nothing else was written into them (a run refused
    by its checks leaves no folder behind)."""
    if fcntl is None:
        logging.warning("no file locks on this system: nothing stops a second run from "
                        "training in %s at the same time", workdir)
        yield
        return
    made = _folders_to_make(workdir)
    path = os.path.join(workdir, LOCK_FILE)
    fd = _acquire(workdir, path)
    try:
        yield
    finally:
        with contextlib.suppress(FileNotFoundError):  # while still locked: no one locks
            os.unlink(path)  # the removed file (``_acquire`` checks that it locked the path's)
        os.close(fd)
        for folder in made:
            try:
                os.rmdir(folder)
            except OSError:  # not empty: the run wrote into it
                break
