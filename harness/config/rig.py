"""``camera.rig``: the cameras on each ego vehicle (issue 31).

``rig`` is a preset's name or a list of cameras::

    camera:
      rig: surround6          # front (default: the one camera of camera:), front3, surround6
    camera:
      rig:
        - {name: front, forward_m: 2.0, height_m: 1.5}
        - {name: back, forward_m: -2.0, height_m: 1.5, yaw_deg: 180, fovy_deg: 90, offset_ms: 10}

Each camera: its mount from the vehicle centre (``forward_m``, ``lateral_m`` left,
``height_m`` above the road), its orientation (``yaw_deg`` positive looks left,
``pitch_deg`` positive looks down, ``roll_deg`` about the optical axis), its vertical
field of view and image size (unset: the ``camera:`` section's), and ``offset_ms``:
when it triggers after camera 0 within a camera period (0: one trigger line, every
camera at the same physics step). A pinhole with square pixels and the principal
point at the image centre: ``fovy_deg`` and the size are its intrinsics.
"""

from __future__ import annotations

from pydantic import BaseModel, Field

from hil.harness.config.types import MODEL_CONFIG, Float, Int

MAX_RIG_CAMERAS = 32  # a frame set's limit on the wire (PROTOCOL.md 4.2)
PRESETS = ("front", "front3", "surround6")


class RigCamera(BaseModel):
    """One camera of a rig (units in the names; unset size and field of view: the
    ``camera:`` section's)."""

    model_config = MODEL_CONFIG

    name: str = Field(pattern=r"^[A-Za-z0-9_-]{1,32}$")
    forward_m: Float = Field(2.3, ge=-5, le=5)
    lateral_m: Float = Field(0.0, ge=-3, le=3)
    height_m: Float = Field(1.3, ge=0.2, le=5)
    yaw_deg: Float = Field(0.0, ge=-180, le=180)
    pitch_deg: Float = Field(0.0, ge=-45, le=45)
    roll_deg: Float = Field(0.0, ge=-180, le=180)
    fovy_deg: Float | None = Field(None, ge=10, le=170)
    width: Int | None = Field(None, ge=16, le=4096)
    height: Int | None = Field(None, ge=16, le=4096)
    offset_ms: Float = Field(0.0, ge=0, le=10_000)


def preset(name: str, *, forward_m: float, lateral_m: float, height_m: float, pitch_deg: float,
           yaw_deg: float, fovy_deg: float) -> tuple[RigCamera, ...]:
    """The cameras of preset ``name``; ``front`` is the ``camera:`` section's own
    camera (its mount), the others are mounted around the roof at ``height_m``.

    ``surround6`` is nuScenes' layout: front, front-left (55 deg), front-right,
    back (180 deg, wider), back-left (110 deg), back-right; ``front3``: front and
    60 deg to each side.
    """
    if name == "front":
        return (RigCamera(name="front", forward_m=forward_m, lateral_m=lateral_m, height_m=height_m,
                          pitch_deg=pitch_deg, yaw_deg=yaw_deg),)
    h, p = height_m, pitch_deg
    if name == "front3":
        return (RigCamera(name="front", forward_m=1.8, height_m=h, pitch_deg=p),
                RigCamera(name="front_left", forward_m=1.6, lateral_m=0.6, height_m=h, pitch_deg=p, yaw_deg=60),
                RigCamera(name="front_right", forward_m=1.6, lateral_m=-0.6, height_m=h, pitch_deg=p, yaw_deg=-60))
    if name == "surround6":
        wide = min(170.0, fovy_deg * 1.5)
        return (RigCamera(name="front", forward_m=1.8, height_m=h, pitch_deg=p),
                RigCamera(name="front_left", forward_m=1.5, lateral_m=0.7, height_m=h, pitch_deg=p, yaw_deg=55),
                RigCamera(name="front_right", forward_m=1.5, lateral_m=-0.7, height_m=h, pitch_deg=p, yaw_deg=-55),
                RigCamera(name="back", forward_m=-2.0, height_m=h, pitch_deg=p, yaw_deg=180, fovy_deg=wide),
                RigCamera(name="back_left", forward_m=-1.0, lateral_m=0.8, height_m=h, pitch_deg=p, yaw_deg=110),
                RigCamera(name="back_right", forward_m=-1.0, lateral_m=-0.8, height_m=h, pitch_deg=p,
                          yaw_deg=-110))
    raise ValueError(f"unknown rig preset {name!r}; one of {', '.join(PRESETS)}")


__all__ = ["MAX_RIG_CAMERAS", "PRESETS", "RigCamera", "preset"]
