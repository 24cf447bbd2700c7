"""How ROS 2 messages map onto the harness's frames and estimates (both directions),
and which frame an answer belongs to. Pure computation: no DDS here.

Stamps. Every message of one frame carries the same ``header.stamp``: the frame's
sim time (clock ``sim``) or its capture time t0 on this host's CLOCK_REALTIME (clock
``system``). ``header.frame_id`` is the camera's optical frame (a TF frame name, as
ROS 2 stacks expect). An answer whose stamp equals a frame's answers that frame
(a detector copies its image's header, as ROS 2 perception does). An answer with
any other stamp (a controller stamping with its own ``now()``) answers the newest
frame sent before it arrived that has no such answer yet; those are counted
(``matched_by_arrival``) and give no clock sample.

Control (``ackermann_msgs/AckermannDriveStamped``, drive ``d``, ego speed ``v`` sent
with the frame): the acceleration ``a = d.acceleration`` when it is not 0, else
``speed_gain_per_s * (d.speed - v)`` (a speed-only command); ``a > 0`` is throttle
``a / max_accel_mps2``, ``a < 0`` brake ``-a / max_decel_mps2`` (both clipped to
[0, 1]: the simulated car's actuator limits, 3 and 8 m/s^2); steering is
``d.steering_angle`` (rad, positive left). The driving state, which no standard
message carries: STOP when ``d.speed <= stop_speed_mps`` and ``a <= 0`` (the stack
commands standstill), SLOW when ``a < 0``, else SAFE.

Detections (``vision_msgs/Detection2DArray``): each detection's box is
``bbox.center.position`` +- ``bbox.size / 2`` (pixels, ROS 2's: a pixel's centre on
the integer, so +0.5 to the harness's edges); its class and confidence are
the best-scoring hypothesis's ``class_id`` (a harness class name, its numeric code,
or a common alias: car, truck, bus -> vehicle; person -> pedestrian; anything else
UNKNOWN) and ``score``; its position is that hypothesis's ``pose.pose.position``,
read in the harness's camera-ground frame (x forward, y left, z up, on the road under
the camera; zeros when the detector gives no hypothesis).
"""

from __future__ import annotations

import math
from collections import OrderedDict
from dataclasses import dataclass, field

from hil.adapters.ros2.msgs import (AckermannDrive, BoundingBox2D, CameraInfo, Detection2D, Detection2DArray, Header,
                                    ObjectHypothesis, ObjectHypothesisWithPose, Point, Point2D, Pose, Pose2D,
                                    PoseWithCovariance, Quaternion, Time)
from hil.adapters.ros2.options import DriveLimits
from hil.adapters.wire.messages import Control, DetectedObject, DrivingState, Estimate, ObjectClass

PIXEL_CENTRE = 0.5  # a pixel's centre: harness coordinates (edges on integers) minus ROS 2's
ALIASES = {"car": ObjectClass.VEHICLE, "truck": ObjectClass.VEHICLE, "bus": ObjectClass.VEHICLE,
           "motorcycle": ObjectClass.VEHICLE, "person": ObjectClass.PEDESTRIAN}


class DriveMapping(DriveLimits):
    """The control mapping (module docstring) with the constants of ``DriveLimits``
    (``hil.adapters.ros2.options``, where their defaults live)."""

    def control_of(self, d: AckermannDrive, ego_speed_mps: float) -> tuple[Control, DrivingState]:
        """The harness's control and driving state for drive command ``d``."""
        a = float(d.acceleration) if d.acceleration != 0 else self.speed_gain_per_s * (float(d.speed) - ego_speed_mps)
        throttle = _clip01(a / self.max_accel_mps2) if a > 0 else 0.0
        brake = _clip01(-a / self.max_decel_mps2) if a < 0 else 0.0
        steer = float(d.steering_angle) if math.isfinite(d.steering_angle) else 0.0
        if d.speed <= self.stop_speed_mps and a <= 0:
            state = DrivingState.STOP
        elif a < 0:
            state = DrivingState.SLOW
        else:
            state = DrivingState.SAFE
        return Control(steer, throttle, brake), state

    def drive_of(self, c: Control, state: DrivingState, ego_speed_mps: float) -> AckermannDrive:
        """The drive command that maps back onto ``c`` (and onto ``state`` except SLOW
        while speeding up, which reads as SAFE): acceleration from throttle and brake,
        speed 0 to stop, else the present speed (held)."""
        a = self.max_accel_mps2 * c.throttle - self.max_decel_mps2 * c.brake
        speed = 0.0 if state == DrivingState.STOP else max(0.0, ego_speed_mps)
        return AckermannDrive(steering_angle=c.steering_rad, speed=speed, acceleration=a)


OPTICAL_Q = Quaternion(-0.5, 0.5, -0.5, 0.5)  # camera_link (x fwd, z up) -> optical frame (z fwd, y down)


def mount_quaternion(pitch_rad: float, yaw_rad: float = 0.0) -> Quaternion:
    """The camera mount's rotation: yaw (about z, positive left) then pitch (about
    y, positive looks down)."""
    cy, sy, cp, sp = math.cos(yaw_rad / 2), math.sin(yaw_rad / 2), math.cos(pitch_rad / 2), math.sin(pitch_rad / 2)
    return Quaternion(-sy * sp, cy * sp, sy * cp, cy * cp)


def camera_info_of(header: Header, width: int, height: int, fx: float, fy: float, cx: float, cy: float) -> CameraInfo:
    """``sensor_msgs/CameraInfo`` of an undistorted pinhole camera whose principal
    point ``(cx, cy)`` is in the harness's pixel coordinates (ROS 2's are 0.5 px less)."""
    cx, cy = cx - PIXEL_CENTRE, cy - PIXEL_CENTRE
    return CameraInfo(header, height, width, "plumb_bob", [0.0] * 5, [fx, 0.0, cx, 0.0, fy, cy, 0.0, 0.0, 1.0],
                      [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
                      [fx, 0.0, cx, 0.0, 0.0, fy, cy, 0.0, 0.0, 0.0, 1.0, 0.0])


def _clip01(x: float) -> float:
    return 0.0 if not x > 0 else 1.0 if x > 1 else x


def stamp_of(t_ns: int) -> Time:
    """``builtin_interfaces/Time`` of ``t_ns`` (>= 0)."""
    sec, nanosec = divmod(t_ns, 1_000_000_000)
    return Time(sec, nanosec)


def ns_of(t: Time) -> int:
    return int(t.sec) * 1_000_000_000 + int(t.nanosec)


def class_of(class_id: str) -> ObjectClass:
    """The harness class a detector's ``class_id`` names (module docstring)."""
    key = class_id.strip().lower()
    if key.isdigit():
        return ObjectClass.of(int(key))
    try:
        return ObjectClass[key.upper()]
    except KeyError:
        return ALIASES.get(key, ObjectClass.UNKNOWN)


def objects_of(arr: Detection2DArray) -> tuple[DetectedObject, ...]:
    """The detections as the harness's objects (module docstring)."""
    out = []
    for det in arr.detections:
        c, b = det.bbox.center.position, det.bbox
        x, y = c.x + PIXEL_CENTRE, c.y + PIXEL_CENTRE
        box = (float(x - b.size_x / 2), float(y - b.size_y / 2), float(x + b.size_x / 2), float(y + b.size_y / 2))
        best = max(det.results, key=lambda h: h.hypothesis.score, default=None)
        if best is None:
            out.append(DetectedObject(ObjectClass.UNKNOWN, 0.0, box, (0.0, 0.0, 0.0)))
            continue
        p = best.pose.pose.position
        score = float(best.hypothesis.score)
        out.append(DetectedObject(class_of(best.hypothesis.class_id), _clip01(score) if math.isfinite(score) else 0.0,
                                  box, (float(p.x), float(p.y), float(p.z))))
    return tuple(out)


def detections_of(objects: tuple[DetectedObject, ...], header: Header) -> Detection2DArray:
    """The harness's objects as a ``Detection2DArray`` under ``header`` (the inverse of
    :func:`objects_of`, class names as ``class_id``)."""
    dets = []
    for i, o in enumerate(objects):
        x0, y0, x1, y1 = o.box_px
        centre = Point2D((x0 + x1) / 2 - PIXEL_CENTRE, (y0 + y1) / 2 - PIXEL_CENTRE)
        bbox = BoundingBox2D(Pose2D(centre, 0.0), x1 - x0, y1 - y0)
        hyp = ObjectHypothesisWithPose(ObjectHypothesis(ObjectClass.of(int(o.cls)).label, float(o.confidence)),
                                       PoseWithCovariance(Pose(Point(*map(float, o.position_m)))))
        dets.append(Detection2D(header, [hyp], bbox, str(i)))
    return Detection2DArray(header, dets)


DETECTIONS, CONTROL = "detections", "control"  # the parts of an answer


@dataclass
class Sent:
    """A frame sent: its id, header stamp (ns on the stamp clock), t_tx (harness ns)
    and the ego speed sent with it (m/s); then its answer as it comes: the control
    and state, the objects, and per part kind (t_rx harness ns, DDS source timestamp ns)."""

    frame_id: int
    stamp_ns: int
    t_tx_ns: int
    ego_speed_mps: float
    control: tuple[Control, DrivingState] | None = None
    objects: tuple[DetectedObject, ...] = ()
    parts: dict[str, tuple[int, int]] = field(default_factory=dict)


class AnswerBook:
    """The frames sent to one node and the answers that came back (module docstring:
    which answer belongs to which frame). ``kinds``: the parts a complete answer has
    (CONTROL, and DETECTIONS when the node publishes detections); at most
    ``capacity`` frames are remembered (older ones have timed out in the harness).
    Not thread-safe: one sender thread calls ``sent``, one reader thread the rest,
    under the caller's lock."""

    def __init__(self, *, vehicle_id: int, kinds: tuple[str, ...], capacity: int = 256) -> None:
        self.vehicle_id = vehicle_id
        self.kinds = kinds
        self.capacity = capacity
        self._by_stamp: OrderedDict[int, Sent] = OrderedDict()
        self.matched_by_arrival = 0
        self.unmatched = 0

    def sent(self, s: Sent) -> None:
        self._by_stamp[s.stamp_ns] = s
        while len(self._by_stamp) > self.capacity:
            self._by_stamp.popitem(last=False)

    def match(self, kind: str, stamp_ns: int, t_rx_ns: int) -> tuple[Sent | None, bool]:
        """The frame an answer part of ``kind`` stamped ``stamp_ns`` belongs to, and
        whether the stamp matched exactly; (None, False) when none (counted)."""
        s = self._by_stamp.get(stamp_ns)
        if s is not None and kind not in s.parts:
            return s, True
        for cand in reversed(self._by_stamp.values()):
            if cand.t_tx_ns <= t_rx_ns and kind not in cand.parts:
                self.matched_by_arrival += 1
                return cand, False
        self.unmatched += 1
        return None, False

    def add(self, s: Sent, kind: str, t_rx_ns: int, source_ns: int) -> tuple[Estimate, int] | None:
        """Record that part ``kind`` of ``s`` came (its value already set on ``s``); the
        estimate and its receipt time t0' (harness ns, the last part's) once every kind
        has come (the frame is then forgotten)."""
        s.parts[kind] = (t_rx_ns, source_ns)
        if s.control is None or any(k not in s.parts for k in self.kinds):
            return None
        self._by_stamp.pop(s.stamp_ns, None)
        control, state = s.control
        t_rx, source = max(s.parts.values())
        return Estimate(self.vehicle_id, s.frame_id, state, control, s.objects, None, None, None, source), t_rx


__all__ = ["ALIASES", "CONTROL", "DETECTIONS", "OPTICAL_Q", "PIXEL_CENTRE", "AnswerBook", "DriveMapping", "Sent",
           "camera_info_of", "class_of", "detections_of", "mount_quaternion", "ns_of", "objects_of", "stamp_of"]
