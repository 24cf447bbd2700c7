"""A run's engine specs and the loop's figures: what the driver builds before the
loop starts, and what the loop hands back."""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from hil.adapters.wire.messages import ImageEncoding
from hil.harness.config.model import CameraConfig, Encoding, Mode, RunConfig
from hil.harness.engine.physics import PhysicsSpec, spread_phases
from hil.harness.engine.procs import physics_core
from hil.harness.engine.render import RenderSpec, encode_image as _encode


def encode_image(rgb: np.ndarray, camera: CameraConfig) -> tuple[bytes, ImageEncoding]:
    """An RGB8 render as the wire carries it: JPEG at the configured quality, or raw."""
    data, enc = _encode(rgb, jpeg=camera.encoding == Encoding.JPEG, quality=camera.jpeg_quality)
    return bytes(data) if isinstance(data, (bytes, bytearray)) else data.tobytes(), ImageEncoding(enc)


def engine_specs(cfg: RunConfig, world: Any, rules: Any) -> tuple[PhysicsSpec, RenderSpec]:
    """The physics and render specs of a run (camera phases, pacing, late tolerance)."""
    step_ns = round(world.physics_step_s * 1e9)
    egos = tuple(v.name for v in world.vehicles if v.ego)
    period = cfg.camera_period_steps
    eng = cfg.engine
    realtime = cfg.mode == Mode.REALTIME
    phases = (spread_phases(len(egos), period) if realtime and eng.capture_phase == "spread"
              else tuple(0 for _ in egos))
    cam = cfg.camera
    # A rig's trigger offsets, in real time; lockstep triggers every camera at camera
    # 0's instant (as it aligns every vehicle's phase): it waits for each set's answer.
    offsets = cfg.rig_offset_steps if realtime else tuple(0 for _ in cfg.rig_offset_steps)
    physics = PhysicsSpec(world=world, rules=rules, realtime=realtime,
                          total_steps=round(cfg.duration_s * 1e9 / step_ns),
                          wall_per_step_ns=step_ns / cfg.realtime_factor, period_steps=period, phases=phases,
                          late_tolerance_ns=int(eng.late_tolerance_ms * 1e6),
                          realtime_priority=eng.realtime_priority if realtime else 0,
                          fallback_nice=eng.fallback_nice if realtime else 0,
                          cpu=physics_core(eng.physics_cpu) if realtime else None, offsets=offsets)
    rig = cam.cameras()
    drop = eng.faults.drop_camera
    if drop is not None:
        physics = replace(physics, dropped=1 << [c.name for c in rig].index(drop))
    most = max((c.width or cam.width) * (c.height or cam.height) for c in rig)
    render = RenderSpec(world=world, vehicles=egos, shm={}, slot_bytes=most * 3 + 65536, cameras=len(rig),
                        jpeg=cam.encoding == Encoding.JPEG, jpeg_quality=cam.jpeg_quality,
                        visible_boxes=cfg.truth.visible_boxes, min_visible_px=cfg.truth.min_visible_px,
                        delay_ns=int(eng.faults.render_delay_ms * 1e6), delay_every=eng.faults.render_delay_every,
                        fail_at=eng.faults.render_fail_at_frame)
    return physics, render


def stall_of(cfg: RunConfig) -> tuple[int, float] | None:
    """The injected stuck consumer (``engine.faults.stall_run_ms``): (the step half a
    second in, seconds) for each ``RingPump`` that reads a physics ring of the run (the
    run process's, and each shard process's), or None."""
    stall_s = cfg.engine.faults.stall_run_ms / 1e3
    return (round(0.5 / cfg.physics_step_s), stall_s) if stall_s else None


@dataclass
class LoopStats:
    wall_start_ns: int = 0
    wall_end_ns: int = 0
    wall_last_step_ns: int = 0  # the loop's last step, before it drained the answers still in flight
    sim_steps: int = 0
    late_steps: int = 0
    max_lateness_ns: int = 0
    physics_span_ns: int = 0   # the physics process's own wall time, start to last step
    ended_by: str = "duration"
    lateness: dict[str, Any] = field(default_factory=dict)   # the physics process's histogram
    scheduling: str = ""
    render_workers: int = 0
    renderer: str = ""         # the render workers' GL_RENDERER
    render_warm_ms: float = 0.0  # how long they rendered before the first step (engine.render_warm_ms)
    loop_cpu_ns: int = 0       # CPU time of the loop thread (frames, estimates, controls)
    analysis_cpu_ns: int = 0   # CPU time of the analysis thread (truth, observers, recording)
    threads_cpu_ns: dict[str, int] = field(default_factory=dict)  # the loop's, by thread role (procs.cpu_by_role)
    analysis_dropped: int = 0  # analysis tasks dropped on a full queue
    behind: dict[str, int] = field(default_factory=dict)  # records the physics's rings lost, by consumer
    # CPU time of every harness process but the physics and render workers (this one,
    # all threads, and any shard processes), from the loop's start until its
    # recording is flushed (set by the driver).
    run_cpu_ns: int = 0
