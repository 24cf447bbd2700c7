"""Ground-truth records and the reference driving state.

Records (all frozen; positions m, velocities m/s, angles rad, times ns of sim time):

* ``EntityState`` — the per-entity state record: id, name, class, position,
  velocity, heading, size, sim time.
* ``EgoTruth`` — one ego's view: the nearest obstacle in its path, the gap to it
  along the ego's route, closing speed, time to collision, reference state.
* ``VisibleBox`` / ``CameraTruth`` — per camera frame: every entity seen, its 2D box
  from the segmentation image (occlusion-aware), visible pixels and visible fraction,
  distance along the ego's path.
* ``Collision`` — a contact between two entities, at its onset.
* ``GroundTruth`` — one instant: all of the above but the camera boxes.

``StateChanges`` turns a stream of ``GroundTruth`` into the record stream: every
entity's initial state once, then an update for each entity whose state changed.
``EntityTable``: one instant's entities as columns, as the simulator takes them (an
``EntityState`` is built only for an entity asked for).

The reference state is what a perfect driver would decide from true distances and
speeds. With ``v`` the ego's speed, ``u`` the obstacle's speed along the ego's path
(0 for a standing one; never counted below 0) and ``gap`` the distance from the
ego's front to the obstacle's nearest face along the ego's route (metres):

* ``stop_distance = max(0, v^2 - u^2) / (2 * comfort_decel) + stop_margin``:
  the room needed to match the obstacle's speed braking at ``comfort_decel``;
* ``STOP`` when ``gap <= stop_distance``;
* ``SLOW`` when ``gap <= stop_distance + slow_headway_s * v``, or the time to
  collision ``gap / (v - u)`` (closing only) is at most ``slow_ttc_s``;
* ``SAFE`` otherwise, and whenever the path ahead is clear.

An obstacle is in the ego's path when its footprint comes within half the ego's
width of the line the ego would drive along its route at its present offset from it
(the route is the ego's lane; straight ahead when it has none). The thresholds come
from the run config's ``truth`` section.
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from enum import IntEnum
from typing import overload

import numpy as np


class RefState(IntEnum):
    """Same numbering as the wire's DrivingState."""

    SAFE = 0
    SLOW = 1
    STOP = 2


@dataclass(frozen=True)
class RefStateRules:
    """Thresholds of the reference state (see the module docstring)."""

    comfort_decel_mps2: float = 4.0
    stop_margin_m: float = 5.0
    slow_headway_s: float = 2.0
    slow_ttc_s: float = 4.0

    def stop_distance_m(self, speed_mps: float, obstacle_speed_mps: float = 0.0) -> float:
        u = max(0.0, obstacle_speed_mps)
        return max(0.0, speed_mps * speed_mps - u * u) / (2 * self.comfort_decel_mps2) + self.stop_margin_m

    def decide(self, *, gap_m: float | None, speed_mps: float, obstacle_speed_mps: float = 0.0) -> RefState:
        if gap_m is None:
            return RefState.SAFE
        v = max(0.0, speed_mps)
        stop = self.stop_distance_m(v, obstacle_speed_mps)
        if gap_m <= stop:
            return RefState.STOP
        closing = v - max(0.0, obstacle_speed_mps)
        ttc = gap_m / closing if closing > 1e-3 else math.inf
        if gap_m <= stop + self.slow_headway_s * v or ttc <= self.slow_ttc_s:
            return RefState.SLOW
        return RefState.SAFE


_KEY_STEPS = (1e4, 1e4, 1e5, 1e4, 1e4)  # x, y, heading, vx, vy: per metre, radian, m/s


def _quantum(v: float) -> float:
    """``v`` rounded to a whole number, halves to even (``np.rint``'s value); not a finite number as it is."""
    return float(round(v)) if math.isfinite(v) else v


@dataclass(frozen=True)
class EntityState:
    """One entity at one instant: position (m), velocity (m/s), heading (rad), its
    bounding box (length, width, height m), its id (index in the world) and class."""

    name: str
    cls: str
    x_m: float
    y_m: float
    vx_mps: float
    vy_mps: float
    heading_rad: float
    size_m: tuple[float, float, float]
    entity_id: int = -1
    sim_time_ns: int = 0

    def key(self) -> tuple[float, ...]:
        """What "changed" compares: position to 0.1 mm, heading to 1e-5 rad, velocity to
        0.1 mm/s (``EntityTable.keys``, the same values: multiples of those steps,
        halves to even)."""
        return tuple(_quantum(v * q) for v, q in zip(
            (self.x_m, self.y_m, self.heading_rad, self.vx_mps, self.vy_mps), _KEY_STEPS, strict=True))

    def to_json(self) -> dict[str, object]:
        return {"id": self.entity_id, "name": self.name, "cls": self.cls, "x_m": self.x_m, "y_m": self.y_m,
                "vx_mps": self.vx_mps, "vy_mps": self.vy_mps, "heading_rad": self.heading_rad,
                "size_m": list(self.size_m), "sim_time_ns": self.sim_time_ns}


@dataclass(frozen=True)
class Collision:
    """A contact between two entities that began at ``sim_time_ns``: ``force_n`` is
    the normal force at onset, ``closing_speed_mps`` their approach speed along the
    contact normal, ``striker`` the one that moved into the other faster (None when
    neither did)."""

    sim_time_ns: int
    a: str
    b: str
    force_n: float
    closing_speed_mps: float = 0.0
    striker: str | None = None

    def to_json(self) -> dict[str, object]:
        return {"sim_time_ns": self.sim_time_ns, "a": self.a, "b": self.b, "force_n": self.force_n,
                "closing_speed_mps": self.closing_speed_mps, "striker": self.striker}


@dataclass(frozen=True)
class EgoTruth:
    """Truth from one ego vehicle's point of view: the gap (m, front bumper to the
    obstacle's nearest face along the ego's route; ``None`` when its path is clear),
    the obstacle's name and speed along the route, time to collision (s, ``None``
    when not closing), and the reference driving state."""

    vehicle: str
    gap_m: float | None
    obstacle: str | None
    speed_mps: float
    ref_state: RefState
    obstacle_speed_mps: float = 0.0
    ttc_s: float | None = None

    def to_json(self) -> dict[str, object]:
        return {"vehicle": self.vehicle, "gap_m": self.gap_m, "obstacle": self.obstacle,
                "speed_mps": self.speed_mps, "ref_state": self.ref_state.name,
                "obstacle_speed_mps": self.obstacle_speed_mps, "ttc_s": self.ttc_s}


@dataclass(frozen=True)
class VisibleBox:
    """One entity seen by one camera. ``box_px`` = (x0, y0, x1, y1), pixel edges
    (x1, y1 exclusive) of its visible pixels; ``visible_px`` their count;
    ``visible_fraction`` = visible pixels / pixels of its unoccluded silhouette in
    the image (the convex hulls of its geoms' projected boxes, clipped to the
    image); ``truncated`` when that silhouette runs past the image border.
    ``path_s_m`` is the distance along the ego's route from the ego's front to the
    entity's nearest face (negative: behind), ``path_lateral_m`` its offset from the
    ego's driving line (positive: left)."""

    entity: str
    entity_id: int
    cls: str
    box_px: tuple[int, int, int, int]
    visible_px: int
    visible_fraction: float
    truncated: bool
    path_s_m: float
    path_lateral_m: float

    def to_json(self) -> dict[str, object]:
        return {"entity": self.entity, "id": self.entity_id, "cls": self.cls, "box_px": list(self.box_px),
                "visible_px": self.visible_px, "visible_fraction": self.visible_fraction,
                "truncated": self.truncated, "path_s_m": self.path_s_m, "path_lateral_m": self.path_lateral_m}


@dataclass(frozen=True)
class CameraTruth:
    """What one ego's camera shows at ``sim_time_ns``, and the ego's own truth."""

    vehicle: str
    sim_time_ns: int
    boxes: tuple[VisibleBox, ...]
    ego: EgoTruth

    def box(self, entity: str) -> VisibleBox | None:
        return next((b for b in self.boxes if b.entity == entity), None)

    def to_json(self) -> dict[str, object]:
        return {"vehicle": self.vehicle, "sim_time_ns": self.sim_time_ns,
                "boxes": [b.to_json() for b in self.boxes], "ego": self.ego.to_json()}


class EntityTable(Sequence[EntityState]):
    """One instant's entities as columns: ``cols`` (5, n) holds x, y (m), heading (rad),
    vx, vy (m/s) of each, in the order of ``names`` (their classes, sizes, world ids
    alongside; ``dims``: the sizes as an (n, 3) array). A sequence of ``EntityState``,
    each built when it is asked for (and kept): the simulator's ground truth of every
    camera instant gives one, and what reads all of its entities reads the columns
    (``StateChanges``, the detector's footprints); equal to the tuple of its states."""

    __slots__ = ("names", "classes", "sizes", "dims", "ids", "cols", "sim_time_ns", "_rows", "_row_of")

    def __init__(self, names: tuple[str, ...], classes: tuple[str, ...], sizes: tuple[tuple[float, float, float], ...],
                 dims: np.ndarray, ids: tuple[int, ...], cols: np.ndarray, sim_time_ns: int, *,
                 row_of: dict[str, int] | None = None) -> None:
        self.names, self.classes, self.sizes, self.dims, self.ids = names, classes, sizes, dims, ids
        self.cols, self.sim_time_ns = cols, sim_time_ns
        self._rows: list[EntityState | None] = [None] * len(names)
        self._row_of = row_of

    def __len__(self) -> int:
        return len(self.names)

    @overload
    def __getitem__(self, i: int) -> EntityState: ...
    @overload
    def __getitem__(self, i: slice) -> tuple[EntityState, ...]: ...

    def __getitem__(self, i: int | slice) -> EntityState | tuple[EntityState, ...]:
        if isinstance(i, slice):
            return tuple(self)[i]
        if i < 0:
            i += len(self.names)
        e = self._rows[i]  # (IndexError past either end)
        if e is None:
            x, y, h, vx, vy = self.cols[:, i].tolist()
            e = self._rows[i] = EntityState(self.names[i], self.classes[i], x, y, vx, vy, h, self.sizes[i],
                                            self.ids[i], self.sim_time_ns)
        return e

    def __iter__(self) -> Iterator[EntityState]:
        return (self[i] for i in range(len(self.names)))

    def __eq__(self, other: object) -> bool:
        if isinstance(other, (tuple, EntityTable)):
            return tuple(self) == tuple(other)
        return NotImplemented

    def __hash__(self) -> int:
        return hash(tuple(self))

    def __repr__(self) -> str:
        return f"EntityTable{tuple(self)!r}"

    @property
    def row_of(self) -> dict[str, int]:
        """Name -> row."""
        if self._row_of is None:
            self._row_of = {n: i for i, n in enumerate(self.names)}
        return self._row_of

    def keys(self) -> np.ndarray:
        """(5, n): what "changed" compares, per entity (``EntityState.key``'s values)."""
        keys: np.ndarray = np.rint(self.cols * _KEY_COLS)
        return keys

    def rows_json(self, rows: Sequence[int]) -> list[dict[str, object]]:
        """``EntityState.to_json`` of the entities in ``rows``, from the columns."""
        x, y, h, vx, vy = self.cols[:, rows].tolist()
        t, names, classes, ids, sizes = self.sim_time_ns, self.names, self.classes, self.ids, self.sizes
        return [{"id": ids[i], "name": names[i], "cls": classes[i], "x_m": x[k], "y_m": y[k], "vx_mps": vx[k],
                 "vy_mps": vy[k], "heading_rad": h[k], "size_m": list(sizes[i]), "sim_time_ns": t}
                for k, i in enumerate(rows)]


_KEY_COLS = np.array(_KEY_STEPS)[:, None]


@dataclass(frozen=True)
class GroundTruth:
    sim_time_ns: int
    entities: Sequence[EntityState]  # a tuple, or the simulator's EntityTable
    egos: tuple[EgoTruth, ...]
    collisions: tuple[Collision, ...]  # those that began since the previous record

    def entity(self, name: str) -> EntityState:
        return next(e for e in self.entities if e.name == name)

    def ego(self, name: str) -> EgoTruth:
        return next(e for e in self.egos if e.vehicle == name)


class StateChanges:
    """The per-entity record stream: ``changes_json(gt)`` gives every entity's state
    the first time, then only those whose state changed since they were last given."""

    def __init__(self) -> None:
        self._last: dict[str, tuple[float, ...]] = {}
        # The keys of the last EntityTable's entities, in its order (while they, not
        # ``_last``, are the latest: ``_last`` is brought up to date from them when a
        # tuple of states comes).
        self._names: tuple[str, ...] | None = None
        self._keys = np.zeros((5, 0))

    @property
    def seen(self) -> bool:
        """True once ``changes_json`` has given the initial states."""
        return bool(self._last) or self._names is not None

    def changes_json(self, gt: GroundTruth) -> list[dict[str, object]]:
        ents = gt.entities
        if isinstance(ents, EntityTable):
            return ents.rows_json(self._changed_rows(ents))
        self._settle()
        out = []
        for e in ents:
            k = e.key()
            if self._last.get(e.name) != k:
                self._last[e.name] = k
                out.append(e.to_json())
        return out

    def _settle(self) -> None:
        """``_last`` brought up to date from the last table's keys."""
        if self._names is not None:
            self._last.update(zip(self._names, map(tuple, self._keys.T.tolist()), strict=True))
            self._names = None

    def _changed_rows(self, table: EntityTable) -> list[int]:
        keys = table.keys()
        if self._names is not table.names:
            self._settle()
            last = [self._last.get(n) for n in table.names]
            self._keys = np.array([k if k is not None else (math.nan,) * 5 for k in last], float).reshape(-1, 5).T
            self._names = table.names
        changed = (keys != self._keys).any(axis=0)  # NaN: never the same
        self._keys = keys
        return np.flatnonzero(changed).tolist()
