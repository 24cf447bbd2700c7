"""Ground truth as Foxglove 3D messages: every entity as a cube in ``/scene``
(``foxglove.SceneUpdate``, frame ``world``) and every vehicle's pose as a
``foxglove.FrameTransform`` (``world`` → ``<vehicle>``) in ``/tf``, so the 3D panel
shows the world and can follow any vehicle."""

from __future__ import annotations

import math
from typing import Any

from harness import foxglove_schemas as fx
from scenarios.ground_truth import GroundTruth

# Colours by class (RGBA 0..1); ego vehicles blue as in the render.
_COLOURS = {"vehicle": (0.8, 0.15, 0.1, 0.9), "pedestrian": (1.0, 0.6, 0.0, 0.9), "obstacle": (0.6, 0.6, 0.6, 0.9)}
_EGO = (0.1, 0.25, 0.8, 0.9)


def yaw_quaternion(yaw: float) -> tuple[float, float, float, float]:
    return (0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2))


def register(rec: Any) -> None:
    rec.register_json_channel("/scene", fx.SCENE_UPDATE, fx.scene_update_schema())
    rec.register_json_channel("/tf", fx.FRAME_TRANSFORM, fx.frame_transform_schema())


def write(rec: Any, gt: GroundTruth, *, egos: set[str], t_ns: int) -> None:
    """One SceneUpdate of every entity and one FrameTransform per vehicle."""
    entities = []
    for e in gt.entities:
        rgba = _EGO if e.name in egos else _COLOURS.get(e.cls, _COLOURS["obstacle"])
        q = yaw_quaternion(e.heading_rad)
        length, width, height = e.size_m
        cube = {"pose": fx.pose((e.x_m, e.y_m, 0.1 + height / 2), q),
                "size": {"x": length, "y": width, "z": height},
                "color": dict(zip("rgba", rgba))}
        label = {"pose": fx.pose((e.x_m, e.y_m, 0.3 + height), q), "billboard": True, "font_size": 14.0,
                 "scale_invariant": True, "color": {"r": 1.0, "g": 1.0, "b": 1.0, "a": 1.0}, "text": e.name}
        entities.append(fx.scene_entity(entity_id=e.name, frame_id="world", timestamp_ns=t_ns, cubes=[cube],
                                        texts=[label]))
        if e.cls == "vehicle":
            rec.write_json("/tf", {"timestamp": fx.ns_to_foxglove_time(t_ns), "parent_frame_id": "world",
                                   "child_frame_id": e.name,
                                   "translation": {"x": e.x_m, "y": e.y_m, "z": 0.0},
                                   "rotation": dict(zip("xyzw", q))}, log_time_ns=t_ns, publish_time_ns=t_ns)
    rec.write_json("/scene", {"deletions": [], "entities": entities}, log_time_ns=t_ns, publish_time_ns=t_ns)
