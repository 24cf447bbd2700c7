"""Runs the corner-case detector inside a run (a ``RunObserver`` with the truth hooks).

Truth at ``t0`` comes from the camera tick of the frame (every entity's position in
the camera-ground frame; "visible" from the segmentation boxes); truth at
``t_apply`` from a snapshot taken when its control is applied. A mismatch is written
to ``/events`` (kind ``mismatch.<kind>``) ``link_delay_s`` after it is found, once
the timing analysis of its frames is done, with those frames' timing anomalies
linked; the corner-case recorder picks it up from there.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from adapters.messages import DrivingState, Estimate
from harness.config import CameraConfig
from harness.detector import (CornerCaseDetector, DetectorConfig, FrameTruth, Mismatch, TruthObject,
                              link_anomalies, nearest_point_in_camera_frame)
from harness.timing_observer import TimingObserver
from scenarios.ground_truth import CameraTruth, EntityState, GroundTruth
from timing.records import FrameStatus, PipelineRecord
from timing.sync import SyncSample

_KEEP_FRAMES = 200  # truth kept for frames in flight (bounded)


@dataclass
class _VehicleJudge:
    detector: CornerCaseDetector
    at_t0: dict[int, FrameTruth] = field(default_factory=dict)
    at_apply: dict[int, FrameTruth] = field(default_factory=dict)
    last_frame: int = -1


class DetectorObserver:
    def __init__(self, cfg: DetectorConfig, vehicles: list[str], *, camera: CameraConfig, recorder: Any,
                 timing: TimingObserver | None, link_delay_s: float = 1.5) -> None:
        self.cfg = cfg
        self.cam = camera
        self.rec = recorder
        self.timing = timing
        self.delay_ns = int(link_delay_s * 1e9)
        self.v = {name: _VehicleJudge(CornerCaseDetector(name, cfg)) for name in vehicles}
        self._gt: GroundTruth | None = None
        self._pending: list[tuple[int, Mismatch]] = []
        self.mismatches: list[Mismatch] = []

    # -- truth ------------------------------------------------------------------

    def _frame_truth(self, vehicle: str, gt: GroundTruth, visible: set[str] | None) -> FrameTruth:
        me = next((e for e in gt.entities if e.name == vehicle), None)
        ego = next((e for e in gt.egos if e.vehicle == vehicle), None)
        objs = []
        if me is not None:
            for e in gt.entities:
                if e.name != vehicle:
                    objs.append(self._in_camera(me, e, visible is None or e.name in visible))
        ref = DrivingState(int(ego.ref_state)) if ego is not None else DrivingState.SAFE
        return FrameTruth(gt.sim_time_ns, tuple(objs), ref)

    def _in_camera(self, me: EntityState, e: EntityState, visible: bool) -> TruthObject:
        x, y = nearest_point_in_camera_frame(
            ego_x=me.x_m, ego_y=me.y_m, ego_yaw=me.heading_rad, mount_forward_m=self.cam.mount_forward_m,
            mount_lateral_m=self.cam.mount_lateral_m, camera_yaw=math.radians(self.cam.yaw_deg),
            x=e.x_m, y=e.y_m, yaw=e.heading_rad, length=e.size_m[0], width=e.size_m[1])
        return TruthObject(e.name, e.cls, x, y, visible)

    # -- observer hooks ------------------------------------------------------------

    def on_truth(self, gt: GroundTruth, *, t_ns: int) -> None:
        self._gt = gt
        for c in gt.collisions:
            for name in (c.a, c.b):
                if name in self.v:
                    vj = self.v[name]
                    for m in vj.detector.on_collision(other=c.b if name == c.a else c.a, sim_time_ns=c.sim_time_ns,
                                                      harness_time_ns=t_ns, frame_id=max(vj.last_frame, 0),
                                                      force_n=c.force_n):
                        self._pending.append((t_ns + self.delay_ns, m))

    def on_camera_truth(self, vehicle: str, frame_id: int, truth: CameraTruth) -> None:
        if self._gt is None or vehicle not in self.v:
            return
        c = self.cfg
        visible = {b.entity for b in truth.boxes
                   if b.visible_px >= c.min_visible_px and b.visible_fraction >= c.min_visible_fraction}
        vj = self.v[vehicle]
        vj.at_t0[frame_id] = self._frame_truth(vehicle, self._gt, visible)
        _trim(vj.at_t0, frame_id)

    def on_apply(self, vehicle: str, frame_id: int, truth_now: Callable[[], GroundTruth]) -> None:
        vj = self.v.get(vehicle)
        if vj is not None and frame_id in vj.at_t0:
            vj.at_apply[frame_id] = self._frame_truth(vehicle, truth_now(), None)
            _trim(vj.at_apply, frame_id)

    def on_record(self, vehicle: str, rec: PipelineRecord, estimate: Estimate | None) -> None:
        vj = self.v.get(vehicle)
        if vj is None or estimate is None or rec.status != FrameStatus.OK:
            return
        vj.last_frame = rec.frame_id
        t0 = vj.at_t0.pop(rec.frame_id, None)
        if t0 is None:
            return  # truth for this frame was not taken (truth.visible_boxes off)
        ta = vj.at_apply.pop(rec.frame_id, None)
        now = rec.t_apply_ns or rec.t0p_ns or rec.t0_ns
        for m in vj.detector.judge(estimate, at_t0=t0, at_apply=ta, harness_time_ns=now):
            self._pending.append((now + self.delay_ns, m))

    def on_sync(self, vehicle: str, sample: SyncSample) -> None:
        pass

    def on_tick(self, *, now_ns: int, sim_time_ns: int) -> None:
        if self._pending and self._pending[0][0] <= now_ns:
            self._emit(lambda due: due <= now_ns)

    def finish(self) -> None:
        self._emit(lambda due: True)

    def _emit(self, ready: Callable[[int], bool]) -> None:
        keep = []
        for due, m in self._pending:
            if not ready(due):
                keep.append((due, m))
                continue
            if self.timing is not None and m.vehicle in self.timing.v:
                m = link_anomalies(m, self.timing.v[m.vehicle].anomalies)
            self.mismatches.append(m)
            self.rec.write_json("/events", m.to_json(), log_time_ns=m.harness_time_ns,
                                publish_time_ns=m.harness_time_ns)
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
