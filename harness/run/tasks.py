"""The run's analysis-thread work: ground truth, observers and recording.

The loop thread (``hil.harness.run.loop``) moves world states, frames, estimates and
controls; everything slower runs here, posted to the analysis thread
(``hil.harness.engine.analysis_thread``) in order: the mirror world's ground truth at each
camera instant (``/ground_truth`` and the Foxglove scene, collisions as events), each
frame's settled pipeline record, its estimate, its camera truth and images, the
clock-sync samples, and the observers' hooks (timing analysis, detector).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from hil.adapters.wire.messages import Estimate
from hil.harness.vocab.events import Event, EventBus, EventKind
from hil.harness.vocab.observers import RunObserver
from hil.harness.record import foxglove_out
from hil.harness.record.channels import sync_sample_json
from hil.harness.record.rig_views import camera_topic, truth_topic
from hil.harness.run.ledger import Answer
from hil.harness.run.vehicle_state import InFlight, VehicleRun
from hil.scenarios.ground_truth import GroundTruth, StateChanges
from hil.scenarios.sim import Simulation
from hil.timing.clock import Clock
from hil.timing.records import FrameStatus, PipelineRecord


def pipeline_record(v: VehicleRun, fl: InFlight, status: FrameStatus, m: Estimate | None = None,
                    t0p: int | None = None, t_apply: int | None = None,
                    sim_apply: int | None = None) -> PipelineRecord:
    """The one place a frame's pipeline record is built."""
    if m is None:
        return PipelineRecord(v.name, fl.frame_id, fl.sim_time_ns, fl.t0_ns, fl.t_tx_ns, status,
                              t_state_ns=fl.t_state_ns, camera=fl.camera)
    return PipelineRecord(v.name, fl.frame_id, fl.sim_time_ns, fl.t0_ns, fl.t_tx_ns, status,
                          m.t_rx_target_ns, m.t_infer_start_target_ns, m.t_infer_end_target_ns,
                          m.t_reply_target_ns, t0p, t_apply, sim_apply, fl.t_state_ns, fl.t0p_uncertainty_ns,
                          fl.camera)


def estimate_json(m: Estimate) -> dict[str, Any]:
    """The ``/<vehicle>/estimate`` message; an object's ``camera`` (the rig camera its
    box is in) only where it is not 0."""
    c = m.control
    return {"frame_id": m.frame_id, "state": m.state.name,
            "control": {"steering_rad": c.steering_rad, "throttle": c.throttle, "brake": c.brake},
            "objects": [{"cls": o.cls.name, "confidence": o.confidence, "box_px": list(o.box_px),
                         "position_m": list(o.position_m), **({"camera": o.camera} if o.camera else {})}
                        for o in m.objects]}


class TruthCache:
    """The latest camera instant's ground truth, by step. In lockstep the physics
    applies a stop's controls in the world of that stop, so the truth at ``t_apply``
    is the one just taken: taken once, not again for every vehicle. (Analysis thread
    only.)"""

    def __init__(self) -> None:
        self.steps = -1
        self.gt: GroundTruth | None = None

    def take(self, sim: Simulation, steps: int, qpos: np.ndarray, qvel: np.ndarray, collisions: tuple[Any, ...],
             names: tuple[str, ...]) -> GroundTruth:
        """The ground truth of a camera instant (``names``: its capturing egos), taken
        on the mirror ``sim`` and kept."""
        sim.load_state(steps, qpos, qvel)
        if collisions:
            sim.add_collisions(list(collisions))
        gt = sim.ground_truth(egos=names)
        self.steps, self.gt = steps, gt
        return gt

    def get(self, steps: int, vehicle: str) -> GroundTruth | None:
        gt = self.gt
        if gt is None or steps != self.steps or not any(e.vehicle == vehicle for e in gt.egos):
            return None
        return GroundTruth(gt.sim_time_ns, gt.entities, gt.egos, ())


class WorldTasks:
    """The analysis thread's work on the whole world: the ground truth of every camera
    instant (``/ground_truth``, the Foxglove scene, collisions as events, the egos'
    smallest gaps) and the final state. ``sim`` is this process's mirror of the world
    (the summary's final state is taken from it); ``observers`` get each ground truth
    (those of a shard in this process; a shard in its own process takes its own).

    The Foxglove views of the world (``/scene``, ``/tf``) are drawn at most once per
    ``view_every_ns`` of simulated time (the camera period; 0: every instant), and at
    every collision: vehicles whose cameras trigger at different instants made them
    N per camera period, the run process's largest per-frame cost at 64 vehicles
    (~0.6 ms of ~0.85 an instant); ``/ground_truth`` keeps every instant."""

    def __init__(self, sim: Simulation, rec: Any, events: EventBus, clock: Clock, *, egos: set[str],
                 observers: list[RunObserver], cache: TruthCache | None = None, view_every_ns: int = 0) -> None:
        self.sim, self.rec, self.events, self.clock = sim, rec, events, clock
        self.view_every_ns = view_every_ns
        self._next_view_ns = 0
        self.observers = observers
        self.cache = cache if cache is not None else TruthCache()
        self.collisions: list[dict[str, object]] = []
        self.min_gap_m: dict[str, float] = {}
        self._egos = egos
        self._changes = StateChanges()

    def truth(self, steps: int, qpos: np.ndarray, qvel: np.ndarray, collisions: tuple[Any, ...],
              names: tuple[str, ...]) -> None:
        self._record_truth(self.cache.take(self.sim, steps, qpos, qvel, collisions, names))

    def final_state(self, steps: int, qpos: np.ndarray, qvel: np.ndarray, collisions: tuple[Any, ...]) -> None:
        """The mirror takes the final state (the summary reads it); collisions since
        the last camera instant are recorded."""
        self.sim.load_state(steps, qpos, qvel)
        if collisions:
            self.sim.add_collisions(list(collisions))
            self._record_truth(self.sim.ground_truth(egos=()))

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
            "entities": self._changes.changes_json(gt),
            "egos": [e.to_json() for e in gt.egos],
            "collisions": [c.to_json() for c in gt.collisions],
        }, log_time_ns=t, publish_time_ns=t)
        if gt.collisions or gt.sim_time_ns >= self._next_view_ns:
            foxglove_out.write(self.rec, gt, egos=self._egos, t_ns=t)
            self._next_view_ns = gt.sim_time_ns + self.view_every_ns



class VehicleTasks:
    """The analysis thread's work on a shard's vehicles: each frame's settled record,
    its estimate, camera truth and image, the clock-sync samples, and the observers'
    hooks (timing analysis, detector). ``sim``: a mirror of the world for the truth at
    ``t_apply`` (and, in a shard's own process, at its egos' camera instants)."""

    def __init__(self, sim: Simulation, rec: Any, clock: Clock, *, cache: TruthCache | None = None,
                 render_worker: dict[str, int] | None = None) -> None:
        self.sim, self.rec, self.clock = sim, rec, clock
        self.observers: list[RunObserver] = []
        self.cache = cache if cache is not None else TruthCache()
        self.render_worker = render_worker or {}  # vehicle -> the render worker that draws its camera

    def truth(self, steps: int, qpos: np.ndarray, qvel: np.ndarray, collisions: tuple[Any, ...],
              names: tuple[str, ...]) -> None:
        """A camera instant of this shard's egos, for its observers (a shard in its own
        process; in the run process they get the world's ground truth)."""
        gt = self.cache.take(self.sim, steps, qpos, qvel, collisions, names)
        t = self.clock.now_ns()
        for ob in self.observers:
            ob.on_truth(gt, t_ns=t)

    def tick(self, now: int, sim_ns: int) -> None:
        for ob in self.observers:
            ob.on_tick(now_ns=now, sim_time_ns=sim_ns)

    def camera_truth(self, name: str, frame_id: int, ct: Any, *, camera: str | None = None,
                     answer_id: int | None = None, truths: int = 1) -> None:
        """Frame ``frame_id``'s camera truth, on ``/<name>/truth`` (camera 0) or a rig
        camera's ``/<name>/truth/<camera>``; the observers get it under the frame id
        its answer carries (``answer_id``: a fused frame set's id), with the number of
        camera truths that answer is judged on (``truths``)."""
        t = self.clock.now_ns()
        for ob in self.observers:
            if hasattr(ob, "on_camera_truth"):
                ob.on_camera_truth(name, frame_id if answer_id is None else answer_id, ct, cameras=truths)
        self.rec.write_json(truth_topic(name, camera), {"frame_id": frame_id, **ct.to_json()}, log_time_ns=t,
                            publish_time_ns=t)

    def applied(self, a: Answer, t_apply: int, steps: int, qpos: np.ndarray, qvel: np.ndarray) -> None:
        sim, v = self.sim, a.v

        def truth_now() -> GroundTruth:
            """The world at ``t_apply`` and this ego's truth (the camera instant's truth
            where it is this step's)."""
            gt = self.cache.get(steps, v.name)
            if gt is not None:
                return gt
            sim.load_state(steps, qpos, qvel)
            return sim.truth_snapshot(egos=(v.name,))

        for ob in self.observers:
            if hasattr(ob, "on_apply"):
                ob.on_apply(v.name, a.m.frame_id, truth_now)
        self.complete(a, FrameStatus.OK, t_apply, steps * sim.step_ns)

    def complete(self, a: Answer, status: FrameStatus, t_apply: int | None = None,
                 sim_apply: int | None = None) -> None:
        """An answered frame's record (applied, or stale) and its estimate."""
        v, m = a.v, a.m
        for fl in (a.fl, *a.rest):  # a set's ESTIMATE answers each of its frames
            self.record(v, pipeline_record(v, fl, status, m, a.t0p_ns, t_apply, sim_apply), m)
        self.rec.write_json(f"/{v.name}/estimate", estimate_json(m), log_time_ns=a.t0p_ns,
                            publish_time_ns=a.t0p_ns if m.t_reply_target_ns is None else m.t_reply_target_ns)

    def record(self, v: VehicleRun, rec: PipelineRecord, estimate: Estimate | None = None) -> None:
        v.add(rec)
        for ob in self.observers:
            ob.on_record(v.name, rec, estimate)
        if rec.t0p_ns is not None and rec.status == FrameStatus.OK:
            v.e2e_window.add(rec.t0p_ns - rec.t0_ns)
        t = rec.t0p_ns or self.clock.now_ns()
        d = rec.to_json()
        d["render_worker"] = self.render_worker.get(v.name)  # which render process drew it (hil trace)
        self.rec.write_json(f"/{v.name}/pipeline", d, log_time_ns=t, publish_time_ns=rec.t0_ns)

    def sync(self, name: str, s: Any) -> None:
        for ob in self.observers:
            ob.on_sync(name, s)
        self.rec.write_json(f"/{name}/clock_sync", sync_sample_json(s), log_time_ns=s.t4_ns,
                            publish_time_ns=s.t1_ns)

    def image(self, name: str, data: bytes, t0: int, *, jpeg: bool, width: int, height: int,
              camera: str | None = None) -> None:
        """A frame's image on ``/<name>/camera`` (camera 0), or a rig camera's on
        ``/<name>/camera/<camera>``; its frame id is the optical frame of that topic."""
        topic = camera_topic(name, camera)
        frame = topic[1:]
        if jpeg:
            self.rec.write_image(topic, data, fmt="jpeg", frame_id=frame, log_time_ns=t0, publish_time_ns=t0)
        else:
            rgb = np.frombuffer(data, np.uint8).reshape(height, width, 3)
            self.rec.write_raw_image(topic, rgb, encoding="rgb8", frame_id=frame, log_time_ns=t0,
                                     publish_time_ns=t0)
