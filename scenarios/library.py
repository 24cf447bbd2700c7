"""The built-in scenario library.

Every scenario is a registered factory ``fn(*, params, seed, camera, physics_step_s,
shadows, reflections) -> WorldSpec``, deterministic in ``(params, seed)``. The seed
feeds ``numpy.random.default_rng(seed)`` and jitters what its summary says (timings,
speeds, paint) by small amounts; the values drawn are recorded in
``WorldSpec.realized``. Lanes are 3.7 m; the ego starts in the right lane (lane 0)
heading +x unless a scenario says otherwise.
"""

from __future__ import annotations

import math

import numpy as np

from hil.scenarios.motion import (
                                  LaneChange,
                                  LateralProfile,
                                  Script,
                                  SpeedChange,
                                  SpeedProfile,
                                  )
from hil.scenarios.params import Param
from hil.scenarios.path import Path
from hil.scenarios.registry import register
from hil.scenarios.road import RoadSpec
from hil.scenarios.world import PAINTS, CameraSpec, VehicleSpec, WorldSpec, pedestrian

LANE_W = 3.7
RIGHT_LANE_Y = -LANE_W / 2
CAR_L = 4.5
HALF_L = CAR_L / 2


def _world(roads: tuple[RoadSpec, ...], vehicles: tuple[VehicleSpec, ...], camera: CameraSpec,
           physics_step_s: float, shadows: bool, reflections: bool, realized: dict[str, float]) -> WorldSpec:
    return WorldSpec(roads=roads, vehicles=vehicles, camera=camera, physics_step_s=physics_step_s,
                     shadows=shadows, reflections=reflections,
                     realized={k: float(v) for k, v in realized.items()})


def _straight_road(length_m: float, *, start_x_m: float = -30.0, shoulder_m: float = 0.5) -> RoadSpec:
    return RoadSpec(path=Path.straight(start_x_m, 0.0, 0.0, length_m), lane_width_m=LANE_W, shoulder_m=shoulder_m)


def _ego(x_m: float, speed_mps: float, road: RoadSpec, name: str = "ego0") -> VehicleSpec:
    return VehicleSpec(name, x_m=x_m, y_m=RIGHT_LANE_Y, ego=True, speed_mps=speed_mps, route=road.lane(0))


@register(
    "stopped_car",
    summary="A car stands still in the ego's lane; the ego must stop before it. "
            "Seed: the car's paint (red, orange, yellow or magenta).",
    params=(
        Param("gap_m", 15.0, 150.0, 45.0, "m", "distance from the ego's front to the stopped car's rear"),
        Param("ego_speed_mps", 0.0, 30.0, 8.0, "m/s", "ego's initial speed"),
        Param("lateral_offset_m", -1.0, 1.0, 0.0, "m", "stopped car's offset from the lane centre"),
    ),
)
def stopped_car(*, params: dict[str, float], seed: int, camera: CameraSpec, physics_step_s: float,
                shadows: bool = False, reflections: bool = False) -> WorldSpec:
    paint = int(np.random.default_rng(seed).integers(4))
    road = RoadSpec(lane_width_m=LANE_W)
    ego = _ego(0.0, params["ego_speed_mps"], road)
    car_x = ego.x_m + HALF_L + params["gap_m"] + HALF_L
    lead = VehicleSpec("car1", x_m=car_x, y_m=RIGHT_LANE_Y + params["lateral_offset_m"], rgba=PAINTS[paint])
    return _world((road,), (ego, lead), camera, physics_step_s, shadows, reflections, {"paint": paint})


@register(
    "pedestrian_occluded",
    summary="A pedestrian waits hidden in front of a van parked on the right shoulder and steps out "
            "across the ego's lane; visible only once it leaves the van's shadow. "
            "Seed: step-out time +-0.3 s, walking speed +-10 %.",
    params=(
        Param("ego_speed_mps", 0.0, 20.0, 8.0, "m/s", "ego's initial speed"),
        Param("parked_gap_m", 10.0, 80.0, 30.0, "m", "ego's front to the van's rear"),
        Param("step_out_s", 0.0, 15.0, 1.2, "s", "when the pedestrian starts walking"),
        Param("walk_speed_mps", 0.5, 3.0, 1.4, "m/s", "pedestrian's walking speed"),
    ),
)
def pedestrian_occluded(*, params: dict[str, float], seed: int, camera: CameraSpec, physics_step_s: float,
                        shadows: bool = False, reflections: bool = False) -> WorldSpec:
    rng = np.random.default_rng(seed)
    step_out = max(0.0, params["step_out_s"] + rng.uniform(-0.3, 0.3))
    walk = params["walk_speed_mps"] * rng.uniform(0.9, 1.1)
    road = _straight_road(500.0, shoulder_m=2.8)
    ego = _ego(0.0, params["ego_speed_mps"], road)
    van_l, van_w = 5.0, 2.0
    van_y = -LANE_W - 0.3 - van_w / 2  # its left side 0.3 m right of the edge line
    van_x = HALF_L + params["parked_gap_m"] + van_l / 2
    van = VehicleSpec("van1", x_m=van_x, y_m=van_y, rgba=PAINTS[0], size_m=(van_l, van_w, 2.3))
    # Half a metre past the van's front, on its footprint: in its shadow from the lane.
    walk_path = Path.straight(van_x + van_l / 2 + 0.5, van_y - 0.3, math.pi / 2, 40.0)
    ped = pedestrian("ped1", Script(walk_path, SpeedProfile(0.0, (SpeedChange(step_out, walk, 2.0),)),
                                    face_path=True))
    return _world((road,), (ego, van, ped), camera, physics_step_s, shadows, reflections,
                  {"step_out_s": step_out, "walk_speed_mps": walk})


@register(
    "lead_brake",
    summary="A lead car ahead in the ego's lane drives at the ego's speed, then brakes hard. "
            "Seed: braking time +-0.25 s, deceleration +-5 %, the lead's paint.",
    params=(
        Param("speed_mps", 2.0, 30.0, 10.0, "m/s", "initial speed of both cars"),
        Param("gap_m", 8.0, 80.0, 25.0, "m", "ego's front to the lead's rear"),
        Param("brake_at_s", 0.5, 30.0, 4.0, "s", "when the lead starts braking"),
        Param("decel_mps2", 1.0, 10.0, 6.0, "m/s^2", "the lead's deceleration"),
        Param("final_speed_mps", 0.0, 30.0, 0.0, "m/s", "speed the lead brakes to (then holds)"),
    ),
)
def lead_brake(*, params: dict[str, float], seed: int, camera: CameraSpec, physics_step_s: float,
               shadows: bool = False, reflections: bool = False) -> WorldSpec:
    rng = np.random.default_rng(seed)
    brake_at = params["brake_at_s"] + rng.uniform(-0.25, 0.25)
    decel = params["decel_mps2"] * rng.uniform(0.95, 1.05)
    paint = int(rng.integers(4))
    v = params["speed_mps"]
    road = _straight_road(2000.0)
    ego = _ego(0.0, v, road)
    lane = road.lane(0)  # starts 30 m behind the ego's centre
    s_lead = 30.0 + HALF_L + params["gap_m"] + HALF_L
    final = min(params["final_speed_mps"], v)
    lead = VehicleSpec("lead1", rgba=PAINTS[paint], script=Script(
        lane, SpeedProfile(v, (SpeedChange(brake_at, final, decel),)), s0_m=s_lead))
    return _world((road,), (ego, lead), camera, physics_step_s, shadows, reflections,
                  {"brake_at_s": brake_at, "decel_mps2": decel, "paint": paint})


@register(
    "cut_in",
    summary="A faster car in the left lane overtakes and cuts into the ego's lane close ahead, "
            "then slows. Seed: cut-in time +-0.3 s, the car's speed +-0.5 m/s, its paint.",
    params=(
        Param("ego_speed_mps", 0.0, 30.0, 10.0, "m/s", "ego's initial speed"),
        Param("npc_speed_mps", 0.0, 35.0, 12.0, "m/s", "cutting car's speed before and during the cut-in"),
        Param("start_ahead_m", -30.0, 60.0, 5.0, "m", "cutting car's rear ahead of the ego's front at t = 0"),
        Param("cut_in_at_s", 0.0, 20.0, 2.5, "s", "when the lane change starts"),
        Param("lane_change_s", 1.0, 8.0, 3.0, "s", "duration of the lane change"),
        Param("final_speed_mps", 0.0, 35.0, 8.0, "m/s", "speed it slows to after the lane change (2 m/s^2)"),
    ),
)
def cut_in(*, params: dict[str, float], seed: int, camera: CameraSpec, physics_step_s: float,
           shadows: bool = False, reflections: bool = False) -> WorldSpec:
    rng = np.random.default_rng(seed)
    cut_at = max(0.0, params["cut_in_at_s"] + rng.uniform(-0.3, 0.3))
    v_npc = max(0.0, params["npc_speed_mps"] + rng.uniform(-0.5, 0.5))
    paint = int(rng.integers(1, 4))
    road = _straight_road(2000.0)
    ego = _ego(0.0, params["ego_speed_mps"], road)
    lane = road.lane(0)
    s0 = (HALF_L + params["start_ahead_m"] + HALF_L) + 30.0  # the lane starts 30 m behind the ego
    t_done = cut_at + params["lane_change_s"]
    npc = VehicleSpec("cutter1", rgba=PAINTS[paint], script=Script(
        lane, SpeedProfile(v_npc, (SpeedChange(t_done, params["final_speed_mps"], 2.0),)), s0_m=s0,
        lateral=LateralProfile(LANE_W, (LaneChange(cut_at, -LANE_W, params["lane_change_s"]),))))
    return _world((road,), (ego, npc), camera, physics_step_s, shadows, reflections,
                  {"cut_in_at_s": cut_at, "npc_speed_mps": v_npc, "paint": paint})


@register(
    "curved_road",
    summary="Lane keeping on an S-bend: straight, a left arc, straight, a right arc, straight; "
            "optionally a slower car ahead in the lane. Seed: radius +-3 %, the lead's speed "
            "+-0.3 m/s.",
    params=(
        Param("radius_m", 60.0, 1000.0, 150.0, "m", "radius of both arcs (lane centre of the road)"),
        Param("arc_deg", 5.0, 120.0, 45.0, "deg", "heading change of each arc"),
        Param("ego_speed_mps", 0.0, 25.0, 10.0, "m/s", "ego's initial speed"),
        Param("lead_gap_m", 0.0, 150.0, 0.0, "m", "a lead car this far ahead in the lane (0: none)"),
        Param("lead_speed_mps", 0.0, 25.0, 7.0, "m/s", "the lead car's constant speed"),
    ),
)
def curved_road(*, params: dict[str, float], seed: int, camera: CameraSpec, physics_step_s: float,
                shadows: bool = False, reflections: bool = False) -> WorldSpec:
    rng = np.random.default_rng(seed)
    radius = params["radius_m"] * rng.uniform(0.97, 1.03)
    lead_v = max(0.0, params["lead_speed_mps"] + rng.uniform(-0.3, 0.3))
    arc = math.radians(params["arc_deg"])
    centre = (Path.start(-30.0, 0.0, 0.0).line(70.0).arc(radius, arc).line(30.0).arc(radius, -arc).line(600.0))
    road = RoadSpec(path=centre, lane_width_m=LANE_W)
    lane = road.lane(0)
    ego = VehicleSpec("ego0", x_m=0.0, y_m=RIGHT_LANE_Y, ego=True, speed_mps=params["ego_speed_mps"], route=lane)
    vehicles = [ego]
    if params["lead_gap_m"] > 0:
        s0 = 30.0 + HALF_L + params["lead_gap_m"] + HALF_L
        vehicles.append(VehicleSpec("lead1", rgba=PAINTS[1], script=Script(lane, SpeedProfile(lead_v), s0_m=s0)))
    return _world((road,), tuple(vehicles), camera, physics_step_s, shadows, reflections,
                  {"radius_m": radius, "lead_speed_mps": lead_v})


CROSS_HALF_M = LANE_W + 0.5  # half width of a road over its shoulders


@register(
    "multi_vehicle",
    summary="N ego vehicles, each with its own camera and target, share a crossroads: platoons in "
            "both lanes of the main road follow each other towards the junction while the crossing "
            "road's egos (half from each side) pass through it first. Seed: each ego's start "
            "+-1.5 m along its lane and speed +-0.5 m/s.",
    params=(
        Param("n_vehicles", 1, 64, 4, "", "ego vehicles (each runs its own target; beyond 16 a real-time run checks first that this machine renders them in time)", integer=True),
        Param("speed_mps", 0.0, 20.0, 10.0, "m/s", "initial speed of every ego"),
        Param("headway_m", 12.0, 80.0, 30.0, "m", "front-to-front spacing within a lane"),
        Param("main_start_m", 20.0, 400.0, 110.0, "m", "first main-road ego's front to the junction's edge"),
        Param("cross_start_m", 3.0, 200.0, 15.0, "m", "first crossing ego's front to the junction's edge"),
        Param("crossing_share", 0.0, 0.5, 0.25, "", "fraction of the egos on the crossing road"),
    ),
)
def multi_vehicle(*, params: dict[str, float], seed: int, camera: CameraSpec, physics_step_s: float,
                  shadows: bool = False, reflections: bool = False) -> WorldSpec:
    rng = np.random.default_rng(seed)
    n = int(params["n_vehicles"])
    n_cross = round(n * params["crossing_share"]) if n > 1 else 0
    n_main = n - n_cross
    headway = params["headway_m"]
    per_lane = math.ceil(n_main / 2)
    main_len = CROSS_HALF_M + params["main_start_m"] + per_lane * headway + 40.0
    main = RoadSpec(path=Path.straight(-main_len, 0.0, 0.0, main_len + 400.0), lane_width_m=LANE_W, name="main",
                    marking_gaps=((main_len - CROSS_HALF_M, main_len + CROSS_HALF_M),))
    cross_len = CROSS_HALF_M + params["cross_start_m"] + math.ceil(n_cross / 2) * headway + 60.0
    cross = RoadSpec(path=Path.straight(0.0, -cross_len, math.pi / 2, 2 * cross_len), lane_width_m=LANE_W,
                     name="cross", marking_gaps=((cross_len - CROSS_HALF_M, cross_len + CROSS_HALF_M),))
    egos: list[VehicleSpec] = []
    realized: dict[str, float] = {"n_crossing": n_cross}

    def add(route: Path, front_s: float) -> None:
        i = len(egos)
        jitter = rng.uniform(-1.5, 1.5)
        speed = max(0.0, params["speed_mps"] + rng.uniform(-0.5, 0.5))
        x, y, h = (float(a) for a in route.pose_at(front_s - HALF_L + jitter))
        egos.append(VehicleSpec(f"ego{i}", x_m=x, y_m=y, yaw_rad=h, ego=True, speed_mps=speed,
                                rgba=PAINTS[i % len(PAINTS)], route=route))
        realized[f"ego{i}_start_jitter_m"] = jitter
        realized[f"ego{i}_speed_mps"] = speed

    lanes = (main.lane(0), main.lane(1))
    junction_s = main_len - CROSS_HALF_M - params["main_start_m"]
    for k in range(n_main):
        lane, rank = k % 2, k // 2
        # The left lane's platoon trails by half a headway: staggered, not abreast.
        add(lanes[lane], junction_s - rank * headway - lane * headway / 2)
    north = cross.lane(0)
    south = Path.straight(-LANE_W / 2, cross_len, -math.pi / 2, 2 * cross_len)
    for k in range(n_cross):
        route, rank = (north, k // 2) if k % 2 == 0 else (south, k // 2)
        add(route, cross_len - CROSS_HALF_M - params["cross_start_m"] - rank * headway)
    return _world((main, cross), tuple(egos), camera, physics_step_s, shadows, reflections, realized)

