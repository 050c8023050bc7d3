"""TensorBoard event files in a workdir, next to ``metrics.jsonl``.

``tensorboard --logdir runs/`` then shows each run's training losses (``loss``,
``loss/reprojection``, ``loss/canonicalisation``, ``grad_norm``, ``lr``, ``steps_per_s``)
and test scores (``test/mpjpe``, ``test/stress``, ..., ``test/per_group/NAME``) against
the step. Viewing needs the ``tensorboard`` program; writing does not.

The writer is tensorboardX's ``EventsWriter``: tensorboardX is small and maintained, and
needs only numpy and protobuf (which orbax needs anyway), whereas ``flax.metrics.tensorboard``
and clu's writers import TensorFlow. Its synchronous ``EventsWriter`` is used rather than
its ``SummaryWriter``, which hands events to a background thread through a queue: here
each record is in the file when ``scalars`` returns (flushed every ``flush_secs``, and
by ``flush`` and ``close``). Without tensorboardX installed, one warning and no events.
``read_scalars`` reads the curves back as TensorBoard shows them.
"""

import glob
import json
import math
import os
import struct
import time

from absl import logging

# Bookkeeping fields of metrics.jsonl and eval_results.json records, not curves.
_SKIP = frozenset({"step", "epoch", "n_samples"})


def _last_logged_step(workdir: str) -> int | None:
    """The step of the last ``metrics.jsonl`` record (None when there is none)."""
    path = os.path.join(workdir, "metrics.jsonl")
    if not os.path.exists(path):
        return None
    with open(path) as f:
        lines = [line for line in f if line.strip()]
    return json.loads(lines[-1]).get("step") if lines else None


def flatten(values: dict, prefix: str = "") -> dict[str, float]:
    """Finite numbers of ``values`` (nested dicts as ``a/b``), bookkeeping fields left out."""
    out = {}
    for key, value in values.items():
        if key in _SKIP:
            continue
        if isinstance(value, dict):
            out.update(flatten(value, f"{prefix}{key}/"))
        elif isinstance(value, int | float) and math.isfinite(value):
            out[f"{prefix}{key}"] = float(value)
    return out


class EventWriter:
    """Scalars into ``logdir/events.out.tfevents.*``, opened at the first write.

    Each file starts with a session START at the step after the last ``metrics.jsonl``
    record when the writer is made (1 for a new run). So for a run resumed in the same
    directory, TensorBoard drops what the earlier run wrote past that point (the resumed
    run replays those steps), as training drops those records from ``metrics.jsonl``.
    """

    def __init__(self, logdir: str, flush_secs: float = 10.0):
        self.logdir, self.flush_secs = logdir, flush_secs
        self._writer, self._last_flush, self._disabled = None, 0.0, False
        self._resumed_after = _last_logged_step(logdir)

    def _open(self):
        try:
            from tensorboardX.event_file_writer import EventsWriter
            from tensorboardX.proto.event_pb2 import Event, SessionLog
        except ImportError:
            logging.warning("tensorboardX is not installed: no TensorBoard events in %s "
                            "(pip install tensorboardX)", self.logdir)
            self._disabled = True
            return None
        os.makedirs(self.logdir, exist_ok=True)
        # The name holds the time in whole seconds: a suffix in nanoseconds keeps a run
        # resumed within the same second from overwriting the file, and sorts after it.
        self._writer = EventsWriter(os.path.join(self.logdir, "events"),
                                    filename_suffix=f".{time.time_ns()}")
        # TensorBoard takes every session START after a run's first as a restart.
        start = SessionLog(status=SessionLog.START)
        self._writer.write_event(Event(wall_time=time.time(), step=(self._resumed_after or 0) + 1,
                                       session_log=start))
        return self._writer

    def scalars(self, step: int, values: dict, prefix: str = "") -> None:
        """Writes the numbers of ``values`` (``flatten``) at ``step``, tags ``prefix + key``."""
        if self._disabled or (self._writer is None and self._open() is None):
            return
        from tensorboardX.proto.event_pb2 import Event
        from tensorboardX.proto.summary_pb2 import Summary

        summary = Summary(value=[Summary.Value(tag=tag, simple_value=v)
                                 for tag, v in flatten(values, prefix).items()])
        self._writer.write_event(Event(wall_time=time.time(), step=int(step), summary=summary))
        if time.monotonic() - self._last_flush >= self.flush_secs:
            self.flush()

    def flush(self) -> None:
        if self._writer is not None:
            self._writer.flush()
            self._last_flush = time.monotonic()

    def close(self) -> None:
        if getattr(self, "_writer", None) is not None:  # also from __del__ after a failed init
            self._writer.close()
            self._writer = None

    def __del__(self):  # a run that stopped with an error still leaves a complete file
        self.close()


def _records(path: str):
    """The payloads of a TFRecord file (8-byte length, 4-byte CRC, payload, 4-byte CRC)."""
    with open(path, "rb") as f:
        while header := f.read(12):
            (length,) = struct.unpack("<Q", header[:8])
            payload = f.read(length)
            if len(payload) < length or len(f.read(4)) < 4:
                return  # a record still being written
            yield payload


def read_scalars(logdir: str) -> dict[str, list[tuple[int, float]]]:
    """``{tag: [(step, value), ...]}`` of the event files in ``logdir``, oldest file first,
    each session START after the first dropping the points at or past its step (a restart,
    as TensorBoard reads it)."""
    from tensorboardX.proto.event_pb2 import Event, SessionLog

    out: dict[str, list[tuple[int, float]]] = {}
    started = False
    for path in sorted(glob.glob(os.path.join(logdir, "events.out.tfevents.*"))):
        for payload in _records(path):
            event = Event.FromString(payload)
            if event.session_log.status == SessionLog.START:
                if started:
                    out = {t: [p for p in pts if p[0] < event.step] for t, pts in out.items()}
                started = True
            for value in event.summary.value:
                out.setdefault(value.tag, []).append((event.step, value.simple_value))
    return out
