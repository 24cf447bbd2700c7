"""Vehicle dynamics: a kinematic bicycle model driving MuJoCo velocity servos.

The AI's steering, throttle and brake go through actuator limits (steering angle
and rate, acceleration, braking); the resulting planar velocity is the set point of
three MuJoCo velocity actuators (x, y, yaw), whose force limits let a collision
really stop the car. Speed is read back from the simulator each step, so a blocked
car does not keep a phantom speed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass(frozen=True)
class VehicleLimits:
    """Actuator limits. Units: m, rad, rad/s, m/s^2, m/s."""

    wheelbase_m: float = 2.7
    max_steer_rad: float = 0.5
    max_steer_rate_radps: float = 1.2
    max_accel_mps2: float = 3.0
    max_brake_mps2: float = 8.0
    drag_per_s: float = 0.02
    max_speed_mps: float = 40.0


@dataclass
class VehicleState:
    """Mutable per-vehicle actuator state (owned by the simulation)."""

    speed_mps: float = 0.0
    steer_rad: float = 0.0
    cmd_steer_rad: float = 0.0
    cmd_throttle: float = 0.0
    cmd_brake: float = 0.0


def clamp(x: float, lo: float, hi: float) -> float:
    return lo if x < lo else hi if x > hi else x


def step_command(state: VehicleState, limits: VehicleLimits, *, measured_speed_mps: float,
                 dt_s: float) -> tuple[float, float]:
    """Advance the actuators by ``dt_s`` and return (speed m/s, yaw rate rad/s) set points.

    ``measured_speed_mps`` is the forward speed the simulator reports (so contacts
    that slowed the car are respected).
    """
    target = clamp(state.cmd_steer_rad, -limits.max_steer_rad, limits.max_steer_rad)
    max_delta = limits.max_steer_rate_radps * dt_s
    state.steer_rad += clamp(target - state.steer_rad, -max_delta, max_delta)
    v = max(0.0, min(state.speed_mps, measured_speed_mps + 0.5))
    accel = (limits.max_accel_mps2 * clamp(state.cmd_throttle, 0.0, 1.0)
             - limits.drag_per_s * v)
    brake = limits.max_brake_mps2 * clamp(state.cmd_brake, 0.0, 1.0)
    v = v + accel * dt_s
    v = max(0.0, v - brake * dt_s) if v > 0 else 0.0
    state.speed_mps = min(v, limits.max_speed_mps)
    yaw_rate = state.speed_mps / limits.wheelbase_m * math.tan(state.steer_rad)
    return state.speed_mps, yaw_rate
