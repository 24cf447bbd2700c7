"""Helpers for the scenario tests: build a scenario's simulation, and drive its egos
in-process with the OpenCV baseline (no transport), as a target would."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any

import cv2
import pytest


def build(name: str, params: dict[str, float] | None = None, *, seed: int = 0, **camera: Any) -> Any:
    """The ``WorldSpec`` of scenario ``name`` (320x240 camera unless overridden)."""
    from hil import scenarios
    from hil.scenarios.world import CameraSpec

    return scenarios.get(name).build(params=params or {}, seed=seed, camera=CameraSpec(**camera),
                                     physics_step_s=0.002)


@pytest.fixture
def make_sim() -> Iterator[Callable[..., Any]]:
    """``make_sim(name, params, seed=..., **camera)`` -> an open Simulation, closed after the test."""
    from hil.scenarios.sim import Simulation

    opened: list[Any] = []

    def make(name: str, params: dict[str, float] | None = None, **kw: Any) -> Any:
        sim = Simulation(build(name, params, **kw))
        opened.append(sim)
        return sim

    yield make
    for sim in opened:
        sim.close()


@dataclass
class Drive:
    """What happened while the baseline drove: per ego, the largest offset from its
    lane centre (m) and the smallest gap (m); every collision; the reference states."""

    max_lane_offset_m: dict[str, float] = field(default_factory=dict)
    min_gap_m: dict[str, float] = field(default_factory=dict)
    collisions: list[Any] = field(default_factory=list)
    ref_states: list[str] = field(default_factory=list)


@pytest.fixture
def baseline_drive() -> Callable[..., Drive]:
    """``baseline_drive(sim, duration_s=...)``: see ``drive_with_baseline``."""
    return drive_with_baseline


def drive_with_baseline(sim: Any, *, duration_s: float, steps_per_frame: int = 25,
                        cruise_speed_mps: float = 10.0) -> Drive:
    """Closed loop in one process: every ``steps_per_frame`` physics steps each ego's
    camera is JPEG-encoded, the baseline infers and its control is applied."""
    from hil.adapters.wire.messages import CameraInfo, Frame, ImageEncoding
    from hil.targets.cv_baseline import CvBaseline

    k = sim.intrinsics()
    cam = sim.world.camera
    info = CameraInfo(k.fx, k.fy, k.cx, k.cy, cam.mount_height_m, cam.pitch_rad)
    ais = {name: CvBaseline(cruise_speed_mps=cruise_speed_mps) for name in sim.egos}
    out = Drive()
    for step in range(round(duration_s / sim.world.physics_step_s)):
        if step % steps_per_frame == 0:
            gt = sim.ground_truth()
            out.collisions.extend(gt.collisions)
            for e in gt.egos:
                out.ref_states.append(e.ref_state.name)
                if e.gap_m is not None:
                    out.min_gap_m[e.vehicle] = min(out.min_gap_m.get(e.vehicle, float("inf")), e.gap_m)
            for name in sim.egos:
                rgb = sim.render(name)
                ok, buf = cv2.imencode(".jpg", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
                assert ok
                frame = Frame(0, step // steps_per_frame, sim.sim_time_ns, 0, 0, rgb.shape[1], rgb.shape[0],
                              ImageEncoding.JPEG, info, sim.speed_mps(name), buf.tobytes())
                c = ais[name].infer(frame).control
                sim.set_control(name, steering_rad=c.steering_rad, throttle=c.throttle, brake=c.brake)
                x, y, _ = sim.pose(name)
                _, lateral = sim.route(name).project(x, y)
                out.max_lane_offset_m[name] = max(out.max_lane_offset_m.get(name, 0.0), abs(float(lateral)))
        sim.step()
    out.collisions.extend(sim.ground_truth().collisions)
    return out
