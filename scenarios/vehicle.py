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

import numpy as np


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


class VehicleBank:
    """The actuator state of many vehicles at once (numpy arrays, one entry per ego),
    stepped together: the same rules as ``step_command``, vectorised so a physics step
    costs the same for 1 or 16 vehicles."""

    def __init__(self, limits: VehicleLimits, initial_speeds_mps: list[float]) -> None:
        n = len(initial_speeds_mps)
        self.limits = limits
        self.speed_mps = np.array(initial_speeds_mps, dtype=np.float64)
        self.steer_rad = np.zeros(n)
        self.cmd_steer_rad = np.zeros(n)
        self.cmd_throttle = np.zeros(n)
        self.cmd_brake = np.zeros(n)
        self._tan_over_l = 1.0 / limits.wheelbase_m
        self._accel_cmd = np.zeros(n)  # throttle and brake as one acceleration (m/s^2)

    def set_command(self, i: int, *, steering_rad: float, throttle: float, brake: float) -> None:
        lim = self.limits
        self.cmd_steer_rad[i] = clamp(steering_rad, -lim.max_steer_rad, lim.max_steer_rad)
        self.cmd_throttle[i] = clamp(throttle, 0.0, 1.0)
        self.cmd_brake[i] = clamp(brake, 0.0, 1.0)
        self._accel_cmd[i] = lim.max_accel_mps2 * self.cmd_throttle[i] - lim.max_brake_mps2 * self.cmd_brake[i]

    def state(self, i: int) -> VehicleState:
        """A snapshot of vehicle ``i`` (for inspection and tests)."""
        return VehicleState(float(self.speed_mps[i]), float(self.steer_rad[i]), float(self.cmd_steer_rad[i]),
                            float(self.cmd_throttle[i]), float(self.cmd_brake[i]))

    def step(self, measured_speed_mps: np.ndarray, dt_s: float) -> tuple[np.ndarray, np.ndarray]:
        """Advance every vehicle by ``dt_s``; (speed m/s, yaw rate rad/s) set points."""
        # np.minimum/np.maximum rather than np.clip: several times cheaper on short arrays.
        lim = self.limits
        max_delta = lim.max_steer_rate_radps * dt_s
        self.steer_rad += np.maximum(np.minimum(self.cmd_steer_rad - self.steer_rad, max_delta), -max_delta)
        v = np.minimum(self.speed_mps, measured_speed_mps + 0.5)
        np.maximum(v, 0.0, out=v)
        v += (self._accel_cmd - lim.drag_per_s * v) * dt_s
        np.maximum(v, 0.0, out=v)
        np.minimum(v, lim.max_speed_mps, out=v)
        self.speed_mps = v
        return v, v * np.tan(self.steer_rad) * self._tan_over_l
