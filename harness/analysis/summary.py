"""``summary.json``: the machine-readable figures of a run (schema in README.md)."""

from __future__ import annotations

from typing import Any

from hil.harness.analysis.detector_observer import DetectorObserver
from hil.harness.analysis.timing_observer import TimingObserver
from hil.harness.run.loop import LoopStats, SimLoop
from hil.harness.run.vehicle_state import VehicleRun
from hil.timing.records import STAGES, FrameStatus
from hil.timing.stats import summarize_ns

SCHEMA_VERSION = 1


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
        **(timing.summary(v.name) if timing is not None else {}),
        **(detector.summary(v.name) if detector is not None else {}),
        "link": {k: val for k, val in v.link.stats.__dict__.items()},
        "target": None if v.link.hello is None else {
            "name": v.link.hello.target_name, "clock": v.link.hello.clock_id.name,
            "clock_resolution_ns": v.link.hello.clock_resolution_ns},
    }


def build_summary(*, loop: SimLoop, stats: LoopStats, recorder_stats: dict[str, Any],
                  meta: dict[str, Any], timing: TimingObserver | None = None,
                  detector: DetectorObserver | None = None) -> dict[str, Any]:
    wall_s = max((stats.wall_end_ns - stats.wall_start_ns) / 1e9, 1e-9)
    sim_s = stats.sim_steps * loop.sim.step_ns / 1e9
    rtf = sim_s / wall_s
    realtime = loop.cfg.mode.value == "realtime"
    requested = loop.cfg.realtime_factor
    lat = stats.lateness
    # Real time is kept when the pace held and no physics step started later than
    # the tolerance (1 ms by default).
    kept = (not realtime) or (rtf >= 0.95 * requested and stats.late_steps == 0)
    vehicles = {v.name: vehicle_summary(v, wall_s=wall_s, timing=timing, detector=detector) for v in loop.vehicles}
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
        "realtime": {
            "mode": loop.cfg.mode.value,
            "requested_factor": requested,
            "achieved_factor": round(rtf, 4),
            "late_steps": stats.late_steps,
            "late_tolerance_ms": lat.get("tolerance_ns", 0) / 1e6,
            "steps_over_10ms": lat.get("steps_over_10ms", 0),
            "lateness_ms": {q: round(lat.get(f"{q}_ns", 0) / 1e6, 3) for q in ("p50", "p99", "p999")},
            "lateness_histogram": {"bin_ns": lat.get("bin_ns"), "bins": lat.get("bins", {})},
            "max_lateness_ms": round(stats.max_lateness_ns / 1e6, 3),
            "kept_realtime": kept,
            "physics_scheduling": stats.scheduling,
            "render_workers": stats.render_workers,
        },
        "harness_cost": _cost(stats, frames=sum(v.next_frame_id for v in loop.vehicles)),
        "collisions": loop.collisions,
        "recorder": recorder_stats,
        "vehicles": vehicles,
    }


def _cost(stats: LoopStats, *, frames: int) -> dict[str, Any]:
    """The run process's own CPU time per frame (µs): the loop thread (frames,
    estimates, controls) and the analysis thread (truth, observers, recording)."""
    per = max(frames, 1)
    return {"frames": frames, "loop_thread_us_per_frame": round(stats.loop_cpu_ns / per / 1e3, 1),
            "analysis_thread_us_per_frame": round(stats.analysis_cpu_ns / per / 1e3, 1),
            "analysis_tasks_dropped": stats.analysis_dropped}
