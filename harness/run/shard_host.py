"""The body of a shard process (``hil.harness.run.shard_proc``): its targets, its
shard, and the loop that keeps its time and answers the run process."""

from __future__ import annotations

import gc
import os
import signal
import threading
import time
from multiprocessing.connection import Connection, wait
from pathlib import Path
from typing import Any

from hil.adapters.impair import record_on
from hil.common.errors import HilError
# What a shard builds its vehicles' work from is imported with the process, while the
# targets start (~0.3 s on 2 cores): built after the run's start, the first frames of
# every vehicle waited for these imports in the render pipes (hand-off 50-290 ms).
from hil.harness.analysis.timing_observer import TimingObserver
from hil.harness.cases.detector_observer import DetectorObserver
from hil.harness.config.loading import dump_config
from hil.harness.record.channels import register_all, sync_sample_json, views_of
from hil.harness.record.producer import EncodingRecorder
from hil.harness.run.rig_frames import rig_cams
from hil.harness.run.shard import VehicleShard
from hil.harness.run.tasks import VehicleTasks
from hil.harness.vocab.events import EventBus
from hil.harness.engine.analysis_thread import AnalysisThread
from hil.harness.engine.messages import (Applied, ApplyControl, CameraTruthReady, ChildGone, Done, Finished,
                                         FrameReady, WorldState)
from hil.harness.engine.procs import Pump, RingPump, ThreadCpu, loop_process
from hil.harness.engine.render import FrameSlots
from hil.harness.engine.rings import Ring
from hil.harness.run.shard_proc import (Doorbell, Outbox, ShardDone, ShardDrain, ShardDrained, ShardFailed,
                                        ShardFinish, ShardIdle, ShardProgress, ShardReady, ShardSpec, ShardStart,
                                        ShardStop, ShardStopRequest)
from hil.harness.run.run_specs import stall_of
from hil.harness.run.target_launch import close_links
from hil.harness.run.vehicle_state import PROGRESS_NS, VehicleRun
from hil.scenarios.sim import Simulation
from hil.timing.clock import MonotonicClock

TICK_NS = 20_000_000
PHYSICS_DONE_TIMEOUT_S = 10.0


def shard_main(spec: ShardSpec, ctl: Connection, data: Connection, parent_pid: int) -> None:
    """Entry point of a shard process."""
    from hil.harness.engine.heap import fix_mmap_threshold
    from hil.harness.engine.procs import die_with_parent

    die_with_parent(parent_pid)
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C reaches the whole group: the run process ends us
    fix_mmap_threshold()
    host = ShardHost(spec, ctl, data)
    try:
        host.serve()
    except (EOFError, BrokenPipeError, OSError):
        pass  # the run process is gone
    finally:
        host.close()
        os._exit(0)


class ShardHost:
    """One shard process's life: targets up, then the shard until the run says finish."""

    def __init__(self, spec: ShardSpec, ctl: Connection, data: Connection) -> None:
        self.spec, self.cfg, self.ctl, self.data = spec, spec.cfg, ctl, data
        self.out = Outbox(ctl)
        self.bell = Doorbell()
        self.clock = MonotonicClock()
        self.vehicles: list[VehicleRun] = []
        self.procs: list[Any] = []
        self.slots: dict[str, FrameSlots] = {}
        self.pumps: list[Any] = []
        self.physics_done = threading.Event()
        self._control_lock = threading.Lock()
        self._stop_told = False
        self.shard: Any = None
        self.analysis: AnalysisThread | None = None
        self._cpu0 = 0
        self._thread_cpu = ThreadCpu()  # each thread's, loop start to the run's last step

    # -- start ----------------------------------------------------------------------------

    def serve(self) -> None:
        try:
            warmup = self._start_targets()
        except HilError as err:
            self.out.send(ShardFailed(str(err)))
            return
        hellos = {v.name: (None if v.link.hello is None else
                           (v.link.hello.target_name, v.link.hello.clock_id.name, v.link.hello.clock_resolution_ns))
                  for v in self.vehicles}
        # Before the run starts, so its first frames find the shard reading its pipes:
        # the detector's world mirror (MuJoCo's model of the whole world) and a full
        # garbage collection of the start-up (each tens of ms; ``loop_process`` then
        # only freezes what is alive).
        self.sim = Simulation(self.spec.world, rules=self.spec.rules)
        gc.collect()
        self.out.send(ShardReady(hellos, warmup))
        start = self.ctl.recv()
        if not isinstance(start, ShardStart):
            return
        self._build(start, warmup)
        self._cpu0 = time.process_time_ns()  # the run's own work from here (as the run process counts it)
        self._thread_cpu.start()
        with loop_process(collect=False):
            self._loop()

    def _start_targets(self) -> dict[str, list[Any]]:
        from hil.harness.run.target_launch import SYNC_WARMUP_SAMPLES, check_identity, make_link, open_links

        cfg, out = self.cfg, Path(self.spec.out_dir)
        opening = []
        for vi, name in self.spec.vehicles:
            link, proc = make_link(cfg, vehicle_id=vi, vehicle=name, clock=self.clock, out_dir=out,
                                   session=self.spec.session)
            if proc is not None:
                self.procs.append(proc)
            self.vehicles.append(VehicleRun(name, vi, link))
            opening.append((name, link, proc))
        open_links(opening, timeout_s=cfg.target.startup_timeout_s)
        warmup = {v.name: [s for _ in range(SYNC_WARMUP_SAMPLES) if (s := v.link.sync_exchange(timeout_s=0.5))]
                  for v in self.vehicles}
        check_identity(cfg, self.vehicles, self.procs)
        return warmup

    def _build(self, start: ShardStart, warmup: dict[str, list[Any]]) -> None:
        cfg, io, names = self.cfg, self.spec.io, [v.name for v in self.vehicles]
        enc = self.encoder = EncodingRecorder(self.data.send_bytes, log_time_offset_ns=start.log_time_offset_ns)
        register_all(enc, names)
        views_of(dump_config(cfg), names, offset_ns=start.log_time_offset_ns).install(enc)
        bus = EventBus()  # counted by the run's bus, where every event goes
        bus.subscribe(lambda ev, log_ns: enc.write_event(ev.to_json(), log_ns))
        for v in self.vehicles:
            record_on(v.link.impairment, enc, f"/{v.name}/impairment")
        self.timing = TimingObserver.for_run(cfg, names, recorder=enc, events=bus)
        self.detector = (DetectorObserver(cfg.detector, names, camera=cfg.camera, recorder=enc,
                                          timing=self.timing, events=bus) if cfg.detector.enabled else None)
        for name, samples in warmup.items():
            for s in samples:
                enc.write_json(f"/{name}/clock_sync", sync_sample_json(s, warmup=True), log_time_ns=s.t4_ns,
                               publish_time_ns=s.t1_ns)
                self.timing.on_sync(name, s)
        self.tasks = VehicleTasks(self.sim, enc, self.clock, render_worker=self.spec.render_worker)
        self.tasks.observers.append(self.timing)
        if self.detector is not None:
            self.tasks.observers.append(self.detector)
        self.analysis = AnalysisThread()
        self.slots = {v: FrameSlots(slot_bytes=io.slot_bytes, name=n, cameras=io.cameras) for v, n in io.shm.items()}
        self.shard = VehicleShard(cfg, self.vehicles, egos=self.sim.egos, step_ns=self.sim.step_ns,
                                  cams=rig_cams(self.sim), tasks=self.tasks, analysis=self.analysis, events=bus,
                                  clock=self.clock, frame_bytes=self._frame_bytes, send_control=self._control,
                                  on_stop=self._ask_stop, wake=self.bell.ring, latency=self.spec.latency)
        self.mine = {v.vehicle_id: v.name for v in self.vehicles}
        ring = Ring.open(io.ring, producer=False)
        self.pumps = [RingPump(ring, self._on_physics, name="physics", stall=stall_of(cfg))]
        self.pumps += [Pump(c, self._on_render, name=f"render-{w}") for w, c in enumerate(io.frames)]
        for v in self.vehicles:
            v.link.deliver_to(self.shard.on_received)

    # -- inputs (pump threads) ------------------------------------------------------------------

    def _on_physics(self, msg: object) -> None:
        match msg:
            case WorldState():
                names = tuple(self.mine[vi] for i, vi in enumerate(msg.vis) if vi in self.mine and msg.cameras(i) & 1)
                if names or msg.collisions:
                    assert self.analysis is not None
                    self.analysis.post(self.tasks.truth, msg.steps, msg.qpos, msg.qvel, msg.collisions, names)
                self.shard.on_state(msg)
                self.bell.ring()
            case Applied():
                self.shard.on_applied(msg)
            case Finished():
                self.shard.states_complete()
                self.bell.ring()
            case Done() | ChildGone():
                self.physics_done.set()
                self.bell.ring()

    def _on_render(self, msg: object) -> None:
        match msg:
            case FrameReady():
                self.shard.on_frame(msg)
            case CameraTruthReady():
                self.shard.on_camera_truth(msg)

    def _frame_bytes(self, vehicle: str, slot: int, nbytes: int) -> bytes:
        return self.slots[vehicle].read(slot, nbytes)

    def _control(self, c: ApplyControl) -> None:
        with self._control_lock:  # every link's reader sends
            self.spec.io.control.send(c)

    def _ask_stop(self, reason: str) -> None:
        if not self._stop_told:
            self._stop_told = True
            self.out.send(ShardStopRequest(reason))

    # -- the loop (main thread) -------------------------------------------------------------------

    def _loop(self) -> None:
        shard, clock = self.shard, self.clock
        reported = -1
        next_tick = next_progress = 0
        while True:
            deadline = shard.next_deadline_ns()
            now = clock.now_ns()
            wait_ns = min(TICK_NS, max(0, deadline - now)) if deadline is not None else TICK_NS
            ready = wait([self.ctl, self.bell.fileno()], wait_ns / 1e9)
            if self.bell.fileno() in ready:
                self.bell.clear()
            if self.ctl in ready:
                msg = self.ctl.recv()
                match msg:
                    case ShardStop():
                        shard.stopping = True
                    case ShardDrain():
                        self._drain(msg.deadline_ns)
                    case ShardFinish():
                        self._finish(msg.wall_s)
                        return
            now = clock.now_ns()
            shard.expire(now)
            if now >= next_tick:
                next_tick = now + TICK_NS
                shard.tick(now)
                self.encoder.flush()
            if now >= next_progress:
                next_progress = now + PROGRESS_NS
                self.out.send(ShardProgress(tuple(v.progress_row(now, self.timing.anomaly_count(v.name))
                                                  for v in self.vehicles)))
            if shard.lockstep:
                seen = shard.state_seen()
                if seen > reported and shard.ready_at(seen):
                    ctls, due = shard.lockstep_stop(seen)
                    self.out.send(ShardIdle(seen, tuple(ctls), due))
                    reported = seen
            gone = shard.gone()
            if gone is not None:
                self._ask_stop(f"target of {gone.name} is gone: {gone.link.peer_gone_reason}")
                shard.expire_all()

    def _drain(self, deadline_ns: int) -> None:
        # The run's last step is past: each thread's CPU while every one still runs (the
        # physics's ring pump ends with the physics).
        self._thread_cpu.mark_end()
        shard = self.shard
        while (shard.busy() or shard.truth_pending()) and self.clock.now_ns() <= deadline_ns \
                and shard.gone() is None:
            ready = wait([self.bell.fileno()], 0.05)
            if ready:
                self.bell.clear()
            shard.expire(self.clock.now_ns())
        ctls = shard.end_of_run()
        shard.collect_sync()
        self.out.send(ShardDrained(tuple(ctls)))

    def _finish(self, wall_s: float) -> None:
        from hil.harness.run.spill import spill_summary
        from hil.harness.run.summary import vehicle_summary

        self.physics_done.wait(PHYSICS_DONE_TIMEOUT_S)  # its last answers are in the ring before it
        threads = self._thread_cpu.by_role()
        shard = self.shard
        shard.unconfirmed()
        assert self.analysis is not None
        self.analysis.close()
        close_links([v.link for v in self.vehicles])
        shard.collect_sync()  # answers that arrived while closing (run here: the thread is closed)
        self.timing.finish()
        if self.detector is not None:
            self.detector.finish()
        vehicles = {v.name: vehicle_summary(v, wall_s=wall_s, timing=self.timing, detector=self.detector)
                    for v in self.vehicles}
        camera = {v.name: (v.next_frame_id, v.late_frames, v.worst_frame_lag_ns) for v in self.vehicles}
        self.encoder.flush()
        self.out.send(ShardDone(vehicles, camera, time.process_time_ns() - self._cpu0, self.analysis.dropped,
                                self.encoder.enqueued, self.encoder.errors, spill_summary(self.vehicles, self.timing),
                                threads))

    # -- lifetime -------------------------------------------------------------------------------

    def close(self) -> None:
        """Links, targets and everything else go (idempotent; the process ends next)."""
        close_links([v.link for v in self.vehicles])
        for p in self.procs:
            try:
                p.close()
            except Exception:  # noqa: BLE001
                pass
        if self.analysis is not None:
            self.analysis.close(timeout_s=5.0)
        for s in self.slots.values():
            s.close()
        self.bell.close()
