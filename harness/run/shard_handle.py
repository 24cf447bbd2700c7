"""The run process's handle on a shard process (``hil.harness.run.shard_proc``).

It starts the process, waits for its targets, and then stands in the run's loop
where a shard in this process would (``busy``, ``lockstep_stop``, ``end_of_run`` ...),
from what the shard reports on its pipe: in lockstep a stop is answered once the
shard says so (``ShardIdle``); at the end it drains and sums up on its own. Two
threads read the shard: its reports (stop requests come through at once), and its
recording, which goes straight to the run's writer as the bytes the shard encoded,
and its events to the run's bus (on the run's analysis thread, the bus's one).
Closing ends the process (asked, then terminated, then killed).
"""

from __future__ import annotations

import multiprocessing as mp
import os
import threading
from collections.abc import Callable
from typing import Any

import orjson

from hil.common.errors import SimulationError, TargetError
from hil.harness.vocab.events import Event, EventBus
from hil.harness.engine.analysis_thread import AnalysisThread
from hil.harness.engine.messages import ApplyControl, WorldState
from hil.harness.engine.pool import without_main_module
from hil.harness.engine.procs import end_child
from hil.harness.record.producer import feed
from hil.harness.run.shard_host import shard_main
from hil.harness.run.shard_proc import (ShardDone, ShardDrain, ShardDrained, ShardFailed, ShardFinish, ShardIdle,
                                        ShardProgress, ShardReady, ShardSpec, ShardStart, ShardStop,
                                        ShardStopRequest)
from hil.harness.run.vehicle_state import ProgressRow, VehicleRun

FINISH_TIMEOUT_S = 120.0


class RemoteShard:
    """A shard process, as the run's loop sees it (see the module docstring)."""

    lockstep_controls: list[ApplyControl]

    def __init__(self, spec: ShardSpec) -> None:
        self.spec = spec
        self.index = spec.index
        self.names = [name for _vi, name in spec.vehicles]
        self.vehicles: list[VehicleRun] = []  # they live in the shard's process
        self.rows: tuple[ProgressRow, ...] = ()
        self.done: ShardDone | None = None
        self.recorder_refused = 0
        self._idle: ShardIdle | None = None
        self._awaited = -1
        self._drained: ShardDrained | None = None
        self._draining = False
        self._stop_pending = False
        self._stop_sent = False
        self._send_lock = threading.Lock()
        self._changed = threading.Condition()
        self._readers: list[threading.Thread] = []
        self._on_stop: Callable[[str], None] = lambda _why: None
        self._wake: Callable[[], None] = lambda: None
        ctx = mp.get_context("spawn")
        self._ctl, child_ctl = ctx.Pipe()
        self._data, child_data = ctx.Pipe(duplex=False)
        self.proc = ctx.Process(target=shard_main, args=(spec, child_ctl, child_data, os.getpid()),
                                name=f"hil-shard-{spec.index}", daemon=True)
        with without_main_module():
            self.proc.start()
        child_ctl.close()
        child_data.close()

    # -- start ----------------------------------------------------------------------------

    def wait_ready(self, timeout_s: float) -> ShardReady:
        """The shard's targets are up (HELLOs and warm-up samples).

        Raises:
            TargetError: a target could not start, did not answer, or was not the one
                expected (the shard's own message).
            SimulationError: the shard process did not start or died.
        """
        if not self._ctl.poll(timeout_s):
            raise SimulationError(f"shard {self.index} did not start its targets within {timeout_s:.0f} s")
        try:
            msg = self._ctl.recv()
        except EOFError as err:
            raise SimulationError(f"shard {self.index} exited while starting") from err
        if isinstance(msg, ShardFailed):
            raise TargetError(msg.text)
        assert isinstance(msg, ShardReady), msg
        return msg

    def start(self, *, wall_start_ns: int, log_time_offset_ns: int, recorder: Any, bus: EventBus,
              analysis: AnalysisThread, on_stop: Callable[[str], None], wake: Callable[[], None]) -> None:
        """Go: the shard's reports and recording are read from now on."""
        self._on_stop, self._wake = on_stop, wake

        def on_event(data: bytes, log_ns: int) -> None:
            analysis.post(bus.publish, Event.from_json(orjson.loads(data)), log_ns)

        self._readers = [threading.Thread(target=self._read_reports, name=f"shard-{self.index}-ctl", daemon=True),
                         threading.Thread(target=self._read_data, args=(recorder, on_event),
                                          name=f"shard-{self.index}-rec", daemon=True)]
        for t in self._readers:
            t.start()
        self._send(ShardStart(wall_start_ns, log_time_offset_ns))

    def _send(self, msg: object) -> None:
        with self._send_lock:
            try:
                self._ctl.send(msg)
            except (OSError, ValueError):  # the shard is gone; its reader says so
                pass

    def _read_reports(self) -> None:
        while True:
            try:
                msg = self._ctl.recv()
            except (EOFError, OSError):
                if self.done is None:
                    self._on_stop(f"shard {self.index} ({', '.join(self.names)}) ended unexpectedly")
                break
            match msg:
                case ShardIdle():
                    self._idle = msg
                case ShardProgress():
                    self.rows = msg.rows
                case ShardStopRequest():
                    self._on_stop(msg.reason)
                case ShardDrained():
                    self._drained = msg
                case ShardDone():
                    self.done = msg
            with self._changed:
                self._changed.notify_all()
            self._wake()
        with self._changed:
            self._changed.notify_all()
        self._wake()

    def _read_data(self, recorder: Any, on_event: Callable[[bytes, int], None]) -> None:
        broken = False
        while True:
            try:
                batch = self._data.recv_bytes()
            except (EOFError, OSError):
                return
            if broken:  # read on, so the shard never blocks on a pipe nobody reads
                continue
            try:
                self.recorder_refused += feed(batch, recorder, on_event)
            except ValueError as err:  # not one of ours: the stream cannot be trusted past it
                broken = True
                self._on_stop(f"shard {self.index} ({', '.join(self.names)}): its recording stream broke "
                              f"({err}); the run stopped, what was recorded before is kept")

    # -- what the loop asks -----------------------------------------------------------------

    @property
    def stopping(self) -> bool:
        return self._stop_pending

    @stopping.setter
    def stopping(self, value: bool) -> None:
        # May be set from a signal handler: sent from the loop's next tick, not here.
        self._stop_pending = self._stop_pending or value

    def on_state(self, ws: WorldState) -> None:
        self._awaited = max(self._awaited, ws.steps)

    def busy(self) -> bool:
        if self.done is not None or not self.proc.is_alive():
            return False
        if self._draining:
            return self._drained is None
        return bool(self.spec.cfg.mode.value == "lockstep" and (self._idle is None or self._idle.step < self._awaited))

    def ready_at(self, step: int) -> bool:
        """Lockstep: the shard said every answer of the stop at ``step`` is in."""
        idle = self._idle
        return (idle is not None and idle.step >= step) or self.done is not None or not self.proc.is_alive()

    def lockstep_stop(self, step: int) -> tuple[list[ApplyControl], int | None]:
        idle = self._idle
        if idle is None or idle.step != step:
            return [], None
        return list(idle.controls), idle.next_due_ns

    def states_complete(self) -> None:
        """Nothing to do here: the shard's process reads ``Finished`` on its own ring."""

    def begin_drain(self, deadline_ns: int) -> None:
        self._draining = True
        self._send(ShardDrain(deadline_ns))

    def end_of_run(self) -> list[ApplyControl]:
        return [] if self._drained is None else list(self._drained.controls)

    def tick(self, now_ns: int) -> None:
        if self._stop_pending and not self._stop_sent:
            self._stop_sent = True
            self._send(ShardStop())

    def next_deadline_ns(self) -> int | None:
        return None

    def truth_pending(self) -> int:
        """The shard waits for its own camera truths when it drains."""
        return 0

    def expire(self, now_ns: int) -> None:
        """The shard keeps its own time."""

    def expire_all(self) -> None:
        """The shard drops its own frames when it drains."""

    def gone(self) -> None:
        """A gone target is the shard's to report (``ShardStopRequest``)."""

    def collect_sync(self) -> None:
        """The shard records its own clock-sync samples."""

    def unconfirmed(self) -> None:
        """The shard records its unconfirmed controls when it finishes."""

    def ask_finish(self, wall_s: float) -> None:
        """Ask the shard to sum up (:meth:`finish` waits for it): every shard asked
        first, so they sum up at once rather than one after another."""
        self._send(ShardFinish(wall_s))

    def finish(self, timeout_s: float = FINISH_TIMEOUT_S) -> ShardDone | None:
        """The shard's sum-up (asked by :meth:`ask_finish`): it finishes its analysis
        and recording and reports; None if it died first (what it recorded so far stays)."""
        with self._changed:
            self._changed.wait_for(lambda: self.done is not None or not self._readers[0].is_alive(), timeout_s)
        self._readers[1].join(timeout_s)  # its recording, to the last batch
        return self.done

    def close(self) -> None:
        """End the process (asked by its pipe closing, then terminated, then killed)."""
        for c in (self._ctl, self._data):
            try:
                c.close()
            except OSError:
                pass
        end_child(self.proc, grace_s=5.0)
