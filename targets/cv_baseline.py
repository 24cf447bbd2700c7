"""A classical OpenCV driving AI: colour-blob vehicle detection, pinhole ranging,
rule-based SAFE/SLOW/STOP, lane keeping from the markings. It sees only the frame.

    python -m hil.targets.cv_baseline --cruise-speed 10

Units: metres, seconds, radians, pixels. Camera frame for positions: origin on the
road under the camera, x forward, y left (the ``CameraInfo`` of each frame gives
fx, fy, cx, cy, mount height and pitch; pixel ``(u, v)`` covers ``[u, u+1)``).

Detection. A pixel is vehicle paint when HSV saturation >= ``min_saturation`` (0.5),
value >= ``min_value`` (0.25) and its hue is outside the green verge band (75-165
deg) and the blue sky band (185-235 deg): grey road and white markings fail the
saturation test, the sky is both too pale and the wrong hue. Green, cyan and blue
cars are therefore invisible to this baseline. The mask is opened (2x2) and split
into connected components; a component is a vehicle when its area >= ``min_area_px``
(8), its width >= 3 px, fill >= 0.5, width/height in [0.6, 4], its bottom lies below
the horizon and the strip under it is unsaturated (road or marking). At 320x240 and
60 deg vertical FOV a 1.8 m car is 3.7 px wide at 100 m: detections end near there
(``max_range_m`` 120).

Ranging. Box edges are refined to sub-pixel: each pixel from the box middle to 2 px
past the edge is unmixed between the car's colour and the background 3 px outside,
and the coverages are summed (anti-aliasing and JPEG's chroma smear move coverage
between pixels but keep its sum). Vehicle prior: width 1.8 m, height
1.4 m, underside 0.1 m and roof 1.5 m above the road. Up to four estimates: width
(Z = fx W / w), height (Z = fy H / h), ground contact of the bottom edge (the ray to
the underside line, Z = fy (mount - 0.1) / (v_bottom - cy) at zero pitch), roof line
(same with the roof). Each has relative error ~ 0.5 px / (its pixel extent), so they
are averaged in inverse depth with weights (extent)^2. An edge clipped by the image
border drops the estimates that use it. With three or more, any estimate more than
20 % from their median is dropped (a visible side face widens the box; the ground
contact is immune to that); with two that disagree, the ground contact is kept, as
the one that does not depend on the size prior. A box cut by the bottom border is
placed no farther than the lowest visible road row (2.1 m at 1.3 m, 60 deg).
Lateral y = -(u_centre - cx) Z / fx.
Objects are reported at their rear face, at road level.

Decision (objects in the path: |y| < ``path_half_width_m`` = 1.6 m, i.e. they
overlap a 1.8 m car; objects are assumed stationary, which is conservative). With v
the ego speed and d the nearest in-path distance:
``stop_d = v^2 / (2 comfort_decel) + stop_margin`` (4 m/s^2, 6 m);
STOP if d <= stop_d; SLOW if d <= stop_d + 2 s * v or d / v <= 4 s; else SAFE.

Control. SAFE: throttle = 0.3 (cruise - v), no brake. SLOW: track
``v_t = 0.6 sqrt(2 comfort_decel (d - standoff))`` (standoff 3 m) with throttle
0.3/(m/s) or brake 0.25/(m/s). STOP: brake = v^2 / (2 (d - 3 m)) / 8 m/s^2, at least
0.3, 1.0 under 4 m; held at >= 0.3 when stopped. Steering: pure pursuit about the
vehicle centre (2.3 m behind the camera, wheelbase 2.7 m) on the lane centre line
fitted from the markings, target point 1.2 s * v ahead of the camera (6-16 m),
clamped to +-0.5 rad; without markings it decays by 0.8 per frame.

Lane markings: pixels with saturation <= 0.25 and value >= 0.65 whose road-plane
projection lies 4-16 m ahead. Those 0-3.35 m to the left are the ego lane's left
line (dashed), those to the right its right line; each side is fitted Y = c0 + c1 X
by least squares with one 0.35 m outlier pass. The centre is their mean, or one
side +- 3.7 m / 2 when the other is missing (a gap in the dashes).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import cv2
import numpy as np

from hil.adapters.wire.messages import (CameraInfo, Control, DetectedObject, DrivingState, Frame, ImageEncoding,
                                        Inference, ObjectClass)

VEHICLE_W_M, VEHICLE_H_M, CLEARANCE_M = 1.8, 1.4, 0.1
CAMERA_TO_CENTRE_M = 2.3  # camera mount ahead of the vehicle centre (the yaw pivot)
WHEELBASE_M, MAX_STEER_RAD = 2.7, 0.5
MAX_BRAKE_MPS2 = 8.0
_EXCLUDED_HUES_DEG = ((75.0, 165.0), (185.0, 235.0))  # green verge, blue sky


def ground_x(cam: CameraInfo, v: float, z_above_road_m: float) -> float | None:
    """Forward distance (m) of the road-parallel plane ``z_above_road_m`` up, seen at
    continuous image row ``v``; None when the ray misses it (at or above the horizon)."""
    sp, cp = math.sin(cam.pitch_rad), math.cos(cam.pitch_rad)
    b = (v - cam.cy) / cam.fy
    den = sp + b * cp
    drop = cam.mount_height_m - z_above_road_m
    if abs(den) < 1e-9 or drop / den <= 0:
        return None
    t = drop / den
    return t * (cp - b * sp)


class CvBaseline:
    """The OpenCV baseline; ``infer`` is the function the SDK serves.

    Keeps only the last steering angle between frames (for the decay when no
    markings are seen); every frame is processed on its own.
    """

    def __init__(self, *, cruise_speed_mps: float = 10.0, comfort_decel_mps2: float = 4.0,
                 stop_margin_m: float = 6.0, slow_headway_s: float = 2.0, slow_ttc_s: float = 4.0,
                 path_half_width_m: float = 1.6, standoff_m: float = 3.0, min_brake: float = 0.3,
                 min_saturation: float = 0.5, min_value: float = 0.25, min_area_px: int = 8,
                 max_range_m: float = 120.0, lane_width_m: float = 3.7,
                 lane_window_m: tuple[float, float] = (4.0, 16.0), lookahead_s: float = 1.2) -> None:
        if cruise_speed_mps < 0 or comfort_decel_mps2 <= 0:
            raise ValueError(f"cruise_speed_mps must be >= 0 and comfort_decel_mps2 > 0; got "
                             f"{cruise_speed_mps} and {comfort_decel_mps2}")
        self.cruise_speed_mps = cruise_speed_mps
        self.comfort_decel_mps2 = comfort_decel_mps2
        self.stop_margin_m = stop_margin_m
        self.slow_headway_s = slow_headway_s
        self.slow_ttc_s = slow_ttc_s
        self.path_half_width_m = path_half_width_m
        self.standoff_m = standoff_m
        self.min_brake = min_brake
        self.min_area_px = min_area_px
        self.max_range_m = max_range_m
        self.lane_width_m = lane_width_m
        self.lane_window_m = lane_window_m
        self.lookahead_s = lookahead_s
        self._sat_min = int(round(min_saturation * 255))
        self._val_min = int(round(min_value * 255))
        self._steer_rad = 0.0
        self._geom_key: tuple[CameraInfo, int, int] | None = None

    # -- the SDK entry point -------------------------------------------------

    def infer(self, frame: Frame) -> Inference:
        """Detect vehicles, decide the driving state and the control for one frame.

        Raises:
            ValueError: the image bytes do not decode to ``height x width x 3``.
        """
        img, bgr = _decode(frame)
        self._prepare_geometry(frame.camera, frame.width, frame.height)
        hsv = cv2.cvtColor(img, cv2.COLOR_BGR2HSV if bgr else cv2.COLOR_RGB2HSV)
        objects = self._detect(img, hsv, frame.camera)
        v = max(0.0, frame.ego_speed_mps)
        in_path = [o.position_m[0] for o in objects if abs(o.position_m[1]) < self.path_half_width_m]
        dist = min(in_path) if in_path else None
        state = self.decide(dist, v)
        throttle, brake = self.longitudinal(state, dist, v)
        steer = self._steering(hsv, v)
        return Inference(state, Control(steer, throttle, brake), tuple(objects))

    def warm_up(self, width: int = 320, height: int = 240) -> None:
        """Run the whole pipeline once on a frame of noise (raw and JPEG) and forget it.
        OpenCV and numpy set themselves up on their first calls (numpy.ma's import
        among them): a rendered frame with a car in view took 18-19 ms the first time
        and 2-3 ms after, here, so without this the run's first frame waited for it.
        ``main`` calls it before serving, so before HELLO."""
        cam = CameraInfo(fx=width / 2, fy=width / 2, cx=width / 2, cy=height / 2, mount_height_m=1.4, pitch_rad=0.05)
        # Noise: saturated blobs everywhere, so that detection, ranging and the lane
        # search all take their first steps (a blank frame skips most of them).
        noise = np.random.default_rng(0).integers(0, 256, (height, width, 3), dtype=np.uint8)
        images = [(ImageEncoding.RGB8, noise.tobytes())]
        ok, jpeg = cv2.imencode(".jpg", noise)
        if ok:
            images.append((ImageEncoding.JPEG, jpeg.tobytes()))
        for encoding, data in images:
            self.infer(Frame(vehicle_id=0, frame_id=0, sim_time_ns=0, t0_ns=0, t_tx_ns=0, width=width, height=height,
                             encoding=encoding, camera=cam, ego_speed_mps=0.0, data=data))
        self._steer_rad = 0.0  # what the noise left of the steering filter
        self._geom_key = None

    # -- geometry ------------------------------------------------------------

    def _prepare_geometry(self, cam: CameraInfo, width: int, height: int) -> None:
        key = (cam, width, height)
        if key == self._geom_key:
            return
        sp, cp = math.sin(cam.pitch_rad), math.cos(cam.pitch_rad)
        self._horizon_v = cam.cy - cam.fy * math.tan(cam.pitch_rad)
        b = (np.arange(height) + 0.5 - cam.cy) / cam.fy
        den = sp + b * cp
        with np.errstate(divide="ignore", invalid="ignore"):
            t = np.where(den > 1e-6, cam.mount_height_m / den, np.nan)
        self._row_x = t * (cp - b * sp)  # forward distance of each row's road point
        self._row_t = t
        self._col_a = (np.arange(width) + 0.5 - cam.cx) / cam.fx
        lo, hi = self.lane_window_m
        rows = np.flatnonzero((self._row_x >= lo) & (self._row_x <= hi))
        self._lane_rows = (int(rows[0]), int(rows[-1]) + 1) if rows.size else (0, 0)
        self._geom_key = key

    # -- detection -----------------------------------------------------------

    def _detect(self, img: np.ndarray, hsv: np.ndarray, cam: CameraInfo) -> list[DetectedObject]:
        mask = cv2.inRange(hsv, (0, self._sat_min, self._val_min), (180, 255, 255))
        for lo, hi in _EXCLUDED_HUES_DEG:  # OpenCV hue is degrees / 2
            band = cv2.inRange(hsv, (int(lo / 2), 0, 0), (int(hi / 2), 255, 255))
            mask = cv2.bitwise_and(mask, cv2.bitwise_not(band))
        # 2x2 opening; the anchors mirror each other so the mask does not shift by a
        # pixel (cv2.morphologyEx with an even kernel does).
        k = np.ones((2, 2), np.uint8)
        mask = cv2.dilate(cv2.erode(mask, k, anchor=(0, 0)), k, anchor=(1, 1))
        _, _, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
        h_img = mask.shape[0]
        out = []
        for x, y, w, h, area in stats[1:]:
            x1, y1 = x + w - 1, y + h - 1
            if area < self.min_area_px or w < 3 or h < 2 or area < 0.5 * w * h or not 0.6 <= w / h <= 4.0:
                continue
            if y1 + 1 <= self._horizon_v + 0.5:
                continue
            if y1 + 1 < h_img:  # the strip under the box must be road (unsaturated)
                strip = hsv[y1 + 1:min(h_img, y1 + 4), x:x1 + 1, 1]
                if np.count_nonzero(strip < self._sat_min // 2) < 0.5 * strip.size:
                    continue
            obj = self._range(img, hsv, cam, int(x), int(y), int(x1), int(y1), area / (w * h))
            if obj is not None:
                out.append(obj)
        out.sort(key=lambda o: o.position_m[0])
        return out

    def _range(self, img: np.ndarray, hsv: np.ndarray, cam: CameraInfo, x0: int, y0: int, x1: int, y1: int,
               fill: float) -> DetectedObject | None:
        h_img, w_img = img.shape[:2]
        # The car's colour: the most saturated tenth of the box (JPEG smears the
        # rim of a small blob towards the background).
        box = img[y0:y1 + 1, x0:x1 + 1].reshape(-1, 3)
        sat = hsv[y0:y1 + 1, x0:x1 + 1, 1].reshape(-1)
        colour = np.median(box[sat >= np.percentile(sat, 90)].astype(np.float32), axis=0)
        rows = np.arange(y0 + 1, y1) if y1 - y0 >= 2 else np.arange(y0, y1 + 1)
        cols = np.arange(x0 + 1, x1) if x1 - x0 >= 2 else np.arange(x0, x1 + 1)
        xm, ym = (x0 + x1 + 1) // 2, (y0 + y1 + 1) // 2
        left = _edge(img, colour, rows, xm, x0, -1, axis=1) if x0 >= 3 else None
        right = _edge(img, colour, rows, xm, x1, +1, axis=1) if x1 + 3 < w_img else None
        top = _edge(img, colour, cols, ym, y0, -1, axis=0) if y0 >= 3 else None
        bottom = _edge(img, colour, cols, ym, y1, +1, axis=0) if y1 + 3 < h_img else None
        cands: list[tuple[float, float, int]] = []  # (Z, weight, robustness rank)
        if left is not None and right is not None and right - left > 0.5:
            cands.append((cam.fx * VEHICLE_W_M / (right - left), (right - left) ** 2, 1))
        if top is not None and bottom is not None and bottom - top > 0.5:
            cands.append((cam.fy * VEHICLE_H_M / (bottom - top), (bottom - top) ** 2, 2))
        if bottom is not None and bottom - self._horizon_v > 0.5:
            z = ground_x(cam, bottom, CLEARANCE_M)
            if z is not None:
                cands.append((z, (bottom - self._horizon_v) ** 2, 3))
        if top is not None and self._horizon_v - top > 0.5:
            z = ground_x(cam, top, CLEARANCE_M + VEHICLE_H_M)
            if z is not None:
                cands.append((z, (self._horizon_v - top) ** 2, 0))
        dist = _combine(cands)
        if y1 + 1 >= h_img:  # cut by the bottom border: no farther than the lowest road row
            bound = ground_x(cam, float(h_img), CLEARANCE_M)
            if bound is not None:
                dist = bound if dist is None else min(dist, bound)
        if dist is None or dist > self.max_range_m:
            return None
        w_expect = cam.fx * VEHICLE_W_M / dist
        if left is not None and right is not None:
            u_c = (left + right) / 2
        elif left is not None:
            u_c = left + w_expect / 2
        elif right is not None:
            u_c = right - w_expect / 2
        else:
            u_c = (x0 + x1 + 1) / 2
        lateral = -(u_c - cam.cx) * dist / cam.fx
        box_px = (float(x0 if left is None else left), float(y0 if top is None else top),
                  float(x1 + 1 if right is None else right), float(y1 + 1 if bottom is None else bottom))
        spread = max(c[0] for c in cands) / min(c[0] for c in cands) - 1.0 if cands else 0.5
        conf = fill * min(1.0, (y1 - y0 + 1) / 8) * max(0.2, 1.0 - spread)
        return DetectedObject(ObjectClass.VEHICLE, float(min(1.0, max(0.05, conf))),
                              box_px, (float(dist), float(lateral), 0.0))

    # -- decision and control ------------------------------------------------

    def stop_distance_m(self, speed_mps: float) -> float:
        """Distance (m) within which an obstacle means STOP at ``speed_mps``."""
        return speed_mps * speed_mps / (2 * self.comfort_decel_mps2) + self.stop_margin_m

    def decide(self, distance_m: float | None, speed_mps: float) -> DrivingState:
        """Driving state for the nearest in-path obstacle at ``distance_m`` (None:
        the path is clear) at ego speed ``speed_mps``."""
        if distance_m is None:
            return DrivingState.SAFE
        v = max(0.0, speed_mps)
        stop = self.stop_distance_m(v)
        if distance_m <= stop:
            return DrivingState.STOP
        if distance_m <= stop + self.slow_headway_s * v or (v > 1e-3 and distance_m / v <= self.slow_ttc_s):
            return DrivingState.SLOW
        return DrivingState.SAFE

    def longitudinal(self, state: DrivingState, distance_m: float | None,
                     speed_mps: float) -> tuple[float, float]:
        """(throttle, brake), each in [0, 1], for ``state`` with the nearest in-path
        obstacle at ``distance_m`` and ego speed ``speed_mps``."""
        v = max(0.0, speed_mps)
        if state == DrivingState.SAFE or distance_m is None:
            return _clip01(0.3 * (self.cruise_speed_mps - v)), 0.0
        room = distance_m - self.standoff_m
        if state == DrivingState.SLOW:
            v_t = min(self.cruise_speed_mps, 0.6 * math.sqrt(2 * self.comfort_decel_mps2 * max(0.0, room)))
            return (_clip01(0.3 * (v_t - v)), 0.0) if v < v_t else (0.0, _clip01(0.25 * (v - v_t)))
        if room < 1.0:  # under ~4 m: full brake, and hold it
            return 0.0, 1.0
        a_needed = v * v / (2 * room)
        return 0.0, min(1.0, max(self.min_brake, a_needed / MAX_BRAKE_MPS2))

    def _steering(self, hsv: np.ndarray, v: float) -> float:
        lane = self._lane(hsv)
        if lane is None:
            self._steer_rad *= 0.8
            return self._steer_rad
        c0, c1 = lane
        lo, hi = self.lane_window_m
        x_la = min(hi, max(lo + 2.0, self.lookahead_s * v))
        x_t, y_t = x_la + CAMERA_TO_CENTRE_M, c0 + c1 * x_la
        steer = math.atan2(2 * WHEELBASE_M * y_t, x_t * x_t + y_t * y_t)
        self._steer_rad = max(-MAX_STEER_RAD, min(MAX_STEER_RAD, steer))
        return self._steer_rad

    def _lane(self, hsv: np.ndarray) -> tuple[float, float] | None:
        """Lane centre line ``Y = c0 + c1 X`` (camera frame, m), or None."""
        r0, r1 = self._lane_rows
        if r1 <= r0:
            return None
        band = cv2.inRange(hsv[r0:r1], (0, 0, 166), (180, 64, 255))
        ys, xs = np.nonzero(band)
        if ys.size < 10:
            return None
        rows = ys + r0
        xf = self._row_x[rows]
        yl = -self._row_t[rows] * self._col_a[xs]
        side_max = self.lane_width_m / 2 + 1.5
        fits = []
        for sel, shift in (((yl > 0) & (yl < side_max), -self.lane_width_m / 2),
                           ((yl < 0) & (yl > -side_max), self.lane_width_m / 2)):
            fit = _line_fit(xf[sel], yl[sel])
            fits.append(None if fit is None else (fit[0] + shift, fit[1], fit[2]))
        left, right = fits
        if left is not None and right is not None:
            width = (left[0] - right[0]) + self.lane_width_m
            if 2.5 <= width <= 5.0:
                n = left[2] + right[2]
                return (left[0] + right[0]) / 2, (left[1] * left[2] + right[1] * right[2]) / n
            left, right = (left, None) if left[2] > right[2] else (None, right)
        best = left if left is not None else right
        return None if best is None else (best[0], best[1])


def _decode(frame: Frame) -> tuple[np.ndarray, bool]:
    """(HxWx3 uint8 image, True when in BGR order)."""
    shape = (frame.height, frame.width, 3)
    if frame.encoding == ImageEncoding.JPEG:
        img = cv2.imdecode(np.frombuffer(frame.data, np.uint8), cv2.IMREAD_COLOR)
        if img is None or img.shape != shape:
            got = "nothing" if img is None else f"{img.shape}"
            raise ValueError(f"frame {frame.frame_id}: JPEG decodes to {got}, expected {shape}")
        return img, True
    if len(frame.data) != frame.height * frame.width * 3:
        raise ValueError(f"frame {frame.frame_id}: {len(frame.data)} bytes of raw pixels, expected "
                         f"{frame.height} x {frame.width} x 3 = {frame.height * frame.width * 3}")
    img = np.frombuffer(frame.data, np.uint8).reshape(shape)
    return img, frame.encoding == ImageEncoding.BGR8


def _edge(img: np.ndarray, colour: np.ndarray, lines: np.ndarray, mid: int, at: int, step: int, *,
          axis: int) -> float | None:
    """Sub-pixel position (continuous coordinate) of a box edge along ``axis`` (1:
    columns, 0: rows): ``at`` is the last car pixel, ``mid`` a pixel boundary inside
    the box, ``step`` the outward direction.

    Every pixel from ``mid`` out to ``at + 2 step`` is unmixed between ``colour`` and
    the background 3 px past ``at``; the coverages sum to the car's extent past
    ``mid`` (a blur or JPEG's chroma smear moves coverage between pixels but keeps
    the sum, so they are not clipped to [0, 1]). Median over ``lines``; None when
    the car does not contrast with the background."""
    idx = np.arange(mid, at + 3) if step > 0 else np.arange(mid - 1, at - 3, -1)
    idx = np.append(idx, at + 3 * step)
    px = (img[lines][:, idx] if axis == 1 else img[idx][:, lines].transpose(1, 0, 2)).astype(np.float32)
    bg = px[:, -1]
    d = colour - bg
    den = (d * d).sum(-1)
    ok = den > 900.0  # 30 grey levels of contrast
    if not ok.any():
        return None
    cover = np.clip(((px[:, :-1] - bg[:, None]) * d[:, None]).sum(-1) / np.maximum(den, 1.0)[:, None], -1, 2)
    reach = float(np.median(cover[ok].sum(-1)))
    return mid + reach if step > 0 else mid - reach


def _combine(cands: list[tuple[float, float, int]]) -> float | None:
    """Inverse-depth weighted mean of (Z, weight, rank) after outlier rejection."""
    if not cands:
        return None
    if len(cands) >= 3:
        med = float(np.median([c[0] for c in cands]))
        cands = [c for c in cands if abs(c[0] - med) <= 0.2 * med] or cands
    elif len(cands) == 2 and abs(cands[0][0] / cands[1][0] - 1.0) > 0.2:
        cands = [max(cands, key=lambda c: c[2])]
    inv = sum(w / z for z, w, _ in cands) / sum(w for _, w, _ in cands)
    return 1.0 / inv


def _line_fit(x: np.ndarray, y: np.ndarray) -> tuple[float, float, int] | None:
    """Least-squares ``y = c0 + c1 x`` with one 0.35 m outlier pass: (c0, c1, n) or
    None when under 12 points or spanning under 1.5 m."""
    for _ in range(2):
        if x.size < 12 or float(x.max() - x.min()) < 1.5:
            return None
        A = np.stack([np.ones_like(x), x], axis=1)
        (c0, c1), *_ = np.linalg.lstsq(A, y, rcond=None)
        keep = np.abs(y - (c0 + c1 * x)) < 0.35
        x, y = x[keep], y[keep]
    if x.size < 12:
        return None
    return float(c0), float(c1), int(x.size)


def _clip01(x: float) -> float:
    return 0.0 if x < 0 else 1.0 if x > 1 else x


def main(argv: Sequence[str] | None = None, *, prog: str = "python -m hil.targets.cv_baseline") -> int:
    """Serve the baseline through the target SDK; 2 when the transport is unusable
    (for example when started by hand rather than by the harness)."""
    from hil.adapters.sdk import TargetArgumentParser, add_transport_args, run_target, serve, transport_options

    p = TargetArgumentParser(prog=prog, description="A classical OpenCV driving AI served over the target SDK.")
    p.add_argument("--cruise-speed", type=float, default=10.0, help="speed to hold when the lane is clear (m/s)")
    p.add_argument("--name", default="cv-baseline", help="target name reported in HELLO")
    add_transport_args(p)
    a = p.parse_args(argv)

    def serve_it() -> object:
        # One OpenCV thread: a host runs a target per vehicle, so the targets are the
        # parallelism; a pool per target (a thread per core) costs CPU and, with many
        # targets, throughput (bench/README, "OpenCV threads").
        cv2.setNumThreads(1)
        model = CvBaseline(cruise_speed_mps=a.cruise_speed)
        model.warm_up()
        return serve(model.infer, target_name=a.name, transport=a.transport, **transport_options(a))

    return run_target(prog, serve_it)


if __name__ == "__main__":
    raise SystemExit(main())
