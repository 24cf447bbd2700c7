"""The built-in scenario library."""

from __future__ import annotations

from scenarios.params import Param
from scenarios.registry import register
from scenarios.world import CameraSpec, RoadSpec, VehicleSpec, WorldSpec

LANE_W = 3.7
RIGHT_LANE_Y = -LANE_W / 2


@register(
    "stopped_car",
    summary="A car stands still in the ego's lane; the ego must stop before it.",
    params=(
        Param("gap_m", 15.0, 150.0, 45.0, "m", "distance from the ego's front to the stopped car's rear"),
        Param("ego_speed_mps", 0.0, 30.0, 8.0, "m/s", "ego's initial speed"),
        Param("lateral_offset_m", -1.0, 1.0, 0.0, "m", "stopped car's offset from the lane centre"),
    ),
)
def stopped_car(*, params: dict[str, float], seed: int, camera: CameraSpec, physics_step_s: float,
                shadows: bool = False, reflections: bool = False) -> WorldSpec:
    del seed  # fully determined by its parameters
    length = 4.5
    ego = VehicleSpec("ego0", x_m=0.0, y_m=RIGHT_LANE_Y, ego=True, size_m=(length, 1.8, 1.4),
                      speed_mps=params["ego_speed_mps"])
    car_x = ego.x_m + length / 2 + params["gap_m"] + length / 2
    lead = VehicleSpec("car1", x_m=car_x, y_m=RIGHT_LANE_Y + params["lateral_offset_m"],
                       rgba=(0.8, 0.1, 0.1, 1.0))
    return WorldSpec(road=RoadSpec(lane_width_m=LANE_W), vehicles=(ego, lead), camera=camera,
                     physics_step_s=physics_step_s, shadows=shadows, reflections=reflections)

