"""Issue 19 at unit level: episodes per cause, no relabelling, escalations that last,
evidence in every event (the cause re-derived from it alone), late reactions."""

from __future__ import annotations

import math

from hil.adapters.wire.messages import Control, DetectedObject, DrivingState, Estimate, ObjectClass
from hil.harness.cases.detector import Cause, CornerCaseDetector, FrameTruth, Mismatch, MismatchKind, TruthObject
from hil.harness.cases.late_reaction import EgoView
from hil.harness.config.detector import DetectorSettings
from hil.timing.anomaly import Severity

S, W, P = DrivingState.SAFE, DrivingState.SLOW, DrivingState.STOP
MS = 1_000_000


def est(frame_id: int, state: DrivingState = S, objects=(), brake: float = 0.0) -> Estimate:
    objs = tuple(DetectedObject(ObjectClass.VEHICLE, 0.9, (0, 0, 1, 1), (x, y, 0.0)) for x, y in objects)
    return Estimate(0, frame_id, state, Control(brake=brake), objs, 0, 0, 0, 0)


def truth(ref: DrivingState, t_ns: int = 0, objects=(), ego: EgoView | None = None) -> FrameTruth:
    return FrameTruth(t_ns, tuple(TruthObject(n, "vehicle", x, y, True) for n, x, y in objects), ref, ego)


def feed(det: CornerCaseDetector, frames, *, start: int = 0) -> list[Mismatch]:
    """frames: (belief, truth at t0, truth at apply) per frame, 50 ms apart, applied 600 ms later."""
    out = []
    for i, (belief, ref0, ref_a) in enumerate(frames, start):
        t = i * 50 * MS
        out += det.judge(est(i, belief), at_t0=truth(ref0, t), at_apply=truth(ref_a, t + 600 * MS),
                         harness_time_ns=t, latency_ns=600 * MS)
    return out


def cause_from_evidence(m: Mismatch) -> Cause:
    """Independent of the detector: wrong against the truth at capture is perception;
    right there and wrong against the truth at apply is latency."""
    ev = m.evidence
    if m.kind == MismatchKind.LATE_REACTION:
        assert ev["belief"]["state"] == "STOP"
        t0 = ev["truth_t0"]
        assert t0["gap_m"] is None or t0["gap_m"] >= t0["stop_distance_m"], "decided in time"
        a = ev["truth_apply"]
        assert (not ev["applied_before_contact"]) or a["gap_m"] < a["stop_distance_m"], "applied too late"
        return Cause.LATENCY
    if m.kind == MismatchKind.COLLISION_WHILE_SAFE:
        assert ev["belief"]["state"] == "SAFE"
        return Cause.LATENCY if ev["truth_t0"]["state"] == "SAFE" else Cause.PERCEPTION
    if m.kind == MismatchKind.STATE_MISMATCH:
        if ev["belief"]["state"] != ev["truth_t0"]["state"]:
            return Cause.PERCEPTION
        assert ev["belief"]["state"] != ev["truth_apply"]["state"]
        return Cause.LATENCY
    if m.kind == MismatchKind.POSITION_ERROR:
        b, t0, ta = ev["belief"], ev["truth_t0"], ev["truth_apply"]
        if math.hypot(b["x_m"] - t0["x_m"], b["y_m"] - t0["y_m"]) > t0["tol_m"]:
            return Cause.PERCEPTION
        assert math.hypot(b["x_m"] - ta["x_m"], b["y_m"] - ta["y_m"]) > ta["tol_m"]
        return Cause.LATENCY
    if m.kind == MismatchKind.MISSED_OBJECT:
        assert ev["belief"] is None and ev["truth_t0"]["visible"] is True
    else:
        assert m.kind == MismatchKind.GHOST_OBJECT and ev["belief"] and ev["truth_t0"] is None
    return Cause.PERCEPTION  # nothing there, or something there unseen, at capture


def test_a_perception_error_is_reported_while_a_latency_episode_is_open():
    det = CornerCaseDetector("ego0")
    # Right at capture, wrong at apply (latency) for 3 frames, then wrong at capture
    # (perception) for 4: both reported, each with its own cause.
    out = feed(det, [(S, S, P)] * 3 + [(S, P, P)] * 4)
    assert [(m.kind, m.cause) for m in out] == [(MismatchKind.STATE_MISMATCH, Cause.LATENCY),
                                                 (MismatchKind.STATE_MISMATCH, Cause.PERCEPTION)]
    assert [m.frame_ids for m in out] == [(0, 1, 2), (3, 4, 5)]
    for m in out:
        assert cause_from_evidence(m) == m.cause


def test_an_episode_is_never_relabelled_by_a_later_frame():
    det = CornerCaseDetector("ego0")
    # perception, perception, latency: no cause lasted three frames: nothing yet.
    assert feed(det, [(S, P, P), (S, P, P), (S, S, P)]) == []
    det = CornerCaseDetector("ego0")
    out = feed(det, [(S, P, P)] * 3 + [(S, S, P)] * 2)
    assert [(m.cause, m.frame_ids) for m in out] == [(Cause.PERCEPTION, (0, 1, 2))]


def test_an_escalation_lasts_min_frames_too():
    det = CornerCaseDetector("ego0", DetectorSettings(min_frames=3, clear_frames=5))
    # SAFE against SLOW (warning) 3 frames, one clean frame, one against STOP: the
    # critical frame alone is no escalation.
    out = feed(det, [(S, W, W)] * 3 + [(S, S, S)] + [(S, P, P)])
    assert [(m.severity, m.frame_ids) for m in out] == [(Severity.WARNING, (0, 1, 2))]
    out = feed(det, [(S, P, P)] * 2, start=5)
    assert [(m.severity, m.frame_ids) for m in out] == [(Severity.CRITICAL, (4, 5, 6))]
    assert out[0].evidence["truth_t0"] == {"state": "STOP"}


def test_mixed_severities_report_the_lasting_one_with_its_own_evidence():
    det = CornerCaseDetector("ego0")
    (m,) = feed(det, [(S, W, W), (S, W, W), (S, P, P)])
    assert m.severity == Severity.WARNING and m.evidence["truth_t0"] == {"state": "SLOW"}
    assert m.evidence["frame_id"] == 1 and m.sim_time_ns == 50 * MS


def test_every_event_carries_its_evidence():
    det = CornerCaseDetector("ego0")
    car0 = [("car1", 30.0, 0.0)]
    moved = [("car1", 20.0, 0.0)]
    out = []
    for i in range(4):
        t = i * 50 * MS
        out += det.judge(est(i, S, [(30.1, 0.0)]), at_t0=truth(S, t, car0), at_apply=truth(P, t + 700 * MS, moved),
                         harness_time_ns=t, latency_ns=712 * MS)
    assert sorted((m.kind.value, m.cause.value) for m in out) == [("position_error", "latency"),
                                                                   ("state_mismatch", "latency")]
    for m in out:
        ev = m.to_json()["evidence"]
        assert ev["sim_time_apply_ns"] - ev["sim_time_t0_ns"] == ev["latency_sim_ns"] == 700 * MS
        assert ev["latency_ns"] == 712 * MS and ev["frame_id"] == m.frame_ids[-1]
        assert ev["belief"] and ev["truth_t0"] and ev["truth_apply"]
        assert cause_from_evidence(m) == m.cause


def view(t_ms: int, gap: float | None, speed: float = 10.0, obstacle: str = "car1") -> EgoView:
    return EgoView(t_ms * MS, gap, obstacle if gap is not None else None, speed, 0.0)


def drive(det: CornerCaseDetector, *, latency_ms: int, stop_from: int, collide_at_ms: int | None,
          frames: int = 40) -> list[Mismatch]:
    """An ego at 10 m/s closing on a stopped car from 30 m; the AI believes STOP from
    frame ``stop_from``; controls apply ``latency_ms`` after capture."""
    out = []
    decisions = []
    for i in range(frames):
        t = i * 50
        gap = max(0.0, 30.0 - 10.0 * t / 1000)
        v = view(t, gap)
        det.on_ego_truth(v)
        if collide_at_ms is not None and t == collide_at_ms:
            out += det.on_collision(other="car1", sim_time_ns=t * MS, harness_time_ns=t * MS, frame_id=i,
                                    force_n=500.0)
        state = P if i >= stop_from else S
        decisions.append((i, state, truth(P if gap < 17.5 else S, t * MS, ego=v)))
        for j, st, t0 in decisions:  # applied once latency_ms has passed
            ta_ms = j * 50 + latency_ms
            if ta_ms == t:
                ta_gap = max(0.0, 30.0 - 10.0 * ta_ms / 1000)
                out += det.judge(est(j, st, brake=1.0 if st == P else 0.0), at_t0=t0,
                                 at_apply=truth(P, ta_ms * MS, ego=view(ta_ms, ta_gap)), harness_time_ns=t * MS)
    return out + det.finish(harness_time_ns=frames * 50 * MS)


def test_late_reaction_when_the_brake_came_too_late():
    # STOP believed at frame 10 (t0 = 0.5 s, gap 25 m, needs 12.5 m at 4 m/s^2: in
    # time); applied 1 s later at gap 15 m... still feasible here, so make the
    # collision come before the control: contact at 1.2 s.
    det = CornerCaseDetector("ego0")
    out = [m for m in drive(det, latency_ms=1000, stop_from=10, collide_at_ms=1200)
           if m.kind == MismatchKind.LATE_REACTION]
    (m,) = out
    assert (m.cause, m.severity, m.entity) == (Cause.LATENCY, Severity.CRITICAL, "car1")
    ev = m.evidence
    assert ev["decision_frame_id"] == 10 and ev["applied_before_contact"] is False
    assert ev["latency_sim_ns"] == 1200 * MS - 500 * MS  # still in flight at contact: at least t_c - t0
    assert ev["budget_ns"] == (1800 - 500) * MS  # the first tick with the gap under 12.5 m: 1.8 s
    assert cause_from_evidence(m) == Cause.LATENCY


def test_no_late_reaction_without_latency_or_without_a_timely_belief():
    # Same belief, no latency: the brake came at capture; a collision anyway is not
    # a late reaction.
    det = CornerCaseDetector("ego0")
    assert not [m for m in drive(det, latency_ms=0, stop_from=10, collide_at_ms=1200)
                if m.kind == MismatchKind.LATE_REACTION]
    # STOP believed only at 2.5 s (gap 5 m < 12.5 m needed): decided too late, perception.
    det = CornerCaseDetector("ego0")
    assert not [m for m in drive(det, latency_ms=1000, stop_from=50, collide_at_ms=1900, frames=60)
                if m.kind == MismatchKind.LATE_REACTION]


def test_near_miss_is_a_late_reaction_too():
    det = CornerCaseDetector("ego0", DetectorSettings(near_miss_m=1.0))
    # Applied 2 s after capture, at 2.5 s: the gap (5 m) is under the 12.5 m needed.
    out = [m for m in drive(det, latency_ms=2000, stop_from=10, collide_at_ms=None, frames=70)
           if m.kind == MismatchKind.LATE_REACTION]
    (m,) = out
    assert m.severity == Severity.WARNING and m.evidence["contact"] == "near_miss"
    assert m.sim_time_ns == 2950 * MS  # the first tick under 1 m (gap 0.5 m)
    assert m.evidence["applied_before_contact"] is True and m.measured == 2000.0
    assert cause_from_evidence(m) == Cause.LATENCY


def test_collision_while_safe_carries_the_belief_it_was_judged_on():
    for ref0, cause in ((S, Cause.LATENCY), (P, Cause.PERCEPTION)):
        det = CornerCaseDetector("ego0")
        det.judge(est(7, S), at_t0=truth(ref0, 350 * MS), at_apply=truth(P, 950 * MS), harness_time_ns=0)
        (m,) = det.on_collision(other="car1", sim_time_ns=990 * MS, harness_time_ns=1, frame_id=7, force_n=1.0)
        assert m.cause == cause == cause_from_evidence(m)
        assert (m.evidence["frame_id"], m.evidence["sim_time_t0_ns"], m.evidence["sim_time_apply_ns"],
                m.evidence["collision_sim_time_ns"]) == (7, 350 * MS, 950 * MS, 990 * MS)
