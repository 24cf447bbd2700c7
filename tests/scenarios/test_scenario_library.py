"""The scenario library: every scenario builds and runs, its parameters are typed and
checked, its seed varies it, and a bad world is refused with names."""

from __future__ import annotations

import math

import numpy as np
import pytest
from conftest import build  # tests/scenarios/conftest.py

from hil.common.classes import ObjectClass
from hil.common.errors import ConfigError
from hil import scenarios
from hil.scenarios.world import CameraSpec, VehicleSpec, WorldSpec, build_mjcf

SIX = {"stopped_car", "pedestrian_occluded", "lead_brake", "cut_in", "curved_road", "multi_vehicle"}


def test_the_library_has_the_six_scenarios_with_typed_params() -> None:
    assert SIX <= set(scenarios.names())
    for name in scenarios.names():
        d = scenarios.get(name)
        assert d.summary and "Seed" in d.summary, name
        assert d.params, name
        for p in d.params:
            assert p.lo <= p.default <= p.hi and p.help, (name, p.name)


@pytest.mark.parametrize("name", sorted(SIX))
def test_each_scenario_builds_steps_renders_and_has_truth(make_sim, name: str) -> None:
    sim = make_sim(name)
    assert sim.egos and all(e.startswith("ego") for e in sim.egos)
    for _ in range(250):
        sim.step()
    gt = sim.ground_truth()
    assert gt.sim_time_ns == 500_000_000
    assert [e.name for e in gt.entities] == [v.name for v in sim.world.vehicles]
    assert [e.entity_id for e in gt.entities] == list(range(len(gt.entities)))
    for e in gt.entities:
        assert all(math.isfinite(v) for v in (e.x_m, e.y_m, e.vx_mps, e.vy_mps, e.heading_rad))
    img = sim.render(sim.egos[0])
    assert img.shape == (240, 320, 3) and img.std() > 10  # sky, verge, road: not blank
    ct = sim.camera_truth(sim.egos[0])
    assert ct.vehicle == sim.egos[0] and ct.sim_time_ns == gt.sim_time_ns


def test_lane_markings_are_visible_in_the_camera(make_sim) -> None:
    sim = make_sim("curved_road")
    img = sim.render("ego0").astype(int)
    white = (img.min(axis=2) > 200) & (img.max(axis=2) - img.min(axis=2) < 30)
    # Road markings below the horizon, on both sides of the image centre.
    assert white[130:, :160].sum() > 50 and white[130:, 160:].sum() > 50


def test_unknown_scenario_lists_the_valid_names() -> None:
    with pytest.raises(ConfigError, match="unknown scenario 'nowhere'; valid: .*curved_road.*stopped_car"):
        scenarios.get("nowhere")


def test_unknown_parameter_lists_names_and_ranges() -> None:
    with pytest.raises(ConfigError) as err:
        scenarios.get("lead_brake").resolve({"speed": 3.0})
    msg = str(err.value)
    assert "scenario.params.speed" in msg and "speed_mps in [2, 30] m/s (default 10)" in msg
    assert "decel_mps2 in [1, 10]" in msg


@pytest.mark.parametrize(("name", "params", "needle"), [
    ("lead_brake", {"decel_mps2": 12.0}, "scenario.params.decel_mps2: got 12; expected a value in [1, 10] m/s^2"),
    ("multi_vehicle", {"n_vehicles": 65}, "n_vehicles: got 65; expected an integer in [1, 64]"),
    ("multi_vehicle", {"n_vehicles": 2.5}, "n_vehicles: got 2.5; expected an integer in [1, 64]"),
    ("curved_road", {"radius_m": float("nan")}, "radius_m: got nan"),
])
def test_out_of_range_values_say_the_range(name: str, params: dict[str, float], needle: str) -> None:
    with pytest.raises(ConfigError) as err:
        scenarios.get(name).resolve(params)
    assert needle in str(err.value)
    assert "parameters of" in str(err.value)  # and every parameter's range


def test_overlapping_vehicles_are_named() -> None:
    a = VehicleSpec("ego0", 0.0, -1.85, ego=True)
    b = VehicleSpec("car7", 3.0, -1.0)
    with pytest.raises(ConfigError, match="vehicles 'ego0' and 'car7' overlap"):
        WorldSpec(roads=(), vehicles=(a, b), camera=CameraSpec())
    # Side by side in adjacent lanes, or yawed clear of each other: fine.
    WorldSpec(roads=(), vehicles=(a, VehicleSpec("car7", 0.0, 1.85)), camera=CameraSpec())
    WorldSpec(roads=(), vehicles=(a, VehicleSpec("car7", 0.0, 2.5, yaw_rad=math.pi / 2, size_m=(4.5, 1.8, 1.4))),
              camera=CameraSpec())
    with pytest.raises(ConfigError, match="repeated: car7"):
        WorldSpec(roads=(), vehicles=(VehicleSpec("car7", 0, 0), VehicleSpec("car7", 50, 0)), camera=CameraSpec())


@pytest.mark.parametrize("name", sorted(SIX))
def test_same_seed_same_world_other_seed_other_world(name: str) -> None:
    a, b = build(name, seed=3), build(name, seed=3)
    assert build_mjcf(a) == build_mjcf(b) and a.realized == b.realized
    others = [build(name, seed=s) for s in (4, 5, 6)]
    assert any(o.realized != a.realized for o in others)


def test_multi_vehicle_places_up_to_sixty_four_egos_apart() -> None:
    for n in (1, 2, 5, 16, 64):
        w = build("multi_vehicle", {"n_vehicles": n})
        egos = [v for v in w.vehicles if v.ego]
        assert len(egos) == n
        assert len({v.paint for v in egos}) == min(n, 8)
    w = build("multi_vehicle", {"n_vehicles": 16})
    headings = {round(v.yaw_rad, 3) for v in w.vehicles}
    assert headings == {0.0, round(math.pi / 2, 3), round(-math.pi / 2, 3)}  # two lanes + both crossing ways


def test_pedestrian_is_a_scripted_pedestrian_with_a_jacket_the_baseline_can_see() -> None:
    import colorsys

    w = build("pedestrian_occluded")
    ped = next(v for v in w.vehicles if v.cls == ObjectClass.PEDESTRIAN)
    assert ped.script is not None
    h, s, v = colorsys.rgb_to_hsv(*ped.paint[:3])
    assert s >= 0.5 and v >= 0.25 and not (75 <= h * 360 <= 165 or 185 <= h * 360 <= 235)
    assert 'mocap="true"' in build_mjcf(w)


def test_npc_paints_avoid_the_hues_the_baseline_ignores() -> None:
    import colorsys

    from hil.scenarios.world import PAINTS

    for rgba in PAINTS:
        h, s, v = colorsys.rgb_to_hsv(*rgba[:3])
        assert s >= 0.5 and v >= 0.25 and not (75 <= h * 360 <= 165 or 185 <= h * 360 <= 235), rgba


def test_scripted_entities_are_not_egos_and_egos_have_routes() -> None:
    for name in SIX:
        w = build(name)
        for v in w.vehicles:
            assert not (v.ego and v.script is not None)
            if v.ego:
                route = v.route_path()
                s, lateral = route.project(v.x_m, v.y_m)
                assert abs(float(lateral)) < 1e-6, (name, v.name)
                assert abs(float(np.asarray(route.pose_at(s)[2])) - v.yaw_rad) < 1e-6
