"""A shard of a run's vehicles in a process of its own (issue 24: per-vehicle work
spreads over processes): what it is given, and what it and the run process tell
each other (its body is ``hil.harness.run.shard_host``).

The process starts its vehicles' targets (all at once), opens their links, takes
the warm-up clock-sync samples and checks who answered; then it is a
:class:`hil.harness.run.shard.VehicleShard` with everything it needs of its own:
the physics writes its egos' world states and answers into its ring and it sends
its controls to the physics on its own pipe; the render workers send its frames on
pipes of its own; its analysis thread runs its vehicles' timing analysis and
detector (on its own mirror of the world) and encodes their recording
(``hil.harness.record.producer``), which goes to the run's one writer as bytes with
its events for the run's bus. Nothing of it passes through the run process per
frame.

With the run process (``hil.harness.run.shard_handle``), on a pipe of messages below:
``ShardReady``/``ShardFailed`` once started; then ``ShardStart``; in lockstep a
``ShardIdle`` when every answer of a stop is in; ``ShardProgress`` for the live
display; ``ShardStopRequest`` when a target is gone; at the end ``ShardDrain`` ->
``ShardDrained`` and ``ShardFinish`` -> ``ShardDone`` (its vehicles' summaries), and
it leaves. It dies with the run process (``PR_SET_PDEATHSIG``), and its targets
with it.
"""

from __future__ import annotations

import os
import threading
from dataclasses import dataclass
from multiprocessing.connection import Connection
from typing import Any, NamedTuple

from hil.harness.engine.messages import ApplyControl
from hil.harness.engine.pool import ShardIO
from hil.harness.run.vehicle_state import ProgressRow



@dataclass(frozen=True)
class ShardSpec:
    """What a shard process needs (pickled once, at its start)."""

    index: int
    cfg: Any                          # hil.harness.config.model.RunConfig
    world: Any                        # hil.scenarios.world.WorldSpec
    rules: Any
    vehicles: tuple[tuple[int, str], ...]  # (ego index, name) of its vehicles
    out_dir: str
    session: str
    latency: Any                      # hil.harness.run.latency.LatencyProfile | None
    io: ShardIO
    render_worker: dict[str, int]     # vehicle -> the render worker drawing its camera


# -- shard -> run -----------------------------------------------------------------------------


class ShardReady(NamedTuple):
    """Targets up: per vehicle its HELLO (name, clock, resolution) and warm-up samples."""

    hellos: dict[str, tuple[str, str, int] | None]
    warmup: dict[str, list[Any]]      # hil.timing.sync.SyncSample


class ShardFailed(NamedTuple):
    text: str


class ShardIdle(NamedTuple):
    """Lockstep: every answer of the stop at ``step`` is in: the controls to apply
    first, and the next held control's due sim time (ns)."""

    step: int
    controls: tuple[ApplyControl, ...]
    next_due_ns: int | None


class ShardProgress(NamedTuple):
    rows: tuple[ProgressRow, ...]


class ShardStopRequest(NamedTuple):
    reason: str


class ShardDrained(NamedTuple):
    controls: tuple[ApplyControl, ...]


class ShardDone(NamedTuple):
    """The shard's vehicles summed up (``vehicle_summary`` dicts and their camera
    figures), its CPU time (ns), by thread role too, and its recording's counts."""

    vehicles: dict[str, dict[str, Any]]
    camera: dict[str, tuple[int, int, int]]
    cpu_ns: int
    analysis_dropped: int
    recorded: int
    record_errors: int
    spill: dict[str, Any]             # hil.harness.run.spill.spill_summary of its vehicles
    threads_cpu_ns: dict[str, int]   # its loop's start to the run's last step, by role (procs.ThreadCpu)


# -- run -> shard -----------------------------------------------------------------------------


class ShardStart(NamedTuple):
    wall_start_ns: int
    log_time_offset_ns: int


class ShardStop(NamedTuple):
    """No more frames out (the run is ending)."""


class ShardDrain(NamedTuple):
    """Wait until every frame is answered or ``deadline_ns`` (then drop the rest)."""

    deadline_ns: int


class ShardFinish(NamedTuple):
    wall_s: float


class Outbox:
    """The shard's side of its pipe to the run process: any thread may send."""

    def __init__(self, ctl: Connection) -> None:
        self._ctl = ctl
        self._lock = threading.Lock()

    def send(self, msg: object) -> None:
        with self._lock:
            self._ctl.send(msg)


class Doorbell:
    """Wakes the shard's main thread from another thread (a self-pipe)."""

    def __init__(self) -> None:
        self._r, self._w = os.pipe()
        os.set_blocking(self._r, False)
        os.set_blocking(self._w, False)

    def fileno(self) -> int:
        return self._r

    def ring(self) -> None:
        try:
            os.write(self._w, b"\0")
        except BlockingIOError:
            pass  # rung already

    def clear(self) -> None:
        try:
            while os.read(self._r, 4096):
                pass
        except BlockingIOError:
            pass

    def close(self) -> None:
        for fd in (self._r, self._w):
            try:
                os.close(fd)
            except OSError:
                pass


__all__ = ["ShardDone", "ShardDrain", "ShardDrained", "ShardFailed", "ShardFinish", "ShardIdle", "ShardProgress",
           "ShardReady", "ShardSpec", "ShardStart", "ShardStop", "ShardStopRequest"]
