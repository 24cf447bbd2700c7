"""Ground truth records and the reference driving state.

The reference state is what a perfect driver would decide from true distances:

* ``STOP`` when the gap to the nearest obstacle ahead in the ego's lane is at most
  ``stop_distance = v^2 / (2 * comfort_decel) + stop_margin`` (metres, v in m/s);
* ``SLOW`` when the gap is at most ``stop_distance + slow_headway_s * v``, or the
  time to collision ``gap / v`` is at most ``slow_ttc_s``;
* ``SAFE`` otherwise.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum


class RefState(IntEnum):
    """Same numbering as the wire's DrivingState."""

    SAFE = 0
    SLOW = 1
    STOP = 2


@dataclass(frozen=True)
class RefStateRules:
    comfort_decel_mps2: float = 4.0
    stop_margin_m: float = 5.0
    slow_headway_s: float = 2.0
    slow_ttc_s: float = 4.0

    def decide(self, *, gap_m: float | None, speed_mps: float) -> RefState:
        if gap_m is None:
            return RefState.SAFE
        stop = speed_mps * speed_mps / (2 * self.comfort_decel_mps2) + self.stop_margin_m
        if gap_m <= stop:
            return RefState.STOP
        ttc = gap_m / speed_mps if speed_mps > 1e-3 else float("inf")
        if gap_m <= stop + self.slow_headway_s * speed_mps or ttc <= self.slow_ttc_s:
            return RefState.SLOW
        return RefState.SAFE


@dataclass(frozen=True)
class EntityState:
    """One entity at one instant: position (m), velocity (m/s), heading (rad)."""

    name: str
    cls: str
    x_m: float
    y_m: float
    vx_mps: float
    vy_mps: float
    heading_rad: float
    size_m: tuple[float, float, float]


@dataclass(frozen=True)
class Collision:
    """A contact between two entities that began at ``sim_time_ns``; ``force_n`` is
    the normal force at onset."""

    sim_time_ns: int
    a: str
    b: str
    force_n: float


@dataclass(frozen=True)
class EgoTruth:
    """Truth from one ego vehicle's point of view: the gap (m, front bumper to the
    obstacle's nearest face, ``None`` when the lane ahead is clear), the obstacle's
    name, and the reference driving state."""

    vehicle: str
    gap_m: float | None
    obstacle: str | None
    speed_mps: float
    ref_state: RefState


@dataclass(frozen=True)
class GroundTruth:
    sim_time_ns: int
    entities: tuple[EntityState, ...]
    egos: tuple[EgoTruth, ...]
    collisions: tuple[Collision, ...]  # those that began since the previous record
