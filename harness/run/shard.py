"""One shard of a run's vehicles: everything per vehicle between the render pool and
the physics (issue 24: per-vehicle work spreads over processes).

A :class:`VehicleShard` owns some vehicles' links and their frame ledger: it sends
each rendered frame to its target (``t_tx``), takes each estimate as the link's reader
stamped it (``t0'``), sends the control to the physics at once and completes the
frame's record when the physics confirms it (``t_apply``); records, estimates,
camera truth, images and clock-sync samples go to its analysis thread (timing
analysis, detector, recording). Its handlers run on the thread that received the
input — a render worker's pump, the physics ring's pump, a link's reader — under
the shard's lock: a frame or an estimate is handled where it arrived, with no
hand-off to another thread (issue 24, item 6). The loop that drives the shard
(``hil.harness.run.loop``) only keeps time: ticks, timeouts and lockstep's stops.

A run has one shard in its own process (``engine.shards``: auto on a machine without
cores to spare), or several, each in a process of its own
(``hil.harness.engine.shard_proc``); the code is the same.
"""

from __future__ import annotations

import functools
import threading
import time
from collections.abc import Callable
from typing import Any

from hil.adapters.link import ProtocolFault, Received
from hil.adapters.wire.messages import Command, ErrorMsg, Estimate, ImageEncoding
from hil.adapters.wire.protocol import ErrorCode
from hil.common.errors import TransportError
from hil.harness.vocab.events import Event, EventBus, EventKind
from hil.harness.config.model import Encoding, Mode, RunConfig
from hil.harness.engine.analysis_thread import AnalysisThread
from hil.harness.engine.messages import Applied, ApplyControl, CameraTruthReady, FrameReady, WorldState
from hil.harness.run.latency import HeldControls, LatencyProfile
from hil.harness.run.ledger import Answer, FrameLedger
from hil.harness.run.rig_frames import RigCam, RigNumbering, target_mode
from hil.harness.run.tasks import VehicleTasks, pipeline_record
from hil.harness.run.vehicle_state import InFlight, VehicleRun
from hil.timing.clock import Clock
from hil.timing.records import FrameStatus, PipelineRecord

MAX_PROTOCOL_EVENTS = 200  # per vehicle; beyond, counted (summary: protocol_events_unwritten)

FrameBytes = Callable[[str, int, int], bytes]     # (vehicle, slot, nbytes) -> the frame
SendControl = Callable[[ApplyControl], None]      # to the physics, now


class VehicleShard:
    """The per-vehicle work of a run for ``vehicles`` (see the module docstring).

    Args:
        egos: every ego of the run, by index (``vi``); the shard's own are ``vehicles``.
        frame_bytes: reads a rendered frame out of its shared-memory slot.
        send_control: hands an applied estimate's control to the physics (real time).
        on_stop: asks the run to end (a target gone, a transport failing), with why.
        wake: tells the loop something it may wait for happened (lockstep).
    """

    def __init__(self, cfg: RunConfig, vehicles: list[VehicleRun], *, egos: tuple[str, ...], step_ns: int,
                 cams: tuple[RigCam, ...], tasks: VehicleTasks, analysis: AnalysisThread, events: EventBus,
                 clock: Clock, frame_bytes: FrameBytes, send_control: SendControl,
                 on_stop: Callable[[str], None], wake: Callable[[], None] = lambda: None,
                 latency: LatencyProfile | None = None) -> None:
        self.cfg, self.vehicles, self.egos, self.clock = cfg, vehicles, egos, clock
        self.by_id = {v.vehicle_id: v for v in vehicles}
        self.by_name = {v.name: v for v in vehicles}
        self.step_ns = step_ns
        self.cams = cams  # the rig's cameras, camera 0 first (one: a single camera)
        self.tasks, self.analysis, self.events = tasks, analysis, events
        self._frame_bytes, self._send_control, self._on_stop, self._wake = frame_bytes, send_control, on_stop, wake
        self.lockstep = cfg.mode == Mode.LOCKSTEP
        offsets = cfg.rig_offset_steps if not self.lockstep else tuple(0 for _ in cams)  # as the physics triggers
        self.rig = {v.vehicle_id: RigNumbering(offsets, step_ns) for v in vehicles}
        self.latency = latency if self.lockstep and latency is not None else None
        self.held = None if self.latency is None else HeldControls(self.latency, step_ns=step_ns)
        self.timeout_ns = int(cfg.target.estimate_timeout_s * 1e9)
        self.frame_tolerance_ns = cfg.frame_late_tolerance_ns
        self.ledger = FrameLedger()
        self.lock = threading.Lock()
        self.stopping = False  # no more frames out (the run is ending)
        cam = cfg.camera
        self._jpeg = cam.encoding == Encoding.JPEG
        self._images = cfg.recording.images
        self._boxes = cfg.truth.visible_boxes
        self._next_command = 0
        self._next_sync_ns = 0
        # (vehicle, steps, camera) -> (frame id, the id its answer carries, camera truths
        # that answer awaits), for camera truth
        self._frame_of: dict[tuple[str, int, int], tuple[int, int, int]] = {}
        # A fused frame set's answer awaits a truth from each camera that triggers.
        self._set_truths = len(cams) - (cfg.engine.faults.drop_camera is not None)
        self._camtruth_early: list[CameraTruthReady] = []  # camera truth ahead of its world state
        self._states_complete = False  # every world state the physics will send is in
        self._sim_ns = 0  # the latest camera instant's sim time
        self._state_seen = -1

    # -- inputs (any thread) ---------------------------------------------------------

    def on_state(self, ws: WorldState) -> None:
        """A camera instant of some of this shard's egos (the render workers have it
        from the physics already): commands due, clock-sync probes, rendering noted."""
        with self.lock:
            steps = ws.steps
            self._state_seen = max(self._state_seen, steps)
            self._sim_ns = steps * self.step_ns
            mine = [vi for vi in ws.vis if vi in self.by_id]
            if not mine:
                return
            self._send_commands()
            early, self._camtruth_early = self._camtruth_early, []
            for ct in early:
                self._camera_truth(ct)
            if self.stopping:
                return
            self.ledger.capturing(steps, [(vi, k) for i, vi in enumerate(ws.vis) if vi in self.by_id
                                          and vi not in ws.unrendered for k in range(len(self.cams))
                                          if ws.cameras(i) >> k & 1])
            for vi in mine:
                v = self.by_id[vi]
                if not v.link.alive:
                    self._on_stop(f"target of {v.name} is gone: {v.link.peer_gone_reason}")
                    return
            self._maybe_sync()

    def on_frame(self, f: FrameReady) -> None:
        t_in = time.monotonic_ns()  # the pump holds it (capture -> send's parts)
        with self.lock:
            self._on_frame(f, t_in)
        if self.lockstep and not self.ledger.busy():
            self._wake()

    def on_camera_truth(self, ct: CameraTruthReady) -> None:
        with self.lock:
            self._camera_truth(ct)

    def on_applied(self, ap: Applied) -> None:
        with self.lock:
            a, lost, released = self.ledger.applied(ap.vi, ap.frame_id)
            if a is None:
                return
            for x in lost:  # applied, but when is not known: no t_apply
                self.analysis.post(self.tasks.complete, x, FrameStatus.OK)
            self.analysis.post(self.tasks.applied, a, ap.t_apply_ns, ap.steps, ap.qpos, ap.qvel)
            for fn, args in released:
                self.analysis.post(fn, *args)

    def on_received(self, r: Received) -> None:
        """What a link's reader took off the wire, stamped ``t0'`` there: handled on
        that thread (the estimate's control goes to the physics from here)."""
        v = self.by_id.get(r.link_vehicle_id)
        if v is None:
            return
        with self.lock:
            self._on_received(v, r)
        if self.lockstep and not self.ledger.busy():  # the last answer of a stop: the loop goes on
            self._wake()

    # -- the loop's side --------------------------------------------------------------

    def busy(self) -> bool:
        """Frames of this shard rendering or in flight."""
        return self.ledger.busy()

    def state_seen(self) -> int:
        return self._state_seen

    def truth_pending(self) -> int:
        """Frames sent whose camera truth (rendered after them) has not come yet."""
        return len(self._frame_of) + len(self._camtruth_early)

    def ready_at(self, step: int) -> bool:
        """Lockstep: the world state of ``step`` is in and nothing renders or flies,
        checked under the lock (``busy`` alone, read unlocked, is a hint)."""
        with self.lock:
            return self._state_seen >= step and not self.ledger.busy()

    def next_deadline_ns(self) -> int | None:
        """When the oldest frame in flight times out (None: none in flight)."""
        if not self.ledger.in_flight():
            return None
        with self.lock:
            oldest = self.ledger.oldest_t0_ns()
        return None if oldest is None else oldest + self.timeout_ns

    def expire(self, now_ns: int) -> None:
        if not self.ledger.in_flight():
            return
        with self.lock:
            for vi, fl in self.ledger.expired(now_ns, self.timeout_ns):
                self._drop(self.by_id[vi], fl)

    def expire_all(self) -> None:
        with self.lock:
            for vi, fl in self.ledger.take_all():
                self._drop(self.by_id[vi], fl)

    def gone(self) -> VehicleRun | None:
        """A vehicle with frames in flight whose target has gone, if any."""
        return next((v for v in self.vehicles if not v.link.alive and self.ledger.in_flight(v.vehicle_id)), None)

    def lockstep_stop(self, step: int) -> tuple[list[ApplyControl], int | None]:
        """Lockstep, every answer of the stop at ``step`` in: the controls to apply
        before stepping on (those answered, and the held ones due now), and the next
        held control's due sim time (ns), if any."""
        with self.lock:
            if self.held is not None:
                for h in self.held.pop_due(step * self.step_ns):
                    self._settle(h.item)  # type: ignore[arg-type]
            ctls, self.ledger.lockstep_controls = self.ledger.lockstep_controls, []
            return ctls, None if self.held is None else self.held.next_due()

    def states_complete(self) -> None:
        """The physics has finished: every world state of this shard's egos it will
        send is in (``Finished`` follows them in the ring). A camera truth of a later
        instant lost its world state on a full ring and never meets it: it and the
        frame awaiting it are forgotten, not awaited to the end of the drain."""
        with self.lock:
            self._states_complete = True
            seen = self._state_seen
            self._camtruth_early = [ct for ct in self._camtruth_early if ct.steps <= seen]
            self._frame_of = {k: v for k, v in self._frame_of.items() if k[1] <= seen}

    def begin_drain(self, deadline_ns: int) -> None:
        """The run ends: answers are awaited until ``deadline_ns`` (the loop waits here)."""

    def end_of_run(self) -> list[ApplyControl]:
        """The run ends: every frame still in flight is dropped, held controls are
        recorded as pending; returns the lockstep controls answered while draining."""
        self.expire_all()
        with self.lock:
            self.stopping = True
            if self.held is not None:
                for h in self.held.pop_all():  # never applied: pending
                    a: Answer = h.item  # type: ignore[assignment]
                    for fl in (a.fl, *a.rest):
                        self._add_record(a.v, pipeline_record(a.v, fl, FrameStatus.PENDING, a.m, a.t0p_ns), a.m)
            ctls, self.ledger.lockstep_controls = self.ledger.lockstep_controls, []
            return ctls

    def unconfirmed(self) -> None:
        """Controls the physics never confirmed (it died, or the run is over) were not
        applied: their frames are recorded as stale, and the records held behind them
        follow."""
        with self.lock:
            answers, held = self.ledger.unconfirmed()
        for a in answers:
            self.analysis.post(self.tasks.complete, a, FrameStatus.STALE)
        for fn, args in held:
            self.analysis.post(fn, *args)

    def tick(self, now_ns: int) -> None:
        self.analysis.post(self.tasks.tick, now_ns, self._sim_ns)
        self.collect_sync()

    def collect_sync(self) -> None:
        """Record (and pass to observers) the clock-sync answers received so far."""
        for v in self.vehicles:
            for s in v.link.sync_samples():
                self.analysis.post(self.tasks.sync, v.name, s)

    # -- frames out (under the lock) ------------------------------------------------------

    def _on_frame(self, f: FrameReady, t_in: int) -> None:
        v = self.by_name[f.vehicle]
        try:
            self._send(v, f, t_in)
        finally:
            # Rendering ends once the frame is in flight (or not sent): the shard is
            # never seen idle in between, by a loop that reads ``busy`` unlocked.
            self.ledger.rendered(v.vehicle_id, f.steps, f.camera)

    def _send(self, v: VehicleRun, f: FrameReady, t_in: int) -> None:
        if self.stopping:
            return
        t_locked = time.monotonic_ns()
        rig = self._rig(v)
        at, v.next_frame_id = rig.number(v.next_frame_id, f.steps, f.camera)
        if at is None:  # another camera of a rig this target does not take
            return
        data = self._frame_bytes(f.vehicle, f.slot, f.nbytes)
        cam = self.cams[f.camera]
        frame_id = at.frame_id
        if self._boxes:  # a fused set's cameras are judged together, as its answer's (the set id)
            fused = rig.answers_sets()
            self._frame_of[(f.vehicle, f.steps, f.camera)] = (
                frame_id, frame_id - at.camera_index if fused else frame_id, self._set_truths if fused else 1)
        try:
            t_tx = v.link.send_frame(frame_id=frame_id, sim_time_ns=at.sim_time_ns, t0_ns=f.t0_ns, width=cam.width,
                                     height=cam.height, encoding=ImageEncoding(f.encoding), camera=cam.info,
                                     ego_speed_mps=f.speed_mps, data=data, camera_index=at.camera_index,
                                     camera_count=at.camera_count)
        except TransportError as err:
            self._on_stop(f"target of {v.name} is gone: {err}")
            return
        self.ledger.sent(v.vehicle_id, InFlight(frame_id, at.sim_time_ns, f.t0_ns, t_tx, f.t_state_ns,
                                                camera=f.camera if rig.sends_sets() else None))
        v.frame_out(t_tx - f.t_state_ns, tolerance_ns=self.frame_tolerance_ns,
                    parts=(f.t_encoded_ns - f.t0_ns, t_in - f.t_encoded_ns, t_locked - t_in, t_tx - t_locked))
        if f.camera == 0:
            v.fps_meter.add(f.t0_ns)
        if self._images:  # camera 0 on the vehicle's /camera, a rig's others on /camera/<name>
            self.analysis.post(functools.partial(self.tasks.image, v.name, data, f.t0_ns, jpeg=self._jpeg,
                                                 width=cam.width, height=cam.height,
                                                 camera=cam.name if f.camera else None))

    def _rig(self, v: VehicleRun) -> RigNumbering:
        """The vehicle's frame numbering, knowing how its target takes a rig (its
        HELLO); a rig of several cameras to a target that takes one is said once."""
        rig = self.rig[v.vehicle_id]
        if rig.mode is None:
            rig.mode = target_mode(v.link.hello.capabilities if v.link.hello is not None else 0)
            if len(self.cams) > 1 and not rig.sends_sets():
                self._event(Event.of(EventKind.RIG_CAMERA_ZERO_ONLY, self.clock.now_ns(), vehicle=v.name,
                                     sim_time_ns=self._sim_ns, detail=f"the target of {v.name} did not announce "
                                     f"CAP_CAMERAS: it gets camera 0 ({self.cams[0].name}) only, as a single camera",
                                     extra={"cameras": len(self.cams)}))
        return rig

    def _camera_truth(self, ct: CameraTruthReady) -> None:
        """Camera truth goes to the analysis after its instant's ground truth (the
        render worker's pipe may overtake the physics's ring); that of a camera whose
        frame this target does not get is dropped."""
        if ct.steps > self._state_seen:
            if self._states_complete:  # its world state was lost: never judged
                self._frame_of.pop((ct.vehicle, ct.steps, ct.camera), None)
            else:
                self._camtruth_early.append(ct)
            return
        sent = self._frame_of.pop((ct.vehicle, ct.steps, ct.camera), None)
        if sent is None:
            return
        frame_id, answer_id, truths = sent
        self.analysis.post(functools.partial(self.tasks.camera_truth, ct.vehicle, frame_id, ct.truth,
                                             camera=self.cams[ct.camera].name if ct.camera else None,
                                             answer_id=answer_id, truths=truths))

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

    def _event(self, ev: Event, log_time_ns: int | None = None) -> None:
        """An event found here, published by the analysis thread (the bus's one thread)."""
        self.analysis.post(self.events.publish, ev, log_time_ns)

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

    # -- answers in (under the lock) --------------------------------------------------------

    def _on_received(self, v: VehicleRun, r: Received) -> None:
        m = r.msg
        match m:
            case Estimate():
                if r.rx_uncertainty_ns:  # its receipt stamp is known only to a span
                    self.ledger.receipt_uncertainty(v.vehicle_id, m.frame_id, r.rx_uncertainty_ns)
                self._on_estimate(v, m, r.t_rx_ns)
            case ProtocolFault():
                self._on_protocol_fault(v, m, r.t_rx_ns)
            case ErrorMsg():
                self._event(Event.of(EventKind.TARGET_ERROR, r.t_rx_ns, vehicle=v.name, sim_time_ns=self._sim_ns,
                                     detail=m.message, extra={"code": m.code, "message": m.message}))
            case Command():  # the target's reply to a command: the swap, on record
                self._event(Event.of(EventKind.TARGET_COMMAND_REPLY, r.t_rx_ns, vehicle=v.name,
                                     sim_time_ns=self._sim_ns,
                                     extra={"seq": m.seq, "text": m.text, "t_target_ns": m.t_sender_ns}))

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

    def _on_estimate(self, v: VehicleRun, m: Estimate, t0p: int) -> None:
        rig = self.rig[v.vehicle_id]
        rest: tuple[InFlight, ...] = ()
        if rig.answers_sets():  # one ESTIMATE answers every frame of its set
            fls = self.ledger.answer_set(v.vehicle_id, m.frame_id, rig.cameras)
            fl, rest = (fls[0], tuple(fls[1:])) if fls else (None, ())
        else:
            fl = self.ledger.answer(v.vehicle_id, m.frame_id)
        if fl is None:
            # Already counted as dropped (late) or never sent (a confused target).
            late = m.frame_id < v.next_frame_id
            if late:
                v.late_estimates += 1
            else:
                v.unknown_estimates += 1
            why = (f"an ESTIMATE for frame {m.frame_id}, already settled: dropped after target.estimate_timeout_s, "
                   "stale, or answered before (a second answer)" if late else
                   f"an ESTIMATE for frame {m.frame_id}, which was never sent (the newest sent is "
                   f"{v.next_frame_id - 1})")
            self._event(Event.of(EventKind.LATE_ESTIMATE if late else EventKind.UNKNOWN_ESTIMATE, t0p,
                                 vehicle=v.name, frame_ids=(m.frame_id,), detail=why, extra={"t0p_ns": t0p}))
            return
        a = Answer(v, fl, m, t0p, rest)
        if self.held is not None:  # lockstep latency profile: applied when sim time comes
            self._hold(a)
            return
        self._settle(a)

    def _settle(self, a: Answer) -> None:
        """Send an answered frame's control to the physics (its record completes when
        the physics says it applied it), or count it stale."""
        ledger = self.ledger
        if not ledger.apply(a):
            self._post_in_order(a.v, self.tasks.complete, a, FrameStatus.STALE)
            return
        c = a.m.control
        ctl = ApplyControl(a.v.vehicle_id, a.m.frame_id, c.steering_rad, c.throttle, c.brake)
        if self.lockstep:
            ledger.lockstep_controls.append(ctl)
            return
        try:
            self._send_control(ctl)
        except (OSError, ValueError):
            ledger.cancel(ctl.vi, ctl.frame_id)
            self._post_in_order(a.v, self.tasks.complete, a, FrameStatus.STALE)

    def _post_in_order(self, v: VehicleRun, fn: Callable[..., None], *args: Any) -> None:
        """Post a record's task behind this vehicle's controls still being applied."""
        if not self.ledger.hold(v.vehicle_id, (fn, args)):
            self.analysis.post(fn, *args)

    def _hold(self, a: Answer) -> None:
        assert self.held is not None and self.latency is not None
        v, fl = a.v, a.fl
        d = self.latency.delay(v.vehicle_id, fl.frame_id, camera=fl.camera,  # lockstep: a set's one instant
                               frame_set=fl.sim_time_ns // (self.step_ns * self.cfg.camera_period_steps))
        if d.latency_ns is None:  # the replayed run lost (or discarded) this frame: so does the replay
            for x in (fl, *a.rest):
                self._add_record(v, pipeline_record(v, x, d.status, a.m, a.t0p_ns), a.m)
            self._event(Event.of(EventKind("replayed_" + d.status.value), fl.t0_ns, vehicle=v.name,
                                 frame_ids=(fl.frame_id,), sim_time_ns=fl.sim_time_ns), a.t0p_ns)
            return
        self.held.hold(self.held.due_time(fl.sim_time_ns, d.latency_ns), v.vehicle_id, fl.frame_id, a)

    def _add_record(self, v: VehicleRun, rec: PipelineRecord, estimate: Estimate | None = None) -> None:
        self._post_in_order(v, self.tasks.record, v, rec, estimate)

    def _drop(self, v: VehicleRun, fl: InFlight) -> None:
        """No estimate within the timeout: the record says DROPPED; the event is the
        timing analysis's ``dropped_frame`` anomaly (one event per dropped frame)."""
        self._add_record(v, pipeline_record(v, fl, FrameStatus.DROPPED))
