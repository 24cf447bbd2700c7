"""Timing analysis of a run: clock sync per target, cross-clock stage splits,
timing anomalies and streaming stage statistics.

Records are analysed in completion order, each once the sync has a sample newer
than its ``t0'`` (so a split is mapped with a model that already knows about any
clock step before it); a record whose ``[t_tx, t0']`` overlaps a detected clock
step window gets no cross-clock split (its mapping is unknowable) rather than a
false causality alarm. When sync is lost, records older than ``lost_after_s`` are
analysed with what is known, so the queue stays bounded.

Writes ``/<vehicle>/clock`` (the sync state after each sample) and every anomaly
to ``/events`` (``kind`` is the anomaly kind's lower-case name).
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
from typing import Any

from adapters.messages import Estimate
from harness.config_timing import TimingConfig
from harness.recorder import Recorder
from scenarios.ground_truth import GroundTruth
from timing.anomaly import Anomaly, AnomalyDetector
from timing.histogram import StageHistograms
from timing.pipeline import split_stages
from timing.records import PipelineRecord
from timing.stats import summarize_ns
from timing.sync import ClockSync, SyncEvent, SyncEventKind, SyncSample, SyncState

TICK_NS = 100_000_000


@dataclass
class _VehicleTiming:
    sync: ClockSync
    detector: AnomalyDetector
    hist: StageHistograms = field(default_factory=StageHistograms)
    pending: deque[PipelineRecord] = field(default_factory=deque)
    step_windows: list[tuple[int, int]] = field(default_factory=list)
    last_sample_t4: int | None = None
    splits: dict[str, list[tuple[int, int]]] = field(default_factory=lambda: {"uplink": [], "downlink": []})
    anomalies: list[Anomaly] = field(default_factory=list)
    sync_events: dict[str, int] = field(default_factory=dict)
    sim_time_ns: int = 0


class TimingObserver:
    """A ``RunObserver``; ``summary()`` gives the per-vehicle timing figures."""

    def __init__(self, cfg: TimingConfig, vehicles: list[str], *, recorder: Recorder) -> None:
        self.cfg = cfg
        self.rec = recorder
        self.lost_after_ns = int(cfg.sync.lost_after_s * 1e9)
        sync_cfg = cfg.sync.to_sync_config()
        self.v: dict[str, _VehicleTiming] = {
            name: _VehicleTiming(ClockSync(sync_cfg), AnomalyDetector(name, cfg.thresholds_for(name)))
            for name in vehicles}
        self._next_tick_ns = 0

    # -- observer hooks -------------------------------------------------------

    def on_truth(self, gt: GroundTruth, *, t_ns: int) -> None:
        for vt in self.v.values():
            vt.sim_time_ns = gt.sim_time_ns

    def on_sync(self, vehicle: str, sample: SyncSample) -> None:
        vt = self.v[vehicle]
        events = vt.sync.add(sample)
        self._sync_events(vehicle, vt, events)
        vt.last_sample_t4 = sample.t4_ns
        st = vt.sync.state()
        if st.samples_used:
            self.rec.write_json(f"/{vehicle}/clock", _state_json(st), log_time_ns=sample.t4_ns,
                                publish_time_ns=sample.t1_ns)
        self._flush(vehicle, vt, now_ns=sample.t4_ns)

    def on_record(self, vehicle: str, rec: PipelineRecord, estimate: Estimate | None) -> None:
        vt = self.v[vehicle]
        vt.pending.append(rec)
        self._flush(vehicle, vt, now_ns=rec.t0p_ns or rec.t_tx_ns)

    def on_tick(self, *, now_ns: int, sim_time_ns: int) -> None:
        if now_ns < self._next_tick_ns:
            return
        self._next_tick_ns = now_ns + TICK_NS
        for name, vt in self.v.items():
            self._sync_events(name, vt, vt.sync.check(now_ns))
            self._emit(name, vt, vt.detector.on_tick(now_ns, sim_time_ns))
            self._flush(name, vt, now_ns=now_ns)

    # -- analysis -------------------------------------------------------------

    def _sync_events(self, vehicle: str, vt: _VehicleTiming, events: list[SyncEvent]) -> None:
        for ev in events:
            vt.sync_events[ev.kind.value] = vt.sync_events.get(ev.kind.value, 0) + 1
            if ev.kind == SyncEventKind.CLOCK_STEP and ev.since_ns is not None:
                vt.step_windows.append((ev.since_ns, ev.harness_time_ns))
        self._emit(vehicle, vt, vt.detector.on_sync_events(events, sim_time_ns=vt.sim_time_ns))

    def _flush(self, vehicle: str, vt: _VehicleTiming, *, now_ns: int, force: bool = False) -> None:
        while vt.pending:
            rec = vt.pending[0]
            mapped_ready = rec.t0p_ns is None or (vt.last_sample_t4 is not None and vt.last_sample_t4 > rec.t0p_ns)
            too_old = now_ns - (rec.t0p_ns or rec.t_tx_ns) > self.lost_after_ns
            if not (mapped_ready or too_old or force):
                return
            vt.pending.popleft()
            self._analyse(vehicle, vt, rec)

    def _analyse(self, vehicle: str, vt: _VehicleTiming, rec: PipelineRecord) -> None:
        st = vt.sync.state()
        in_step = any(a <= (rec.t0p_ns or rec.t_tx_ns) and rec.t_tx_ns <= b for a, b in vt.step_windows)
        mapper = st if st.samples_used and not in_step else None
        splits = split_stages(rec, mapper) if mapper is not None else None
        anomalies = vt.detector.on_record(rec, splits=splits, mapper=mapper)
        self._emit(vehicle, vt, anomalies)
        if vt.hist.record_record(rec) and splits is not None:
            for name in ("uplink", "downlink"):
                if name in splits:
                    vt.splits[name].append((splits[name].value_ns, splits[name].uncertainty_ns))
                    vt.hist.record(name, splits[name].value_ns)

    def _emit(self, vehicle: str, vt: _VehicleTiming, anomalies: list[Anomaly]) -> None:
        for a in anomalies:
            vt.anomalies.append(a)
            d = a.to_json()
            d["kind"] = a.kind.value.lower()
            d["vehicle"] = vehicle
            t = a.harness_time_ns
            self.rec.write_json("/events", d, log_time_ns=t, publish_time_ns=t)

    # -- results --------------------------------------------------------------

    def finish(self) -> None:
        """Analyse what is still pending (end of run)."""
        for name, vt in self.v.items():
            self._flush(name, vt, now_ns=0, force=True)

    def anomaly_count(self, vehicle: str) -> int:
        return len(self.v[vehicle].anomalies)

    def live_p(self, vehicle: str, q: float) -> float | None:
        p = self.v[vehicle].hist.percentiles_ms("end_to_end")
        return p.get(f"p{q:g}_ms") if p.get("count") else None  # type: ignore[return-value]

    def summary(self, vehicle: str) -> dict[str, Any]:
        vt = self.v[vehicle]
        st = vt.sync.state()
        splits: dict[str, Any] = {}
        for name, vals in vt.splits.items():
            s = summarize_ns(v for v, _ in vals)
            if vals:
                s["uncertainty_p50_ms"] = round(float(sorted(u for _, u in vals)[len(vals) // 2]) / 1e6, 4)
                s["uncertainty_max_ms"] = round(max(u for _, u in vals) / 1e6, 4)
            splits[name] = s
        counts: dict[str, int] = {}
        for a in vt.anomalies:
            counts[a.kind.value.lower()] = counts.get(a.kind.value.lower(), 0) + 1
        return {
            "clock": {
                "synced": st.synced, "offset_ns": st.offset_ns if st.samples_used else None,
                "skew_ppm": round(st.skew_ppm, 3), "skew_uncertainty_ppm": round(st.skew_uncertainty_ppm, 3),
                "uncertainty_ns": st.uncertainty_ns if st.samples_used else None, "delay_ns": st.delay_ns,
                "samples_used": st.samples_used, "events": dict(vt.sync_events),
                "rejected": dict(getattr(vt.sync, "rejected", {})),
            },
            "splits_ms": splits,
            "streaming_ms": vt.hist.summary_ms(),
            "anomalies": counts,
            "records_excluded": vt.detector.excluded,
        }


def _state_json(st: SyncState) -> dict[str, Any]:
    return {"offset_ns": st.offset_ns, "ref_ns": st.ref_ns, "skew_ppm": st.skew_ppm,
            "skew_uncertainty_ppm": st.skew_uncertainty_ppm, "uncertainty_ns": st.uncertainty_ns,
            "delay_ns": st.delay_ns, "samples_used": st.samples_used, "synced": st.synced}
