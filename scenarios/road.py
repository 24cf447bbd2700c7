"""Roads: a surface and its markings laid along a ``Path``, written as MJCF boxes.

A road's reference line is its centre. Lanes are numbered from the right (lane 0
is the rightmost in the direction of travel); all lanes run the same way (a
carriageway). Solid edge lines bound the lanes, dashed lines separate them, and a
shoulder of bare asphalt lies beyond each edge line. Straight segments are one box
each; arcs are chains of short chords (overlapping a little on the outside so no
verge shows through). ``marking_gaps`` leave the markings out over ranges of arc
length, as across an intersection.

Every road geom is in geom group ``ROAD_GROUP`` and never collides, so the
segmentation pass can leave the road out and physics never sees it.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import numpy as np

from hil.scenarios.path import Path

ROAD_GROUP = 2
CHORD_M = 2.0  # longest chord of an arc
ROAD_RGBA = "0.32 0.32 0.34 1"
GRASS_RGBA = "0.25 0.45 0.2 1"
MARKING_RGBA = "0.95 0.95 0.95 1"


@dataclass(frozen=True)
class RoadSpec:
    """A road along ``path`` (its centre line). ``path=None`` is the classic straight
    road along +x from ``start_x_m`` of ``length_m`` centred on y = 0."""

    path: Path | None = None
    length_m: float = 400.0
    start_x_m: float = -20.0
    lanes: int = 2
    lane_width_m: float = 3.7
    shoulder_m: float = 0.5
    marking_width_m: float = 0.15
    dash_m: float = 3.0
    gap_m: float = 6.0
    marking_gaps: tuple[tuple[float, float], ...] = ()
    name: str = "road"

    @property
    def centre(self) -> Path:
        if self.path is not None:
            return self.path
        return Path.straight(self.start_x_m, 0.0, 0.0, self.length_m)

    @property
    def half_width_m(self) -> float:
        """Centre to the outer edge lines."""
        return self.lanes * self.lane_width_m / 2

    def lane_offset_m(self, lane: int) -> float:
        """Lateral offset (left positive) of lane ``lane``'s centre from the road centre."""
        if not 0 <= lane < self.lanes:
            raise ValueError(f"lane {lane} outside 0..{self.lanes - 1}")
        return -self.half_width_m + (lane + 0.5) * self.lane_width_m

    def lane(self, lane: int) -> Path:
        """The centre line of lane ``lane`` (0: rightmost)."""
        return self.centre.offset(self.lane_offset_m(lane))


def road_xml(road: RoadSpec) -> list[str]:
    """The MJCF geoms of ``road`` (worldbody children)."""
    centre = road.centre
    out: list[str] = []
    half = road.half_width_m + road.shoulder_m
    n = 0

    def box(kind: str, x: float, y: float, h: float, length: float, width: float, z: float, thick: float,
            material: str) -> None:
        nonlocal n
        out.append(
            f'    <geom name="{road.name}/{kind}{n}" type="box" pos="{x:.4f} {y:.4f} {z:.4f}" '
            f'euler="0 0 {h:.6f}" size="{length / 2:.4f} {width / 2:.4f} {thick:.4f}" '
            f'material="{material}" group="{ROAD_GROUP}" contype="0" conaffinity="0"/>'
        )
        n += 1

    # Surface: chords along the centre; each is lengthened so that its outer corners
    # meet the next chord's (the wedge between chords on the outside of a curve).
    for s0, s1 in _pieces(centre, 0.0, centre.length_m):
        x, y, h, length = _chord(centre, s0, s1)
        k = abs(float(centre.curvature_at((s0 + s1) / 2)))
        box("surface", x, y, h, length + 2 * half * k * (s1 - s0) / 2 + 0.02, 2 * half, 0.005, 0.005, "road")

    mw = road.marking_width_m
    spans = _subtract(0.0, centre.length_m, road.marking_gaps)
    for side in (-1, 1):  # solid edge lines
        line = centre.offset(side * road.half_width_m)
        for a, b in spans:
            sa, sb = _scaled(centre, line, a), _scaled(centre, line, b)
            for s0, s1 in _pieces(line, sa, sb):
                x, y, h, length = _chord(line, s0, s1)
                box("edge", x, y, h, length, mw, 0.0105, 0.0005, "marking")
    period = road.dash_m + road.gap_m
    for lane in range(1, road.lanes):  # dashed lines between lanes
        line = centre.offset(-road.half_width_m + lane * road.lane_width_m)
        for k in range(int(line.length_m // period) + 1):
            a = k * period
            b = min(a + road.dash_m, line.length_m)
            if b - a < 0.3 or not _free(_unscaled(centre, line, a), _unscaled(centre, line, b), road.marking_gaps):
                continue
            x, y, h, length = _chord(line, a, b)
            box("dash", x, y, h, length, mw, 0.0105, 0.0005, "marking")
    return out


def _pieces(path: Path, s_from: float, s_to: float) -> list[tuple[float, float]]:
    """Consecutive (s0, s1) ranges: one per straight stretch, chords of at most
    ``CHORD_M`` on arcs."""
    if s_to - s_from <= 1e-6:
        return []
    knots = path.sample(math.inf, s_from=s_from, s_to=s_to)
    out: list[tuple[float, float]] = []
    for a, b in itertools.pairwise(knots):
        k = float(path.curvature_at((a + b) / 2))
        m = 1 if abs(k) < 1e-12 else max(1, math.ceil((b - a) / CHORD_M))
        edges = np.linspace(a, b, m + 1)
        out.extend(zip(edges[:-1].tolist(), edges[1:].tolist()))
    return out


def _chord(path: Path, s0: float, s1: float) -> tuple[float, float, float, float]:
    x, y, _ = path.pose_at(np.array([s0, s1]))
    return (float(x.mean()), float(y.mean()), math.atan2(float(y[1] - y[0]), float(x[1] - x[0])),
            float(math.hypot(x[1] - x[0], y[1] - y[0])))


def _subtract(a: float, b: float, gaps: tuple[tuple[float, float], ...]) -> list[tuple[float, float]]:
    spans = [(a, b)]
    for g0, g1 in gaps:
        spans = [piece for s0, s1 in spans
                 for piece in ((s0, min(s1, g0)), (max(s0, g1), s1)) if piece[1] - piece[0] > 1e-6]
    return spans


def _free(a: float, b: float, gaps: tuple[tuple[float, float], ...]) -> bool:
    return all(b <= g0 or a >= g1 for g0, g1 in gaps)


def _scaled(centre: Path, line: Path, s: float) -> float:
    """Arc length on the offset ``line`` at the point abreast of centre arc length ``s``."""
    return float(line.project(*[float(v) for v in centre.pose_at(s)[:2]])[0])


def _unscaled(centre: Path, line: Path, s: float) -> float:
    return float(centre.project(*[float(v) for v in line.pose_at(s)[:2]])[0])
