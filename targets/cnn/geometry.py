"""Object position from a bounding box: the pinhole model with known intrinsics and
class size priors (the seed paper's Figure 3). Pure Python; no torch.

Frame: x forward, y left, z up, origin on the road under the camera (the wire's
camera-ground frame); the reported point is the centre of the object's nearest face
at road level. Pixel (u, v) covers [u, u+1); a box's x1, y1 are exclusive edges.

Up to three range estimates from one box of ``w`` x ``h`` px whose bottom edge is
at row ``v_b``:

* width:  Z = fx W / w          (W: the class's width prior)
* height: Z = fy H / h          (H: its height prior)
* ground contact: the ray through the bottom edge meets the plane ``B`` above the
  road (the class's underside: 0.1 m for a vehicle, 0 for the rest):
  Z = fy (mount - B) / (v_b - cy) at zero pitch (the general form tilts the ray).

Each has a relative variance ``(SIGMA_PX / extent)^2 + prior^2``, with ``extent``
the pixels it rests on (w, h, or v_b minus the horizon row) and ``prior`` the
relative spread of the size it assumes; they are averaged in inverse depth with
weights 1 / variance (so an obstacle of unexpected size is ranged by its ground
contact, and a far car, whose bottom edge is few pixels under the horizon, mostly by
its size).
An edge on the image border drops the estimates that use it; a box cut by the
bottom border is no farther than the lowest road row. A vehicle box wider than
1.25 x its prior aspect shows a side face: its width estimate is dropped.

Priors (m; relative spread): vehicle 1.8 (5 %) x 1.4 (15 %, vans are taller),
underside 0.1; pedestrian 0.5 (25 %) x 1.75 (8 %); obstacle 0.7 (35 %) x 0.7
(35 %): obstacles come in any size, so their range rests on the ground contact.
Lateral: y = -(u_centre - cx) Z / fx.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from hil.adapters.wire.messages import CameraInfo, ObjectClass
from hil.targets.cv_baseline import ground_x  # one ground-plane projection for both AIs

SIGMA_PX = 1.0  # box edge error assumed, px


@dataclass(frozen=True)
class SizePrior:
    """Width and height (m) with their relative spreads, and the height (m) of the
    object's lowest visible edge above the road."""

    width_m: float
    width_spread: float
    height_m: float
    height_spread: float
    underside_m: float


PRIORS: dict[ObjectClass, SizePrior] = {
    ObjectClass.VEHICLE: SizePrior(1.8, 0.05, 1.4, 0.15, 0.1),
    ObjectClass.PEDESTRIAN: SizePrior(0.5, 0.25, 1.75, 0.08, 0.0),
    ObjectClass.OBSTACLE: SizePrior(0.7, 0.35, 0.7, 0.35, 0.0),
}


def horizon_v(cam: CameraInfo) -> float:
    """Row (continuous px) of the horizon of a level road."""
    return cam.cy - cam.fy * math.tan(cam.pitch_rad)


def estimate_position(box_px: tuple[float, float, float, float], cls: ObjectClass, cam: CameraInfo,
                      width: int, height: int) -> tuple[float, float, float] | None:
    """(x, y, 0) in metres for a box in a ``width`` x ``height`` frame, or None when
    no estimate is possible (a box above the horizon and cut on every side)."""
    prior = PRIORS.get(cls, PRIORS[ObjectClass.VEHICLE])
    x0, y0, x1, y1 = box_px
    w, h = x1 - x0, y1 - y0
    if w <= 0 or h <= 0:
        return None
    cut_l, cut_r, cut_t, cut_b = x0 <= 1.0, x1 >= width - 1.0, y0 <= 1.0, y1 >= height - 1.0
    hv = horizon_v(cam)
    cands: list[tuple[float, float]] = []  # (Z, weight)
    side_view = cls == ObjectClass.VEHICLE and w / h > 1.25 * prior.width_m / prior.height_m
    if not (cut_l or cut_r or side_view):
        cands.append((cam.fx * prior.width_m / w, 1.0 / ((SIGMA_PX / w) ** 2 + prior.width_spread ** 2)))
    if not (cut_t or cut_b):
        cands.append((cam.fy * prior.height_m / h, 1.0 / ((SIGMA_PX / h) ** 2 + prior.height_spread ** 2)))
    if not cut_b and y1 - hv > 0.5:
        z = ground_x(cam, y1, prior.underside_m)
        if z is not None:
            cands.append((z, 1.0 / (SIGMA_PX / (y1 - hv)) ** 2))
    dist = _combine(cands)
    if cut_b:
        bound = ground_x(cam, float(height), prior.underside_m)
        if bound is not None:
            dist = bound if dist is None else min(dist, bound)
    if dist is None or dist <= 0:
        return None
    w_expect = cam.fx * prior.width_m / dist
    if cut_l and not cut_r:
        u_c = x1 - w_expect / 2
    elif cut_r and not cut_l:
        u_c = x0 + w_expect / 2
    else:
        u_c = (x0 + x1) / 2
    return float(dist), float(-(u_c - cam.cx) * dist / cam.fx), 0.0


def _combine(cands: list[tuple[float, float]]) -> float | None:
    if not cands:
        return None
    inv = sum(wt / z for z, wt in cands) / sum(wt for _, wt in cands)
    return 1.0 / inv
