"""Foxglove views of a camera rig (issue 31): each camera's image, calibration and mount.

Camera 0 keeps the single camera's topics, ``/<V>/camera``, ``/<V>/camera_info``,
``/<V>/truth`` and ``/<V>/annotations``; every other camera of a rig appends its name
to each: ``/<V>/camera/<name>``, ``/<V>/camera_info/<name>``, ``/<V>/truth/<name>``
(its true visible boxes) and ``/<V>/annotations/<name>``, so an Image panel pairs
them the same way for every camera.

On ``/tf`` (vehicle axes: +x forward, +y left, +z up; optical axes: +x right, +y
down, +z forward): camera 0 as for one camera, ``<V>`` → ``<V>/camera_ground`` (on
the road under the camera: the AI's object frame; a single camera's turned by its
yaw, a rig's of two or more cameras in the vehicle's axes, PROTOCOL.md 4.3) →
``<V>/camera`` (its optical frame); every other camera ``<V>`` →
``<V>/camera/<name>`` (its optical frame), the mount and orientation MuJoCo renders
it with (``hil.scenarios.world``).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

Quaternion = tuple[float, float, float, float]
_IDENTITY = {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0}


def camera_topic(vehicle: str, camera: str | None = None) -> str:
    """The image topic of ``vehicle``'s camera 0 (``camera`` None) or of the rig camera named ``camera``."""
    return f"/{vehicle}/camera" + (f"/{camera}" if camera else "")


def calibration_topic(vehicle: str, camera: str | None = None) -> str:
    """The ``foxglove.CameraCalibration`` topic beside :func:`camera_topic`."""
    return f"/{vehicle}/camera_info" + (f"/{camera}" if camera else "")


def truth_topic(vehicle: str, camera: str | None = None) -> str:
    """The ``hil.CameraTruth`` topic (true visible boxes) beside :func:`camera_topic`."""
    return f"/{vehicle}/truth" + (f"/{camera}" if camera else "")


def annotations_topic(vehicle: str, camera: str | None = None) -> str:
    """The ``foxglove.ImageAnnotations`` topic (truth and AI boxes) beside :func:`camera_topic`."""
    return f"/{vehicle}/annotations" + (f"/{camera}" if camera else "")


def calibration(width: int, height: int, fovy_deg: float) -> dict[str, Any]:
    """A pinhole's calibration (square pixels, principal point at the centre, no distortion)."""
    f = (height / 2) / math.tan(math.radians(fovy_deg) / 2)
    cx, cy = width / 2, height / 2
    return {"width": width, "height": height, "distortion_model": "plumb_bob", "D": [0.0] * 5,
            "K": [f, 0.0, cx, 0.0, f, cy, 0.0, 0.0, 1.0],
            "R": [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
            "P": [f, 0.0, cx, 0.0, 0.0, f, cy, 0.0, 0.0, 0.0, 1.0, 0.0]}


def optical_axes(yaw_rad: float, pitch_rad: float, roll_rad: float = 0.0) -> np.ndarray:
    """The optical axes (columns: right, down, forward) in vehicle axes of a camera
    turned left by ``yaw_rad``, down by ``pitch_rad`` and about its optical axis by
    ``roll_rad``, as ``hil.scenarios.world`` mounts it."""
    s, c = math.sin(pitch_rad), math.cos(pitch_rad)
    sy, cy = math.sin(yaw_rad), math.cos(yaw_rad)
    right = np.array([sy, -cy, 0.0])
    down = -np.array([s * cy, s * sy, c])
    forward = np.array([c * cy, c * sy, -s])
    if roll_rad:
        sr, cr = math.sin(roll_rad), math.cos(roll_rad)
        right, down = cr * right - sr * down, sr * right + cr * down
    return np.column_stack([right, down, forward])


def quaternion(m: np.ndarray) -> Quaternion:
    """The unit quaternion (x, y, z, w) of rotation matrix ``m`` (any angle)."""
    tr = float(m[0, 0] + m[1, 1] + m[2, 2])
    if tr > 0:
        s = 2 * math.sqrt(1 + tr)
        q = ((m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, s / 4)
    elif m[0, 0] >= m[1, 1] and m[0, 0] >= m[2, 2]:
        s = 2 * math.sqrt(1 + m[0, 0] - m[1, 1] - m[2, 2])
        q = (s / 4, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s, (m[2, 1] - m[1, 2]) / s)
    elif m[1, 1] >= m[2, 2]:
        s = 2 * math.sqrt(1 + m[1, 1] - m[0, 0] - m[2, 2])
        q = ((m[0, 1] + m[1, 0]) / s, s / 4, (m[1, 2] + m[2, 1]) / s, (m[0, 2] - m[2, 0]) / s)
    else:
        s = 2 * math.sqrt(1 + m[2, 2] - m[0, 0] - m[1, 1])
        q = ((m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, s / 4, (m[1, 0] - m[0, 1]) / s)
    x, y, z, w = (float(a) for a in q)
    return (x, y, z, w) if w >= 0 else (-x, -y, -z, -w)


@dataclass(frozen=True)
class RigView:
    """One rig camera as Foxglove draws it: its name (``None``: camera 0), calibration
    and mount (m from the vehicle centre; angles in rad); ``vehicle_axes``: camera 0
    of a rig of two or more, whose ground frame keeps the vehicle's axes."""

    name: str | None
    calib: dict[str, Any]
    forward_m: float
    lateral_m: float
    height_m: float
    yaw_rad: float
    pitch_rad: float
    roll_rad: float
    vehicle_axes: bool = False

    def transforms(self, v: str, ts: dict[str, int]) -> list[dict[str, Any]]:
        """The ``/tf`` messages from ``v`` to this camera's optical frame at ``ts``."""
        axes = optical_axes(self.yaw_rad, self.pitch_rad, self.roll_rad)
        if self.name is not None:
            return [_tf(ts, v, f"{v}/camera/{self.name}", (self.forward_m, self.lateral_m, self.height_m),
                        dict(zip("xyzw", quaternion(axes))))]
        yaw = 0.0 if self.vehicle_axes else self.yaw_rad
        cy, sy = math.cos(yaw), math.sin(yaw)
        ground = np.array([[cy, -sy, 0.0], [sy, cy, 0.0], [0.0, 0.0, 1.0]])
        return [_tf(ts, v, f"{v}/camera_ground", (self.forward_m, self.lateral_m, 0.0),
                    dict(zip("xyzw", quaternion(ground))) if yaw else dict(_IDENTITY)),
                _tf(ts, f"{v}/camera_ground", f"{v}/camera", (0.0, 0.0, self.height_m),
                    dict(zip("xyzw", quaternion(ground.T @ axes))))]


def rig_views(camera: Mapping[str, Any]) -> tuple[RigView, ...] | None:
    """Each camera of the run config's ``camera`` section (as JSON) with a rig, camera 0
    first; ``None`` for the one camera of the section itself (``rig`` unset or
    ``front``: drawn as before rigs) or a section that does not validate."""
    rig = camera.get("rig", "front")
    if rig == "front":
        return None
    from hil.harness.config.model import CameraConfig

    try:
        cams = CameraConfig.model_validate(dict(camera)).cameras()
    except ValueError:
        return None
    return tuple(RigView(c.name if k else None, calibration(int(c.width or 0), int(c.height or 0),
                                                            float(c.fovy_deg or 0.0)),
                         c.forward_m, c.lateral_m, c.height_m, math.radians(c.yaw_deg), math.radians(c.pitch_deg),
                         math.radians(c.roll_deg), k == 0 and len(cams) > 1) for k, c in enumerate(cams))


def _tf(ts: dict[str, int], parent: str, child: str, xyz: tuple[float, float, float],
        rotation: dict[str, float]) -> dict[str, Any]:
    return {"timestamp": ts, "parent_frame_id": parent, "child_frame_id": child,
            "translation": dict(zip("xyz", xyz)), "rotation": rotation}


__all__ = ["RigView", "annotations_topic", "calibration", "calibration_topic", "camera_topic", "optical_axes",
           "quaternion", "rig_views", "truth_topic"]
