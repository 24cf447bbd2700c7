"""World building: a scenario's road and vehicles as an MJCF string.

Coordinates: world x along the road, y to the left, z up; metres and radians.
Vehicles drive towards +x; the right lane's centre is at ``y = -lane_width/2``.
No MuJoCo import here: this module only writes XML, so it is cheap to test.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import Enum


class EntityClass(str, Enum):
    VEHICLE = "vehicle"
    PEDESTRIAN = "pedestrian"
    OBSTACLE = "obstacle"


@dataclass(frozen=True)
class VehicleSpec:
    """One vehicle in the world.

    ``ego`` vehicles carry a camera and are driven by an AI target; others are static
    (or scripted, later). Size is length x width x height in metres; ``speed_mps`` is
    the initial forward speed.
    """

    name: str
    x_m: float
    y_m: float
    yaw_rad: float = 0.0
    ego: bool = False
    speed_mps: float = 0.0
    rgba: tuple[float, float, float, float] = (0.8, 0.1, 0.1, 1.0)
    size_m: tuple[float, float, float] = (4.5, 1.8, 1.4)


@dataclass(frozen=True)
class CameraSpec:
    """Camera mounted on each ego vehicle: vertical field of view (deg), mount
    position from the vehicle centre (m) and pitch (rad, positive looks down)."""

    width: int = 320
    height: int = 240
    fovy_deg: float = 60.0
    mount_forward_m: float = 2.3
    mount_height_m: float = 1.3
    pitch_rad: float = 0.0


@dataclass(frozen=True)
class RoadSpec:
    length_m: float = 400.0
    lanes: int = 2
    lane_width_m: float = 3.7
    marking_width_m: float = 0.15
    dash_m: float = 3.0
    gap_m: float = 6.0
    start_x_m: float = -20.0


@dataclass(frozen=True)
class WorldSpec:
    road: RoadSpec
    vehicles: tuple[VehicleSpec, ...]
    camera: CameraSpec
    physics_step_s: float = 0.002
    reflections: bool = False
    shadows: bool = False

    def __post_init__(self) -> None:
        _check_no_overlap(self.vehicles)


# Colours chosen so a classical detector can separate them: grey road, green verge,
# white markings, blue sky, saturated vehicle paint.
ROAD_RGBA = "0.32 0.32 0.34 1"
GRASS_RGBA = "0.25 0.45 0.2 1"
MARKING_RGBA = "0.95 0.95 0.95 1"
EGO_RGBA = (0.1, 0.25, 0.8, 1.0)


def _check_no_overlap(vehicles: tuple[VehicleSpec, ...]) -> None:
    from timing.errors import ConfigError

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


def camera_name(vehicle: str) -> str:
    return f"{vehicle}/camera"


def build_mjcf(world: WorldSpec) -> str:
    """Return the MJCF XML of ``world``."""
    road = world.road
    half_w = road.lanes * road.lane_width_m / 2
    cx = road.start_x_m + road.length_m / 2
    cam = world.camera
    reflect = "0.2" if world.reflections else "0"
    parts: list[str] = [
        '<mujoco model="hil_world">',
        f'  <option timestep="{world.physics_step_s:.9g}" integrator="implicitfast" gravity="0 0 -9.81"/>',
        "  <visual>",
        f'    <global offwidth="{max(640, cam.width)}" offheight="{max(480, cam.height)}"/>',
        '    <headlight ambient="0.45 0.45 0.45" diffuse="0.55 0.55 0.55" specular="0 0 0"/>',
        f'    <quality shadowsize="{4096 if world.shadows else 0}"/>',
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
        '    <geom name="ground" type="plane" size="2000 2000 1" material="grass" contype="0" conaffinity="0"/>',
        f'    <geom name="road" type="box" pos="{cx:.3f} 0 0.005" size="{road.length_m / 2:.3f} {half_w + 0.5:.3f} 0.005" material="road" contype="0" conaffinity="0"/>',
    ]
    mw = road.marking_width_m / 2
    # Solid edge lines, dashed lines between lanes.
    for side, y in (("left", half_w), ("right", -half_w)):
        parts.append(
            f'    <geom name="edge_{side}" type="box" pos="{cx:.3f} {y:.3f} 0.011" '
            f'size="{road.length_m / 2:.3f} {mw:.3f} 0.001" material="marking" contype="0" conaffinity="0"/>'
        )
    period = road.dash_m + road.gap_m
    n_dash = int(road.length_m // period)
    for lane in range(1, road.lanes):
        y = -half_w + lane * road.lane_width_m
        for k in range(n_dash):
            x = road.start_x_m + k * period + road.dash_m / 2
            parts.append(
                f'    <geom name="dash_{lane}_{k}" type="box" pos="{x:.3f} {y:.3f} 0.011" '
                f'size="{road.dash_m / 2:.3f} {mw:.3f} 0.001" material="marking" contype="0" conaffinity="0"/>'
            )
    for v in world.vehicles:
        parts.extend(_vehicle_xml(v, cam))
    parts.append("  </worldbody>")
    actuators = [v for v in world.vehicles if v.ego]
    if actuators:
        parts.append("  <actuator>")
        for v in actuators:
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


def _vehicle_xml(v: VehicleSpec, cam: CameraSpec) -> list[str]:
    length, width, height = v.size_m
    rgba = " ".join(f"{c:.3g}" for c in (EGO_RGBA if v.ego else v.rgba))
    body = [f'    <body name="{v.name}" pos="{v.x_m:.4f} {v.y_m:.4f} 0" euler="0 0 {v.yaw_rad:.6f}">']
    if v.ego:
        body += [
            f'      <joint name="{v.name}/x" type="slide" axis="1 0 0" damping="0"/>',
            f'      <joint name="{v.name}/y" type="slide" axis="0 1 0" damping="0"/>',
            f'      <joint name="{v.name}/yaw" type="hinge" axis="0 0 1" damping="0"/>',
        ]
    # Body from 0.1 m (ground clearance) to the roof.
    body.append(
        f'      <geom name="{v.name}/body" type="box" pos="0 0 {0.1 + height / 2:.3f}" '
        f'size="{length / 2:.3f} {width / 2:.3f} {height / 2:.3f}" rgba="{rgba}" mass="1500"/>'
    )
    if v.ego:
        s, c = math.sin(cam.pitch_rad), math.cos(cam.pitch_rad)
        body.append(
            f'      <camera name="{camera_name(v.name)}" pos="{cam.mount_forward_m:.3f} 0 {cam.mount_height_m:.3f}" '
            f'xyaxes="0 -1 0 {s:.6f} 0 {c:.6f}" fovy="{cam.fovy_deg:.4f}"/>'
        )
    body.append("    </body>")
    return body
