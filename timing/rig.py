"""Timing of a vehicle's camera rig: its frame sets, camera by camera (issue 31).

A rig's frames come as settled pipeline records that name their camera
(``PipelineRecord.camera``); a frame set is ``frame_id - camera`` (PROTOCOL.md
4.2.1). :class:`RigTracker` gathers each set's records and, once the set is settled
(every camera's record in, or ``horizon_ns`` after its first frame when a later
record shows time has passed), measures it on the harness clock alone:

* capture skew: the spread of the set's capture instants (``t_state``): 0 with one
  trigger line, the trigger offsets otherwise (exact: one clock);
* arrival spread: the spread of the set's hand-offs to the link (``t_tx``): how far
  apart the target can get the set's frames;
* end-to-end from the set's first capture and from its last, to its last answer (``t0'``).

Conditions are flagged once per episode, at the set where they begin, and re-armed
by a set without them (as ``hil.timing.anomaly`` does):

* ``RIG_DESYNC``: capture skew over ``skew_ms`` or arrival spread over ``spread_ms``;
* ``CAMERA_MISSING``: a set answered (one camera's estimate applied at least) without
  some camera: its frame never sent, dropped, or stale;
* ``CAMERA_LATE``: one camera's end-to-end (``t0' - t0``) above the median of its
  set's cameras by more than ``late_ms``, in ``late_sets`` sets running, where the
  target answers camera by camera; the event names the camera.
"""

from __future__ import annotations

from collections import OrderedDict, deque
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from hil.timing.anomaly import SEVERITY, Anomaly, AnomalyKind
from hil.timing.records import FrameStatus, PipelineRecord
from hil.timing.stats import SpillColumn, summarize_ns

MAX_PENDING_SETS = 256  # sets awaiting their records; beyond, the oldest is settled as it stands
SETTLED_MEMORY = 4096   # settled set ids remembered (a late record of one is not a new set)


@dataclass(frozen=True, kw_only=True)
class RigThresholds:
    """Limits of a rig's anomalies (ms; ``late_sets`` in sets). ``horizon_ns``: how
    long after its first frame's capture a set may wait for its records (the
    estimate timeout and a camera period: every sent frame has its record by then)."""

    skew_ms: float = 1.0
    spread_ms: float = 100.0
    late_ms: float = 20.0
    late_sets: int = 5
    horizon_ns: int = 2_000_000_000
    frame_late_tolerance_ns: int = 100_000_000


@dataclass
class _Camera:
    frames: int = 0
    late_frames: int = 0  # handed to the link more than the frame tolerance after its capture
    missing: int = 0      # sets answered without this camera
    run_late: int = 0     # sets running in which it was late
    flagged_late: bool = False
    stages: dict[str, SpillColumn] = field(default_factory=lambda: {
        s: SpillColumn() for s in ("render", "capture_to_send", "end_to_end")})


class RigTracker:
    """One vehicle's rig (``cameras``: their names, camera 0 first); feed it every
    settled record of the vehicle in settling order."""

    def __init__(self, vehicle: str, cameras: tuple[str, ...], th: RigThresholds) -> None:
        self.vehicle, self.names, self.th = vehicle, cameras, th
        self.n = len(cameras)
        self.cams = [_Camera() for _ in cameras]
        self._pending: OrderedDict[int, dict[int, PipelineRecord]] = OrderedDict()
        self.sets = self.complete = self.desynced = 0
        self.skew_max_ns = 0
        self._spread, self._from_first, self._from_last = SpillColumn(), SpillColumn(), SpillColumn()
        self._desync = self._missing = False
        # Sets settled lately: a record of one of them is not a new set. A set whose
        # every frame was dropped comes whole after later ones: a set of its own.
        self._settled: set[int] = set()
        self._settled_order: deque[int] = deque()

    def on_record(self, rec: PipelineRecord) -> list[Anomaly]:
        """A settled record; the anomalies of the sets this settles."""
        if rec.camera is None or not 0 <= rec.camera < self.n:
            return []
        self._count(rec)
        set_id = rec.frame_id - rec.camera
        if set_id in self._settled:  # its set was settled without it (a drop's record comes late)
            return []
        self._pending.setdefault(set_id, {})[rec.camera] = rec
        out: list[Anomaly] = []
        now = rec.t_state_ns if rec.t_state_ns is not None else rec.t0_ns
        while self._pending:
            sid, recs = next(iter(self._pending.items()))
            first = min(r.t_state_ns if r.t_state_ns is not None else r.t0_ns for r in recs.values())
            if len(recs) < self.n and now - first <= self.th.horizon_ns and len(self._pending) <= MAX_PENDING_SETS:
                break
            del self._pending[sid]
            out += self._settle(sid, recs)
        return out

    def finish(self) -> list[Anomaly]:
        """The end of the run: every set still waiting is settled as it stands."""
        out: list[Anomaly] = []
        while self._pending:
            sid, recs = self._pending.popitem(last=False)
            out += self._settle(sid, recs)
        return out

    def _count(self, rec: PipelineRecord) -> None:
        assert rec.camera is not None
        c = self.cams[rec.camera]
        c.frames += 1
        if rec.t_state_ns is not None and rec.t_tx_ns - rec.t_state_ns > self.th.frame_late_tolerance_ns:
            c.late_frames += 1
        if rec.status == FrameStatus.OK:
            for name, v in rec.stages_ns().items():
                if name in c.stages and v >= 0:
                    c.stages[name].append(v)

    def _settle(self, set_id: int, recs: dict[int, PipelineRecord]) -> list[Anomaly]:
        self.sets += 1
        self._settled.add(set_id)
        self._settled_order.append(set_id)
        if len(self._settled_order) > SETTLED_MEMORY:
            self._settled.discard(self._settled_order.popleft())
        ok = {k: r for k, r in recs.items() if r.status == FrameStatus.OK and r.t0p_ns is not None}
        states = [r.t_state_ns if r.t_state_ns is not None else r.t0_ns for r in recs.values()]
        skew = max(states) - min(states)
        spread = max(r.t_tx_ns for r in recs.values()) - min(r.t_tx_ns for r in recs.values())
        self.skew_max_ns = max(self.skew_max_ns, skew)
        self._spread.append(spread)
        if ok:  # the set's last answer, from the first and the last capture it answers
            last_answer = max(r.t0p_ns or 0 for r in ok.values())
            answered = [r.t_state_ns if r.t_state_ns is not None else r.t0_ns for r in ok.values()]
            self._from_first.append(last_answer - min(answered))
            self._from_last.append(last_answer - max(answered))
        sim_ns = next(iter(recs.values())).sim_time_ns
        t_ns = max(r.t0p_ns or r.t_tx_ns for r in recs.values())
        frames = tuple(sorted(r.frame_id for r in recs.values()))
        out: list[Anomaly] = []

        def flag(kind: AnomalyKind, measured: float, threshold: float, unit: str, detail: str) -> None:
            out.append(Anomaly(kind, self.vehicle, frames, sim_ns, t_ns, round(measured, 4), threshold, unit,
                               SEVERITY[kind], detail=detail))

        desync = skew > self.th.skew_ms * 1e6 or spread > self.th.spread_ms * 1e6
        self.desynced += desync
        if desync and not self._desync:
            by_skew = skew > self.th.skew_ms * 1e6
            flag(AnomalyKind.RIG_DESYNC, (skew if by_skew else spread) / 1e6,
                 self.th.skew_ms if by_skew else self.th.spread_ms, "ms",
                 f"frame set {set_id}: capture skew {skew / 1e6:.3f} ms, arrival spread {spread / 1e6:.3f} ms "
                 f"(limits {self.th.skew_ms:g} and {self.th.spread_ms:g} ms)")
        self._desync = desync
        missing = [k for k in range(self.n) if k not in ok]
        if ok and not missing:
            self.complete += 1
        for k in missing if ok else ():
            self.cams[k].missing += 1
        if ok and missing and not self._missing:
            names = ", ".join(self.names[k] for k in missing)
            flag(AnomalyKind.CAMERA_MISSING, len(missing), 0, "cameras",
                 f"frame set {set_id} answered without camera(s) {names}")
        self._missing = bool(ok and missing)
        self._late(set_id, ok, flag)
        return out

    def _late(self, set_id: int, ok: dict[int, PipelineRecord], flag: Any) -> None:
        """Each camera's end-to-end (``t0' - t0``: its own render left out, as the
        cameras of an instant are rendered one after another) against its set's
        median. Only where the target answered camera by camera: one answer for the
        whole set is as late as the set's last frame (arrival spread says that)."""
        e2e = {k: (r.t0p_ns or 0) - r.t0_ns for k, r in ok.items()}
        if len(e2e) < 2 or len({r.t0p_ns for r in ok.values()}) == 1:
            return
        median = float(np.median(list(e2e.values())))
        for k, c in enumerate(self.cams):
            over = k in e2e and e2e[k] - median > self.th.late_ms * 1e6
            c.run_late = c.run_late + 1 if over else 0
            if c.run_late >= self.th.late_sets and not c.flagged_late:
                c.flagged_late = True
                flag(AnomalyKind.CAMERA_LATE, (e2e[k] - median) / 1e6, self.th.late_ms, "ms",
                     f"camera {self.names[k]} (index {k}) late in {c.run_late} frame sets running, up to frame "
                     f"set {set_id}: its end-to-end {(e2e[k] - median) / 1e6:.3f} ms over its set's median")
            elif k in e2e and not over:
                c.flagged_late = False

    def summary(self) -> dict[str, Any]:
        """``cameras`` (per camera: frames, late frames, sets answered without it, the
        p50 of its stages) and ``rig`` (per set) of the vehicle's summary."""
        cameras = {}
        for name, c in zip(self.names, self.cams):
            cameras[name] = {"frames": c.frames, "late_frames": c.late_frames, "missing_in_sets": c.missing,
                             **{f"{s}_p50_ms": summarize_ns(col).get("p50_ms") for s, col in c.stages.items()}}
        spread = summarize_ns(self._spread)
        return {"cameras": cameras, "rig": {
            "sets": self.sets, "complete": self.complete, "desynced": self.desynced,
            "capture_skew_ms_max": self.skew_max_ns / 1e6,
            "arrival_spread_ms_p50": spread.get("p50_ms"), "arrival_spread_ms_max": spread.get("max_ms"),
            "e2e_from_first_capture_ms_p50": summarize_ns(self._from_first).get("p50_ms"),
            "e2e_from_last_capture_ms_p50": summarize_ns(self._from_last).get("p50_ms"),
            "thresholds": {"skew_ms": self.th.skew_ms, "spread_ms": self.th.spread_ms, "late_ms": self.th.late_ms,
                           "late_sets": self.th.late_sets}}}


__all__ = ["RigThresholds", "RigTracker"]
