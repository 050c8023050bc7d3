"""Stopping on SIGINT (Ctrl-C) and SIGTERM: the package's one place that handles them.

- ``end_at_once(message)``: a command's handling (``cli.run``), in force from its start. A
  signal ends the process there and then with one line on stderr, ``interrupted: MESSAGE``,
  and the shell's status for it (130 for SIGINT, 143 for SIGTERM).
- ``StopRequests``: the training loop's, in force while the loop runs and put back after
  it. The first signal only asks the loop to stop: it finishes its chunk, checkpoints and
  raises ``Interrupted``, whose message is the one line to show and ``exit_code`` the
  status. The same signal again within ``REPEAT_S`` is the same request delivered twice
  (``timeout`` and batch schedulers signal the process and then its process group) and is
  ignored; a later one acts as the handling from before the loop (a command's: it ends at
  once; Ctrl-C twice in a notebook: a KeyboardInterrupt).

Signals can only be caught in the main thread; elsewhere both leave the handling as it is.
"""

import os
import signal
import sys
import threading
import time

SIGNALS = (signal.SIGINT, signal.SIGTERM)


class Interrupted(Exception):
    """Training stopped by SIGINT or SIGTERM after checkpointing the step it had reached;
    ``exit_code`` is the shell's code for that signal (130, 143)."""

    def __init__(self, signum: int, step: int, total: int):
        super().__init__(f"{signal.Signals(signum).name}: stopped at step {step} of {total} with "
                         "a checkpoint; the same command resumes from it")
        self.exit_code = 128 + signum


def _install(handler) -> dict:
    """Sets ``handler`` for ``SIGNALS``; returns the handlers it replaced ({} outside the
    main thread, where nothing is set)."""
    if threading.current_thread() is not threading.main_thread():
        return {}
    return {sig: signal.signal(sig, handler) for sig in SIGNALS}


def _put_back(previous: dict) -> None:
    for sig, handler in previous.items():
        signal.signal(sig, handler)


def end_at_once(message: str) -> None:
    """A command's handling (module docstring). It ends the process with ``os._exit``: a
    KeyboardInterrupt would not always get out, since raised inside a callback (JAX's
    garbage collection hook) Python prints it as "Exception ignored" and goes on."""

    def end(signum, frame):
        for stream in (sys.stdout, sys.stderr):
            try:
                stream.flush()
            except Exception:  # noqa: BLE001 (a stream mid-write: its line is lost)
                pass
        os.write(2, f"interrupted: {message}\n".encode())
        os._exit(128 + signum)

    _install(end)


class StopRequests:
    """The training loop's handling (module docstring): ``with StopRequests() as requests``,
    then ``requests.requested`` between chunks and ``requests.raise_if_requested`` once
    the loop has checkpointed and closed."""

    REPEAT_S = 1.0

    def __init__(self):
        self.received, self.received_at, self.previous = None, 0.0, {}

    @property
    def requested(self) -> bool:
        return self.received is not None

    def _handle(self, signum, frame):
        now = time.monotonic()
        if self.received is None:
            self.received, self.received_at = signum, now
            return
        if now - self.received_at < self.REPEAT_S:
            return
        _put_back(self.previous)  # the handling from before, for this signal too
        if signum == signal.SIGINT:  # unwinds through the loop's clean-up (saves finished)
            raise KeyboardInterrupt
        signal.raise_signal(signum)

    def raise_if_requested(self, step: int, total: int) -> None:
        """``Interrupted`` at ``step`` of ``total`` if a signal asked to stop."""
        if self.received is not None:
            raise Interrupted(self.received, step, total)

    def __enter__(self):
        self.previous = _install(self._handle)
        return self

    def __exit__(self, *exc):
        _put_back(self.previous)
