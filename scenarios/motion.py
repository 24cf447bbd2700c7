"""Scripted motion: where an NPC vehicle or a pedestrian is at any simulated time.

A ``Script`` moves along a ``Path`` with a ``SpeedProfile`` (piecewise constant
acceleration) and a ``LateralProfile`` (an offset from the path, with smooth lane
changes). Everything is a closed-form function of time, vectorised over numpy
arrays, so the simulation can precompute a block of physics steps at once and the
same seed gives the same motion to the last bit.

Units: seconds, metres, m/s, m/s^2, radians.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from hil.scenarios.path import Path


@dataclass(frozen=True)
class SpeedChange:
    """From ``at_s`` on, change speed towards ``target_mps`` at ``rate_mps2``
    (a magnitude: it accelerates or brakes, whichever the target needs), then hold it."""

    at_s: float
    target_mps: float
    rate_mps2: float

    def __post_init__(self) -> None:
        if self.at_s < 0 or self.target_mps < 0 or self.rate_mps2 <= 0:
            raise ValueError(f"speed change needs at_s >= 0, target >= 0, rate > 0; got {self}")


@dataclass(frozen=True)
class SpeedProfile:
    """Speed over time: ``initial_mps`` until the first change, then each change in
    turn (a later change overrides an earlier one still under way).

    Example: cruise at 12 m/s, brake at 6 m/s^2 from t = 4 s to a stop::

        SpeedProfile(12.0, (SpeedChange(4.0, 0.0, 6.0),))
    """

    initial_mps: float
    changes: tuple[SpeedChange, ...] = ()
    _knots: np.ndarray = field(init=False, repr=False, compare=False)  # (n, 4): t, s, v, a

    def __post_init__(self) -> None:
        if self.initial_mps < 0:
            raise ValueError(f"initial speed must be >= 0, got {self.initial_mps}")
        knots: list[tuple[float, float, float, float]] = [(0.0, 0.0, self.initial_mps, 0.0)]
        for ch in sorted(self.changes, key=lambda c: c.at_s):
            t, s, v, a = knots[-1]
            # Drop knots after the change's start (it overrides them), then state at at_s.
            while len(knots) > 1 and knots[-1][0] > ch.at_s:
                knots.pop()
            t, s, v, a = knots[-1]
            dt = ch.at_s - t
            s, v = s + v * dt + 0.5 * a * dt * dt, v + a * dt
            dv = ch.target_mps - v
            if abs(dv) < 1e-12:
                knots.append((ch.at_s, s, v, 0.0))
                continue
            acc = math.copysign(ch.rate_mps2, dv)
            knots.append((ch.at_s, s, v, acc))
            t_end = abs(dv) / ch.rate_mps2
            knots.append((ch.at_s + t_end, s + v * t_end + 0.5 * acc * t_end * t_end, ch.target_mps, 0.0))
        object.__setattr__(self, "_knots", np.array(knots, dtype=np.float64))

    def _at(self, t_s: float | np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        t = np.maximum(np.asarray(t_s, dtype=np.float64), 0.0)
        k = self._knots
        i = np.clip(np.searchsorted(k[:, 0], t, side="right") - 1, 0, len(k) - 1)
        dt = t - k[i, 0]
        return k[i, 1] + k[i, 2] * dt + 0.5 * k[i, 3] * dt * dt, k[i, 2] + k[i, 3] * dt

    def speed_at(self, t_s: float | np.ndarray) -> np.ndarray:
        """Speed (m/s) at time ``t_s``."""
        return self._at(t_s)[1]

    def distance_at(self, t_s: float | np.ndarray) -> np.ndarray:
        """Distance travelled (m) from t = 0 to ``t_s``."""
        return self._at(t_s)[0]


@dataclass(frozen=True)
class LaneChange:
    """Move ``by_m`` sideways (positive: left) over ``duration_s`` from ``at_s``, on a
    quintic (zero lateral speed and acceleration at both ends)."""

    at_s: float
    by_m: float
    duration_s: float

    def __post_init__(self) -> None:
        if self.duration_s <= 0 or self.at_s < 0:
            raise ValueError(f"lane change needs at_s >= 0 and duration_s > 0; got {self}")


@dataclass(frozen=True)
class LateralProfile:
    """Offset from the path (m, positive left): ``initial_m`` plus lane changes."""

    initial_m: float = 0.0
    changes: tuple[LaneChange, ...] = ()

    def at(self, t_s: float | np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(offset m, lateral rate m/s) at ``t_s``."""
        t = np.asarray(t_s, dtype=np.float64)
        off = np.full(t.shape, self.initial_m)
        rate = np.zeros(t.shape)
        for ch in self.changes:
            u = np.clip((t - ch.at_s) / ch.duration_s, 0.0, 1.0)
            off = off + ch.by_m * u * u * u * (10 - 15 * u + 6 * u * u)
            rate = rate + ch.by_m / ch.duration_s * 30 * u * u * (1 - u) * (1 - u)
        return off, rate


@dataclass(frozen=True)
class ScriptState:
    """Arrays (one entry per queried time): position (m), heading (rad), velocity (m/s)."""

    x_m: np.ndarray
    y_m: np.ndarray
    heading_rad: np.ndarray
    vx_mps: np.ndarray
    vy_mps: np.ndarray


@dataclass(frozen=True)
class Script:
    """Motion along ``path`` from arc length ``s0_m``: speed by ``speed``, sideways by
    ``lateral``. ``face_path`` keeps the heading on the path's (a pedestrian side-
    stepping); otherwise a lane change turns the body into the motion."""

    path: Path
    speed: SpeedProfile
    s0_m: float = 0.0
    lateral: LateralProfile = field(default_factory=LateralProfile)
    face_path: bool = False

    def state_at(self, t_s: float | np.ndarray) -> ScriptState:
        t = np.atleast_1d(np.asarray(t_s, dtype=np.float64))
        dist, v = self.speed._at(t)
        off, off_rate = self.lateral.at(t)
        x, y, h = self.path.pose_at(self.s0_m + dist)
        nx, ny = -np.sin(h), np.cos(h)
        x, y = x + off * nx, y + off * ny
        k = self.path.curvature_at(self.s0_m + dist)
        v_along = v * (1.0 - k * off)  # an offset path is longer on the outside of a curve
        vx = v_along * np.cos(h) + off_rate * nx
        vy = v_along * np.sin(h) + off_rate * ny
        heading = h if self.face_path else h + np.arctan2(off_rate, np.maximum(v_along, 0.5))
        return ScriptState(x, y, heading, vx, vy)

    def pose0(self) -> tuple[float, float, float]:
        st = self.state_at(0.0)
        return float(st.x_m[0]), float(st.y_m[0]), float(st.heading_rad[0])


class ScriptTable:
    """Poses (position, quaternion) and velocities of many scripts on the physics-step
    grid, computed ``chunk_steps`` steps at a time (vectorised) and looked up by step.

    ``row(step)`` gives the row of ``pos`` (n_rows x n x 3), ``quat`` (w, x, y, z) and
    ``vel`` (vx, vy) for time ``step * step_ns``.
    """

    def __init__(self, scripts: list[Script | None], step_ns: int, *, chunk_steps: int = 500) -> None:
        self.scripts = scripts
        self.step_ns = step_ns
        self.chunk_steps = chunk_steps
        self.first = -1
        n = len(scripts)
        self.pos = np.zeros((0, n, 3))
        self.quat = np.zeros((0, n, 4))
        self.vel = np.zeros((0, n, 2))

    def row(self, step: int) -> int:
        if not (self.first <= step < self.first + len(self.pos)):
            self._fill(step)
        return step - self.first

    def _fill(self, step: int) -> None:
        n, k = len(self.scripts), self.chunk_steps
        t = np.arange(step, step + k, dtype=np.int64) * self.step_ns / 1e9
        self.pos = np.zeros((k, n, 3))
        self.quat = np.zeros((k, n, 4))
        self.vel = np.zeros((k, n, 2))
        for j, script in enumerate(self.scripts):
            assert script is not None
            st = script.state_at(t)
            self.pos[:, j, 0], self.pos[:, j, 1] = st.x_m, st.y_m
            self.quat[:, j, 0], self.quat[:, j, 3] = np.cos(st.heading_rad / 2), np.sin(st.heading_rad / 2)
            self.vel[:, j, 0], self.vel[:, j, 1] = st.vx_mps, st.vy_mps
        self.first = step
