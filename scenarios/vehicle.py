"""Vehicle dynamics: a kinematic bicycle model driving MuJoCo velocity servos.

The AI's steering, throttle and brake go through actuator limits (steering angle
and rate, acceleration, braking); the resulting planar velocity is the set point of
three MuJoCo velocity actuators (x, y, yaw), whose force limits let a collision
really stop the car. Speed is read back from the simulator each step, so a blocked
car does not keep a phantom speed.

``step_command`` steps one vehicle, ``VehicleBank`` many at once (numpy), and
``EgoActuators`` is what the simulation uses: it picks one of the two by the
number of egos and writes the servos' set points every physics step.
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


class EgoActuators:
    """Every ego's actuator state, stepped each physics step into its velocity servos.

    Works on the simulation's numpy arrays: ``qpos``/``qvel``/``ctrl`` with each
    ego's (x, y, yaw) joints, dofs and servos at ``start + 0, 1, 2`` (``qpos_x``,
    ``dof_x``, ``act_x``: the x entries, one per ego, 3 apart). With one or two egos
    plain floats (``step_command``) beat numpy's per-call cost; with more, one
    ``VehicleBank`` steps them all at once.
    """

    SCALAR_MAX = 2

    def __init__(self, limits: VehicleLimits, initial_speeds_mps: list[float], *, qpos: np.ndarray,
                 qvel: np.ndarray, ctrl: np.ndarray, qpos_x: list[int], dof_x: list[int], act_x: list[int]) -> None:
        n = len(initial_speeds_mps)
        self.limits, self.n = limits, n
        self._q, self._qv, self._u = qpos, qvel, ctrl
        self._idx = list(zip(qpos_x, dof_x, act_x))
        self._scalar = [VehicleState(speed_mps=v) for v in initial_speeds_mps] if n <= self.SCALAR_MAX else None
        self._bank = VehicleBank(limits, initial_speeds_mps)
        self._views: tuple[tuple[np.ndarray, ...], ...] = ()
        if n and self._scalar is None:
            for name, idx in (("qpos", qpos_x), ("dofs", dof_x), ("actuators", act_x)):
                if list(idx) != [idx[0] + 3 * i for i in range(n)]:
                    raise ValueError(f"ego {name} are not laid out as consecutive (x, y, yaw) triples: {idx}")
            # Strided views: cheaper every step than index arrays.
            self._views = tuple(tuple(arr[start + k::3][:n] for k in range(3))
                                for arr, start in ((qpos, qpos_x[0]), (qvel, dof_x[0]), (ctrl, act_x[0])))

    def set_command(self, i: int, *, steering_rad: float, throttle: float, brake: float) -> None:
        if self._scalar is not None:
            st = self._scalar[i]
            st.cmd_steer_rad, st.cmd_throttle, st.cmd_brake = steering_rad, throttle, brake
        else:
            self._bank.set_command(i, steering_rad=steering_rad, throttle=throttle, brake=brake)

    def state(self, i: int) -> VehicleState:
        if self._scalar is not None:
            st = self._scalar[i]
            return VehicleState(st.speed_mps, st.steer_rad, st.cmd_steer_rad, st.cmd_throttle, st.cmd_brake)
        return self._bank.state(i)

    def step(self, dt_s: float) -> None:
        """Advance every ego's actuators by ``dt_s`` and write the servos' set points
        (world-frame velocity, yaw rate) from the measured speeds and headings."""
        if self._scalar is not None:
            q, qv, u, lim = self._q, self._qv, self._u, self.limits
            for st, (iq, iv, ia) in zip(self._scalar, self._idx):
                yaw = float(q[iq + 2])
                c, s = math.cos(yaw), math.sin(yaw)
                speed, yaw_rate = step_command(st, lim, measured_speed_mps=float(qv[iv]) * c + float(qv[iv + 1]) * s,
                                               dt_s=dt_s)
                u[ia], u[ia + 1], u[ia + 2] = speed * c, speed * s, yaw_rate
        elif self.n:
            (_, _, yaws), (vx, vy, _), (ux, uy, uyaw) = self._views
            cos, sin = np.cos(yaws), np.sin(yaws)
            measured = vx * cos
            measured += vy * sin
            speeds, yaw_rates = self._bank.step(measured, dt_s)
            np.multiply(speeds, cos, out=ux)
            np.multiply(speeds, sin, out=uy)
            uyaw[:] = yaw_rates
