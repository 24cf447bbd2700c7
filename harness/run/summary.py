"""``summary.json``: the machine-readable figures of a run (schema in README.md)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from hil.harness.cases.detector_observer import DetectorObserver
from hil.harness.analysis.timing_observer import TimingObserver
from hil.harness.vocab.verdict import stage_budgets
from hil.harness.run.loop import LoopStats, SimLoop
from hil.harness.run.vehicle_state import VehicleRun
from hil.timing.records import STAGES, FrameStatus
from hil.timing.stats import summarize_ns

SCHEMA_VERSION = 1


@dataclass(frozen=True)
class CameraFigures:
    """One vehicle's camera pipeline in real time: frames handed to its link, those
    more than the frame tolerance after their camera instant, and the worst lag (ns)."""

    frames: int
    late_frames: int
    worst_lag_ns: int

    @classmethod
    def of(cls, v: VehicleRun) -> CameraFigures:
        return cls(v.next_frame_id, v.late_frames, v.worst_frame_lag_ns)


def wall_seconds(stats: LoopStats) -> float:
    """The loop's wall time (s), the answers still in flight at its end drained."""
    return max((stats.wall_end_ns - stats.wall_start_ns) / 1e9, 1e-9)


def rate_seconds(stats: LoopStats) -> float:
    """The wall time (s) a vehicle's frames and estimates per second are per: the loop's
    start to its last step. (Over ``wall_seconds`` a slow target's drain counted: a
    run that sent 20 frames a second said 18.3 with a 150 ms target.)"""
    end = stats.wall_last_step_ns or stats.wall_end_ns
    return max((end - stats.wall_start_ns) / 1e9, 1e-9)


def vehicle_summary(v: VehicleRun, *, wall_s: float, timing: TimingObserver | None = None,
                    detector: DetectorObserver | None = None) -> dict[str, Any]:
    # Exact percentiles over the recorded frames; absurd records (flagged as causality
    # anomalies) are kept out so the summary never shows a negative latency.
    stages: dict[str, Any] = {name: summarize_ns(v.stage_values[name]) for name in STAGES}
    frames = v.frames_settled
    applied = v.count(FrameStatus.OK)
    return {
        "frames_sent": v.next_frame_id,
        "frames_accounted": frames,
        "estimates_applied": applied,
        "dropped": v.count(FrameStatus.DROPPED),
        "stale": v.count(FrameStatus.STALE),
        "late_estimates": v.late_estimates,
        "unknown_estimates": v.unknown_estimates,
        "protocol_errors": v.protocol_faults,
        "protocol_events_unwritten": max(0, v.protocol_faults - 200),
        "drop_rate": round(v.count(FrameStatus.DROPPED) / frames, 6) if frames else 0.0,
        "frames_per_s": round(v.next_frame_id / wall_s, 3) if wall_s > 0 else 0.0,
        "estimates_per_s": round(applied / wall_s, 3) if wall_s > 0 else 0.0,
        "order_violations": v.order_violations,
        "latency_ms": stages,
        "capture_to_send_parts_ms": {p: summarize_ns(col) for p, col in v.send_parts.items()},
        "budgets": _budgets(v, timing),
        "late_frames": v.late_frames,
        **(timing.summary(v.name) if timing is not None else {}),
        **(detector.summary(v.name) if detector is not None else {}),
        "link": {k: val for k, val in v.link.stats.__dict__.items()},
        "target": None if v.link.hello is None else {
            "name": v.link.hello.target_name, "clock": v.link.hello.clock_id.name,
            "clock_resolution_ns": v.link.hello.clock_resolution_ns},
    }


def _budgets(v: VehicleRun, timing: TimingObserver | None) -> dict[str, Any]:
    """Per-frame budget figures of each budgeted stage: sync-free stages exact,
    cross-clock ones by their lower bound (value − uncertainty, as the deadline
    anomaly judges them)."""
    if timing is None:
        return {}
    deadlines = timing.deadlines(v.name)
    lower = timing.split_lower_bounds(v.name)
    values = {s: lower[s] if s in lower else v.stage_values[s].to_numpy()
              for s in deadlines if s in lower or s in v.stage_values}
    return stage_budgets(values, deadlines)


def build_summary(*, loop: SimLoop, stats: LoopStats, recorder_stats: dict[str, Any], meta: dict[str, Any],
                  vehicles: dict[str, dict[str, Any]], camera: dict[str, CameraFigures]) -> dict[str, Any]:
    """The run's summary from its loop and, per vehicle, what its shard summed up
    (``vehicle_summary``, ``CameraFigures``)."""
    wall_s = wall_seconds(stats)
    sim_s = stats.sim_steps * loop.sim.step_ns / 1e9
    for name, s in vehicles.items():  # what /events holds for this vehicle, kind by kind
        s["events"] = loop.events.counts(name)
    final = {e.vehicle: e for e in loop.sim.truth_snapshot().egos}  # once, and without taking collisions
    for name, s in vehicles.items():
        s["outcome"] = {
            "min_gap_m": loop.min_gap_m.get(name),
            "final_gap_m": final[name].gap_m if name in final else None,
            "final_speed_mps": round(loop.sim.speed_mps(name), 4),
            "collisions": sum(1 for c in loop.collisions if name in (c["a"], c["b"])),
        }
    return {
        "schema_version": SCHEMA_VERSION,
        **meta,
        "ended_by": stats.ended_by,
        "sim_time_s": round(sim_s, 6),
        "wall_time_s": round(wall_s, 6),
        "realtime": realtime_summary(loop, stats, camera, sim_s=sim_s, wall_s=wall_s),
        "harness_cost": _cost(stats, frames=sum(c.frames for c in camera.values())),
        "collisions": loop.collisions,
        # Every event the run published (per vehicle: vehicles.<name>.events; here those of
        # no vehicle); /events holds them all but the `unrecorded` (recording queue full).
        "events": {"published": loop.events.published, "unrecorded": loop.events.unrecorded,
                   "run": loop.events.counts(None)},
        "recorder": recorder_stats,
        "vehicles": vehicles,
    }


def realtime_summary(loop: SimLoop, stats: LoopStats, camera: dict[str, CameraFigures], *, sim_s: float,
                     wall_s: float) -> dict[str, Any]:
    """``summary.json``'s ``realtime``: the one definition of whether a run kept real time.

    Two paths must keep up. The physics: its own pace (simulated over its own wall
    time, start to last step: ``achieved_factor``) at least 0.95 of the requested, and
    no step later than ``engine.late_tolerance_ms``. The cameras: no frame handed to
    its link later than the frame tolerance after its camera instant (``t_tx -
    t_state``; ``engine.frame_late_tolerance_ms``, default one camera period).
    ``kept_realtime`` needs both, and no consumer of the physics's rings behind
    (``behind``: records each lost); ``lagging`` names what did not keep up. Lockstep runs wait
    by design: they keep real time trivially."""
    cfg = loop.cfg
    realtime = cfg.mode.value == "realtime"
    requested = cfg.realtime_factor
    lat = stats.lateness
    span_s = stats.physics_span_ns / 1e9
    rtf = sim_s / span_s if span_s > 0 else sim_s / wall_s
    frames = sum(c.frames for c in camera.values())
    late_frames = sum(c.late_frames for c in camera.values())
    worst_ns = max((c.worst_lag_ns for c in camera.values()), default=0)
    lagging = []
    if realtime and (rtf < 0.95 * requested or stats.late_steps > 0):
        lagging.append("physics")
    if realtime and late_frames > 0:
        lagging.append("camera")
    if stats.behind:
        lagging.append("consumers")
    return {
        "mode": cfg.mode.value,
        "requested_factor": requested,
        "achieved_factor": round(rtf, 4),
        "run_factor": round(sim_s / wall_s, 4),  # simulated over the whole run's wall time (start-up, drain)
        "late_steps": stats.late_steps,
        "late_tolerance_ms": lat.get("tolerance_ns", 0) / 1e6,
        "steps_over_10ms": lat.get("steps_over_10ms", 0),
        "lateness_ms": {q: round(lat.get(f"{q}_ns", 0) / 1e6, 3) for q in ("p50", "p99", "p999")},
        "lateness_histogram": {"bin_ns": lat.get("bin_ns"), "bins": lat.get("bins", {})},
        "max_lateness_ms": round(stats.max_lateness_ns / 1e6, 3),
        "camera": {"frames": frames, "late_frames": late_frames, "tolerance_ms": loop.frame_tolerance_ns / 1e6,
                   "worst_lag_ms": round(worst_ns / 1e6, 3),
                   "by_vehicle": {name: c.late_frames for name, c in camera.items() if c.late_frames}},
        # Consumers of the physics's rings that fell behind (records lost, the physics
        # never waits): "run" (this process), "render-<w>" (a render worker).
        "behind": dict(stats.behind),
        "lagging": lagging,
        "kept_realtime": not lagging,
        "physics_scheduling": stats.scheduling,
        "render_workers": stats.render_workers,
        "renderer": stats.renderer,
        "render_warm_ms": stats.render_warm_ms,
    }


def _cost(stats: LoopStats, *, frames: int) -> dict[str, Any]:
    """The harness's own CPU time per frame (µs): every process of the run but the
    physics and the render workers (``run_us_per_frame``: all threads, links,
    recording and analysis included, until the recording is flushed), and of it the
    loop thread (frames, estimates, controls) and the analysis thread (truth,
    observers, recording); ``threads_us_per_frame``: every thread of the run process
    from the loop's start to its last step, by role, and the shard processes' as
    ``shard:<role>``, summed over the shards."""
    per = max(frames, 1)
    return {"frames": frames, "run_us_per_frame": round(stats.run_cpu_ns / per / 1e3, 1),
            "loop_thread_us_per_frame": round(stats.loop_cpu_ns / per / 1e3, 1),
            "analysis_thread_us_per_frame": round(stats.analysis_cpu_ns / per / 1e3, 1),
            "analysis_tasks_dropped": stats.analysis_dropped,
            "threads_us_per_frame": {role: round(ns / per / 1e3, 1) for role, ns in stats.threads_cpu_ns.items()}}
