"""Runs the corner-case detector inside a run (a ``RunObserver`` with the truth hooks).

Truth at ``t0`` comes from the ground truth of the frame's camera instant (every
entity's position in the frame the AI reports in, PROTOCOL.md 4.3: a single camera's
camera-ground frame, or for a rig of two or more cameras the vehicle frame on the
road under camera 0's mount in the vehicle's axes; "visible" from the segmentation
boxes; the ego's route truth). A fused frame set's answer is judged once, against
the union of its cameras' visible sets (an entity any camera showed is visible): it
waits for each camera's truth, and one that never comes (a camera left out of the
set) no longer counts once a later answer's truth arrives. Truth at ``t_apply`` comes
from a snapshot taken when its control is applied, of that ego's route truth only
(``truth_now`` is called with ``egos=(vehicle,)`` where it takes that keyword) and
the entities it had in range at ``t0``, read off the snapshot's columns (the
simulator's ``EntityTable``): the work per estimate grows little with the number of
vehicles. Ground truths are kept by sim time (bounded) so that a camera truth
rendered late still meets its own instant. A mismatch is written to ``/events``
(kind ``mismatch.<kind>``) ``link_delay_s`` after it is found, once the timing
analysis of its frames is done, with those frames' timing anomalies linked; the
corner-case recorder picks it up from there.
"""

from __future__ import annotations

import math
import inspect
from collections import OrderedDict
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from hil.adapters.wire.messages import DrivingState, Estimate
from hil.harness.cases.detector import (CornerCaseDetector, FrameTruth, Mismatch, TruthObject, camera_position,
                                           footprints_in_camera_frame, link_anomalies)
from hil.harness.vocab.events import Event, EventBus
from hil.harness.cases.late_reaction import EgoView
from hil.harness.analysis.timing_observer import TimingObserver
from hil.harness.config.detector import DetectorSettings
from hil.harness.config.model import CameraConfig
from hil.scenarios.ground_truth import CameraTruth, EntityState, EntityTable, GroundTruth
from hil.timing.records import FrameStatus, PipelineRecord
from hil.timing.sync import SyncSample

_KEEP_FRAMES = 200  # truth kept for frames in flight (bounded)
_KEEP_TRUTHS = 64   # ground truths kept by sim time, for camera truths rendered late (bounded)


@dataclass
class _Gathered:
    """The camera truths of one answer so far: the ground truth of its instant, the
    union of what the cameras showed, how many came of how many awaited."""

    gt: GroundTruth
    visible: set[str]
    came: int
    awaited: int


@dataclass
class _VehicleJudge:
    detector: CornerCaseDetector
    at_t0: dict[int, FrameTruth] = field(default_factory=dict)
    at_apply: dict[int, FrameTruth] = field(default_factory=dict)
    # Applied frames whose camera truth has not arrived yet (frame id -> record,
    # estimate), judged in frame order once it does.
    waiting: dict[int, tuple[PipelineRecord, Estimate]] = field(default_factory=dict)
    last_frame: int = -1
    last_answer: int = -1  # the frame id of the last estimate taken (a set's is judged once)
    # Answers whose camera truths are still coming (frame id of the answer -> gathered).
    gathering: dict[int, _Gathered] = field(default_factory=dict)


class _Footprints:
    """One instant's entities as arrays, for the point of each footprint nearest a
    camera (``hil.harness.cases.detector.footprints_in_camera_frame`` on all of them at
    once: one at a time, a view of 30 entities took ~100 µs of the analysis thread,
    twice a frame; ~47 µs so)."""

    def __init__(self, entities: Sequence[EntityState]) -> None:
        self.entities = entities
        if isinstance(entities, EntityTable):  # the simulator's: its columns, no state object built
            self.index, self.names, self.classes = entities.row_of, entities.names, entities.classes
            self.x, self.y, self.h = entities.cols[0], entities.cols[1], entities.cols[2]
            self.half_l, self.half_w = entities.dims[:, 0] / 2, entities.dims[:, 1] / 2
        else:
            self.index = {e.name: i for i, e in enumerate(entities)}
            self.names, self.classes = tuple(e.name for e in entities), tuple(e.cls for e in entities)
            self.x = np.array([e.x_m for e in entities], dtype=np.float64)
            self.y = np.array([e.y_m for e in entities], dtype=np.float64)
            self.h = np.array([e.heading_rad for e in entities], dtype=np.float64)
            self.half_l = np.array([e.size_m[0] / 2 for e in entities], dtype=np.float64)
            self.half_w = np.array([e.size_m[1] / 2 for e in entities], dtype=np.float64)
        self.cos, self.sin = np.cos(self.h), np.sin(self.h)

    def view(self, me: int, mount: tuple[float, float, float], visible: set[str] | None, *,
             only: set[str] | None, within_m: float | None) -> tuple[TruthObject, ...]:
        """Every entity but the one in row ``me`` in its camera-ground frame (``mount``:
        forward, lateral, yaw of the camera), those named in ``only`` (or all), those no
        farther than ``within_m`` (or all); ``visible``: the names seen (None: all)."""
        forward, lateral, yaw = mount
        heading = float(self.h[me])
        cam_x, cam_y = camera_position(float(self.x[me]), float(self.y[me]), heading, forward, lateral)
        xs, ys = footprints_in_camera_frame(cam_x, cam_y, heading + yaw, self.x, self.y, self.cos, self.sin,
                                            self.half_l, self.half_w)
        pick: Sequence[int]
        if only is not None:
            pick = sorted(i for i in (self.index.get(n) for n in only) if i is not None)
        elif within_m is not None:  # a margin over the exact test below, made per object
            pick = np.flatnonzero(xs * xs + ys * ys <= within_m * within_m * (1 + 1e-9) + 1e-9).tolist()
        else:
            pick = range(len(self.names))
        out = []
        names, classes, mine = self.names, self.classes, self.names[me]
        for i in pick:
            name = names[i]
            if name == mine:
                continue
            t = TruthObject(name, classes[i], float(xs[i]), float(ys[i]), visible is None or name in visible)
            if within_m is None or t.distance_m <= within_m:
                out.append(t)
        return tuple(out)


class DetectorObserver:
    def __init__(self, cfg: DetectorSettings, vehicles: list[str], *, camera: CameraConfig, recorder: Any,
                 timing: TimingObserver | None, events: EventBus | None = None, link_delay_s: float = 1.5) -> None:
        """``events``: the run's bus the mismatches go on (default: one that records
        them on ``recorder``'s ``/events``)."""
        self.cfg = cfg
        cams = camera.cameras()
        # Where positions are compared (PROTOCOL.md 4.3): under camera 0's mount, turned
        # by its yaw for a single camera, in the vehicle's axes for a rig.
        c0 = cams[0]
        self._mount = (c0.forward_m, c0.lateral_m, 0.0 if len(cams) > 1 else math.radians(c0.yaw_deg))
        self.events = events if events is not None else EventBus.recording_to(recorder)
        self.timing = timing
        self.delay_ns = int(link_delay_s * 1e9)
        self.v = {name: _VehicleJudge(CornerCaseDetector(name, cfg)) for name in vehicles}
        self._gts: OrderedDict[int, GroundTruth] = OrderedDict()
        self._takes: dict[object, bool] = {}
        self._last_ns = 0  # the latest harness time seen (ns)
        self._pending: list[tuple[int, Mismatch]] = []
        self.mismatches: list[Mismatch] = []
        self._footprints: _Footprints | None = None  # the latest instant's entities, as arrays

    # -- truth ------------------------------------------------------------------

    def _frame_truth(self, vehicle: str, gt: GroundTruth, visible: set[str] | None, *,
                     only: set[str] | None = None) -> FrameTruth:
        """``vehicle``'s view of ``gt``: every other entity in its camera-ground frame
        (those named in ``only``; without ``only``, those within the 1.5 x range the
        judgement compares at all), its reference state and route truth."""
        world = self._world(gt)
        k = world.index.get(vehicle)  # (entity names are unique: WorldSpec)
        ego = next((e for e in gt.egos if e.vehicle == vehicle), None)
        objs: tuple[TruthObject, ...] = ()
        if k is not None:
            objs = world.view(k, self._mount, visible, only=only,
                              within_m=None if only is not None else self.cfg.max_range_m * 1.5)
        if ego is None:
            return FrameTruth(gt.sim_time_ns, objs, DrivingState.SAFE)
        view = EgoView(gt.sim_time_ns, ego.gap_m, ego.obstacle, ego.speed_mps, ego.obstacle_speed_mps)
        return FrameTruth(gt.sim_time_ns, objs, DrivingState(int(ego.ref_state)), view)

    def _world(self, gt: GroundTruth) -> _Footprints:
        """The footprints of ``gt``'s entities, built once per instant: every ego of a
        camera instant views the same world (and ``truth_now`` copies share it)."""
        w = self._footprints
        if w is None or w.entities is not gt.entities:
            w = self._footprints = _Footprints(gt.entities)
        return w

    # -- observer hooks ------------------------------------------------------------

    def on_truth(self, gt: GroundTruth, *, t_ns: int) -> None:
        self._last_ns = max(self._last_ns, t_ns)
        self._gts[gt.sim_time_ns] = gt
        while len(self._gts) > _KEEP_TRUTHS:
            self._gts.popitem(last=False)
        for e in gt.egos:
            vj = self.v.get(e.vehicle)
            if vj is not None:
                vj.detector.on_ego_truth(EgoView(gt.sim_time_ns, e.gap_m, e.obstacle, e.speed_mps,
                                                 e.obstacle_speed_mps))
        for c in gt.collisions:
            for name in (c.a, c.b):
                if name in self.v:
                    vj = self.v[name]
                    for m in vj.detector.on_collision(other=c.b if name == c.a else c.a, sim_time_ns=c.sim_time_ns,
                                                      harness_time_ns=t_ns, frame_id=max(vj.last_frame, 0),
                                                      force_n=c.force_n):
                        self._pending.append((t_ns + self.delay_ns, m))

    def on_camera_truth(self, vehicle: str, frame_id: int, truth: CameraTruth, *, cameras: int = 1) -> None:
        """One camera's truth of the answer to ``frame_id`` (a fused set's id), which
        is judged on ``cameras`` of them (fewer if the others never come)."""
        vj = self.v.get(vehicle)
        if vj is None:
            return
        # A render worker draws a vehicle's cameras in order: once a later answer's
        # truth is here, an earlier answer's missing cameras never will be.
        for earlier in [k for k in vj.gathering if k < frame_id]:
            self._gathered(vehicle, vj, earlier)
        g = vj.gathering.get(frame_id)
        if g is None:
            gt = self._gts.get(truth.sim_time_ns)
            if gt is None:  # not its exact instant: the latest one before it
                gt = next((x for t, x in reversed(self._gts.items()) if t <= truth.sim_time_ns), None)
            if gt is None:
                return
            g = vj.gathering[frame_id] = _Gathered(gt, set(), 0, cameras)
        c = self.cfg
        g.visible.update(b.entity for b in truth.boxes
                         if b.visible_px >= c.min_visible_px and b.visible_fraction >= c.min_visible_fraction)
        g.came += 1
        if g.came >= g.awaited:
            self._gathered(vehicle, vj, frame_id)

    def _gathered(self, vehicle: str, vj: _VehicleJudge, frame_id: int) -> None:
        """The answer to ``frame_id`` has the camera truths it will get: its truth at
        ``t0``; the answers waiting for it are judged."""
        g = vj.gathering.pop(frame_id)
        vj.at_t0[frame_id] = self._frame_truth(vehicle, g.gt, g.visible)
        _trim(vj.at_t0, frame_id)
        if vj.waiting:
            self._release(vj, upto=frame_id)

    def on_apply(self, vehicle: str, frame_id: int, truth_now: Callable[..., GroundTruth]) -> None:
        vj = self.v.get(vehicle)
        if vj is None:
            return
        # Only what the t0 judgement can compare: the entities it had in range (all of
        # them while its camera truth is still on its way).
        t0 = vj.at_t0.get(frame_id)
        near = None if t0 is None else {o.name for o in t0.objects if o.distance_m <= self.cfg.max_range_m * 1.5}
        gt = truth_now(egos=(vehicle,)) if self._takes_egos(truth_now) else truth_now()
        vj.at_apply[frame_id] = self._frame_truth(vehicle, gt, None, only=near)
        _trim(vj.at_apply, frame_id)

    def _takes_egos(self, fn: Callable[..., GroundTruth]) -> bool:
        """Whether a ``truth_now`` takes ``egos=``."""
        # Keyed by the code, not the callable: the run makes a new closure per applied
        # control, and keeping each one (with the world state it holds) leaked ~2 MB/min.
        func = getattr(fn, "__func__", fn)
        key = getattr(func, "__code__", func)
        known = self._takes.get(key)
        if known is None:
            try:
                known = "egos" in inspect.signature(fn).parameters
            except (TypeError, ValueError):
                known = False
            self._takes[key] = known
        return known

    def on_record(self, vehicle: str, rec: PipelineRecord, estimate: Estimate | None) -> None:
        vj = self.v.get(vehicle)
        if vj is None or estimate is None or rec.status != FrameStatus.OK:
            return
        vj.last_frame = rec.frame_id
        answer = estimate.frame_id  # a fused set's: its set id, one estimate for each of its frames
        if answer == vj.last_answer:
            return
        vj.last_answer = answer
        if answer not in vj.at_t0 or vj.waiting:
            # Its camera truth (rendered after the frame) is still on its way, or an
            # earlier frame waits for its own: judged in frame order when they come.
            vj.waiting[answer] = (rec, estimate)
            while vj.waiting:  # truth never came (truth.visible_boxes off): bounded, oldest out first
                oldest = next(iter(vj.waiting))
                if oldest >= answer - _KEEP_FRAMES:
                    break
                del vj.waiting[oldest]
            return
        self._judge(vj, rec, estimate)

    def _release(self, vj: _VehicleJudge, *, upto: int) -> None:
        """Judge the waiting frames up to ``upto`` in order; one whose camera truth
        did not come before a later frame's never will (it is skipped)."""
        for fid in sorted(k for k in vj.waiting if k <= upto):
            rec, estimate = vj.waiting.pop(fid)
            if fid in vj.at_t0:
                self._judge(vj, rec, estimate)

    def _judge(self, vj: _VehicleJudge, rec: PipelineRecord, estimate: Estimate) -> None:
        t0 = vj.at_t0.pop(estimate.frame_id)
        ta = vj.at_apply.pop(estimate.frame_id, None)
        now = rec.t_apply_ns or rec.t0p_ns or rec.t0_ns
        self._last_ns = max(self._last_ns, now)
        lat = rec.t_apply_ns - rec.t0_ns if rec.t_apply_ns is not None else None
        for m in vj.detector.judge(estimate, at_t0=t0, at_apply=ta, harness_time_ns=now, latency_ns=lat):
            self._pending.append((now + self.delay_ns, m))

    def on_sync(self, vehicle: str, sample: SyncSample) -> None:
        pass

    def on_tick(self, *, now_ns: int, sim_time_ns: int) -> None:
        if self._pending and self._pending[0][0] <= now_ns:
            self._emit(lambda due: due <= now_ns)

    def finish(self) -> None:
        for name, vj in self.v.items():
            for frame_id in list(vj.gathering):  # a set's cameras that never came: judged with those that did
                self._gathered(name, vj, frame_id)
            for m in vj.detector.finish(harness_time_ns=self._last_ns):
                self._pending.append((self._last_ns, m))
        self._emit(lambda due: True)

    def _emit(self, ready: Callable[[int], bool]) -> None:
        keep = []
        for due, m in self._pending:
            if not ready(due):
                keep.append((due, m))
                continue
            if self.timing is not None:
                m = link_anomalies(m, self.timing.anomalies_of(m.vehicle))
            self.mismatches.append(m)
            self.events.publish(Event.from_mismatch(m))
        self._pending = keep

    def summary(self, vehicle: str) -> dict[str, Any]:
        by: dict[str, int] = {}
        for m in self.mismatches:
            if m.vehicle == vehicle:
                key = f"{m.kind.value}/{m.cause.value}"
                by[key] = by.get(key, 0) + 1
        return {"mismatches": by}


def _trim(d: dict[int, FrameTruth], newest: int) -> None:
    for k in [k for k in d if k < newest - _KEEP_FRAMES]:
        del d[k]
