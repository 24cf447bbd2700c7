"""What a camera sees of each entity: pixel boxes from a segmentation image, and
the unoccluded image area of a box (the denominator of a visible fraction).

The silhouette of a convex solid seen by a pinhole camera is the convex hull of its
projected vertices. The part of the box behind the camera's near plane is cut off
first (its edges are clipped at the plane), and the hull is clipped to the image
rectangle, so the area counts only pixels the image could show. Pure numpy and
Python on a dozen points; no MuJoCo import.
"""

from __future__ import annotations

import numpy as np

NEAR_M = 0.05
_SIGNS = np.array([[(i & 1) * 2 - 1, (i >> 1 & 1) * 2 - 1, (i >> 2 & 1) * 2 - 1] for i in range(8)], float)
_EDGES = [(a, a | bit) for a in range(8) for bit in (1, 2, 4) if not a & bit]


def pixel_boxes(ids: np.ndarray, entities: list[int]) -> list[tuple[int, int, int, int]]:
    """(x0, y0, x1, y1) pixel edges (x1, y1 exclusive) of each entity's pixels in an
    entity-id image; every entity listed must have at least one pixel."""
    out = []
    for e in entities:
        mask = ids == e
        rows = np.flatnonzero(mask.any(axis=1))
        cols = np.flatnonzero(mask.any(axis=0))
        out.append((int(cols[0]), int(rows[0]), int(cols[-1]) + 1, int(rows[-1]) + 1))
    return out


def silhouette_area(pos: np.ndarray, mat: np.ndarray, half_size: np.ndarray, cam_pos: np.ndarray,
                    cam_mat: np.ndarray, fx: float, fy: float, cx: float, cy: float, width: int,
                    height: int) -> tuple[float, bool]:
    """(area in pixels, truncated) of a box (centre ``pos``, rotation ``mat`` 3x3,
    half sizes) in a camera at ``cam_pos`` with rotation ``cam_mat`` (MuJoCo's: the
    camera looks along its -z, image up is +y). ``truncated``: the silhouette runs
    past the image border or behind the camera."""
    corners = pos + (_SIGNS * half_size) @ mat.T
    pc = (corners - cam_pos) @ cam_mat
    depth = -pc[:, 2]
    front = depth >= NEAR_M
    if not front.any():
        return 0.0, True
    pts = [pc[i] for i in range(8) if front[i]]
    cut = not front.all()
    if cut:
        for a, b in _EDGES:
            if front[a] != front[b]:
                t = (NEAR_M - depth[a]) / (depth[b] - depth[a])
                pts.append(pc[a] + t * (pc[b] - pc[a]))
    p = np.array(pts)
    d = -p[:, 2]
    u = cx + fx * p[:, 0] / d
    v = cy - fy * p[:, 1] / d
    hull = _hull(list(zip(u.tolist(), v.tolist())))
    clipped = _clip(hull, float(width), float(height))
    truncated = cut or bool(u.min() < 0 or v.min() < 0 or u.max() > width or v.max() > height)
    return _area(clipped), truncated


def _hull(points: list[tuple[float, float]]) -> list[tuple[float, float]]:
    """Convex hull, counter-clockwise (Andrew's monotone chain)."""
    pts = sorted(set(points))
    if len(pts) < 3:
        return pts

    def cross(o: tuple[float, float], a: tuple[float, float], b: tuple[float, float]) -> float:
        return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])

    lower: list[tuple[float, float]] = []
    for p in pts:
        while len(lower) >= 2 and cross(lower[-2], lower[-1], p) <= 0:
            lower.pop()
        lower.append(p)
    upper: list[tuple[float, float]] = []
    for p in reversed(pts):
        while len(upper) >= 2 and cross(upper[-2], upper[-1], p) <= 0:
            upper.pop()
        upper.append(p)
    return lower[:-1] + upper[:-1]


def _clip(poly: list[tuple[float, float]], w: float, h: float) -> list[tuple[float, float]]:
    """Sutherland-Hodgman clipping of a convex polygon to [0, w] x [0, h]."""
    for axis, bound, keep_below in ((0, 0.0, False), (0, w, True), (1, 0.0, False), (1, h, True)):
        if not poly:
            return poly
        out: list[tuple[float, float]] = []
        for i, cur in enumerate(poly):
            prev = poly[i - 1]
            cin = cur[axis] <= bound if keep_below else cur[axis] >= bound
            pin = prev[axis] <= bound if keep_below else prev[axis] >= bound
            if cin != pin:
                t = (bound - prev[axis]) / (cur[axis] - prev[axis])
                out.append((prev[0] + t * (cur[0] - prev[0]), prev[1] + t * (cur[1] - prev[1])))
            if cin:
                out.append(cur)
        poly = out
    return poly


def _area(poly: list[tuple[float, float]]) -> float:
    n = len(poly)
    if n < 3:
        return 0.0
    s = 0.0
    for i in range(n):
        x0, y0 = poly[i - 1]
        x1, y1 = poly[i]
        s += x0 * y1 - x1 * y0
    return abs(s) / 2
