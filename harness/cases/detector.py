"""The corner-case detector: what the AI believed against what was true.

Each applied estimate is judged twice (DESIGN.md, "Two kinds of events"):

* at ``t0`` against the truth of the frame it answers (what the camera showed):
  wrong here means the **perception** was wrong;
* at ``t_apply`` against the truth when its control took effect: right at ``t0``
  but wrong here means **latency** made it wrong.

Checks (positions in the vehicle frame of PROTOCOL.md 4.3: x forward, y left; a
rig's under camera 0's mount, in the vehicle's axes):

* ``position_error``: a matched object off by more than
  ``pos_tol_m + pos_tol_rel * distance``;
* ``missed_object``: a truth object the camera showed (at least
  ``min_visible_px`` pixels and ``min_visible_fraction`` of it, within
  ``max_range_m``) that no estimated object matches;
* ``ghost_object``: an estimated object with no entity of its class within
  ``ghost_gate_m + pos_tol_rel * distance``;
* ``state_mismatch``: the driving state differs from the reference state;
  severity by direction: believing SAFE where truth says STOP is critical, one
  level less cautious is a warning, more cautious than truth is info;
* ``collision_while_safe``: a collision while the last applied estimate said SAFE;
* ``late_reaction``: a collision or near miss although the AI believed STOP in
  time; its brake came too late (``harness/cases/late_reaction.py``). Always latency.

Objects are matched by class and position with an optimal assignment (Hungarian,
``harness/cases/assignment.py``).

Episodes are kept per (kind, entity, cause): a perception error is reported while a
latency episode of the same kind is open, and the reverse; a later frame never
relabels an episode's cause. A mismatch must persist for ``min_frames`` consecutive
frames before it is reported, and is reported once per episode (it ends after
``clear_frames`` clean frames): flicker at a threshold is not a corner case, a
lasting wrong belief is. An episode is reported at the lowest severity of its last
``min_frames`` frames, and again when that lasting severity rises (SAFE against
SLOW, then three frames against STOP): an escalation lasts ``min_frames`` too.

Every event carries its evidence (``Mismatch.evidence``, JSON): the frame, its sim
times at capture (``sim_time_t0_ns``) and when its control took effect
(``sim_time_apply_ns``), ``latency_sim_ns`` between them and the harness-clock
``latency_ns`` (``t_apply - t0``), what the AI believed (``belief``) and what was true
at both instants (``truth_t0``, ``truth_apply``; positions with their tolerance
``tol_m``, states by name). The cause follows from it alone: wrong against
``truth_t0`` is perception; right there and wrong against ``truth_apply`` is latency.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from enum import Enum
from typing import Any

import numpy as np

from hil.adapters.wire.messages import DrivingState, Estimate
from hil.common.classes import ObjectClass
from hil.harness.cases.assignment import assign
from hil.harness.cases.late_reaction import Decision, EgoView, LateReaction, LateReactionJudge
from hil.harness.config.detector import DetectorSettings
from hil.timing.anomaly import Anomaly, Severity

_INF = 1e9
_RANK = {Severity.INFO: 0, Severity.WARNING: 1, Severity.CRITICAL: 2}
REPEAT_COLLISION_NS = 2_000_000_000


class MismatchKind(str, Enum):
    POSITION_ERROR = "position_error"
    MISSED_OBJECT = "missed_object"
    GHOST_OBJECT = "ghost_object"
    STATE_MISMATCH = "state_mismatch"
    COLLISION_WHILE_SAFE = "collision_while_safe"
    LATE_REACTION = "late_reaction"


class Cause(str, Enum):
    PERCEPTION = "perception"  # wrong at t0
    LATENCY = "latency"        # right at t0, wrong at t_apply


@dataclass(frozen=True)
class TruthObject:
    """An entity in the camera-ground frame at one instant. ``visible``: the camera
    showed enough of it to demand a detection."""

    name: str
    cls: str
    x_m: float
    y_m: float
    visible: bool = True

    @property
    def distance_m(self) -> float:
        return math.hypot(self.x_m, self.y_m)


@dataclass(frozen=True)
class FrameTruth:
    """Truth at one instant from one ego's point of view; ``ego``: its route truth
    (gap to the obstacle ahead, speeds), for late reactions (``None``: not known)."""

    sim_time_ns: int
    objects: tuple[TruthObject, ...]
    ref_state: DrivingState
    ego: EgoView | None = None


@dataclass(frozen=True)
class Mismatch:
    """One corner-case event. ``frame_ids``: the last ``min_frames`` frames of the
    episode (the one that triggered the report last); ``linked_anomalies``: timing
    anomalies of those frames (``kind@frame``); ``evidence``: what the verdict rests
    on, for the triggering frame (see the module docstring)."""

    kind: MismatchKind
    cause: Cause
    vehicle: str
    frame_ids: tuple[int, ...]
    sim_time_ns: int
    harness_time_ns: int
    measured: float
    threshold: float
    unit: str
    severity: Severity
    entity: str | None = None
    detail: str = ""
    linked_anomalies: tuple[str, ...] = ()
    evidence: Mapping[str, object] = field(default_factory=dict)

    def to_json(self) -> dict[str, object]:
        return {"kind": f"mismatch.{self.kind.value}", "mismatch": self.kind.value, "cause": self.cause.value,
                "vehicle": self.vehicle, "frame_ids": list(self.frame_ids), "sim_time_ns": self.sim_time_ns,
                "harness_time_ns": self.harness_time_ns, "measured": self.measured, "threshold": self.threshold,
                "unit": self.unit, "severity": self.severity.value, "entity": self.entity, "detail": self.detail,
                "linked_anomalies": list(self.linked_anomalies), "evidence": dict(self.evidence)}


def camera_position(ego_x: float, ego_y: float, ego_yaw: float, mount_forward_m: float,
                    mount_lateral_m: float) -> tuple[float, float]:
    """Where a camera mounted on an ego stands, in the world frame (m)."""
    c, s = math.cos(ego_yaw), math.sin(ego_yaw)
    return ego_x + c * mount_forward_m - s * mount_lateral_m, ego_y + s * mount_forward_m + c * mount_lateral_m


def footprints_in_camera_frame(cam_x: float, cam_y: float, heading: float, x: Any, y: Any, cos_yaw: Any,
                               sin_yaw: Any, half_l: Any, half_w: Any) -> tuple[Any, Any]:
    """The point of each footprint (a rectangle: centre ``x``, ``y``, its heading's
    ``cos_yaw``, ``sin_yaw``, half length and width; floats or arrays alike, the same
    operations either way) nearest to the camera at ``cam_x``, ``cam_y`` looking along
    ``heading``, in the camera-ground frame (m)."""
    # The camera's point in each entity's frame, clamped to its footprint.
    dx, dy = cam_x - x, cam_y - y
    lx = np.minimum(np.maximum(cos_yaw * dx + sin_yaw * dy, -half_l), half_l)
    ly = np.minimum(np.maximum(-sin_yaw * dx + cos_yaw * dy, -half_w), half_w)
    # Back into the world, then into the camera-ground frame.
    rx = (x + cos_yaw * lx - sin_yaw * ly) - cam_x
    ry = (y + sin_yaw * lx + cos_yaw * ly) - cam_y
    ch, sh = math.cos(heading), math.sin(heading)
    return ch * rx + sh * ry, -sh * rx + ch * ry


def nearest_point_in_camera_frame(*, ego_x: float, ego_y: float, ego_yaw: float, mount_forward_m: float,
                                  mount_lateral_m: float, camera_yaw: float, x: float, y: float, yaw: float,
                                  length: float, width: float) -> tuple[float, float]:
    """The point of an entity's footprint (a rectangle) nearest to the camera, in the
    camera-ground frame (m). World frame: x along the road, y left."""
    cam_x, cam_y = camera_position(ego_x, ego_y, ego_yaw, mount_forward_m, mount_lateral_m)
    px, py = footprints_in_camera_frame(cam_x, cam_y, ego_yaw + camera_yaw, x, y, math.cos(yaw), math.sin(yaw),
                                        length / 2, width / 2)
    return float(px), float(py)


def match(est: Sequence[tuple[str, float, float]], truth: Sequence[TruthObject], *,
          gate: Callable[[float], float]) -> list[tuple[int, int]]:
    """Optimal class-respecting assignment of estimated ``(cls, x, y)`` to truth
    objects; pairs farther apart than ``gate(truth_distance)`` are not matched."""
    if not est or not truth:
        return []
    cost = [[_INF] * len(truth) for _ in est]
    for i, (cls, x, y) in enumerate(est):
        for j, t in enumerate(truth):
            if cls == t.cls:
                d = math.hypot(x - t.x_m, y - t.y_m)
                if d <= gate(t.distance_m):
                    cost[i][j] = d
    return [(i, j) for i, j in assign(cost) if cost[i][j] < _INF]


@dataclass
class _Episode:
    # The current run of consecutive bad frames: (frame id, severity rank, what was found).
    run: list[tuple[int, int, _Found]] = field(default_factory=list)
    reported: int | None = None  # severity rank last reported in this episode
    clean: int = 0


@dataclass(frozen=True)
class _Found:
    """One check's verdict on one frame."""

    measured: float
    threshold: float
    unit: str
    severity: Severity
    detail: str
    evidence: dict[str, object]


_Key = tuple[MismatchKind, "str | None", Cause]


class CornerCaseDetector:
    """Judges one vehicle's estimates; returns the mismatches to report."""

    def __init__(self, vehicle: str, config: DetectorSettings | None = None) -> None:
        self.vehicle = vehicle
        self.cfg = config or DetectorSettings()
        self._episodes: dict[_Key, _Episode] = {}
        self.last_state: DrivingState | None = None
        self.last_state_right_at_t0 = True
        self._last_frame: dict[str, object] = {}
        self.counts: dict[str, int] = {}
        self._collided: dict[str, int] = {}
        self.late = LateReactionJudge(decel_mps2=self.cfg.avoid_decel_mps2, near_miss_m=self.cfg.near_miss_m)

    def tolerance(self, distance_m: float) -> float:
        return self.cfg.pos_tol_m + self.cfg.pos_tol_rel * distance_m

    def judge(self, est: Estimate, *, at_t0: FrameTruth, at_apply: FrameTruth | None,
              harness_time_ns: int, latency_ns: int | None = None) -> list[Mismatch]:
        """Judge one applied estimate (see the module docstring). ``latency_ns``: the
        harness-clock ``t_apply - t0`` of its frame, for the evidence."""
        frame = {"frame_id": est.frame_id, "sim_time_t0_ns": at_t0.sim_time_ns,
                 "sim_time_apply_ns": at_apply.sim_time_ns if at_apply is not None else None,
                 "latency_sim_ns": at_apply.sim_time_ns - at_t0.sim_time_ns if at_apply is not None else None,
                 "latency_ns": latency_ns}
        found: dict[_Key, _Found] = {}
        objs = [(ObjectClass.of(int(o.cls)).label, float(o.position_m[0]), float(o.position_m[1]))
                for o in est.objects]
        self._objects(objs, at_t0, at_apply, found, frame)
        self._state(est.state, at_t0, at_apply, found, frame)
        self.last_state = est.state
        self.last_state_right_at_t0 = est.state == at_t0.ref_state
        self._last_frame = {**frame, "belief": {"state": est.state.name},
                            "truth_t0": {"state": at_t0.ref_state.name},
                            "truth_apply": {"state": at_apply.ref_state.name} if at_apply is not None else None}
        out = self._episodes_update(found, frame_id=est.frame_id, sim_time_ns=at_t0.sim_time_ns,
                                    harness_time_ns=harness_time_ns)
        if at_t0.ego is not None:
            d = Decision(est.frame_id, est.state, float(est.control.brake), at_t0.ego,
                         at_apply.ego if at_apply is not None else None)
            out += self._late(self.late.on_decision(d), harness_time_ns)
        return out

    def on_ego_truth(self, view: EgoView) -> None:
        """The ego's route truth at a camera tick (near misses, late-reaction budget)."""
        self.late.on_truth(view)

    def finish(self, *, harness_time_ns: int) -> list[Mismatch]:
        """Judge the contacts still waiting for later frames (end of the run)."""
        return self._late(self.late.finish(), harness_time_ns)

    def _late(self, verdicts: Iterable[tuple[object, LateReaction | None]], harness_time_ns: int) -> list[Mismatch]:
        out = []
        for c, lr in verdicts:
            if lr is None:
                continue
            sev = Severity.CRITICAL if lr.contact == "collision" else Severity.WARNING
            budget = "" if lr.budget_ns is None else f" (within {lr.budget_ns / 1e6:.0f} ms it could still stop)"
            when = "applied" if lr.applied_before_contact else "still in flight"
            m = Mismatch(MismatchKind.LATE_REACTION, Cause.LATENCY, self.vehicle, (lr.frame_id,), lr.sim_time_ns,
                         harness_time_ns, round(lr.latency_ns / 1e6, 3),
                         -1.0 if lr.budget_ns is None else round(lr.budget_ns / 1e6, 3), "ms", sev, lr.other,
                         f"{lr.contact} with {lr.other}: the AI believed STOP at frame {lr.frame_id}, in time, "
                         f"but its brake was {when} {lr.latency_ns / 1e6:.0f} ms after capture{budget}",
                         evidence=lr.evidence)
            self.counts[m.kind.value] = self.counts.get(m.kind.value, 0) + 1
            out.append(m)
        return out

    def on_collision(self, *, other: str, sim_time_ns: int, harness_time_ns: int, frame_id: int,
                     force_n: float) -> list[Mismatch]:
        """A collision of this vehicle: a mismatch when its last belief was SAFE. A
        bounce (contact again with the same entity within ``REPEAT_COLLISION_NS``)
        belongs to the same case. Also a contact for the late-reaction judge."""
        self.late.on_collision(other=other, sim_time_ns=sim_time_ns, force_n=force_n)
        last = self._collided.get(other)
        self._collided[other] = sim_time_ns
        if self.last_state != DrivingState.SAFE or (last is not None and sim_time_ns - last < REPEAT_COLLISION_NS):
            return []
        cause = Cause.LATENCY if self.last_state_right_at_t0 else Cause.PERCEPTION
        ev = {**self._last_frame, "collision_sim_time_ns": sim_time_ns, "other": other}
        last_fid = self._last_frame.get("frame_id")
        fid = last_fid if isinstance(last_fid, int) else frame_id
        m = Mismatch(MismatchKind.COLLISION_WHILE_SAFE, cause, self.vehicle, (fid,), sim_time_ns,
                     harness_time_ns, force_n, 0.0, "N", Severity.CRITICAL, other,
                     f"collided with {other} while the AI believed SAFE", evidence=ev)
        self.counts[m.kind.value] = self.counts.get(m.kind.value, 0) + 1
        return [m]

    # -- checks ------------------------------------------------------------------

    def _objects(self, objs: Sequence[tuple[str, float, float]], at_t0: FrameTruth, at_apply: FrameTruth | None,
                 found: dict[_Key, _Found], frame: Mapping[str, object]) -> None:
        c = self.cfg
        truth = [t for t in at_t0.objects if t.distance_m <= c.max_range_m * 1.5]
        pairs = match(objs, truth, gate=lambda d: c.ghost_gate_m + c.pos_tol_rel * d)
        matched_e = {i for i, _ in pairs}
        matched_t = {j for _, j in pairs}
        apply_by_name = {t.name: t for t in at_apply.objects} if at_apply is not None else {}
        for i, j in pairs:
            cls, x, y = objs[i]
            t = truth[j]
            ta = apply_by_name.get(t.name)
            err, tol = math.hypot(x - t.x_m, y - t.y_m), self.tolerance(t.distance_m)
            ev = {**frame, "belief": _xy(x, y), "truth_t0": {**_xy(t.x_m, t.y_m), "tol_m": round(tol, 4)},
                  "truth_apply": None}
            if ta is not None:
                ev["truth_apply"] = {**_xy(ta.x_m, ta.y_m), "tol_m": round(self.tolerance(ta.distance_m), 4)}
            if err > tol:
                found[(MismatchKind.POSITION_ERROR, t.name, Cause.PERCEPTION)] = _Found(
                    err, tol, "m", Severity.WARNING,
                    f"{t.name} believed at ({x:.1f}, {y:.1f}) m, truly at ({t.x_m:.1f}, {t.y_m:.1f}) m", ev)
                continue
            if ta is not None:
                err_a, tol_a = math.hypot(x - ta.x_m, y - ta.y_m), self.tolerance(ta.distance_m)
                if err_a > tol_a:
                    found[(MismatchKind.POSITION_ERROR, t.name, Cause.LATENCY)] = _Found(
                        err_a, tol_a, "m", Severity.WARNING,
                        f"{t.name} right at capture but {err_a:.2f} m off when control applied", ev)
        for j, t in enumerate(truth):
            if j not in matched_t and t.visible and t.distance_m <= c.max_range_m:
                ta = apply_by_name.get(t.name)
                ev = {**frame, "belief": None, "truth_t0": {**_xy(t.x_m, t.y_m), "visible": True},
                      "truth_apply": _xy(ta.x_m, ta.y_m) if ta is not None else None}
                found[(MismatchKind.MISSED_OBJECT, t.name, Cause.PERCEPTION)] = _Found(
                    t.distance_m, c.max_range_m, "m", Severity.WARNING,
                    f"{t.cls} {t.name} visible at {t.distance_m:.1f} m not detected", ev)
        for i, (cls, x, y) in enumerate(objs):
            if i not in matched_e:
                d = math.hypot(x, y)
                ev = {**frame, "belief": {"cls": cls, **_xy(x, y)}, "truth_t0": None, "truth_apply": None}
                found[(MismatchKind.GHOST_OBJECT, f"{cls}@{round(d / 5) * 5:g}m", Cause.PERCEPTION)] = _Found(
                    d, 0.0, "m", Severity.WARNING, f"{cls} believed at ({x:.1f}, {y:.1f}) m where there is none", ev)

    def _state(self, state: DrivingState, at_t0: FrameTruth, at_apply: FrameTruth | None, found: dict[_Key, _Found],
               frame: Mapping[str, object]) -> None:
        if state != at_t0.ref_state:
            cause, truth = Cause.PERCEPTION, at_t0.ref_state
        elif at_apply is not None and state != at_apply.ref_state:
            cause, truth = Cause.LATENCY, at_apply.ref_state
        else:
            return
        gap = int(truth) - int(state)  # >0: the AI was less cautious than the truth
        sev = Severity.CRITICAL if gap >= 2 else Severity.WARNING if gap == 1 else Severity.INFO
        ev = {**frame, "belief": {"state": state.name}, "truth_t0": {"state": at_t0.ref_state.name},
              "truth_apply": {"state": at_apply.ref_state.name} if at_apply is not None else None}
        found[(MismatchKind.STATE_MISMATCH, None, cause)] = _Found(
            float(int(state)), float(int(truth)), "state", sev, f"AI said {state.name} where truth says {truth.name}",
            ev)

    def _episodes_update(self, found: dict[_Key, _Found], *, frame_id: int, sim_time_ns: int,
                         harness_time_ns: int) -> list[Mismatch]:
        """Episodes per (kind, entity, cause). One is reported once its mismatch has
        lasted ``min_frames`` consecutive frames, at the lowest severity of those
        frames; again only when that lasting severity rises."""
        out: list[Mismatch] = []
        n = self.cfg.min_frames
        for key, ep in list(self._episodes.items()):
            if key not in found:
                ep.clean += 1
                ep.run.clear()  # persistence counts consecutive frames
                if ep.clean >= self.cfg.clear_frames:
                    del self._episodes[key]
        for key, f in found.items():
            ep = self._episodes.setdefault(key, _Episode())
            ep.clean = 0
            ep.run.append((frame_id, _RANK[f.severity], f))
            del ep.run[:-n]  # only the last min_frames matter
            if len(ep.run) < n:
                continue
            level = min(r for _, r, _ in ep.run)
            if ep.reported is not None and level <= ep.reported:
                continue
            ep.reported = level
            # The newest frame at the lasting severity speaks for the episode.
            fid, _, g = next(x for x in reversed(ep.run) if x[1] == level)
            kind, entity, cause = key
            t0_ns = g.evidence.get("sim_time_t0_ns")
            t_ns = t0_ns if isinstance(t0_ns, int) else sim_time_ns
            m = Mismatch(kind, cause, self.vehicle, tuple(x[0] for x in ep.run), t_ns, harness_time_ns,
                         round(g.measured, 4), round(g.threshold, 4), g.unit, g.severity, entity, g.detail,
                         evidence=g.evidence)
            self.counts[kind.value] = self.counts.get(kind.value, 0) + 1
            out.append(m)
        return out


def _xy(x: float, y: float) -> dict[str, float]:
    return {"x_m": round(x, 4), "y_m": round(y, 4)}


def link_anomalies(m: Mismatch, anomalies: Iterable[Anomaly], *, before_frames: int = 3) -> Mismatch:
    """``m`` with the timing anomalies of its frames (and the few before) linked."""
    lo, hi = min(m.frame_ids) - before_frames, max(m.frame_ids)
    links = tuple(f"{a.kind.value.lower()}@{f}" for a in anomalies for f in a.frame_ids if lo <= f <= hi)
    return m if not links else Mismatch(**{**m.__dict__, "linked_anomalies": links})
