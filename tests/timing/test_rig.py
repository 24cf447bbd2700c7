"""hil.timing.rig: a rig's frame sets measured from injected stamps: exact skew and
spread, and each anomaly flagged once per episode at the set where it begins."""

from __future__ import annotations

from hil.timing.anomaly import AnomalyKind
from hil.timing.records import FrameStatus, PipelineRecord
from hil.timing.rig import RigThresholds, RigTracker

MS = 1_000_000
NAMES = ("front", "left", "right")
PERIOD = 100 * MS


def rec(set_no: int, cam: int, *, skew: int = 0, tx: int = 0, e2e: int = 5 * MS, shared_answer: bool = False,
        status: FrameStatus = FrameStatus.OK) -> PipelineRecord:
    """Camera ``cam``'s record of set ``set_no`` (frame ids 3 per set): captured
    ``skew`` ns after the set's instant, handed over ``tx`` ns after its render."""
    t_state = set_no * PERIOD + skew
    t0 = t_state + (2 + cam) * MS  # the cameras of an instant render one after another
    t_tx = t0 + tx
    t0p = (set_no * PERIOD + 50 * MS) if shared_answer else t0 + e2e
    ok = status == FrameStatus.OK
    return PipelineRecord("ego0", 3 * set_no + cam, set_no * PERIOD, t0, t_tx, status, t0p_ns=t0p if ok else None,
                          t_state_ns=t_state, camera=cam)


def feed(tr: RigTracker, recs: list[PipelineRecord]) -> list:
    out = []
    for r in recs:
        out += tr.on_record(r)
    return out + tr.finish()


def tracker(**kw: object) -> RigTracker:
    return RigTracker("ego0", NAMES, RigThresholds(**{"horizon_ns": 10 * PERIOD, **kw}))  # type: ignore[arg-type]


def test_a_rig_on_one_trigger_line_has_skew_exactly_zero_and_flags_nothing() -> None:
    tr = tracker()
    assert feed(tr, [rec(s, k, tx=k * MS) for s in range(10) for k in range(3)]) == []
    rig = tr.summary()["rig"]
    assert rig["sets"] == rig["complete"] == 10 and rig["capture_skew_ms_max"] == 0.0
    assert rig["arrival_spread_ms_max"] == 4.0  # 1 ms of render and 1 ms of hand-off a camera
    assert tr.summary()["cameras"]["left"]["frames"] == 10


def test_a_trigger_offset_is_rig_desync_once_with_the_exact_skew() -> None:
    tr = tracker()
    found = feed(tr, [rec(s, k, skew=7 * MS if (k == 2 and s >= 3) else 0) for s in range(10) for k in range(3)])
    assert [(a.kind, a.frame_ids) for a in found] == [(AnomalyKind.RIG_DESYNC, (9, 10, 11))]
    assert found[0].measured == 7.0 and found[0].threshold == 1.0
    assert tr.summary()["rig"]["capture_skew_ms_max"] == 7.0 and tr.summary()["rig"]["desynced"] == 7


def test_desync_is_flagged_again_only_after_a_set_in_step() -> None:
    skews = [0, 5, 5, 0, 5, 0]
    found = feed(tracker(), [rec(s, k, skew=skews[s] * MS if k == 1 else 0) for s in range(6) for k in range(3)])
    assert [a.frame_ids[0] // 3 for a in found] == [1, 4]


def test_a_set_answered_without_a_camera_is_camera_missing_once_naming_it() -> None:
    recs = [rec(s, k) for s in range(8) for k in range(3) if not (k == 1 and s >= 2)]
    tr = tracker()
    found = feed(tr, recs)
    assert [a.kind for a in found] == [AnomalyKind.CAMERA_MISSING]
    assert "left" in found[0].detail and found[0].frame_ids == (6, 8)
    assert tr.summary()["cameras"]["left"]["missing_in_sets"] == 6 and tr.summary()["rig"]["complete"] == 2


def test_a_dropped_camera_counts_as_missing_but_a_wholly_dropped_set_does_not() -> None:
    recs = [rec(0, 0), rec(0, 1, status=FrameStatus.DROPPED), rec(0, 2)]
    recs += [rec(1, k, status=FrameStatus.DROPPED) for k in range(3)]
    found = feed(tracker(), recs)
    assert [(a.kind, a.frame_ids) for a in found] == [(AnomalyKind.CAMERA_MISSING, (0, 1, 2))]


def test_one_camera_persistently_late_is_camera_late_once_naming_it() -> None:
    recs = [rec(s, k, e2e=(40 if k == 2 and s >= 2 else 5) * MS) for s in range(12) for k in range(3)]
    found = feed(tracker(), recs)
    assert [a.kind for a in found] == [AnomalyKind.CAMERA_LATE]
    assert "right" in found[0].detail and found[0].frame_ids[0] == 3 * 6  # the 5th late set running: set 6
    assert found[0].measured == 35.0


def test_a_camera_late_in_fewer_sets_than_the_limit_is_not_flagged() -> None:
    recs = [rec(s, k, e2e=(40 if k == 0 and s in (1, 2, 3, 4, 6, 7) else 5) * MS) for s in range(10) for k in range(3)]
    assert feed(tracker(), recs) == []


def test_one_answer_for_the_whole_set_is_never_camera_late() -> None:
    recs = [rec(s, k, shared_answer=True) for s in range(10) for k in range(3)]
    assert feed(tracker(), recs) == []


def test_an_incomplete_set_waits_for_its_horizon_and_a_late_record_of_it_is_not_a_new_set() -> None:
    tr = tracker(horizon_ns=3 * PERIOD)
    recs = [rec(0, 0), rec(0, 2)] + [rec(s, k) for s in range(1, 6) for k in range(3)]
    found = [a for r in recs for a in tr.on_record(r)]
    assert [a.kind for a in found] == [AnomalyKind.CAMERA_MISSING]  # set 0 settled once set 4 came
    assert tr.on_record(rec(0, 1, status=FrameStatus.DROPPED)) == []  # set 0's drop, after its settling
    tr.finish()
    assert tr.summary()["rig"]["sets"] == 6


def test_records_of_a_single_camera_are_not_a_rig() -> None:
    r = PipelineRecord("ego0", 0, 0, 1, 2, FrameStatus.OK, t0p_ns=3)
    tr = tracker()
    assert tr.on_record(r) == [] and tr.finish() == [] and tr.summary()["rig"]["sets"] == 0
    assert "camera" not in r.to_json() and rec(0, 1).to_json()["camera"] == 1


def test_a_set_whose_every_frame_was_dropped_is_still_one_set_when_its_records_come_late() -> None:
    tr = tracker(horizon_ns=3 * PERIOD)
    recs = [rec(0, k) for k in range(3)] + [rec(s, k) for s in range(2, 9) for k in range(3)]
    recs += [rec(1, k, status=FrameStatus.DROPPED) for k in range(3)]  # after their timeout
    assert feed(tr, recs) == []  # wholly dropped: the dropped_frame anomalies say so, not camera_missing
    rig = tr.summary()["rig"]
    assert (rig["sets"], rig["complete"]) == (9, 8)
