"""The corner-case detector on hand-made truth: perception vs latency, severity by
direction, optimal matching, persistence and episodes."""

from __future__ import annotations

import math

import pytest

from hil.adapters.wire.messages import Control, DetectedObject, DrivingState, Estimate, ObjectClass
from hil.harness.cases.detector import (Cause, CornerCaseDetector, FrameTruth, MismatchKind,
                                           TruthObject, link_anomalies, match, nearest_point_in_camera_frame)
from hil.harness.config.detector import DetectorSettings
from hil.timing.anomaly import Anomaly, AnomalyKind, Severity

S, W, P = DrivingState.SAFE, DrivingState.SLOW, DrivingState.STOP


def est(frame_id, state=S, objects=()):
    objs = tuple(DetectedObject(ObjectClass.VEHICLE if c == "vehicle" else ObjectClass.PEDESTRIAN, 0.9,
                                (0, 0, 1, 1), (x, y, 0.0)) for c, x, y in objects)
    return Estimate(0, frame_id, state, Control(), objs, 0, 0, 0, 0)


def truth(ref=S, objects=(), t=0):
    return FrameTruth(t, tuple(TruthObject(n, c, x, y, v) for n, c, x, y, v in objects), ref)


CAR = ("car1", "vehicle", 30.0, 0.0, True)


def run(det, frames):
    out = []
    for i, (e, t0, ta) in enumerate(frames):
        out += det.judge(est(i, *e), at_t0=t0, at_apply=ta, harness_time_ns=i)
    return out


def test_right_belief_is_no_corner_case():
    det = CornerCaseDetector("ego0")
    frames = [((S, [("vehicle", 30.2, 0.1)]), truth(S, [CAR]), truth(S, [CAR]))] * 20
    assert run(det, frames) == []


def test_missed_object_is_perception_after_persistence():
    det = CornerCaseDetector("ego0", DetectorSettings(min_frames=3))
    frames = [((S, []), truth(S, [CAR]), truth(S, [CAR]))] * 10
    out = run(det, frames)
    assert [(m.kind, m.cause, m.entity) for m in out] == [(MismatchKind.MISSED_OBJECT, Cause.PERCEPTION, "car1")]
    assert out[0].frame_ids == (0, 1, 2)


def test_invisible_or_far_objects_are_not_demanded():
    det = CornerCaseDetector("ego0")
    hidden = ("ped", "pedestrian", 10.0, 1.0, False)
    far = ("car9", "vehicle", 120.0, 0.0, True)
    assert run(det, [((S, []), truth(S, [hidden, far]), None)] * 10) == []


def test_ghost_object():
    det = CornerCaseDetector("ego0")
    out = run(det, [((S, [("vehicle", 20.0, 0.0)]), truth(S, []), None)] * 5)
    assert [m.kind for m in out] == [MismatchKind.GHOST_OBJECT]


def test_position_error_perception_vs_latency():
    # Believed at 30 m; truly at 40 m at capture: perception.
    det = CornerCaseDetector("ego0")
    out = run(det, [((S, [("vehicle", 30.0, 0.0)]), truth(S, [("car1", "vehicle", 36.0, 0, True)]), None)] * 4)
    assert [(m.kind, m.cause) for m in out] == [(MismatchKind.POSITION_ERROR, Cause.PERCEPTION)]
    # Right at capture, but the car moved 8 m by the time control applied: latency.
    det = CornerCaseDetector("ego0")
    moved = truth(S, [("car1", "vehicle", 22.0, 0, True)])
    out = run(det, [((S, [("vehicle", 30.0, 0.0)]), truth(S, [CAR]), moved)] * 4)
    assert [(m.kind, m.cause) for m in out] == [(MismatchKind.POSITION_ERROR, Cause.LATENCY)]


@pytest.mark.parametrize("believed, truth_state, severity", [
    (S, P, Severity.CRITICAL), (S, W, Severity.WARNING), (W, P, Severity.WARNING), (P, S, Severity.INFO)])
def test_state_mismatch_severity_by_direction(believed, truth_state, severity):
    det = CornerCaseDetector("ego0")
    out = run(det, [((believed, []), truth(truth_state), truth(truth_state))] * 4)
    assert [(m.kind, m.severity, m.cause) for m in out] == [(MismatchKind.STATE_MISMATCH, severity, Cause.PERCEPTION)]


def test_state_right_at_t0_wrong_at_apply_is_latency():
    det = CornerCaseDetector("ego0")
    out = run(det, [((S, []), truth(S), truth(P))] * 4)
    assert [(m.kind, m.cause, m.severity) for m in out] == [(MismatchKind.STATE_MISMATCH, Cause.LATENCY,
                                                             Severity.CRITICAL)]


def test_flicker_is_not_reported_and_episodes_report_once():
    det = CornerCaseDetector("ego0", DetectorSettings(min_frames=3, clear_frames=5))
    flicker = [((S, []), truth(P), None), ((P, []), truth(P), None)] * 10
    assert run(det, flicker) == []
    det = CornerCaseDetector("ego0", DetectorSettings(min_frames=3, clear_frames=5))
    bad, good = ((S, []), truth(P), None), ((P, []), truth(P), None)
    out = run(det, [bad] * 6 + [good] * 2 + [bad] * 6 + [good] * 6 + [bad] * 3)
    assert len(out) == 2  # a short clean spell continues the episode; a long one ends it


def test_collision_while_safe():
    det = CornerCaseDetector("ego0")
    det.judge(est(0, S), at_t0=truth(S), at_apply=truth(S), harness_time_ns=0)
    out = det.on_collision(other="car1", sim_time_ns=5, harness_time_ns=6, frame_id=0, force_n=900.0)
    assert [(m.kind, m.cause, m.severity) for m in out] == [(MismatchKind.COLLISION_WHILE_SAFE, Cause.LATENCY,
                                                             Severity.CRITICAL)]
    det.judge(est(1, P), at_t0=truth(P), at_apply=truth(P), harness_time_ns=1)
    assert det.on_collision(other="car1", sim_time_ns=5, harness_time_ns=6, frame_id=1, force_n=900.0) == []


def test_optimal_assignment_beats_greedy():
    # Greedy (nearest first) would pair e0-t1 and leave e1 unmatched; optimal pairs both.
    truth_objs = [TruthObject("a", "vehicle", 10.0, 0.0), TruthObject("b", "vehicle", 12.0, 0.0)]
    pairs = match([("vehicle", 11.5, 0.0), ("vehicle", 9.0, 0.0)], truth_objs, gate=lambda d: 3.0)
    assert sorted(pairs) == [(0, 1), (1, 0)]
    assert match([("pedestrian", 10.0, 0.0)], truth_objs, gate=lambda d: 3.0) == []


def test_nearest_point_geometry():
    # Ego at the origin heading +x, camera 2.3 m ahead; a car centred 30 m ahead.
    x, y = nearest_point_in_camera_frame(ego_x=0, ego_y=0, ego_yaw=0, mount_forward_m=2.3, mount_lateral_m=0,
                                         camera_yaw=0, x=30, y=0, yaw=0, length=4.5, width=1.8)
    assert (round(x, 6), round(y, 6)) == (30 - 2.25 - 2.3, 0.0)
    # Ego turned left 90 degrees: the same car is now to its right.
    x, y = nearest_point_in_camera_frame(ego_x=0, ego_y=0, ego_yaw=math.pi / 2, mount_forward_m=0,
                                         mount_lateral_m=0, camera_yaw=0, x=30, y=0, yaw=0, length=4.5,
                                         width=1.8)
    assert x == pytest.approx(0.0, abs=1e-9) and y == pytest.approx(-(30 - 2.25))


def test_linked_anomalies():
    det = CornerCaseDetector("ego0")
    (m,) = run(det, [((S, []), truth(S, [CAR]), None)] * 3)
    a = Anomaly(AnomalyKind.LATENCY_SPIKE, "ego0", (1,), 0, 0, 90.0, 20.0, "ms", Severity.WARNING, "end_to_end", "")
    far = Anomaly(AnomalyKind.DROPPED_FRAME, "ego0", (40,), 0, 0, 1.0, 0.0, "frames", Severity.WARNING, None, "")
    assert link_anomalies(m, [a, far]).linked_anomalies == ("latency_spike@1",)
