"""The simulator loop: step physics, capture and send frames, apply estimates.

Real-time mode paces physics to the harness clock at ``realtime_factor`` and never
waits for a target: an estimate is applied the moment it arrives, between physics
steps, so latency has physical consequences. A physics step that runs more than
``LATE_TOLERANCE_NS`` after its due time is counted as late (as a real-time test
system counts late iterations); the summary says when real time was not kept.

Lockstep mode waits at each camera tick for every vehicle's estimate (or its
timeout, a drop) before stepping on: deterministic, for regression and replay.
With a latency profile (``harness.latency``) each control is held and applied when
sim time reaches its capture time plus the frame's latency.

Ground truth goes to ``/ground_truth`` at every camera tick (every entity's state
the first time, then the entities that changed; ego truth; collisions) and, with
``truth.visible_boxes``, to ``/<vehicle>/truth`` (the camera's visible boxes from a
segmentation render, after the frames are sent so it adds no capture latency).
"""

from __future__ import annotations

import math
import gc
import queue
from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np

from adapters.link import Received
from adapters.messages import CameraInfo, Command, ErrorMsg, Estimate, Heartbeat, ImageEncoding
from harness import foxglove_out
from harness.channels import sync_sample_json
from harness.config import CameraConfig, Encoding, Mode, RunConfig
from harness.latency import HeldControls, LatencyProfile
from harness.observers import RunObserver
from harness.recorder import Recorder
from harness.vehicle_state import InFlight, VehicleRun
from scenarios.ground_truth import GroundTruth, StateChanges
from scenarios.sim import Simulation
from timing.clock import MonotonicClock
from timing.errors import TransportError
from timing.records import FrameStatus, PipelineRecord

LATE_TOLERANCE_NS = 10_000_000


def encode_image(rgb: np.ndarray, camera: CameraConfig) -> tuple[bytes, ImageEncoding]:
    """An RGB8 render as the wire carries it: JPEG at the configured quality, or raw."""
    if camera.encoding == Encoding.JPEG:
        ok, buf = cv2.imencode(".jpg", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR),
                               (cv2.IMWRITE_JPEG_QUALITY, camera.jpeg_quality))
        if not ok:  # pragma: no cover - OpenCV failing to encode a valid array
            raise RuntimeError("JPEG encoding failed")
        return buf.tobytes(), ImageEncoding.JPEG
    return rgb.tobytes(), ImageEncoding.RGB8


@dataclass
class LoopStats:
    wall_start_ns: int = 0
    wall_end_ns: int = 0
    sim_steps: int = 0
    late_steps: int = 0
    max_lateness_ns: int = 0
    ended_by: str = "duration"


class SimLoop:
    """Runs one configured simulation against its vehicles' links."""

    def __init__(self, cfg: RunConfig, sim: Simulation, vehicles: list[VehicleRun],
                 rx: queue.Queue[Received], recorder: Recorder, clock: MonotonicClock,
                 *, on_tick: Callable[[], None] | None = None, latency: LatencyProfile | None = None) -> None:
        self.cfg, self.sim, self.vehicles, self.rx, self.rec, self.clock = cfg, sim, vehicles, rx, recorder, clock
        self.by_id = {v.vehicle_id: v for v in vehicles}
        self.stats = LoopStats()
        self.stop_reason: str | None = None
        self.on_tick = on_tick
        self.timeout_ns = int(cfg.target.estimate_timeout_s * 1e9)
        self.period = cfg.camera_period_steps
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

    def request_stop(self, reason: str) -> None:
        """Ask the loop to end after the current step (signal handlers call this)."""
        if self.stop_reason is None:
            self.stop_reason = reason

    # -- main loop -----------------------------------------------------------

    def run(self) -> LoopStats:
        """Run to the configured duration (or a stop request); returns the loop's stats.

        Python's full (generation 2) garbage collection is held off during the loop
        and everything allocated before it is frozen: a full collection over a run's
        growing history stalled the loop for 60-80 ms (measured); with it held off
        the worst physics-step lateness fell to ~24 ms. It is restored afterwards.
        """
        thresholds = gc.get_threshold()
        gc.collect()
        gc.freeze()
        gc.set_threshold(thresholds[0], thresholds[1], 1_000_000)
        try:
            return self._run()
        finally:
            gc.set_threshold(*thresholds)
            gc.unfreeze()

    def _run(self) -> LoopStats:
        total_steps = round(self.cfg.duration_s * 1e9 / self.sim.step_ns)
        wall_per_step = self.sim.step_ns / self.cfg.realtime_factor
        lockstep = self.cfg.mode == Mode.LOCKSTEP
        st = self.stats
        st.wall_start_ns = self.clock.now_ns()
        self._next_sync_ns = st.wall_start_ns
        try:
            while self.sim.steps < total_steps and self.stop_reason is None:
                if not lockstep:
                    due = st.wall_start_ns + int(self.sim.steps * wall_per_step)
                    now = self.clock.now_ns()
                    if now < due:
                        self._service(until_ns=due)
                        continue
                    lateness = now - due
                    st.max_lateness_ns = max(st.max_lateness_ns, lateness)
                    if lateness > LATE_TOLERANCE_NS:
                        st.late_steps += 1
                if self.sim.steps % self.period == 0:
                    self._send_commands()
                    self._capture_all()
                    if lockstep:
                        self._await_answers()
                if self.held is not None:
                    for h in self.held.pop_due(self.sim.sim_time_ns):
                        self._settle(*h.item)  # type: ignore[misc]
                self.sim.step()
                self._service(until_ns=0)
                if self.observers:
                    now_ns, sim_ns = self.clock.now_ns(), self.sim.sim_time_ns
                    for ob in self.observers:
                        ob.on_tick(now_ns=now_ns, sim_time_ns=sim_ns)
                if self.on_tick is not None:
                    self.on_tick()
            # Let the frames in flight finish (answer or time out): nothing unaccounted.
            self._drain()
            self._settle_held_at_end()
        except KeyboardInterrupt:
            self.request_stop("interrupted (Ctrl-C)")
            self._expire_all()
        st.sim_steps = self.sim.steps
        st.wall_end_ns = self.clock.now_ns()
        if self.stop_reason is not None:
            st.ended_by = self.stop_reason
        return st

    # -- frames out ----------------------------------------------------------

    def _capture_all(self) -> None:
        gt = self.sim.ground_truth()
        self._record_truth(gt)
        for v in self.vehicles:
            if not v.link.alive:
                self.request_stop(f"target of {v.name} is gone: {v.link.peer_gone_reason}")
                return
            rgb = self.sim.render(v.name)
            t0 = self.clock.now_ns()
            data, enc = encode_image(rgb, self.cfg.camera)
            frame_id = v.next_frame_id
            v.next_frame_id += 1
            try:
                t_tx = v.link.send_frame(frame_id=frame_id, sim_time_ns=self.sim.sim_time_ns, t0_ns=t0,
                                         width=rgb.shape[1], height=rgb.shape[0], encoding=enc,
                                         camera=self.camera_info, ego_speed_mps=self.sim.speed_mps(v.name),
                                         data=data)
            except TransportError as err:
                self.request_stop(f"target of {v.name} is gone: {err}")
                return
            v.in_flight[frame_id] = InFlight(frame_id, self.sim.sim_time_ns, t0, t_tx)
            v.fps_meter.add(t0)
            if self.cfg.recording.images:
                topic = f"/{v.name}/camera"
                if enc == ImageEncoding.JPEG:
                    self.rec.write_image(topic, data, fmt="jpeg", frame_id=f"{v.name}/camera",
                                         log_time_ns=t0, publish_time_ns=t0)
                else:
                    self.rec.write_raw_image(topic, rgb, encoding="rgb8", frame_id=f"{v.name}/camera",
                                             log_time_ns=t0, publish_time_ns=t0)
        if self.cfg.truth.visible_boxes:
            self._record_camera_truth()
        now = self.clock.now_ns()
        if now >= self._next_sync_ns:
            sync = self.cfg.timing.sync
            self._next_sync_ns = now + int(sync.interval_s * 1e9)
            for v in self.vehicles:
                try:
                    for _ in range(sync.burst):  # the clock filter keeps the fastest
                        v.link.send_sync_request()
                except TransportError:
                    pass

    def _record_truth(self, gt: GroundTruth) -> None:
        t = self.clock.now_ns()
        for ob in self.observers:
            ob.on_truth(gt, t_ns=t)
        for e in gt.egos:
            if e.gap_m is not None:
                self.min_gap_m[e.vehicle] = min(self.min_gap_m.get(e.vehicle, float("inf")), e.gap_m)
        for c in gt.collisions:
            ev = {"kind": "collision", **c.to_json()}
            self.collisions.append(ev)
            self.rec.write_json("/events", ev, log_time_ns=t, publish_time_ns=t)
        initial = not self._changes.seen
        self.rec.write_json("/ground_truth", {
            "sim_time_ns": gt.sim_time_ns,
            "initial": initial,  # every entity's state once, then only those that changed
            "entities": [e.to_json() for e in self._changes.changes(gt)],
            "egos": [e.to_json() for e in gt.egos],
            "collisions": [c.to_json() for c in gt.collisions],
        }, log_time_ns=t, publish_time_ns=t)
        foxglove_out.write(self.rec, gt, egos=self._ego_names, t_ns=t)

    def _record_camera_truth(self) -> None:
        """Per camera: the entities it shows (segmentation render), for the frame just sent."""
        for v in self.vehicles:
            ct = self.sim.camera_truth(v.name, min_visible_px=self.cfg.truth.min_visible_px)
            t = self.clock.now_ns()
            for ob in self.observers:
                if hasattr(ob, "on_camera_truth"):
                    ob.on_camera_truth(v.name, v.next_frame_id - 1, ct)
            self.rec.write_json(f"/{v.name}/truth", {"frame_id": v.next_frame_id - 1, **ct.to_json()},
                                log_time_ns=t, publish_time_ns=t)

    # -- answers in ----------------------------------------------------------

    def _service(self, *, until_ns: int, until_answered: bool = False) -> None:
        """Handle received messages until ``until_ns`` (0: only what is waiting), or,
        with ``until_answered``, as soon as no frame is in flight any more."""
        while True:
            now = self.clock.now_ns()
            self._expire(now)
            timeout_s = max(0.0, (until_ns - now) / 1e9)
            try:
                r = self.rx.get(timeout=timeout_s) if timeout_s > 0 else self.rx.get_nowait()
            except queue.Empty:
                self.collect_sync()
                return
            self._handle(r)
            if until_answered and not any(v.in_flight for v in self.vehicles):
                self.collect_sync()
                return

    def _handle(self, r: Received) -> None:
        v = self.by_id.get(r.link_vehicle_id)
        if v is None:
            return
        m = r.msg
        if isinstance(m, Estimate):
            self._on_estimate(v, m, r.t_rx_ns)
        elif isinstance(m, ErrorMsg):
            ev = {"kind": "target_error", "vehicle": v.name, "code": m.code, "message": m.message}
            self.rec.write_json("/events", ev, log_time_ns=r.t_rx_ns, publish_time_ns=r.t_rx_ns)
        elif isinstance(m, Command):  # the target's reply to a command: the swap, on record
            ev = {"kind": "target_command_reply", "vehicle": v.name, "seq": m.seq, "text": m.text,
                  "t_target_ns": m.t_sender_ns}
            self.rec.write_json("/events", ev, log_time_ns=r.t_rx_ns, publish_time_ns=r.t_rx_ns)
        elif isinstance(m, Heartbeat):
            pass

    def _send_commands(self) -> None:
        """Send the configured commands whose sim time has come (each once)."""
        cmds = self.cfg.target.commands
        while self._next_command < len(cmds) and cmds[self._next_command].at_s * 1e9 <= self.sim.sim_time_ns:
            c = cmds[self._next_command]
            self._next_command += 1
            for v in self.vehicles:
                if c.vehicle not in (None, v.name):
                    continue
                t = self.clock.now_ns()
                try:
                    sent = v.link.send_command(c.command)
                    ev = {"kind": "target_command", "vehicle": v.name, "seq": sent.seq, "text": c.command,
                          "sim_time_ns": self.sim.sim_time_ns}
                except TransportError as err:
                    ev = {"kind": "target_command_failed", "vehicle": v.name, "text": c.command,
                          "detail": str(err), "sim_time_ns": self.sim.sim_time_ns}
                self.rec.write_json("/events", ev, log_time_ns=t, publish_time_ns=t)

    def _on_estimate(self, v: VehicleRun, m: Estimate, t0p: int) -> None:
        fl = v.in_flight.pop(m.frame_id, None)
        if fl is None:
            # Already counted as dropped (late) or never sent (a confused target).
            if m.frame_id < v.next_frame_id:
                v.late_estimates += 1
            else:
                v.unknown_estimates += 1
            ev = {"kind": "late_estimate" if m.frame_id < v.next_frame_id else "unknown_estimate",
                  "vehicle": v.name, "frame_id": m.frame_id, "t0p_ns": t0p}
            self.rec.write_json("/events", ev, log_time_ns=t0p, publish_time_ns=t0p)
            return
        if self.held is not None:  # lockstep latency profile: applied when sim time comes
            self._hold(v, fl, m, t0p)
            return
        self._settle(v, fl, m, t0p)

    def _settle(self, v: VehicleRun, fl: InFlight, m: Estimate, t0p: int) -> None:
        """Apply an answered frame's control now (or count it stale) and record it."""
        t_apply: int | None = None
        sim_apply: int | None = None
        if m.frame_id > v.last_applied_frame_id:
            c = m.control
            self.sim.set_control(v.name, steering_rad=c.steering_rad, throttle=c.throttle, brake=c.brake)
            t_apply = self.clock.now_ns()
            sim_apply = self.sim.sim_time_ns
            v.last_applied_frame_id = m.frame_id
            status = FrameStatus.OK
            for ob in self.observers:
                if hasattr(ob, "on_apply"):
                    ob.on_apply(v.name, m.frame_id, self.sim.truth_snapshot)
        else:
            status = FrameStatus.STALE
        rec = PipelineRecord(v.name, fl.frame_id, fl.sim_time_ns, fl.t0_ns, fl.t_tx_ns, status,
                             m.t_rx_target_ns, m.t_infer_start_target_ns, m.t_infer_end_target_ns,
                             m.t_reply_target_ns, t0p, t_apply, sim_apply)
        self._add_record(v, rec, m)
        self.rec.write_json(f"/{v.name}/estimate", {
            "frame_id": m.frame_id, "state": m.state.name,
            "control": {"steering_rad": m.control.steering_rad, "throttle": m.control.throttle,
                        "brake": m.control.brake},
            "objects": [{"cls": o.cls.name, "confidence": o.confidence, "box_px": list(o.box_px),
                         "position_m": list(o.position_m)} for o in m.objects],
        }, log_time_ns=t0p, publish_time_ns=m.t_reply_target_ns)

    def _hold(self, v: VehicleRun, fl: InFlight, m: Estimate, t0p: int) -> None:
        assert self.held is not None and self.latency is not None
        d = self.latency.delay(v.vehicle_id, fl.frame_id)
        if d.latency_ns is None:  # the replayed run lost (or discarded) this frame: so does the replay
            self._add_record(v, PipelineRecord(v.name, fl.frame_id, fl.sim_time_ns, fl.t0_ns, fl.t_tx_ns, d.status,
                                               m.t_rx_target_ns, m.t_infer_start_target_ns, m.t_infer_end_target_ns,
                                               m.t_reply_target_ns, t0p), m)
            ev = {"kind": "replayed_" + d.status.value, "vehicle": v.name, "frame_id": fl.frame_id}
            self.rec.write_json("/events", ev, log_time_ns=t0p, publish_time_ns=fl.t0_ns)
            return
        self.held.hold(self.held.due_time(fl.sim_time_ns, d.latency_ns), v.vehicle_id, fl.frame_id, (v, fl, m, t0p))

    def _settle_held_at_end(self) -> None:
        """Controls still held when the run ends were never applied: recorded as pending."""
        if self.held is None:
            return
        for h in self.held.pop_all():
            v, fl, m, t0p = h.item  # type: ignore[misc]
            self._add_record(v, PipelineRecord(v.name, fl.frame_id, fl.sim_time_ns, fl.t0_ns, fl.t_tx_ns,
                                               FrameStatus.PENDING, m.t_rx_target_ns, m.t_infer_start_target_ns,
                                               m.t_infer_end_target_ns, m.t_reply_target_ns, t0p), m)

    def _add_record(self, v: VehicleRun, rec: PipelineRecord, estimate: Estimate | None = None) -> None:
        v.add(rec)
        for ob in self.observers:
            ob.on_record(v.name, rec, estimate)
        if rec.t0p_ns is not None and rec.status == FrameStatus.OK:
            v.e2e_window.add(rec.t0p_ns - rec.t0_ns)
        t = rec.t0p_ns or self.clock.now_ns()
        self.rec.write_json(f"/{v.name}/pipeline", rec.to_json(), log_time_ns=t, publish_time_ns=rec.t0_ns)

    def _expire(self, now: int) -> None:
        for v in self.vehicles:
            if not v.in_flight:
                continue
            for fid in [f for f, fl in v.in_flight.items() if now - fl.t0_ns > self.timeout_ns]:
                self._drop(v, v.in_flight.pop(fid), now)

    def _expire_all(self) -> None:
        now = self.clock.now_ns()
        for v in self.vehicles:
            for fid in sorted(v.in_flight):
                self._drop(v, v.in_flight.pop(fid), now)

    def _drop(self, v: VehicleRun, fl: InFlight, now: int) -> None:
        self._add_record(v, PipelineRecord(v.name, fl.frame_id, fl.sim_time_ns, fl.t0_ns, fl.t_tx_ns,
                                           FrameStatus.DROPPED))
        ev = {"kind": "dropped_frame", "vehicle": v.name, "frame_id": fl.frame_id,
              "timeout_ms": self.timeout_ns / 1e6}
        self.rec.write_json("/events", ev, log_time_ns=now, publish_time_ns=fl.t0_ns)

    def _await_answers(self) -> None:
        """Lockstep: wait until no vehicle has a frame in flight."""
        while any(v.in_flight for v in self.vehicles) and self.stop_reason is None:
            deadline = min(fl.t0_ns for v in self.vehicles for fl in v.in_flight.values()) + self.timeout_ns
            self._service(until_ns=deadline + 1, until_answered=True)
            if any(not v.link.alive for v in self.vehicles if v.in_flight):
                gone = next(v for v in self.vehicles if not v.link.alive)
                self.request_stop(f"target of {gone.name} is gone: {gone.link.peer_gone_reason}")
                self._expire_all()

    def _drain(self) -> None:
        if any(v.in_flight for v in self.vehicles):
            deadline = max(fl.t0_ns for v in self.vehicles for fl in v.in_flight.values()) + self.timeout_ns
            while any(v.in_flight for v in self.vehicles) and self.clock.now_ns() <= deadline:
                if not all(v.link.alive for v in self.vehicles if v.in_flight):
                    break
                self._service(until_ns=min(deadline + 1, self.clock.now_ns() + 50_000_000))
        self._expire_all()
        self.collect_sync()

    def collect_sync(self) -> None:
        """Record (and pass to observers) the clock-sync answers received so far."""
        for v in self.vehicles:
            for s in v.link.sync_samples():
                for ob in self.observers:
                    ob.on_sync(v.name, s)
                self.rec.write_json(f"/{v.name}/clock_sync", sync_sample_json(s), log_time_ns=s.t4_ns,
                                    publish_time_ns=s.t1_ns)
