"""The run process's loop: world states in, frames out, estimates in, controls out.

The simulation itself runs in the physics process and the cameras in the render
pool (``hil.harness.engine``); this loop is everything between them and the targets:

* a world state from the physics process at a camera instant (stamped ``t_state``)
  becomes ground truth (computed on a mirror of the world, ``self.sim``) and a
  render job for the capturing vehicles;
* a rendered frame (stamped ``t0``, bytes in shared memory) is sent to its target
  (``t_tx``) and waits in flight for its estimate;
* an estimate (``t0'`` stamped by the link's reader, at the wire where the socket
  allows) sends its control to the physics process, which applies it at once and
  answers with ``t_apply`` and the world at that instant; then the frame's pipeline
  record is complete and goes to the observers and the recording.

Truth, observers (timing analysis, detector) and recording run on the analysis
thread (``hil.harness.engine.analysis_thread``); the loop thread only moves world states,
frames, estimates and controls, so none of them waits behind analysis.

Real-time mode: the physics process paces itself and never waits for this loop or
a target. Lockstep mode: this loop tells the physics process how far to step and
which controls to apply first, waiting at each camera instant for every vehicle's
estimate (or its timeout, a drop): deterministic, for regression and replay. With a
latency profile (``hil.harness.run.latency``) each control is held and applied when sim time
reaches its capture time plus the frame's latency.

Ground truth goes to ``/ground_truth`` at every camera instant (every entity's state
the first time, then the entities that changed; the capturing egos' truth;
collisions) and, with ``truth.visible_boxes``, to ``/<vehicle>/truth`` (the camera's
visible boxes from a segmentation render done by the render worker after the frame).
"""

from __future__ import annotations

import functools
import gc
import math
import queue
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from hil.adapters.link import ProtocolFault, Received
from hil.adapters.process import prioritise_this_thread
from hil.adapters.wire.messages import CameraInfo, Command, ErrorMsg, Estimate, Heartbeat, ImageEncoding
from hil.adapters.wire.protocol import ErrorCode
from hil.common.errors import TransportError
from hil.harness.vocab.events import Event, EventBus, EventKind
from hil.harness.vocab.observers import RunObserver
from hil.harness.config.model import CameraConfig, Encoding, Mode, RunConfig
from hil.harness.engine.analysis_thread import AnalysisThread
from hil.harness.engine.physics import PhysicsSpec, capture_table, spread_phases
from hil.harness.engine.pool import Engine
from hil.harness.engine.render import RenderSpec, encode_image as _encode
from hil.harness.record import foxglove_out
from hil.harness.record.channels import sync_sample_json
from hil.harness.record.recorder import Recorder
from hil.harness.run.latency import HeldControls, LatencyProfile
from hil.harness.run.vehicle_state import InFlight, VehicleRun
from hil.scenarios.ground_truth import GroundTruth, StateChanges
from hil.scenarios.sim import Simulation
from hil.timing.clock import Clock
from hil.timing.records import FrameStatus, PipelineRecord

MAX_PROTOCOL_EVENTS = 200  # per vehicle; beyond, counted (summary: protocol_events_unwritten)
TICK_NS = 20_000_000         # observers' on_tick and the live display, at most this often
PHYSICS_END_TIMEOUT_S = 10.0
# How long a thread of the run process may hold the interpreter while another waits:
# the loop thread gets it back within this of a frame or an estimate arriving, even
# while the analysis and recording threads are busy (Python's default is 5 ms).
SWITCH_INTERVAL_S = 0.0001


def encode_image(rgb: np.ndarray, camera: CameraConfig) -> tuple[bytes, ImageEncoding]:
    """An RGB8 render as the wire carries it: JPEG at the configured quality, or raw."""
    data, enc = _encode(rgb, jpeg=camera.encoding == Encoding.JPEG, quality=camera.jpeg_quality)
    return bytes(data) if isinstance(data, (bytes, bytearray)) else data.tobytes(), ImageEncoding(enc)


def engine_specs(cfg: RunConfig, world: Any, rules: Any) -> tuple[PhysicsSpec, RenderSpec]:
    """The physics and render specs of a run (camera phases, pacing, late tolerance)."""
    step_ns = round(world.physics_step_s * 1e9)
    egos = tuple(v.name for v in world.vehicles if v.ego)
    period = cfg.camera_period_steps
    eng = cfg.engine
    realtime = cfg.mode == Mode.REALTIME
    phases = (spread_phases(len(egos), period) if realtime and eng.capture_phase == "spread"
              else tuple(0 for _ in egos))
    cam = cfg.camera
    physics = PhysicsSpec(world=world, rules=rules, realtime=realtime,
                          total_steps=round(cfg.duration_s * 1e9 / step_ns),
                          wall_per_step_ns=step_ns / cfg.realtime_factor, period_steps=period, phases=phases,
                          late_tolerance_ns=int(eng.late_tolerance_ms * 1e6),
                          realtime_priority=eng.realtime_priority if realtime else 0)
    render = RenderSpec(world=world, vehicles=egos, shm={}, slot_bytes=cam.width * cam.height * 3 + 65536,
                        jpeg=cam.encoding == Encoding.JPEG, jpeg_quality=cam.jpeg_quality,
                        visible_boxes=cfg.truth.visible_boxes, min_visible_px=cfg.truth.min_visible_px,
                        delay_ns=int(eng.faults.render_delay_ms * 1e6), delay_every=eng.faults.render_delay_every)
    return physics, render


@dataclass
class LoopStats:
    wall_start_ns: int = 0
    wall_end_ns: int = 0
    sim_steps: int = 0
    late_steps: int = 0
    max_lateness_ns: int = 0
    physics_span_ns: int = 0   # the physics process's own wall time, start to last step
    ended_by: str = "duration"
    lateness: dict[str, Any] = field(default_factory=dict)   # the physics process's histogram
    scheduling: str = ""
    render_workers: int = 0
    loop_cpu_ns: int = 0       # CPU time of the loop thread (frames, estimates, controls)
    analysis_cpu_ns: int = 0   # CPU time of the analysis thread (truth, observers, recording)
    analysis_dropped: int = 0  # analysis tasks dropped on a full queue


class SimLoop:
    """Runs one configured simulation (in ``engine``) against its vehicles' links.

    ``sim`` is a mirror of the physics process's world in this process: ground truth
    and the summary's final state are taken from it. ``received`` is the one queue the
    links and the engine's pumps deliver into; ``events`` the run's event bus.
    """

    def __init__(self, cfg: RunConfig, sim: Simulation, vehicles: list[VehicleRun],
                 received: queue.Queue[Any], recorder: Recorder, clock: Clock, *, engine: Engine,
                 physics: PhysicsSpec, on_tick: Callable[[], None] | None = None,
                 latency: LatencyProfile | None = None, events: EventBus | None = None) -> None:
        self.cfg, self.sim, self.vehicles, self.rx, self.rec, self.clock = cfg, sim, vehicles, received, recorder, clock
        # The run's event bus (default: one that records on the recorder's /events).
        self.events = events if events is not None else EventBus.recording_to(recorder)
        self.engine, self.physics = engine, physics
        self.by_id = {v.vehicle_id: v for v in vehicles}
        self.by_name = {v.name: v for v in vehicles}
        self.egos = sim.egos
        self.stats = LoopStats(render_workers=engine.workers, scheduling=engine.scheduling)
        self.stop_reason: str | None = None
        self.on_tick = on_tick
        self.timeout_ns = int(cfg.target.estimate_timeout_s * 1e9)
        self.frame_tolerance_ns = cfg.frame_late_tolerance_ns
        self.period = cfg.camera_period_steps
        self.table = capture_table(self.period, physics.phases)
        intr = sim.intrinsics()
        cam = cfg.camera
        self.camera_info = CameraInfo(intr.fx, intr.fy, intr.cx, intr.cy, cam.mount_height_m,
                                      math.radians(cam.pitch_deg))
        self.latency = latency if cfg.mode == Mode.LOCKSTEP and latency is not None else None
        self.held = None if self.latency is None else HeldControls(self.latency, step_ns=sim.step_ns)
        self._changes = StateChanges()
        self.observers: list[RunObserver] = []
        self._next_command = 0
        self._ego_names = {v.name for v in vehicles}
        self.collisions: list[dict[str, object]] = []
        self.min_gap_m: dict[str, float] = {}
        self._next_sync_ns = 0
        self._frame_of: dict[tuple[str, int], int] = {}  # (vehicle, steps) -> frame id, for camera truth
        self._camtruth_early: list[tuple[str, int, int, Any]] = []  # camera truth ahead of its world state
        self._sim_ns = 0  # the latest camera instant's sim time (loop thread)
        self.analysis = AnalysisThread()
        self._rendering = 0
        self._applying: dict[tuple[int, int], tuple[VehicleRun, InFlight, Estimate, int]] = {}
        # Per vehicle: records settled while an earlier-received estimate waits for the
        # physics to apply it; they follow it, so observers see receipt order.
        self._behind_apply: dict[int, list[tuple[Any, ...]]] = {}
        self._lockstep_ctls: list[tuple[Any, ...]] = []
        self._sim_steps = 0
        self._state_seen = -1
        self._finished = False
        self._done: tuple[Any, ...] | None = None
        self._physics_eof = False
        self._halted = False
        self._next_tick_ns = 0

    def request_stop(self, reason: str) -> None:
        """Ask the loop to end (signal handlers call this): stepping stops, frames in
        flight are still answered or time out."""
        if self.stop_reason is None:
            self.stop_reason = reason

    # -- main loop -----------------------------------------------------------

    def run(self) -> LoopStats:
        """Run to the configured duration (or a stop request); returns the loop's stats.

        Python's full garbage collection is held off during the loop (a collection
        over a run's growing history stalled it for 60-80 ms) and restored afterwards.
        """
        thresholds = gc.get_threshold()
        switch = sys.getswitchinterval()
        gc.collect()
        gc.freeze()
        gc.set_threshold(thresholds[0], thresholds[1], 1_000_000)
        # The links' readers and the engine's pumps stamp and hand over in threads.
        sys.setswitchinterval(SWITCH_INTERVAL_S)
        boosted = prioritise_this_thread()  # (root) served before the analysis and recording threads
        cpu0 = time.thread_time_ns()
        try:
            return self._run()
        finally:
            self.stats.loop_cpu_ns = time.thread_time_ns() - cpu0
            self.analysis.close()
            self.stats.analysis_cpu_ns = self.analysis.cpu_ns
            self.stats.analysis_dropped = self.analysis.dropped
            sys.setswitchinterval(switch)
            if boosted:
                prioritise_this_thread(0)
            gc.set_threshold(*thresholds)
            gc.unfreeze()

    def _run(self) -> LoopStats:
        st = self.stats
        st.wall_start_ns = self.clock.now_ns()
        self._next_sync_ns = st.wall_start_ns
        try:
            self.engine.start(st.wall_start_ns)
            if self.cfg.mode == Mode.LOCKSTEP:
                self._run_lockstep()
            else:
                while not self._finished:
                    if self.stop_reason is not None and not self._halted:
                        self._halted = True
                        self.engine.halt()
                    self._service(until_ns=self.clock.now_ns() + TICK_NS)
                    if not self.engine.alive() and not self._finished:
                        self.request_stop("the physics or a render process ended unexpectedly")
                        break
            self._drain()
            self._settle_held_at_end()
        except KeyboardInterrupt:
            self.request_stop("interrupted (Ctrl-C)")
            self._expire_all()
        self._end_physics()
        st.sim_steps = self._sim_steps
        st.wall_end_ns = self.clock.now_ns()
        if self.stop_reason is not None:
            st.ended_by = self.stop_reason
        return st

    def _run_lockstep(self) -> None:
        """Step to each camera instant (or held control's due step), capture, wait for
        every answer, then tell the physics the controls to apply and the next stop."""
        total = self.physics.total_steps
        step, ctls = 0, []
        while self.stop_reason is None:
            self.engine.advance(step, ctls)
            if step >= total:
                break
            while self._state_seen < step and self.stop_reason is None:
                self._service(until_ns=self.clock.now_ns() + TICK_NS)
                if not self.engine.alive():
                    self.request_stop("the physics or a render process ended unexpectedly")
            self._await_answers()
            if self.held is not None:
                for h in self.held.pop_due(step * self.sim.step_ns):
                    self._settle(*h.item)  # type: ignore[misc]
            ctls, self._lockstep_ctls = self._lockstep_ctls, []
            step = self._next_stop(step, total)
        if self.stop_reason is not None:
            self.engine.halt()
        while not self._finished and self.engine.alive():
            self._service(until_ns=self.clock.now_ns() + TICK_NS)

    def _next_stop(self, step: int, total: int) -> int:
        nxt = (step // self.period + 1) * self.period
        for p in self.table:
            cand = (step // self.period) * self.period + p
            cand = cand if cand > step else cand + self.period
            nxt = min(nxt, cand)
        if self.held is not None:
            due = self.held.next_due()
            if due is not None:
                nxt = min(nxt, max(step + 1, -(-due // self.sim.step_ns)))
        return min(nxt, total)

    def _end_physics(self) -> None:
        """Let the physics process finish, take its histogram and final state."""
        try:
            self._await_physics_end()
        finally:
            self._flush_unapplied()

    def _flush_unapplied(self) -> None:
        """Controls the physics never confirmed (it died) were never applied: their
        frames are recorded as stale, and the records held behind them follow."""
        for (_vi, _fid), (v, fl, m, t0p) in sorted(self._applying.items()):
            self.analysis.post(self._complete_task, v, fl, m, t0p, FrameStatus.STALE)
        self._applying.clear()
        held, self._behind_apply = self._behind_apply, {}
        for items in held.values():
            for fn, *args in items:
                self.analysis.post(fn, *args)

    def _await_physics_end(self) -> None:
        try:
            self.engine.exit_physics()
        except (OSError, ValueError):
            return
        deadline = self.clock.now_ns() + int(PHYSICS_END_TIMEOUT_S * 1e9)
        while self._done is None and not self._physics_eof and self.clock.now_ns() < deadline:
            self._service(until_ns=self.clock.now_ns() + TICK_NS)
        if self._done is None:
            return
        hist, steps, qpos, qvel, collisions = self._done
        st = self.stats
        st.lateness = hist
        st.late_steps = int(hist["late_steps"])
        st.max_lateness_ns = int(hist["max_ns"])
        st.physics_span_ns = int(hist.get("span_ns", 0))
        self._sim_steps = int(steps)
        self.analysis.post(self._final_state_task, steps, qpos, qvel, collisions)

    # -- events ----------------------------------------------------------------

    def _service(self, *, until_ns: int, until_answered: bool = False) -> None:
        """Handle events until ``until_ns`` (0: only what is waiting), or, with
        ``until_answered``, as soon as nothing is rendering or in flight."""
        while True:
            now = self.clock.now_ns()
            self._expire(now)
            if now >= self._next_tick_ns:
                self._tick(now)
            timeout_s = max(0.0, (until_ns - now) / 1e9)
            try:
                ev = self.rx.get(timeout=min(timeout_s, TICK_NS / 1e9)) if timeout_s > 0 else self.rx.get_nowait()
            except queue.Empty:
                self.collect_sync()
                if until_ns == 0 or self.clock.now_ns() >= until_ns:
                    return
                continue
            self._dispatch(ev)
            if until_answered and not self._busy():
                self.collect_sync()
                return

    def _busy(self) -> bool:
        return self._rendering > 0 or any(v.in_flight for v in self.vehicles)

    def _tick(self, now: int) -> None:
        self._next_tick_ns = now + TICK_NS
        failure = getattr(self.rec, "failure", None)
        if failure is not None and self.stop_reason is None:
            self.request_stop(f"the recording failed ({failure}): is the disk full? What was written is kept")
        self.analysis.post(self._tick_task, now, self._sim_ns)
        if self.on_tick is not None:
            self.on_tick()

    def _dispatch(self, ev: Any) -> None:
        if isinstance(ev, Received):
            self._handle(ev)
        elif ev[0] == "physics":
            self._on_physics(ev[1:])
        elif ev[0] == "render":
            self._on_render(ev[1:])
        elif ev[0] == "eof":
            if ev[1] == "physics":
                self._physics_eof = True
            if self._done is None:
                self.request_stop(f"the {ev[1]} process ended unexpectedly")

    def _on_physics(self, m: tuple[Any, ...]) -> None:
        tag = m[0]
        if tag == "state":
            self._on_state(*m[1:])
        elif tag == "applied":
            self._on_applied(*m[1:])
        elif tag == "finished":
            self._finished = True
            self._sim_steps = int(m[1])
        elif tag == "done":
            self._done = m[1:]

    # -- frames out ----------------------------------------------------------

    def _on_state(self, vis: tuple[int, ...], t_state: int, steps: int, qpos: np.ndarray, qvel: np.ndarray,
                  collisions: list[Any]) -> None:
        """A camera instant (the render workers have it from the physics already):
        truth, commands due, clock-sync probes."""
        self._sim_steps = max(self._sim_steps, steps)
        self._state_seen = steps
        self._sim_ns = steps * self.sim.step_ns
        names = [self.egos[i] for i in vis]
        if not names and not collisions:
            return
        self._send_commands()
        self.analysis.post(self._truth_task, steps, qpos, qvel, collisions, tuple(names))
        if self._camtruth_early:
            early, self._camtruth_early = self._camtruth_early, []
            for item in early:
                self._on_camtruth(*item)
        if not names or self.stop_reason is not None:
            return
        self._rendering += len(names)
        for name in names:
            v = self.by_name[name]
            if not v.link.alive:
                self.request_stop(f"target of {v.name} is gone: {v.link.peer_gone_reason}")
                return
        self._maybe_sync()

    def _on_render(self, m: tuple[Any, ...]) -> None:
        tag = m[0]
        if tag == "frame":
            self._on_frame(*m[1:])
        elif tag == "camtruth":
            name, steps, ct = m[1:]
            frame_id = self._frame_of.pop((name, steps), None)
            if frame_id is not None:
                self._on_camtruth(name, steps, frame_id, ct)
        elif tag == "error":
            self.request_stop(str(m[1]))

    def _on_camtruth(self, name: str, steps: int, frame_id: int, ct: Any) -> None:
        """Camera truth goes to the analysis after its instant's ground truth (the
        render worker's pipe may overtake the physics's)."""
        if steps > self._state_seen:
            self._camtruth_early.append((name, steps, frame_id, ct))
            return
        self.analysis.post(self._camtruth_task, name, frame_id, ct)

    def _on_frame(self, name: str, steps: int, t_state: int, speed_mps: float, t0: int, _t_encoded: int,
                  slot: int, nbytes: int, enc: int) -> None:
        self._rendering -= 1
        if self.stop_reason is not None:
            return
        v = self.by_name[name]
        data = self.engine.frame_bytes(name, slot, nbytes)
        cam = self.cfg.camera
        frame_id = v.next_frame_id
        v.next_frame_id += 1
        if self.cfg.truth.visible_boxes:
            self._frame_of[(name, steps)] = frame_id
        sim_time_ns = steps * self.sim.step_ns
        encoding = ImageEncoding(enc)
        try:
            t_tx = v.link.send_frame(frame_id=frame_id, sim_time_ns=sim_time_ns, t0_ns=t0, width=cam.width,
                                     height=cam.height, encoding=encoding, camera=self.camera_info,
                                     ego_speed_mps=speed_mps, data=data)
        except TransportError as err:
            self.request_stop(f"target of {v.name} is gone: {err}")
            return
        v.in_flight[frame_id] = InFlight(frame_id, sim_time_ns, t0, t_tx, t_state)
        v.frame_out(t_tx - t_state, tolerance_ns=self.frame_tolerance_ns)
        v.fps_meter.add(t0)
        if self.cfg.recording.images:
            topic = f"/{v.name}/camera"
            if encoding == ImageEncoding.JPEG:
                self.analysis.post(functools.partial(self.rec.write_image, topic, data, fmt="jpeg",
                                                     frame_id=f"{v.name}/camera", log_time_ns=t0, publish_time_ns=t0))
            else:
                rgb = np.frombuffer(data, np.uint8).reshape(cam.height, cam.width, 3)
                self.analysis.post(functools.partial(self.rec.write_raw_image, topic, rgb, encoding="rgb8",
                                                     frame_id=f"{v.name}/camera", log_time_ns=t0, publish_time_ns=t0))

    def _maybe_sync(self) -> None:
        now = self.clock.now_ns()
        if now < self._next_sync_ns:
            return
        sync = self.cfg.timing.sync
        self._next_sync_ns = now + int(sync.interval_s * 1e9)
        for v in self.vehicles:
            try:
                for _ in range(sync.burst):  # the clock filter keeps the fastest
                    v.link.send_sync_request()
            except TransportError:
                pass

    # -- analysis-thread tasks ------------------------------------------------------

    def _truth_task(self, steps: int, qpos: np.ndarray, qvel: np.ndarray, collisions: list[Any],
                    names: tuple[str, ...]) -> None:
        sim = self.sim
        sim.load_state(steps, qpos, qvel)
        if collisions:
            sim.add_collisions(collisions)
        self._record_truth(sim.ground_truth(egos=names))

    def _final_state_task(self, steps: int, qpos: np.ndarray, qvel: np.ndarray, collisions: list[Any]) -> None:
        """The mirror takes the final state (the summary reads it); collisions since
        the last camera instant are recorded."""
        self.sim.load_state(steps, qpos, qvel)
        if collisions:
            self.sim.add_collisions(collisions)
            self._record_truth(self.sim.ground_truth(egos=()))

    def _camtruth_task(self, name: str, frame_id: int, ct: Any) -> None:
        t = self.clock.now_ns()
        for ob in self.observers:
            if hasattr(ob, "on_camera_truth"):
                ob.on_camera_truth(name, frame_id, ct)
        self.rec.write_json(f"/{name}/truth", {"frame_id": frame_id, **ct.to_json()}, log_time_ns=t, publish_time_ns=t)

    def _tick_task(self, now: int, sim_ns: int) -> None:
        for ob in self.observers:
            ob.on_tick(now_ns=now, sim_time_ns=sim_ns)

    def _apply_task(self, v: VehicleRun, fl: InFlight, m: Estimate, t0p: int, t_apply: int, steps: int,
                    qpos: np.ndarray, qvel: np.ndarray) -> None:
        sim = self.sim

        def truth_now() -> GroundTruth:
            sim.load_state(steps, qpos, qvel)
            return sim.truth_snapshot(egos=(v.name,))

        for ob in self.observers:
            if hasattr(ob, "on_apply"):
                ob.on_apply(v.name, m.frame_id, truth_now)
        self._complete_task(v, fl, m, t0p, FrameStatus.OK, t_apply, steps * sim.step_ns)

    def _complete_task(self, v: VehicleRun, fl: InFlight, m: Estimate, t0p: int, status: FrameStatus,
                       t_apply: int | None = None, sim_apply: int | None = None) -> None:
        self._record_task(v, _record(v, fl, status, m, t0p, t_apply, sim_apply), m)
        self.rec.write_json(f"/{v.name}/estimate", {
            "frame_id": m.frame_id, "state": m.state.name,
            "control": {"steering_rad": m.control.steering_rad, "throttle": m.control.throttle,
                        "brake": m.control.brake},
            "objects": [{"cls": o.cls.name, "confidence": o.confidence, "box_px": list(o.box_px),
                         "position_m": list(o.position_m)} for o in m.objects],
        }, log_time_ns=t0p, publish_time_ns=t0p if m.t_reply_target_ns is None else m.t_reply_target_ns)

    def _record_task(self, v: VehicleRun, rec: PipelineRecord, estimate: Estimate | None = None) -> None:
        v.add(rec)
        for ob in self.observers:
            ob.on_record(v.name, rec, estimate)
        if rec.t0p_ns is not None and rec.status == FrameStatus.OK:
            v.e2e_window.add(rec.t0p_ns - rec.t0_ns)
        t = rec.t0p_ns or self.clock.now_ns()
        d = rec.to_json()
        d["render_worker"] = self.engine.assign[v.name]  # which render process drew it (hil trace)
        self.rec.write_json(f"/{v.name}/pipeline", d, log_time_ns=t, publish_time_ns=rec.t0_ns)

    def _sync_task(self, name: str, s: Any) -> None:
        for ob in self.observers:
            ob.on_sync(name, s)
        self.rec.write_json(f"/{name}/clock_sync", sync_sample_json(s), log_time_ns=s.t4_ns, publish_time_ns=s.t1_ns)

    def _event(self, ev: Event, log_time_ns: int | None = None) -> None:
        """An event from the loop thread, published by the analysis thread (the bus's
        one thread)."""
        self.analysis.post(self.events.publish, ev, log_time_ns)

    def _record_truth(self, gt: GroundTruth) -> None:
        t = self.clock.now_ns()
        for ob in self.observers:
            ob.on_truth(gt, t_ns=t)
        for e in gt.egos:
            if e.gap_m is not None:
                self.min_gap_m[e.vehicle] = min(self.min_gap_m.get(e.vehicle, float("inf")), e.gap_m)
        for c in gt.collisions:
            ev = Event.of(EventKind.COLLISION, t, sim_time_ns=c.sim_time_ns, extra=c.to_json(),
                          detail=f"{c.a} and {c.b} collided at {c.closing_speed_mps:.1f} m/s")
            self.collisions.append(ev.to_json())
            self.events.publish(ev)
        initial = not self._changes.seen
        self.rec.write_json("/ground_truth", {
            "sim_time_ns": gt.sim_time_ns,
            "initial": initial,  # every entity's state once, then only those that changed
            "entities": [e.to_json() for e in self._changes.changes(gt)],
            "egos": [e.to_json() for e in gt.egos],
            "collisions": [c.to_json() for c in gt.collisions],
        }, log_time_ns=t, publish_time_ns=t)
        foxglove_out.write(self.rec, gt, egos=self._ego_names, t_ns=t)

    # -- answers in ----------------------------------------------------------

    def _handle(self, r: Received) -> None:
        v = self.by_id.get(r.link_vehicle_id)
        if v is None:
            return
        m = r.msg
        if isinstance(m, Estimate):
            if r.rx_uncertainty_ns and (fl := v.in_flight.get(m.frame_id)) is not None:
                fl.t0p_uncertainty_ns = r.rx_uncertainty_ns  # its receipt stamp is known only to a span
            self._on_estimate(v, m, r.t_rx_ns)
        elif isinstance(m, ProtocolFault):
            self._on_protocol_fault(v, m, r.t_rx_ns)
        elif isinstance(m, ErrorMsg):
            self._event(Event.of(EventKind.TARGET_ERROR, r.t_rx_ns, vehicle=v.name, sim_time_ns=self._sim_ns,
                                 detail=m.message, extra={"code": m.code, "message": m.message}))
        elif isinstance(m, Command):  # the target's reply to a command: the swap, on record
            self._event(Event.of(EventKind.TARGET_COMMAND_REPLY, r.t_rx_ns, vehicle=v.name, sim_time_ns=self._sim_ns,
                                 extra={"seq": m.seq, "text": m.text, "t_target_ns": m.t_sender_ns}))
        elif isinstance(m, Heartbeat):
            pass

    def _on_protocol_fault(self, v: VehicleRun, f: ProtocolFault, t_rx: int) -> None:
        """A message the target sent could not be decoded: an event (bounded per
        vehicle, the rest counted) and an ERROR MALFORMED back (PROTOCOL.md section 8)."""
        v.protocol_faults += 1
        if v.protocol_faults <= MAX_PROTOCOL_EVENTS:
            self._event(Event.of(EventKind.PROTOCOL_ERROR, t_rx, vehicle=v.name, sim_time_ns=self._sim_ns,
                                 detail=f.detail, extra={"offset": f.offset, "t_rx_ns": t_rx}))
        try:
            v.link.send_error(ErrorCode.MALFORMED, f.detail)
        except TransportError:
            pass

    def _send_commands(self) -> None:
        """Send the configured commands whose sim time has come (each once)."""
        cmds = self.cfg.target.commands
        while self._next_command < len(cmds) and cmds[self._next_command].at_s * 1e9 <= self._sim_ns:
            c = cmds[self._next_command]
            self._next_command += 1
            for v in self.vehicles:
                if c.vehicle not in (None, v.name):
                    continue
                t = self.clock.now_ns()
                try:
                    sent = v.link.send_command(c.command)
                    ev = Event.of(EventKind.TARGET_COMMAND, t, vehicle=v.name, sim_time_ns=self._sim_ns,
                                  extra={"seq": sent.seq, "text": c.command})
                except TransportError as err:
                    ev = Event.of(EventKind.TARGET_COMMAND_FAILED, t, vehicle=v.name, sim_time_ns=self._sim_ns,
                                  detail=str(err), extra={"text": c.command})
                self._event(ev)

    def _on_estimate(self, v: VehicleRun, m: Estimate, t0p: int) -> None:
        fl = v.in_flight.pop(m.frame_id, None)
        if fl is None:
            # Already counted as dropped (late) or never sent (a confused target).
            late = m.frame_id < v.next_frame_id
            if late:
                v.late_estimates += 1
            else:
                v.unknown_estimates += 1
            self._event(Event.of(EventKind.LATE_ESTIMATE if late else EventKind.UNKNOWN_ESTIMATE, t0p,
                                 vehicle=v.name, frame_ids=(m.frame_id,), extra={"t0p_ns": t0p}))
            return
        if self.held is not None:  # lockstep latency profile: applied when sim time comes
            self._hold(v, fl, m, t0p)
            return
        self._settle(v, fl, m, t0p)

    def _settle(self, v: VehicleRun, fl: InFlight, m: Estimate, t0p: int) -> None:
        """Send an answered frame's control to the physics (its record completes when
        the physics says it applied it), or count it stale."""
        if m.frame_id <= v.last_applied_frame_id:
            self._complete(v, fl, m, t0p, FrameStatus.STALE)
            return
        v.last_applied_frame_id = m.frame_id
        c = m.control
        self._applying[(v.vehicle_id, m.frame_id)] = (v, fl, m, t0p)
        ctl = (v.vehicle_id, m.frame_id, c.steering_rad, c.throttle, c.brake)
        if self.cfg.mode == Mode.LOCKSTEP:
            self._lockstep_ctls.append(("ctl", *ctl))
        else:
            try:
                self.engine.control(*ctl)
            except (OSError, ValueError):
                self._applying.pop((v.vehicle_id, m.frame_id))
                self._complete(v, fl, m, t0p, FrameStatus.STALE)

    def _on_applied(self, vi: int, frame_id: int, t_apply: int, steps: int, qpos: np.ndarray,
                    qvel: np.ndarray) -> None:
        item = self._applying.pop((vi, frame_id), None)
        if item is None:
            return
        self.analysis.post(self._apply_task, *item, t_apply, steps, qpos, qvel)
        if not any(k[0] == vi for k in self._applying):
            for fn, *args in self._behind_apply.pop(vi, ()):
                self.analysis.post(fn, *args)

    def _complete(self, v: VehicleRun, fl: InFlight, m: Estimate, t0p: int, status: FrameStatus) -> None:
        self._post_in_order(v, self._complete_task, v, fl, m, t0p, status)

    def _post_in_order(self, v: VehicleRun, fn: Callable[..., None], *args: Any) -> None:
        """Post a record's task behind this vehicle's controls still being applied."""
        if any(k[0] == v.vehicle_id for k in self._applying):
            self._behind_apply.setdefault(v.vehicle_id, []).append((fn, *args))
        else:
            self.analysis.post(fn, *args)

    def _hold(self, v: VehicleRun, fl: InFlight, m: Estimate, t0p: int) -> None:
        assert self.held is not None and self.latency is not None
        d = self.latency.delay(v.vehicle_id, fl.frame_id)
        if d.latency_ns is None:  # the replayed run lost (or discarded) this frame: so does the replay
            self._add_record(v, _record(v, fl, d.status, m, t0p), m)
            self._event(Event.of(EventKind("replayed_" + d.status.value), fl.t0_ns, vehicle=v.name,
                                 frame_ids=(fl.frame_id,), sim_time_ns=fl.sim_time_ns), t0p)
            return
        self.held.hold(self.held.due_time(fl.sim_time_ns, d.latency_ns), v.vehicle_id, fl.frame_id, (v, fl, m, t0p))

    def _settle_held_at_end(self) -> None:
        """Controls still held when the run ends were never applied: recorded as pending."""
        if self.held is None:
            return
        for h in self.held.pop_all():
            v, fl, m, t0p = h.item  # type: ignore[misc]
            self._add_record(v, _record(v, fl, FrameStatus.PENDING, m, t0p), m)

    def _add_record(self, v: VehicleRun, rec: PipelineRecord, estimate: Estimate | None = None) -> None:
        self._post_in_order(v, self._record_task, v, rec, estimate)

    def _expire(self, now: int) -> None:
        for v in self.vehicles:
            if not v.in_flight:
                continue
            for fid in [f for f, fl in v.in_flight.items() if now - fl.t0_ns > self.timeout_ns]:
                self._drop(v, v.in_flight.pop(fid))

    def _expire_all(self) -> None:
        for v in self.vehicles:
            for fid in sorted(v.in_flight):
                self._drop(v, v.in_flight.pop(fid))

    def _drop(self, v: VehicleRun, fl: InFlight) -> None:
        """No estimate within the timeout: the record says DROPPED; the event is the
        timing analysis's ``dropped_frame`` anomaly (one event per dropped frame)."""
        self._add_record(v, _record(v, fl, FrameStatus.DROPPED))

    def _await_answers(self) -> None:
        """Lockstep: wait until nothing renders and no vehicle has a frame in flight."""
        while self._busy() and self.stop_reason is None:
            deadline = self.clock.now_ns() + self.timeout_ns
            if any(v.in_flight for v in self.vehicles):
                deadline = min(fl.t0_ns for v in self.vehicles for fl in v.in_flight.values()) + self.timeout_ns
            self._service(until_ns=deadline + 1, until_answered=True)
            if any(not v.link.alive for v in self.vehicles if v.in_flight):
                gone = next(v for v in self.vehicles if not v.link.alive)
                self.request_stop(f"target of {gone.name} is gone: {gone.link.peer_gone_reason}")
                self._expire_all()
            if not self.engine.alive():
                self.request_stop("the physics or a render process ended unexpectedly")

    def _drain(self) -> None:
        """Let the frames being rendered or in flight finish (answer or time out)."""
        deadline = self.clock.now_ns() + self.timeout_ns + 1_000_000_000
        while self._busy() and self.clock.now_ns() <= deadline:
            if not all(v.link.alive for v in self.vehicles if v.in_flight) or not self.engine.alive():
                break
            self._service(until_ns=min(deadline + 1, self.clock.now_ns() + 50_000_000), until_answered=True)
        self._expire_all()
        if self._lockstep_ctls:  # answers that came while draining a lockstep run
            ctls, self._lockstep_ctls = self._lockstep_ctls, []
            for c in ctls:
                self.engine.control(*c[1:])
        self.collect_sync()

    def collect_sync(self) -> None:
        """Record (and pass to observers) the clock-sync answers received so far."""
        for v in self.vehicles:
            for s in v.link.sync_samples():
                self.analysis.post(self._sync_task, v.name, s)


def _record(v: VehicleRun, fl: InFlight, status: FrameStatus, m: Estimate | None = None, t0p: int | None = None,
            t_apply: int | None = None, sim_apply: int | None = None) -> PipelineRecord:
    """The one place a frame's pipeline record is built."""
    if m is None:
        return PipelineRecord(v.name, fl.frame_id, fl.sim_time_ns, fl.t0_ns, fl.t_tx_ns, status,
                              t_state_ns=fl.t_state_ns)
    return PipelineRecord(v.name, fl.frame_id, fl.sim_time_ns, fl.t0_ns, fl.t_tx_ns, status,
                          m.t_rx_target_ns, m.t_infer_start_target_ns, m.t_infer_end_target_ns,
                          m.t_reply_target_ns, t0p, t_apply, sim_apply, fl.t_state_ns, fl.t0p_uncertainty_ns)
