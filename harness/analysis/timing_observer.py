"""Timing analysis of a run: clock sync per target, cross-clock stage splits,
timing anomalies and streaming stage statistics.

Records are analysed in completion order, each once the sync has *accepted* a
sample newer than its ``t0'`` and holds no unconfirmed outlier (so a split is mapped
with a model that already knows about any clock step before it). A record whose
``[t_tx, t0']`` overlaps a detected clock step's window (last good sample before it
→ its detection) gets no cross-clock split: its mapping is unknowable, and the old
mapping put splits far outside their stated bound (issue 12). A record wholly
before a step is mapped with the model from before it. Such records, and those
whose mapped stamps break causality, are left out of the split statistics and
counted (``splits_excluded``). When sync is lost, records older than
``lost_after_s`` are analysed with what is known, so the queue stays bounded.

The frame-rate floor counts estimates by their receipt time ``t0'`` over windows
that are complete: a window ends before the oldest record still waiting for a
sync sample, and at least ``handoff_margin_ns`` before now while no record flows.

Writes ``/<vehicle>/clock`` (the sync state after each sample) and every anomaly
to ``/events`` (``kind`` is the anomaly kind's lower-case name).
"""

from __future__ import annotations

from bisect import bisect_right
from collections import deque
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import Any, NamedTuple

import numpy as np

from hil.adapters.wire.messages import Estimate
from hil.harness.config.model import RunConfig
from hil.harness.config.timing import TimingConfig
from hil.harness.vocab.events import Event, EventBus, JsonSink
from hil.scenarios.ground_truth import GroundTruth
from hil.timing.anomaly import Anomaly, AnomalyDetector
from hil.timing.histogram import StageHistograms
from hil.timing.pipeline import Split, causality_violations, split_stages
from hil.timing.records import PipelineRecord
from hil.timing.rig import RigThresholds, RigTracker
from hil.timing.stats import SpillColumn, summarize_ns
from hil.timing.sync import ClockSync, SyncEvent, SyncEventKind, SyncSample, SyncState

TICK_NS = 100_000_000
HANDOFF_MARGIN_NS = 500_000_000  # an estimate is handed over well within this after t0'
TICK_MEMORY = 600                # ticks remembered to date frame-rate anomalies (60 s)
RECENT_ANOMALIES = 4096          # anomalies kept to link to mismatches (their counts: all)


class SplitRow(NamedTuple):
    """One frame's cross-clock split as reported (signed value and bound, ns)."""

    frame_id: int
    value_ns: int
    uncertainty_ns: int


class SplitColumns:
    """A run's split rows in three int64 columns spilled to disk in blocks
    (``hil.timing.stats.SpillColumn``: bounded memory however long the run): append
    ``SplitRow``s, read them back in order as arrays or rows."""

    def __init__(self) -> None:
        self._frame, self._value, self._unc = SpillColumn(), SpillColumn(), SpillColumn()

    def append(self, row: SplitRow) -> None:
        self._frame.append(row.frame_id)
        self._value.append(row.value_ns)
        self._unc.append(row.uncertainty_ns)

    def __len__(self) -> int:
        return len(self._frame)

    @property
    def columns(self) -> tuple[SpillColumn, SpillColumn, SpillColumn]:
        """The three columns (frame ids, values, bounds), e.g. for their spill failures."""
        return self._frame, self._value, self._unc

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(frame ids, values, bounds), int64, in order of appending."""
        return self._frame.to_numpy(), self._value.to_numpy(), self._unc.to_numpy()

    def __iter__(self) -> Iterator[SplitRow]:
        frames, values, uncs = self.arrays()
        return (SplitRow(f, v, u) for f, v, u in zip(frames.tolist(), values.tolist(), uncs.tolist()))


@dataclass(frozen=True)
class _StepWindow:
    """A detected clock step: the last good sample before it, its detection (harness
    ns), and the model that held before it."""

    since_ns: int
    detected_ns: int
    before: SyncState


@dataclass
class _VehicleTiming:
    sync: ClockSync
    detector: AnomalyDetector
    hist: StageHistograms = field(default_factory=StageHistograms)
    pending: deque[PipelineRecord] = field(default_factory=deque)
    step_windows: list[_StepWindow] = field(default_factory=list)
    last_handed_t0p_ns: int | None = None
    splits: dict[str, SplitColumns] = field(default_factory=lambda: {"uplink": SplitColumns(),
                                                                      "downlink": SplitColumns()})
    excluded: dict[str, int] = field(default_factory=dict)
    anomalies: deque[Anomaly] = field(default_factory=lambda: deque(maxlen=RECENT_ANOMALIES))  # to link mismatches
    anomaly_counts: dict[str, int] = field(default_factory=dict)  # every anomaly, by kind
    anomaly_causes: dict[str, dict[str, int]] = field(default_factory=dict)  # side -> kind -> count
    sync_events: dict[str, int] = field(default_factory=dict)
    sim_time_ns: int = 0
    rig: RigTracker | None = None  # a rig of several cameras: its frame sets


def rig_of(cfg: RunConfig) -> tuple[tuple[str, ...], RigThresholds] | None:
    """A run's rig as its timing analysis needs it (None: one camera)."""
    cams = cfg.camera.cameras()
    if len(cams) < 2:
        return None
    r, period_ms = cfg.timing.rig, 1e3 / cfg.camera.fps
    return tuple(c.name for c in cams), RigThresholds(
        skew_ms=r.skew_ms, spread_ms=r.spread_ms if r.spread_ms is not None else period_ms, late_ms=r.late_ms,
        late_sets=r.late_sets, horizon_ns=int((cfg.target.estimate_timeout_s * 1e3 + 2 * period_ms) * 1e6),
        frame_late_tolerance_ns=cfg.frame_late_tolerance_ns)


class TimingObserver:
    """A ``RunObserver``; ``summary()`` gives the per-vehicle timing figures."""

    def __init__(self, cfg: TimingConfig, vehicles: list[str], *, recorder: JsonSink,
                 events: EventBus | None = None, handoff_margin_ns: int = HANDOFF_MARGIN_NS,
                 rig: tuple[tuple[str, ...], RigThresholds] | None = None, rate_floor: bool = True) -> None:
        """``events``: the run's bus the anomalies go on (default: one that records
        them on ``recorder``'s ``/events``). ``handoff_margin_ns``: the longest the
        loop takes to hand a received estimate over; frame-rate windows closer to now
        than that are judged only once a record has shown them complete. ``rig``: the
        names of a rig's cameras and its limits (``rig_of``), for its frame sets.
        ``rate_floor``: judge the estimates' rate against the frame-rate floor (not in
        lockstep: ``for_run``)."""
        self.cfg = cfg
        self.rate_floor = rate_floor
        self.handoff_margin_ns = handoff_margin_ns
        self.rec = recorder
        self.events = events if events is not None else EventBus.recording_to(recorder)
        self.lost_after_ns = int(cfg.sync.lost_after_s * 1e9)
        sync_cfg = cfg.sync.to_sync_config()
        self.v: dict[str, _VehicleTiming] = {
            name: _VehicleTiming(ClockSync(sync_cfg), AnomalyDetector(name, cfg.thresholds_for(name)))
            for name in vehicles}
        if rig is not None:
            for name, vt in self.v.items():
                vt.rig = RigTracker(name, rig[0], rig[1])
        self._next_tick_ns = 0
        self._ticks: deque[tuple[int, int]] = deque(maxlen=TICK_MEMORY)  # (harness ns, sim ns)

    @classmethod
    def for_run(cls, cfg: RunConfig, vehicles: list[str], *, recorder: JsonSink, events: EventBus) -> TimingObserver:
        """The observer of a run of ``cfg``: its rig's frame sets (``rig_of``) and, in
        real time only, the frame-rate floor (``Mode.judges_rate_floor``)."""
        return cls(cfg.timing, vehicles, recorder=recorder, events=events, rig=rig_of(cfg),
                   rate_floor=cfg.mode.judges_rate_floor)

    # -- observer hooks -------------------------------------------------------

    def on_truth(self, gt: GroundTruth, *, t_ns: int) -> None:
        for vt in self.v.values():
            vt.sim_time_ns = gt.sim_time_ns

    def on_sync(self, vehicle: str, sample: SyncSample) -> None:
        vt = self.v[vehicle]
        before = vt.sync.state()
        events = vt.sync.add(sample)
        for ev in events:
            if ev.kind == SyncEventKind.CLOCK_STEP:
                since = ev.since_ns if ev.since_ns is not None else before.last_sample_ns
                vt.step_windows.append(_StepWindow(since if since is not None else 0, ev.harness_time_ns,
                                                   before))
        self._sync_events(vehicle, vt, events)
        st = vt.sync.state()
        if st.samples_used:
            self.rec.write_json(f"/{vehicle}/clock", _state_json(st), log_time_ns=sample.t4_ns,
                                publish_time_ns=sample.t1_ns)
        self._flush(vehicle, vt, now_ns=sample.t4_ns)

    def on_record(self, vehicle: str, rec: PipelineRecord, estimate: Estimate | None) -> None:
        vt = self.v[vehicle]
        if vt.rig is not None and rec.camera is None and not vt.rig.sets:
            # A rig whose target takes one camera gets camera 0 as a single camera
            # (the run said so once, rig_camera_zero_only): no frame sets to judge.
            vt.rig = None
        if vt.rig is not None:
            self._emit(vehicle, vt, vt.rig.on_record(rec))
        vt.pending.append(rec)
        if rec.t0p_ns is not None:
            vt.last_handed_t0p_ns = max(vt.last_handed_t0p_ns or 0, rec.t0p_ns)
        self._flush(vehicle, vt, now_ns=rec.t0p_ns or rec.t_tx_ns)

    def on_tick(self, *, now_ns: int, sim_time_ns: int) -> None:
        if now_ns < self._next_tick_ns:
            return
        self._next_tick_ns = now_ns + TICK_NS
        self._ticks.append((now_ns, sim_time_ns))
        for name, vt in self.v.items():
            self._sync_events(name, vt, vt.sync.check(now_ns))
            self._flush(name, vt, now_ns=now_ns)
            if not self.rate_floor:
                continue
            found = vt.detector.on_tick(now_ns, sim_time_ns, complete_until_ns=self._complete_until(vt, now_ns))
            self._emit(name, vt, [replace(a, sim_time_ns=self._sim_time_at(a.harness_time_ns)) for a in found])

    def _sim_time_at(self, t_ns: int) -> int | None:
        """Sim time (ns) at harness instant ``t_ns`` (a frame-rate window's end, up to
        a few seconds back), from the ticks: the last tick at or before it."""
        i = bisect_right(self._ticks, (t_ns, 2**63)) - 1
        return self._ticks[i][1] if i >= 0 else None

    def _complete_until(self, vt: _VehicleTiming, now_ns: int) -> int:
        """Harness instant up to which every received estimate has been analysed:
        before the oldest record still pending, and no later than the newest
        handed-over ``t0'`` or ``now − handoff_margin_ns`` (receipt order is
        completion order, so a newer ``t0'`` shows all older ones are in)."""
        horizon = max(vt.last_handed_t0p_ns or 0, now_ns - self.handoff_margin_ns)
        waiting = [r.t0p_ns for r in vt.pending if r.t0p_ns is not None]
        return min(horizon, min(waiting) - 1) if waiting else horizon

    # -- analysis -------------------------------------------------------------

    def _sync_events(self, vehicle: str, vt: _VehicleTiming, events: list[SyncEvent]) -> None:
        for ev in events:
            vt.sync_events[ev.kind.value] = vt.sync_events.get(ev.kind.value, 0) + 1
        self._emit(vehicle, vt, vt.detector.on_sync_events(events, sim_time_ns=vt.sim_time_ns))

    def _flush(self, vehicle: str, vt: _VehicleTiming, *, now_ns: int, force: bool = False) -> None:
        st = vt.sync.state()
        covered_ns = st.last_sample_ns if st.samples_used and not vt.sync.unconfirmed else None
        while vt.pending:
            rec = vt.pending[0]
            mapped_ready = rec.t0p_ns is None or (covered_ns is not None and covered_ns > rec.t0p_ns)
            too_old = now_ns - (rec.t0p_ns or rec.t_tx_ns) > self.lost_after_ns
            if not (mapped_ready or too_old or force):
                return
            vt.pending.popleft()
            self._analyse(vehicle, vt, rec, covered=mapped_ready)

    def _mapper(self, vt: _VehicleTiming, rec: PipelineRecord, *, covered: bool) -> tuple[SyncState | None, str]:
        """The model that maps ``rec``'s target stamps, or ``None`` and why not."""
        st = vt.sync.state()
        if not st.samples_used:
            return None, ""
        lo, hi = rec.t_tx_ns, rec.t0p_ns or rec.t_tx_ns
        for w in vt.step_windows:
            if w.since_ns <= hi and lo <= w.detected_ns:
                return None, "clock_step"  # the step may lie anywhere in its window
            if hi < w.since_ns:
                return (w.before if w.before.samples_used else None), ""
        if not covered and vt.sync.unconfirmed:
            return None, "unconfirmed_sync"  # maybe a step not yet confirmed
        return st, ""

    def _analyse(self, vehicle: str, vt: _VehicleTiming, rec: PipelineRecord, *, covered: bool = True) -> None:
        mapper, why = self._mapper(vt, rec, covered=covered)
        splits = split_stages(rec, mapper) if mapper is not None else None
        anomalies = vt.detector.on_record(rec, splits=splits, mapper=mapper)
        self._emit(vehicle, vt, anomalies)
        if not vt.hist.record_record(rec):
            return
        if mapper is None:
            if why and rec.t_rx_target_ns is not None and rec.t0p_ns is not None:
                vt.excluded[why] = vt.excluded.get(why, 0) + 1
            return
        assert splits is not None
        if "uplink" not in splits:
            return
        if causality_violations(rec, mapper):  # the mapping is wrong here: no honest split
            vt.excluded["causality"] = vt.excluded.get("causality", 0) + 1
            return
        for name in ("uplink", "downlink"):
            sp: Split = splits[name]
            vt.splits[name].append(SplitRow(rec.frame_id, sp.value_ns, sp.uncertainty_ns))
            if sp.value_ns >= 0:  # the streaming histograms hold only non-negative values
                vt.hist.record(name, sp.value_ns)

    def _emit(self, vehicle: str, vt: _VehicleTiming, anomalies: list[Anomaly]) -> None:
        for a in anomalies:
            vt.anomalies.append(a)
            kind = a.kind.value.lower()
            vt.anomaly_counts[kind] = vt.anomaly_counts.get(kind, 0) + 1
            if a.cause is not None:
                by = vt.anomaly_causes.setdefault(a.cause, {})
                by[kind] = by.get(kind, 0) + 1
            self.events.publish(Event.from_anomaly(a, vehicle))

    # -- results --------------------------------------------------------------

    def finish(self) -> None:
        """Analyse what is still pending (end of run)."""
        for name, vt in self.v.items():
            self._flush(name, vt, now_ns=0, force=True)
            if vt.rig is not None:
                self._emit(name, vt, vt.rig.finish())

    def anomaly_count(self, vehicle: str) -> int:
        return sum(self.v[vehicle].anomaly_counts.values())

    def anomalies_of(self, vehicle: str) -> Sequence[Anomaly]:
        """The vehicle's latest ``RECENT_ANOMALIES`` anomalies, in the order they were
        found (none for a vehicle this observer does not time)."""
        vt = self.v.get(vehicle)
        return vt.anomalies if vt is not None else ()

    def live_p(self, vehicle: str, q: float) -> float | None:
        p = self.v[vehicle].hist.percentiles_ms("end_to_end")
        v = p.get(f"p{q:g}_ms") if p.get("count") else None
        return None if v is None else float(v)

    def splits(self, vehicle: str) -> dict[str, list[SplitRow]]:
        """Every reported cross-clock split of ``vehicle``, in analysis order."""
        return {name: list(rows) for name, rows in self.v[vehicle].splits.items()}

    def deadlines(self, vehicle: str) -> Mapping[str, float]:
        """The vehicle's stage budgets (ms), as its anomaly detector judges them."""
        return self.v[vehicle].detector.thresholds.deadline_ms

    def split_lower_bounds(self, vehicle: str) -> dict[str, np.ndarray]:
        """Each cross-clock split's values less their bound (ns, int64), in order."""
        out = {}
        for name, rows in self.v[vehicle].splits.items():
            _frames, values, uncs = rows.arrays()
            out[name] = values - uncs
        return out

    def summary(self, vehicle: str) -> dict[str, Any]:
        vt = self.v[vehicle]
        st = vt.sync.state()
        splits: dict[str, Any] = {name: _split_summary(rows) for name, rows in vt.splits.items()}
        counts = dict(vt.anomaly_counts)
        return {
            "clock": {
                "synced": st.synced, "offset_ns": st.offset_ns if st.samples_used else None,
                "ref_ns": st.ref_ns if st.samples_used else None,
                "skew_ppm": round(st.skew_ppm, 3), "skew_uncertainty_ppm": round(st.skew_uncertainty_ppm, 3),
                "uncertainty_ns": st.uncertainty_ns if st.samples_used else None, "delay_ns": st.delay_ns,
                "samples_used": st.samples_used, "events": dict(vt.sync_events),
                "rejected": dict(getattr(vt.sync, "rejected", {})),
            },
            "splits_ms": splits,
            "splits_excluded": {k: vt.excluded.get(k, 0) for k in SPLIT_EXCLUSIONS},
            "streaming_ms": vt.hist.summary_ms(),
            "anomalies": counts,
            "anomaly_causes": {side: dict(by) for side, by in sorted(vt.anomaly_causes.items())},
            "records_excluded": vt.detector.excluded,
            **(vt.rig.summary() if vt.rig is not None else {}),
        }


SPLIT_EXCLUSIONS = ("clock_step", "unconfirmed_sync", "causality")


def _split_summary(rows: SplitColumns) -> dict[str, Any]:
    """Exact statistics of signed split values (ms), with the bound of the smallest
    and largest, and how many came out negative (each within its bound)."""
    _frames, values, uncs = rows.arrays()
    s: dict[str, Any] = summarize_ns(values)
    if len(values):
        unc = np.sort(uncs)
        lo, hi = int(np.argmin(values)), int(np.argmax(values))  # the first of equals, as min()/max()
        s["uncertainty_p50_ms"] = round(int(unc[len(unc) // 2]) / 1e6, 4)
        s["uncertainty_max_ms"] = round(int(unc[-1]) / 1e6, 4)
        s["min_uncertainty_ms"] = round(int(uncs[lo]) / 1e6, 4)
        s["max_uncertainty_ms"] = round(int(uncs[hi]) / 1e6, 4)
        s["negative"] = int(np.count_nonzero(values < 0))
    return s


def _state_json(st: SyncState) -> dict[str, Any]:
    return {"offset_ns": st.offset_ns, "ref_ns": st.ref_ns, "skew_ppm": st.skew_ppm,
            "skew_uncertainty_ppm": st.skew_uncertainty_ppm, "uncertainty_ns": st.uncertainty_ns,
            "delay_ns": st.delay_ns, "samples_used": st.samples_used, "synced": st.synced}
