"""The anomaly detector on a camera rig's records (issue 31): per-frame baselines and
episodes are each camera's own, and the frame-rate floor counts frame sets."""

from __future__ import annotations

import numpy as np

from hil.timing.anomaly import AnomalyDetector, AnomalyKind
from hil.timing.records import FrameStatus, PipelineRecord

MS = 1_000_000
START_NS = 1_000_000_000_000
PERIOD_NS = 50 * MS


def _rig(sets: int, e2e_ms: list[float], *, seed: int = 5) -> list[PipelineRecord]:
    """Each set's records (camera k's end to end ``e2e_ms[k]`` plus 0.3 ms of noise),
    answered camera by camera in completion order."""
    rng = np.random.default_rng(seed)
    n = len(e2e_ms)
    out = []
    for s in range(sets):
        t0 = START_NS + s * PERIOD_NS
        recs = [PipelineRecord("ego", s * n + k, s * PERIOD_NS, t0, t0 + 100_000, FrameStatus.OK,
                               t0p_ns=t0 + int((e2e_ms[k] + rng.uniform(0, 0.3)) * MS), camera=k)
                for k in range(n)]
        out += sorted(recs, key=lambda r: r.t0p_ns or 0)
    return out


def test_a_steadily_slower_camera_is_no_spike_jitter_or_reordering_of_the_others() -> None:
    e2e = [4.0, 4.0, 4.0, 19.0, 19.0, 19.0]  # cameras 3-5 steadily 15 ms later (behind camera 3)
    det = AnomalyDetector("ego")
    found = [a for r in _rig(120, e2e) for a in det.on_record(r)]
    assert found == []
    # The same values as one stream (the records without their camera) were flagged.
    flat = AnomalyDetector("ego")
    as_one = [a.kind for r in _rig(120, e2e) for a in flat.on_record(PipelineRecord(
        **{**r.__dict__, "camera": None}))]
    assert AnomalyKind.JITTER in as_one


def test_a_spike_of_one_camera_is_flagged_once_against_its_own_baseline() -> None:
    recs = _rig(120, [4.0, 4.0, 30.0])
    k = next(i for i, r in enumerate(recs) if r.frame_id == 100 * 3 + 1)  # set 100, camera 1
    r = recs[k]
    recs[k] = PipelineRecord(**{**r.__dict__, "t0p_ns": r.t0_ns + 15 * MS})  # 11 ms over its 4 ms
    det = AnomalyDetector("ego")
    found = [a for r in recs for a in det.on_record(r)]
    assert [(a.kind, a.frame_ids) for a in found] == [(AnomalyKind.LATENCY_SPIKE, (301,))]


def test_the_frame_rate_floor_counts_frame_sets_not_frames() -> None:
    # 6 cameras at 5 sets a second: 30 estimates a second, but 5 answered triggers,
    # under the 10 Hz floor.
    det = AnomalyDetector("ego")
    out = []
    for s in range(40):
        t0 = START_NS + s * 200 * MS
        for k in range(6):
            out += det.on_record(PipelineRecord("ego", s * 6 + k, s * 200 * MS, t0, t0 + 100_000, FrameStatus.OK,
                                                t0p_ns=t0 + 5 * MS, camera=k))
        out += det.on_tick(t0 + 6 * MS, s * 200 * MS)
    floors = [a for a in out if a.kind is AnomalyKind.FRAME_RATE_FLOOR]
    assert len(floors) == 1 and floors[0].measured == 5.0
