"""The run process's loop: keeps time for the run, and the world's truth.

The simulation runs in the physics process and the cameras in the render pool
(``hil.harness.engine``); the vehicles' work — frames to targets, estimates back,
controls to the physics, records — is done by the run's shards
(``hil.harness.run.shard``), each on the threads its inputs arrive on. This loop:

* starts the physics, and in real time lets it pace itself (it never waits for this
  loop or a target); ticks the shards (timeouts, the observers' clocks, clock-sync
  samples) and the progress display;
* takes each world state from the physics's ring (stamped ``t_state``): its ground
  truth is computed on this process's mirror of the world (``self.sim``) and
  recorded — ``/ground_truth`` (every entity's state the first time, then the
  entities that changed; the capturing egos' truth; collisions) — and the shard of
  each capturing ego is told;
* in lockstep, tells the physics how far to step and which controls to apply first,
  and waits at each camera instant until every shard has every answer (or its
  timeout, a drop): deterministic, for regression and replay. With a latency profile
  (``hil.harness.run.latency``) each control is held and applied when sim time reaches its
  capture time plus the frame's latency;
* at the end drains the shards, lets the physics finish and takes its histogram.

Truth and the shards' analysis run on the analysis thread
(``hil.harness.engine.analysis_thread``); nothing here waits behind it.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import Any

from hil.adapters.process import prioritise_this_thread, restore_thread_priority
from hil.harness.vocab.events import Event, EventBus, EventKind
from hil.harness.config.model import Mode, RunConfig
from hil.harness.engine.analysis_thread import AnalysisThread
from hil.harness.engine.messages import (Applied, ApplyControl, CameraTruthReady, ChildGone, Done, Finished,
                                         FrameReady, WorkerFailed, WorldState)
from hil.harness.engine.physics import PhysicsSpec, capture_table
from hil.harness.engine.pool import Engine
from hil.harness.engine.procs import ThreadCpu, loop_process
from hil.harness.run.run_specs import LoopStats, encode_image, engine_specs
from hil.harness.run.shard import VehicleShard
from hil.harness.run.tasks import WorldTasks
from hil.harness.run.vehicle_state import VehicleRun
from hil.scenarios.sim import Simulation
from hil.timing.clock import Clock

TICK_NS = 20_000_000         # shards' and observers' on_tick and the live display, at most this often
PHYSICS_END_TIMEOUT_S = 10.0
DRAIN_EXTRA_NS = 1_000_000_000  # drain: the estimate timeout and this, at most

__all__ = ["LoopStats", "SimLoop", "encode_image", "engine_specs"]


class SimLoop:
    """Runs one configured simulation (in ``engine``) with its shards.

    ``sim`` mirrors the physics process's world in this process: ground truth and the
    summary's final state are taken from it. ``shards`` hold the vehicles (one in this
    process: ``VehicleShard``); ``analysis`` is this process's analysis thread, which
    their tasks share; ``events`` is the run's bus.
    """

    def __init__(self, cfg: RunConfig, sim: Simulation, shards: list[VehicleShard], *, engine: Engine,
                 physics: PhysicsSpec, world: WorldTasks, analysis: AnalysisThread, events: EventBus, clock: Clock,
                 recorder: Any, on_tick: Callable[[], None] | None = None) -> None:
        self.cfg, self.sim, self.shards, self.clock, self.rec = cfg, sim, shards, clock, recorder
        self.engine, self.physics, self.world, self.analysis, self.events = engine, physics, world, analysis, events
        self.vehicles: list[VehicleRun] = [v for sh in shards for v in sh.vehicles]
        self.shard_of = {v.vehicle_id: sh for sh in shards for v in sh.vehicles}
        self.shard_by_name = {v.name: sh for sh in shards for v in sh.vehicles}
        self.egos = sim.egos
        self.stats = LoopStats(render_workers=engine.workers, scheduling=engine.scheduling,
                               renderer=next((r for r in engine.renderers if r), ""))
        self.stop_reason: str | None = None
        self.on_tick = on_tick
        self.frame_tolerance_ns = cfg.frame_late_tolerance_ns
        self.period = cfg.camera_period_steps
        self.table = capture_table(self.period, physics.phases, physics.offsets, physics.dropped)
        self._cv = threading.Condition()
        self._sim_steps = 0
        self._state_seen = -1
        self._finished = False
        self._done: Done | None = None
        self._physics_eof = False
        self._exiting = False  # Exit sent: the physics and then the render workers end
        self._halted = False
        self._thread_cpu = ThreadCpu()  # each thread's, loop start to last step
        self._next_tick_ns = 0
        self._behind_told: dict[str, tuple[int, int]] = {}  # consumer -> (records told, next event ns)

    @property
    def collisions(self) -> list[dict[str, object]]:
        return self.world.collisions

    @property
    def min_gap_m(self) -> dict[str, float]:
        return self.world.min_gap_m

    def request_stop(self, reason: str) -> None:
        """Ask the loop to end (signal handlers and shards call this): stepping stops,
        frames in flight are still answered or time out."""
        if self.stop_reason is None:
            self.stop_reason = reason
            for sh in self.shards:
                sh.stopping = True
        self.wake()

    def wake(self) -> None:
        """Something the loop may be waiting for happened (any thread)."""
        with self._cv:
            self._cv.notify()

    # -- inputs (the engine's pumps' threads) -------------------------------------------------

    def on_physics(self, msg: object) -> None:
        match msg:
            case WorldState():
                self._on_state(msg)
            case Applied():
                sh = self.shard_of.get(msg.vi)
                if sh is not None:
                    sh.on_applied(msg)
            case Finished():
                self._sim_steps = msg.steps
                for sh in self.shards:
                    sh.states_complete()
                self._finished = True
            case Done():
                self._done = msg
            case ChildGone():
                self._physics_eof = True
                if self._done is None:
                    self.request_stop("the physics process ended unexpectedly")
        self.wake()

    def on_render(self, msg: object) -> None:
        match msg:
            case FrameReady():
                self.shard_by_name[msg.vehicle].on_frame(msg)
            case CameraTruthReady():
                self.shard_by_name[msg.vehicle].on_camera_truth(msg)
            case WorkerFailed():
                self.request_stop(msg.text)
            case ChildGone():
                # Once the physics is told to exit, a render worker leaves when its job
                # ring closes, which may be read before the physics's Done is.
                if self._done is None and not self._exiting:
                    self.request_stop(f"the {msg.name} process ended unexpectedly")

    def _on_state(self, ws: WorldState) -> None:
        """A camera instant: its truth (analysis thread), then the capturing egos'
        shards (a camera truth of the instant must find its truth there first)."""
        steps = ws.steps
        self._sim_steps = max(self._sim_steps, steps)
        # The truth of an instant is its camera 0's (a rig's trigger-offset cameras add none).
        names = tuple(self.egos[vi] for i, vi in enumerate(ws.vis) if ws.cameras(i) & 1)
        if names or ws.collisions:
            self.analysis.post(self.world.truth, steps, ws.qpos, ws.qvel, ws.collisions, names)
        for sh in self.shards:
            sh.on_state(ws)
        self._state_seen = steps

    # -- the run ------------------------------------------------------------------------------

    def run(self) -> LoopStats:
        """Run to the configured duration (or a stop request); returns the loop's stats.

        The process is set for the loop while it goes (``procs.loop_process``: full
        garbage collection held off, a short switch interval) and restored afterwards.
        """
        with loop_process():
            boosted = prioritise_this_thread()  # (root) served before the analysis and recording threads
            cpu0 = time.thread_time_ns()
            self._thread_cpu.start()
            try:
                return self._run()
            finally:
                self.stats.loop_cpu_ns = time.thread_time_ns() - cpu0
                self.stats.threads_cpu_ns = self._thread_cpu.by_role()
                self.analysis.close()
                self.stats.analysis_cpu_ns = self.analysis.cpu_ns
                self.stats.analysis_dropped = self.analysis.dropped
                if boosted is not None:
                    restore_thread_priority(boosted)

    def _run(self) -> LoopStats:
        st = self.stats
        # Real time: paced from after the render workers' warm-up (a GPU awake for the
        # first frames; engine.render_warm_ms), which the start-up (start_s) includes.
        lead = self.engine.warm_ns if self.cfg.mode != Mode.LOCKSTEP else 0
        st.render_warm_ms = lead / 1e6
        st.wall_start_ns = self.clock.now_ns() + lead
        try:
            self.engine.start(st.wall_start_ns, warm=lead > 0)
            if self.cfg.mode == Mode.LOCKSTEP:
                self._run_lockstep()
            else:
                while not self._finished:
                    if self.stop_reason is not None and not self._halted:
                        self._halted = True
                        self.engine.halt()
                    self._wait(lambda: self._finished)
                    if not self.engine.alive() and not self._finished:
                        self.request_stop("the physics or a render process ended unexpectedly")
                        break
            # Each thread's CPU up to the last step, read while they all still run (the
            # physics's ring pump ends with the physics, below).
            self._thread_cpu.mark_end()
            st.wall_last_step_ns = self.clock.now_ns()
            self._drain()
        except KeyboardInterrupt:
            self.request_stop("interrupted (Ctrl-C)")
            for sh in self.shards:
                sh.expire_all()
        self._end_physics()
        st.sim_steps = self._sim_steps
        st.wall_end_ns = self.clock.now_ns()
        if self.stop_reason is not None:
            st.ended_by = self.stop_reason
        return st

    def _wait(self, done: Callable[[], bool], until_ns: int | None = None) -> None:
        """Until ``done()`` or ``until_ns`` (at most one tick), keeping time meanwhile:
        frames past their timeout are dropped, the tick runs when due."""
        now = self.clock.now_ns()
        end = now + TICK_NS if until_ns is None else min(until_ns, now + TICK_NS)
        # The shards' deadlines are read outside the condition's lock: a shard holds its
        # own lock when it wakes this loop.
        deadline = min([end] + [d for sh in self.shards if (d := sh.next_deadline_ns()) is not None])
        with self._cv:
            while not done() and (now := self.clock.now_ns()) < deadline:
                self._cv.wait((deadline - now) / 1e9)
        now = self.clock.now_ns()
        for sh in self.shards:
            sh.expire(now)
        if now >= self._next_tick_ns:
            self._tick(now)

    def _tick(self, now: int) -> None:
        self._next_tick_ns = now + TICK_NS
        failure = getattr(self.rec, "failure", None)
        if failure is not None and self.stop_reason is None:
            self.request_stop(f"the recording failed ({failure}): is the disk full? What was written is kept")
        for sh in self.shards:
            sh.tick(now)
        self._watch_consumers(now)
        if self.on_tick is not None:
            self.on_tick()

    def _run_lockstep(self) -> None:
        """Step to each camera instant (or held control's due step), capture, wait for
        every answer, then tell the physics the controls to apply and the next stop."""
        total = self.physics.total_steps
        step = 0
        ctls: tuple[ApplyControl, ...] = ()
        while self.stop_reason is None:
            self.engine.advance(step, ctls)
            if step >= total:
                break
            self._await_stop(step)
            if self.stop_reason is not None:
                break
            got, dues = [], []
            for sh in self.shards:
                c, due = sh.lockstep_stop(step)
                got += c
                if due is not None:
                    dues.append(due)
            ctls = tuple(sorted(got, key=lambda c: (c.vi, c.frame_id)))  # one order, however they came
            step = self._next_stop(step, total, min(dues, default=None))
        if self.stop_reason is not None:
            self.engine.halt()
        while not self._finished and self.engine.alive():
            self._wait(lambda: self._finished)

    def _await_stop(self, step: int) -> None:
        """Lockstep: until the world state of ``step`` is in and no shard has a frame
        rendering or in flight (each times out after the estimate timeout)."""
        def idle() -> bool:
            return self.stop_reason is not None or (
                self._state_seen >= step and not any(sh.busy() for sh in self.shards))

        while self.stop_reason is None and not all(sh.ready_at(step) for sh in self.shards):
            self._wait(idle)
            gone = next((v for sh in self.shards if (v := sh.gone()) is not None), None)
            if gone is not None:
                self.request_stop(f"target of {gone.name} is gone: {gone.link.peer_gone_reason}")
                for sh in self.shards:
                    sh.expire_all()
            if not self.engine.alive():
                self.request_stop("the physics or a render process ended unexpectedly")

    def _next_stop(self, step: int, total: int, due_ns: int | None) -> int:
        nxt = (step // self.period + 1) * self.period
        for p in self.table:
            cand = (step // self.period) * self.period + p
            cand = cand if cand > step else cand + self.period
            nxt = min(nxt, cand)
        if due_ns is not None:
            nxt = min(nxt, max(step + 1, -(-due_ns // self.sim.step_ns)))
        return min(nxt, total)

    def _drain(self) -> None:
        """Let the frames being rendered or in flight finish (answer or time out); the
        controls answered meanwhile in lockstep still go to the physics."""
        deadline = self.clock.now_ns() + int(self.cfg.target.estimate_timeout_s * 1e9) + DRAIN_EXTRA_NS

        def settled() -> bool:  # every answer, and every camera truth (rendered after its frame)
            return not any(sh.busy() or sh.truth_pending() for sh in self.shards)

        for sh in self.shards:
            sh.begin_drain(deadline)
        while not settled() and self.clock.now_ns() <= deadline:
            if any(sh.gone() is not None for sh in self.shards) or not self.engine.alive():
                break
            self._wait(settled, deadline + 1)
        for sh in self.shards:
            for c in sh.end_of_run():
                self.engine.control(c)
            sh.collect_sync()

    def _end_physics(self) -> None:
        """Let the physics process finish, take its histogram and final state; the
        controls it never confirmed were not applied (recorded stale)."""
        try:
            self._await_physics_end()
        finally:
            for sh in self.shards:
                sh.unconfirmed()

    def _await_physics_end(self) -> None:
        self._exiting = True
        try:
            self.engine.exit_physics()
        except (OSError, ValueError):
            return
        deadline = self.clock.now_ns() + int(PHYSICS_END_TIMEOUT_S * 1e9)
        while self._done is None and not self._physics_eof and self.clock.now_ns() < deadline:
            self._wait(lambda: self._done is not None or self._physics_eof, deadline)
        done = self._done
        if done is None:
            return
        hist = done.lateness
        st = self.stats
        st.lateness = hist
        st.late_steps = int(hist["late_steps"])
        st.max_lateness_ns = int(hist["max_ns"])
        st.physics_span_ns = int(hist.get("span_ns", 0))
        st.behind = {str(k): int(n) for k, n in (hist.get("behind") or {}).items()}
        self._watch_consumers(self.clock.now_ns(), final=st.behind)
        self._sim_steps = done.steps
        self.analysis.post(self.world.final_state, done.steps, done.qpos, done.qvel, done.collisions)

    def _watch_consumers(self, now: int, *, final: dict[str, int] | None = None) -> None:
        """An event when a consumer of the physics's rings lost records since it was
        last told (at most one a second per consumer, and one with the final count)."""
        for name, n in (self.engine.behind() if final is None else final).items():
            told, next_ns = self._behind_told.get(name, (0, 0))
            if n <= told or (final is None and now < next_ns):
                continue
            self._behind_told[name] = (n, now + 1_000_000_000)
            ev = Event.of(EventKind.CONSUMER_BEHIND, now, sim_time_ns=self._sim_steps * self.sim.step_ns,
                          measured=float(n), unit="records", extra={"consumer": name},
                          detail=f"{name} fell behind the physics: {n} records it could not take were lost "
                                 "(the physics did not wait)")
            self.analysis.post(self.events.publish, ev, None)

    def collect_sync(self) -> None:
        """Record (and pass to observers) the clock-sync answers received so far."""
        for sh in self.shards:
            sh.collect_sync()
