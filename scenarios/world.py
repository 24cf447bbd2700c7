"""World building: a scenario's roads and entities as an MJCF string.

Coordinates: world x east, y north (left of a car heading +x), z up; metres and
radians. No MuJoCo import here: this module only writes XML, so it is cheap to test.

Entities come in three kinds:

* ego vehicles (``ego=True``): planar joints (x, y, yaw) driven by velocity servos,
  a camera each, an AI target each;
* scripted entities (``script`` set): MuJoCo mocap bodies that the simulation moves
  every physics step along their ``Script`` (NPC cars, pedestrians); egos collide
  with them;
* static entities (neither): parked cars and obstacles, welded to the world.

An entity's id is its index in ``WorldSpec.vehicles``; an ego's vehicle id (on the
wire) is its index among the egos.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from hil.common.classes import ObjectClass
from hil.scenarios.motion import Script
from hil.scenarios.path import Path
from hil.scenarios.road import (
                                GRASS_RGBA,
                                MARKING_RGBA,
                                ROAD_GROUP,
                                ROAD_RGBA,
                                RoadSpec,
                                road_xml,
                                )

ENTITY_GROUP = 0
EGO_RGBA = (0.1, 0.25, 0.8, 1.0)
NPC_RGBA = (0.8, 0.1, 0.1, 1.0)
# Saturated paints a colour-based detector can tell from verge, sky and road (no
# green, cyan or blue hues): red, orange, yellow, magenta, purple, crimson, amber, pink.
PAINTS: tuple[tuple[float, float, float, float], ...] = (
    (0.8, 0.1, 0.1, 1.0), (0.95, 0.45, 0.05, 1.0), (0.9, 0.8, 0.1, 1.0), (0.8, 0.1, 0.7, 1.0),
    (0.5, 0.15, 0.8, 1.0), (0.7, 0.05, 0.3, 1.0), (0.95, 0.65, 0.1, 1.0), (0.95, 0.35, 0.55, 1.0),
)
JACKET_RGBA = (1.0, 0.55, 0.0, 1.0)  # a pedestrian's high-visibility orange
TROUSERS_RGBA = (0.25, 0.25, 0.27, 1.0)
SKIN_RGBA = (0.85, 0.68, 0.55, 1.0)
VEHICLE_SIZE_M = (4.5, 1.8, 1.4)
PEDESTRIAN_SIZE_M = (0.45, 0.55, 1.75)
CLEARANCE_M = 0.1  # vehicle underside above the road


@dataclass(frozen=True)
class VehicleSpec:
    """One entity of the world (a vehicle, a pedestrian or an obstacle).

    Size is length x width x height in metres (its bounding box); ``speed_mps`` the
    initial forward speed of an ego. A scripted entity takes its start pose and
    speed from its script. ``route`` is the path an ego means to follow (its lane):
    ground truth measures distances along it; default: straight ahead.
    ``rgba`` defaults to blue for egos and red for the others.
    """

    name: str
    x_m: float = 0.0
    y_m: float = 0.0
    yaw_rad: float = 0.0
    ego: bool = False
    speed_mps: float = 0.0
    rgba: tuple[float, float, float, float] | None = None
    size_m: tuple[float, float, float] = VEHICLE_SIZE_M
    cls: ObjectClass = ObjectClass.VEHICLE
    script: Script | None = None
    route: Path | None = None

    def __post_init__(self) -> None:
        if self.ego and self.script is not None:
            raise ValueError(f"{self.name}: an ego is driven by its target, it cannot have a script")
        if self.script is not None:
            x, y, h = self.script.pose0()
            object.__setattr__(self, "x_m", x)
            object.__setattr__(self, "y_m", y)
            object.__setattr__(self, "yaw_rad", h)
            object.__setattr__(self, "speed_mps", float(self.script.speed.initial_mps))

    @property
    def paint(self) -> tuple[float, float, float, float]:
        if self.rgba is not None:
            return self.rgba
        return EGO_RGBA if self.ego else NPC_RGBA

    def route_path(self) -> Path:
        """The ego's intended path (straight ahead from its start pose by default)."""
        if self.route is not None:
            return self.route
        return Path.straight(self.x_m, self.y_m, self.yaw_rad, 5000.0)


EntitySpec = VehicleSpec


def pedestrian(name: str, script: Script, *, rgba: tuple[float, float, float, float] = JACKET_RGBA) -> VehicleSpec:
    """A scripted pedestrian: grey trousers, a jacket of ``rgba``, a head."""
    return VehicleSpec(name, rgba=rgba, size_m=PEDESTRIAN_SIZE_M, cls=ObjectClass.PEDESTRIAN, script=script)


@dataclass(frozen=True)
class CameraSpec:
    """Camera mounted on each ego vehicle: image size (px), vertical field of view
    (deg), mount position from the vehicle centre (m: forward, left, up), pitch (rad,
    positive looks down) and yaw (rad, positive looks left)."""

    width: int = 320
    height: int = 240
    fovy_deg: float = 60.0
    mount_forward_m: float = 2.3
    mount_height_m: float = 1.3
    pitch_rad: float = 0.0
    mount_lateral_m: float = 0.0
    yaw_rad: float = 0.0
    # A rig of several cameras (camera 0 first); empty: the one camera above.
    rig: tuple[RigMount, ...] = ()
    # Multisample anti-aliasing of every camera's offscreen render: samples per pixel
    # (MuJoCo's offsamples; 0 off). Segmentation renders are unaffected (ids are not blended).
    antialias: int = 4

    def mounts(self) -> tuple[RigMount, ...]:
        """Every camera of an ego, camera 0 first."""
        if self.rig:
            return self.rig
        return (RigMount("front", self.mount_forward_m, self.mount_lateral_m, self.mount_height_m, self.yaw_rad,
                         self.pitch_rad, 0.0, self.fovy_deg, self.width, self.height),)


@dataclass(frozen=True)
class RigMount:
    """One camera of a rig: mount from the vehicle centre (m: forward, left, up),
    yaw (rad, positive looks left), pitch (rad, positive looks down), roll about the
    optical axis (rad), vertical field of view (deg) and image size (px)."""

    name: str
    forward_m: float
    lateral_m: float
    height_m: float
    yaw_rad: float
    pitch_rad: float
    roll_rad: float
    fovy_deg: float
    width: int
    height: int


@dataclass(frozen=True)
class WorldSpec:
    """Everything a simulation needs. ``realized`` records the values a scenario drew
    from its seed (jittered speeds, timings), for the run's metadata.

    Raises:
        ConfigError: two entities overlap at their start poses, or names repeat.
    """

    roads: tuple[RoadSpec, ...]
    vehicles: tuple[VehicleSpec, ...]
    camera: CameraSpec
    physics_step_s: float = 0.002
    reflections: bool = False
    shadows: bool = False
    realized: dict[str, float] = field(default_factory=dict)

    def __post_init__(self) -> None:
        _check_no_overlap(self.vehicles)

    @property
    def egos(self) -> tuple[VehicleSpec, ...]:
        return tuple(v for v in self.vehicles if v.ego)


def _check_no_overlap(vehicles: tuple[VehicleSpec, ...]) -> None:
    from hil.common.errors import ConfigError

    names = [v.name for v in vehicles]
    dup = {n for n in names if names.count(n) > 1}
    if dup:
        raise ConfigError(f"vehicle names must be unique; repeated: {', '.join(sorted(dup))}")
    for i, a in enumerate(vehicles):
        for b in vehicles[i + 1:]:
            # Bounding circles are conservative for any yaw.
            ra = math.hypot(a.size_m[0], a.size_m[1]) / 2
            rb = math.hypot(b.size_m[0], b.size_m[1]) / 2
            if math.hypot(a.x_m - b.x_m, a.y_m - b.y_m) < ra + rb and _boxes_overlap(a, b):
                raise ConfigError(
                    f"vehicles {a.name!r} and {b.name!r} overlap at their start poses "
                    f"(({a.x_m:.1f}, {a.y_m:.1f}) and ({b.x_m:.1f}, {b.y_m:.1f})); move them apart"
                )


def _boxes_overlap(a: VehicleSpec, b: VehicleSpec) -> bool:
    """Separating-axis test of two yawed rectangles on the road plane."""

    def corners(v: VehicleSpec) -> list[tuple[float, float]]:
        c, s = math.cos(v.yaw_rad), math.sin(v.yaw_rad)
        hl, hw = v.size_m[0] / 2, v.size_m[1] / 2
        return [(v.x_m + c * dx - s * dy, v.y_m + s * dx + c * dy)
                for dx, dy in ((hl, hw), (hl, -hw), (-hl, -hw), (-hl, hw))]

    ca, cb = corners(a), corners(b)
    for v in (a, b):
        for ang in (v.yaw_rad, v.yaw_rad + math.pi / 2):
            ax, ay = math.cos(ang), math.sin(ang)
            pa = [x * ax + y * ay for x, y in ca]
            pb = [x * ax + y * ay for x, y in cb]
            if max(pa) < min(pb) or max(pb) < min(pa):
                return False
    return True


def camera_name(vehicle: str, index: int = 0) -> str:
    """The MJCF name of ``vehicle``'s camera ``index`` (0: the first or only one)."""
    return f"{vehicle}/camera" if index == 0 else f"{vehicle}/camera{index}"


def build_mjcf(world: WorldSpec) -> str:
    """Return the MJCF XML of ``world``."""
    cam = world.camera
    width, height = max(m.width for m in cam.mounts()), max(m.height for m in cam.mounts())
    reflect = "0.2" if world.reflections else "0"
    parts: list[str] = [
        '<mujoco model="hil_world">',
        '  <compiler angle="radian"/>',  # every euler in this file is radians (fovy stays degrees)
        f'  <option timestep="{world.physics_step_s:.9g}" integrator="implicitfast" gravity="0 0 -9.81"/>',
        "  <visual>",
        f'    <global offwidth="{max(640, width)}" offheight="{max(480, height)}"/>',
        '    <headlight ambient="0.45 0.45 0.45" diffuse="0.55 0.55 0.55" specular="0 0 0"/>',
        f'    <quality shadowsize="{4096 if world.shadows else 0}" offsamples="{cam.antialias}"/>',
        # znear/zfar are multiples of the extent: clip at 0.1 m and 1 km.
        '    <map znear="0.001" zfar="10"/>',
        "  </visual>",
        '  <statistic extent="100" center="0 0 0"/>',
        "  <asset>",
        '    <texture name="sky" type="skybox" builtin="gradient" rgb1="0.55 0.7 0.9" rgb2="0.9 0.93 0.97" width="64" height="64"/>',
        f'    <material name="road" rgba="{ROAD_RGBA}" reflectance="{reflect}"/>',
        f'    <material name="grass" rgba="{GRASS_RGBA}"/>',
        f'    <material name="marking" rgba="{MARKING_RGBA}"/>',
        "  </asset>",
        "  <worldbody>",
        f'    <light name="sun" directional="true" pos="0 0 50" dir="0.3 0.2 -1" castshadow="{str(world.shadows).lower()}" diffuse="0.5 0.5 0.5"/>',
        f'    <geom name="ground" type="plane" size="3000 3000 1" material="grass" group="{ROAD_GROUP}" contype="0" conaffinity="0"/>',
    ]
    for road in world.roads:
        parts.extend(road_xml(road))
    for v in world.vehicles:
        parts.extend(_entity_xml(v, cam))
    parts.append("  </worldbody>")
    egos = world.egos
    if egos:
        parts.append("  <actuator>")
        for v in egos:
            # Velocity servos track the bicycle model's commanded planar velocity;
            # their force limits let a collision really stop the car.
            for j in ("x", "y", "yaw"):
                gain = "30000" if j != "yaw" else "60000"
                limit = "60000" if j != "yaw" else "120000"
                parts.append(
                    f'    <velocity name="{v.name}/{j}" joint="{v.name}/{j}" kv="{gain}" '
                    f'forcelimited="true" forcerange="-{limit} {limit}"/>'
                )
        parts.append("  </actuator>")
    parts.append("</mujoco>")
    return "\n".join(parts) + "\n"


def _rgba(c: tuple[float, ...]) -> str:
    return " ".join(f"{v:.3g}" for v in c)


def _entity_xml(v: VehicleSpec, cam: CameraSpec) -> list[str]:
    length, width, height = v.size_m
    if v.ego:
        # Unrotated body with world-axis slide joints; the sim sets the yaw joint to
        # the start heading, so qpos is (dx, dy, yaw) in world axes for any heading.
        body = [f'    <body name="{v.name}" pos="{v.x_m:.4f} {v.y_m:.4f} 0">',
                f'      <joint name="{v.name}/x" type="slide" axis="1 0 0" damping="0"/>',
                f'      <joint name="{v.name}/y" type="slide" axis="0 1 0" damping="0"/>',
                f'      <joint name="{v.name}/yaw" type="hinge" axis="0 0 1" damping="0"/>']
    else:
        mocap = ' mocap="true"' if v.script is not None else ""
        body = [f'    <body name="{v.name}" pos="{v.x_m:.4f} {v.y_m:.4f} 0" euler="0 0 {v.yaw_rad:.6f}"{mocap}>']
    g = f'group="{ENTITY_GROUP}"'
    if v.cls == ObjectClass.PEDESTRIAN:
        legs, torso = 0.9 / 1.75 * height, 0.6 / 1.75 * height
        head = height - legs - torso
        for part, z0, dz, rgba, scale in (("legs", 0.0, legs, TROUSERS_RGBA, 0.8), ("torso", legs, torso, v.paint, 1.0),
                                          ("head", legs + torso, head, SKIN_RGBA, 0.45)):
            body.append(
                f'      <geom name="{v.name}/{part}" type="box" pos="0 0 {z0 + dz / 2:.3f}" '
                f'size="{length * scale / 2:.3f} {width * scale / 2:.3f} {dz / 2:.3f}" rgba="{_rgba(rgba)}" '
                f'mass="20" {g}/>'
            )
    else:
        bottom = CLEARANCE_M if v.cls == ObjectClass.VEHICLE else 0.0
        body.append(
            f'      <geom name="{v.name}/body" type="box" pos="0 0 {bottom + height / 2:.3f}" '
            f'size="{length / 2:.3f} {width / 2:.3f} {height / 2:.3f}" rgba="{_rgba(v.paint)}" mass="1500" {g}/>'
        )
    if v.ego:
        for k, m in enumerate(cam.mounts()):
            body.append(_camera_xml(camera_name(v.name, k), m))
    body.append("    </body>")
    return body


def _camera_xml(name: str, m: RigMount) -> str:
    s, c = math.sin(m.pitch_rad), math.cos(m.pitch_rad)
    sy, cy = math.sin(m.yaw_rad), math.cos(m.yaw_rad)
    x, y = [sy, -cy, 0.0], [s * cy, s * sy, c]  # image right, image up (world axes of the body)
    if m.roll_rad:  # turned about the optical axis
        sr, cr = math.sin(m.roll_rad), math.cos(m.roll_rad)
        x, y = [cr * a + sr * b for a, b in zip(x, y)], [cr * b - sr * a for a, b in zip(x, y)]
        axes = " ".join(f"{a:.6f}" for a in (*x, *y))
    else:
        axes = f"{sy:.6f} {-cy:.6f} 0 {s * cy:.6f} {s * sy:.6f} {c:.6f}"
    return (f'      <camera name="{name}" pos="{m.forward_m:.3f} {m.lateral_m:.3f} {m.height_m:.3f}" '
            f'xyaxes="{axes}" fovy="{m.fovy_deg:.4f}"/>')
