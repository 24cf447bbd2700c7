"""Decision and control of the CNN target, on top of the OpenCV baseline's rules.

The thresholds of SAFE/SLOW/STOP and the longitudinal control are the baseline's
(``CvBaseline.decide`` and ``CvBaseline.longitudinal``, documented in
``targets/cv_baseline.py``): with v the ego speed and d the distance to the
nearest object in the path, ``stop_d = v^2 / (2 * 4 m/s^2) + 6 m``; STOP if
d <= stop_d, SLOW if d <= stop_d + 2 s * v or d / v <= 4 s, else SAFE. Objects are
assumed to stand still (conservative).

What this module adds:

* The path is the arc the present steering command drives: an object at (x, y) is
  in it when ``|y - path_y(x)|`` < ego half width 0.9 m + the class's half width
  prior + ``path_margin_m`` 0.1 m (pedestrians another ``pedestrian_margin_m``
  0.5 m: they may step in), with ``path_y(x) = k ((x + 2.3)^2 - 2.3^2) / 2``,
  ``k = tan(steering) / 2.7 m`` (the yaw pivot is 2.3 m behind the camera). On a
  straight road that is |y| < 1.9 m for a car (the baseline uses 1.6 m).
* Low confidence (``Policy``), counted by the target:
  - a detection with confidence in [``det_uncertain`` 0.15, ``det_confidence`` 0.35)
    is *uncertain*: not reported. When one lies in the path nearer than any
    confident object, the OpenCV baseline is run on the frame and its in-path
    vehicles join the confident ones; if the uncertain object would still matter
    (the rules say SLOW or STOP at its distance), the state is at least SLOW,
    tracking the baseline's SLOW speed for that distance, never STOP on an
    uncertain detection alone;
  - a steering output whose own error estimate exceeds ``steer_error_max_rad`` is
    replaced by the baseline's lane keeping for that frame, and the car slows down:
    the state is at least SLOW and the speed is held at or under
    ``low_confidence_speed_mps`` 4 m/s (throttle 0.3 / (m/s) below it, brake 0.25 /
    (m/s) above it, the baseline's SLOW gains).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from hil.adapters.wire.messages import DetectedObject, DrivingState, ObjectClass
from hil.targets.cnn.geometry import PRIORS
from hil.targets.cv_baseline import CAMERA_TO_CENTRE_M, WHEELBASE_M, CvBaseline


@dataclass(frozen=True)
class Policy:
    """Confidence thresholds and path margins (see the module docstring)."""

    det_confidence: float = 0.35
    det_uncertain: float = 0.15
    steer_error_max_rad: float = 0.02
    low_confidence_speed_mps: float = 4.0
    ego_half_width_m: float = 0.9
    path_margin_m: float = 0.1
    pedestrian_margin_m: float = 0.5

    def __post_init__(self) -> None:
        if not 0.0 < self.det_uncertain <= self.det_confidence <= 1.0:
            raise ValueError(f"need 0 < det_uncertain <= det_confidence <= 1; got {self.det_uncertain} "
                             f"and {self.det_confidence}")
        if self.steer_error_max_rad <= 0 or self.low_confidence_speed_mps < 0:
            raise ValueError("steer_error_max_rad must be > 0 and low_confidence_speed_mps >= 0")


@dataclass(frozen=True)
class Decision:
    """The state, (throttle, brake) and the distance (m) it acted on."""

    state: DrivingState
    throttle: float
    brake: float
    distance_m: float | None


def path_y(x_m: float, steering_rad: float) -> float:
    """Lateral offset (m, left) of the driven arc ``x_m`` ahead of the camera."""
    k = math.tan(steering_rad) / WHEELBASE_M
    return k * ((x_m + CAMERA_TO_CENTRE_M) ** 2 - CAMERA_TO_CENTRE_M ** 2) / 2


def in_path(obj: DetectedObject, steering_rad: float, policy: Policy) -> bool:
    x, y, _ = obj.position_m
    prior = PRIORS.get(obj.cls, PRIORS[ObjectClass.VEHICLE])
    half = policy.ego_half_width_m + prior.width_m / 2 + policy.path_margin_m
    if obj.cls == ObjectClass.PEDESTRIAN:
        half += policy.pedestrian_margin_m
    return x > 0 and abs(y - path_y(x, steering_rad)) < half


def nearest_in_path(objects: list[DetectedObject] | tuple[DetectedObject, ...], steering_rad: float,
                    policy: Policy) -> float | None:
    """Forward distance (m) of the nearest object in the path, or None."""
    d = [o.position_m[0] for o in objects if in_path(o, steering_rad, policy)]
    return min(d) if d else None


def track_speed(speed_mps: float, target_mps: float) -> tuple[float, float]:
    """(throttle, brake) towards ``target_mps`` with the baseline's SLOW gains."""
    if speed_mps < target_mps:
        return min(1.0, 0.3 * (target_mps - speed_mps)), 0.0
    return 0.0, min(1.0, 0.25 * (speed_mps - target_mps))


def decide(rules: CvBaseline, policy: Policy, *, distance_m: float | None, uncertain_m: float | None,
           speed_mps: float, steering_low_confidence: bool) -> Decision:
    """State and longitudinal control from the nearest confident in-path distance,
    the nearest uncertain in-path distance (None: none) and the ego speed."""
    v = max(0.0, speed_mps)
    state = rules.decide(distance_m, v)
    acted_on = distance_m
    if uncertain_m is not None and (distance_m is None or uncertain_m < distance_m):
        if rules.decide(uncertain_m, v) != DrivingState.SAFE and state != DrivingState.STOP:
            state, acted_on = DrivingState.SLOW, uncertain_m
    throttle, brake = rules.longitudinal(state, acted_on, v)
    if steering_low_confidence:
        if state == DrivingState.SAFE:
            state = DrivingState.SLOW
            throttle, brake = track_speed(v, policy.low_confidence_speed_mps)
        elif state == DrivingState.SLOW and v > policy.low_confidence_speed_mps and throttle > 0:
            throttle, brake = track_speed(v, policy.low_confidence_speed_mps)
    return Decision(state, throttle, brake, acted_on)
