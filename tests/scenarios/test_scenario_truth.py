"""Ground truth and dynamics in the simulator: scripted NPCs follow their profiles,
egos respond to steering/throttle/brake within their limits, segmentation boxes are
occlusion-aware, collisions say who hit whom, the reference state follows its rules."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from conftest import build  # tests/scenarios/conftest.py

from hil.scenarios.ground_truth import EntityTable, GroundTruth, RefState, RefStateRules, StateChanges
from hil.scenarios.motion import SpeedChange, SpeedProfile
from hil.scenarios.world import CameraSpec, VehicleSpec, WorldSpec


def run_until(sim, t_s: float) -> None:
    while sim.sim_time_ns < round(t_s * 1e9):
        sim.step()


# -- scripted motion -------------------------------------------------------------


def test_lead_follows_its_speed_profile_and_brakes_to_a_stop(make_sim) -> None:
    sim = make_sim("lead_brake", {"speed_mps": 12.0, "gap_m": 30.0, "brake_at_s": 2.0, "decel_mps2": 6.0})
    sim.set_control("ego0", steering_rad=0.0, throttle=0.0, brake=1.0)  # stay out of its way
    r = sim.world.realized
    profile = SpeedProfile(12.0, (SpeedChange(r["brake_at_s"], 0.0, r["decel_mps2"]),))
    x0 = sim.ground_truth().entity("lead1").x_m
    for t_run in (0.5, 1.0, r["brake_at_s"] + 0.5, r["brake_at_s"] + 1.0, 5.0, 6.0):
        run_until(sim, t_run)
        t = sim.sim_time_ns / 1e9
        lead = sim.ground_truth().entity("lead1")
        assert lead.vx_mps == pytest.approx(float(profile.speed_at(t)), abs=1e-9)
        assert lead.x_m - x0 == pytest.approx(float(profile.distance_at(t)), abs=1e-9)
        assert lead.vy_mps == pytest.approx(0.0) and lead.cls == "vehicle"
    # Stopped after v^2 / (2 a) of braking.
    run_until(sim, 8.0)
    lead = sim.ground_truth().entity("lead1")
    assert lead.vx_mps == 0.0
    assert lead.x_m - x0 == pytest.approx(12.0 * r["brake_at_s"] + 144 / (2 * r["decel_mps2"]), abs=1e-6)


def test_cut_in_moves_into_the_ego_lane_and_becomes_the_obstacle(make_sim) -> None:
    sim = make_sim("cut_in", {"ego_speed_mps": 10.0, "npc_speed_mps": 12.0, "cut_in_at_s": 2.0,
                              "lane_change_s": 2.0, "final_speed_mps": 12.0})
    cut_at = sim.world.realized["cut_in_at_s"]
    sim.set_control("ego0", steering_rad=0.0, throttle=0.05, brake=0.0)
    run_until(sim, cut_at - 0.1)
    gt = sim.ground_truth()
    assert gt.entity("cutter1").y_m == pytest.approx(1.85)  # still in the left lane
    assert gt.ego("ego0").obstacle is None
    run_until(sim, cut_at + 1.0)  # halfway: heading turned towards the ego lane
    mid = sim.ground_truth().entity("cutter1")
    assert mid.y_m == pytest.approx(0.0, abs=0.01) and mid.vy_mps < -1.0 and mid.heading_rad < -0.05
    run_until(sim, cut_at + 2.5)
    gt = sim.ground_truth()
    assert gt.entity("cutter1").y_m == pytest.approx(-1.85) and gt.entity("cutter1").heading_rad == 0.0
    e = gt.ego("ego0")
    assert e.obstacle == "cutter1" and 0 < e.gap_m < 40 and e.obstacle_speed_mps == pytest.approx(12.0)


def test_pedestrian_is_occluded_until_it_steps_out(make_sim) -> None:
    sim = make_sim("pedestrian_occluded", {"ego_speed_mps": 0.0, "parked_gap_m": 25.0, "step_out_s": 1.0,
                                           "walk_speed_mps": 1.4})
    sim.set_control("ego0", steering_rad=0.0, throttle=0.0, brake=1.0)
    step_out = sim.world.realized["step_out_s"]
    seen: list[tuple[float, float]] = []
    for k in range(60):
        t = 0.1 * k
        run_until(sim, t)
        ct = sim.camera_truth("ego0")
        van = ct.box("van1")
        assert van is not None and van.visible_fraction > 0.9  # the van is in plain view
        ped = ct.box("ped1")
        seen.append((t, 0.0 if ped is None else ped.visible_fraction))
    visible = [t for t, f in seen if f > 0.0]
    assert all(f == 0.0 for t, f in seen if t <= step_out)  # standing behind the van: hidden
    assert visible[0] > step_out + 0.3  # and walking its first steps, still in the van's shadow
    assert max(f for _, f in seen) > 0.7  # then fully in view, in the lane
    assert any(0.0 < f < 0.7 for t, f in seen if t < visible[0] + 0.5)  # emerging: partly hidden
    ped = sim.ground_truth().entity("ped1")
    assert ped.cls == "pedestrian" and ped.vy_mps == pytest.approx(sim.world.realized["walk_speed_mps"])


# -- ego dynamics ----------------------------------------------------------------


def test_ego_accelerates_brakes_and_steers_within_its_limits(make_sim) -> None:
    sim = make_sim("stopped_car", {"gap_m": 150.0, "ego_speed_mps": 0.0})
    lim = sim.limits
    sim.set_control("ego0", steering_rad=0.0, throttle=1.0, brake=0.0)
    run_until(sim, 2.0)
    assert sim.speed_mps("ego0") == pytest.approx(2.0 * lim.max_accel_mps2, rel=0.05)
    # Full brake: the speed falls at the brake limit (past the servo's 0.05 s lag).
    sim.set_control("ego0", steering_rad=0.0, throttle=0.0, brake=1.0)
    run_until(sim, 2.1)
    v0 = sim.speed_mps("ego0")
    run_until(sim, 2.3)
    assert v0 - sim.speed_mps("ego0") == pytest.approx(0.2 * lim.max_brake_mps2, rel=0.05)
    # Full lock asked (beyond the limit): the wheel turns at the rate limit, then stops at the limit.
    sim.set_control("ego0", steering_rad=2.0, throttle=0.5, brake=0.0)
    run_until(sim, 2.5)
    assert sim.vehicle_state("ego0").steer_rad == pytest.approx(0.2 * lim.max_steer_rate_radps, abs=0.01)
    run_until(sim, 3.0)
    assert sim.vehicle_state("ego0").steer_rad == pytest.approx(lim.max_steer_rad)
    v = sim.speed_mps("ego0")
    yaw0 = sim.pose("ego0")[2]
    run_until(sim, 3.1)
    yaw_rate = (sim.pose("ego0")[2] - yaw0) / 0.1
    assert yaw_rate == pytest.approx(v * math.tan(lim.max_steer_rad) / lim.wheelbase_m, rel=0.05)
    # Braking to a stop, it stays stopped.
    sim.set_control("ego0", steering_rad=0.0, throttle=0.0, brake=1.0)
    run_until(sim, 5.0)
    assert abs(sim.speed_mps("ego0")) < 0.01


def test_a_collision_stops_the_ego_and_says_who_hit_whom(make_sim) -> None:
    sim = make_sim("stopped_car", {"gap_m": 15.0, "ego_speed_mps": 8.0})
    sim.set_control("ego0", steering_rad=0.0, throttle=0.2, brake=0.0)  # keeps ~8 m/s: no braking
    states = []
    collisions = []
    for _ in range(40):
        run_until(sim, sim.sim_time_ns / 1e9 + 0.1)
        gt = sim.ground_truth()
        states.append(gt.ego("ego0").ref_state)
        collisions += gt.collisions
    assert states[0] == RefState.SLOW and RefState.STOP in states  # warned before the hit
    c = collisions[0]  # (it may bounce off and touch again: each new contact is a record)
    assert {c.a, c.b} == {"ego0", "car1"} and c.striker == "ego0"
    assert 1.5 < c.sim_time_ns / 1e9 < 2.2  # 15 m at ~8 m/s
    assert c.closing_speed_mps == pytest.approx(8.0, abs=1.0) and c.force_n > 0
    assert sim.speed_mps("ego0") < 0.5  # the car really stopped against it
    assert sim.ground_truth().ego("ego0").gap_m == pytest.approx(0.0, abs=0.05)


# -- visible boxes ----------------------------------------------------------------


def _two_cars(offset_m: float) -> WorldSpec:
    ego = VehicleSpec("ego0", 0.0, -1.85, ego=True)
    near = VehicleSpec("near", 22.25, -1.85 + offset_m, rgba=(0.9, 0.8, 0.1, 1.0))
    far = VehicleSpec("far", 42.25, -1.85, rgba=(0.8, 0.1, 0.1, 1.0))
    from hil.scenarios.road import RoadSpec

    return WorldSpec(roads=(RoadSpec(),), vehicles=(ego, near, far), camera=CameraSpec())


def test_boxes_are_exact_and_occlusion_aware() -> None:
    from hil.scenarios.sim import Simulation

    with Simulation(_two_cars(offset_m=6.0)) as sim:  # both in plain view
        ct = sim.camera_truth("ego0")
        far, near = ct.box("far"), ct.box("near")
        assert far is not None and near is not None
        assert far.visible_fraction > 0.9 and near.visible_fraction > 0.9 and not far.truncated
        # The far car's rear face by the pinhole model: 1.8 x 1.4 m at 37.75 m from the camera.
        k = sim.intrinsics()
        z = 42.25 - 2.25 - 2.3
        x0, y0, x1, y1 = far.box_px
        assert x1 - x0 == pytest.approx(k.fx * 1.8 / z, abs=1.5)
        assert y1 - y0 == pytest.approx(k.fy * 1.4 / z, abs=1.5)
        assert (x0 + x1) / 2 == pytest.approx(k.cx, abs=1.0)
        assert far.path_s_m == pytest.approx(42.25 - 2.25 - 2.25 - 2.25 + 2.25, abs=0.01)  # 35.75 m gap
        assert far.path_lateral_m == pytest.approx(0.0, abs=1e-9) and near.path_lateral_m == pytest.approx(6.0)
        assert far.cls == "vehicle" and far.entity_id == 2
        assert ct.ego.obstacle == "far"
    with Simulation(_two_cars(offset_m=1.0)) as sim:  # the near car hides part of the far one
        ct = sim.camera_truth("ego0")
        far, near = ct.box("far"), ct.box("near")
        assert near.visible_fraction > 0.9
        assert far is not None and 0.1 < far.visible_fraction < 0.9
        assert ct.ego.obstacle == "near"
    with Simulation(_two_cars(offset_m=0.0)) as sim:  # fully hidden: no box at all
        ct = sim.camera_truth("ego0")
        assert ct.box("far") is None and ct.box("near") is not None
        assert sim.segmentation("ego0").max() == 1  # entity ids: only "near" is seen


def test_camera_mount_pose_moves_the_view() -> None:
    from hil.scenarios.sim import Simulation

    def box(**cam: float) -> tuple[int, int, int, int]:
        with Simulation(build("stopped_car", {"gap_m": 20.0}, **cam)) as sim:
            b = sim.camera_truth("ego0").box("car1")
            assert b is not None
            return b.box_px

    straight = box()
    left = box(yaw_rad=0.2)       # looking left: the car moves right in the image
    down = box(pitch_rad=0.1)     # looking down: the car moves up
    shifted = box(mount_lateral_m=0.5)  # camera 0.5 m left: the car moves right
    assert left[0] > straight[0] + 30 and down[1] < straight[1] - 10 and shifted[0] > straight[0] + 2
    wide = box(width=640, height=480)
    assert wide[2] - wide[0] == pytest.approx(2 * (straight[2] - straight[0]), abs=2)


def test_antialias_smooths_the_camera_image_and_leaves_the_truth_alone() -> None:
    """``camera.antialias``: samples per pixel of the offscreen render. Off, each
    pixel takes one colour (edges step); on, edge pixels blend their neighbours'. The
    segmentation, and so every true box, is the same either way."""
    from hil.scenarios.sim import Simulation

    seen = {}
    for samples in (4, 0):
        with Simulation(build("stopped_car", {"gap_m": 20.0}, antialias=samples)) as sim:
            assert sim.model.vis.quality.offsamples == samples
            rgb = sim.render("ego0").copy()
            seen[samples] = (rgb, len(np.unique(rgb.reshape(-1, 3), axis=0)), sim.segmentation("ego0").copy(),
                             sim.camera_truth("ego0").boxes)
    (smooth, smooth_colours, seg4, boxes4), (sharp, sharp_colours, seg0, boxes0) = seen[4], seen[0]
    assert smooth.shape == sharp.shape and not np.array_equal(smooth, sharp)
    assert smooth_colours > sharp_colours + 20  # blended edge colours
    assert np.array_equal(seg4, seg0) and boxes4 == boxes0 and boxes4


def test_distance_along_a_curved_path(make_sim) -> None:
    sim = make_sim("curved_road", {"lead_gap_m": 60.0, "lead_speed_mps": 10.0, "ego_speed_mps": 10.0})
    sim.set_control("ego0", steering_rad=0.0, throttle=0.0, brake=1.0)
    run_until(sim, 10.0)  # the lead is now deep in the first arc; the ego stopped ~6 m on
    gt = sim.ground_truth()
    route = sim.route("ego0")
    ego, lead = gt.entity("ego0"), gt.entity("lead1")
    s_ego, _ = route.project(ego.x_m, ego.y_m)
    s_lead, lat = route.project(lead.x_m, lead.y_m)
    assert abs(float(lat)) < 1e-6
    e = gt.ego("ego0")
    assert e.obstacle == "lead1"
    assert e.gap_m == pytest.approx(float(s_lead - s_ego) - 4.5, abs=1e-6)  # along the lane, not straight
    assert e.gap_m > math.hypot(lead.x_m - ego.x_m, lead.y_m - ego.y_m) - 4.5 + 0.5


# -- records and rules -------------------------------------------------------------


def test_state_records_are_initial_then_changes(make_sim) -> None:
    sim = make_sim("pedestrian_occluded", {"step_out_s": 0.5})
    changes = StateChanges()
    first = changes.changes_json(sim.ground_truth())
    assert [e["name"] for e in first] == ["ego0", "van1", "ped1"]
    assert first == [e.to_json() for e in sim.ground_truth().entities]
    run_until(sim, 0.1)
    assert [e["name"] for e in changes.changes_json(sim.ground_truth())] == ["ego0"]  # the pedestrian still waits
    run_until(sim, 1.0)
    assert [e["name"] for e in changes.changes_json(sim.ground_truth())] == ["ego0", "ped1"]
    assert changes.changes_json(sim.ground_truth()) == []  # same instant: nothing changed


def test_state_records_from_columns_are_those_from_states(make_sim) -> None:
    # The simulator gives its entities as columns (EntityTable) and the records are
    # made from them; a ground truth holding EntityState objects (any other maker, or
    # both in one stream) gives the same records: same keys, same rounding.
    sim = make_sim("pedestrian_occluded", {"step_out_s": 0.3})
    cols, objs, mixed = StateChanges(), StateChanges(), StateChanges()
    seen = set()
    for k in range(40):
        run_until(sim, 0.025 * k)
        gt = sim.ground_truth()
        assert isinstance(gt.entities, EntityTable) and gt.entities == tuple(gt.entities)
        as_states = replace(gt, entities=tuple(gt.entities))
        a, b = cols.changes_json(gt), objs.changes_json(as_states)
        assert a == b
        assert mixed.changes_json(gt if k % 3 else as_states) == a
        assert mixed.changes_json(as_states if k % 3 else gt) == []  # the same instant the other way
        seen.update(e["name"] for e in a)
    assert seen == {"ego0", "van1", "ped1"}


def test_an_entity_table_is_the_sequence_of_its_states(make_sim) -> None:
    sim = make_sim("pedestrian_occluded", {"step_out_s": 0.3})
    run_until(sim, 0.5)
    t = sim.ground_truth().entities
    states = tuple(t)
    assert len(t) == 3 and t[-1] is t[2] is states[2] and t[0:2] == states[0:2]
    assert [e.name for e in states] == ["ego0", "van1", "ped1"] and [e.entity_id for e in states] == [0, 1, 2]
    assert states[0].x_m == float(sim.pose("ego0")[0]) and states[0].size_m == sim.world.vehicles[0].size_m
    assert t.rows_json([2, 0]) == [states[2].to_json(), states[0].to_json()]
    assert hash(t) == hash(states) and t.row_of == {"ego0": 0, "van1": 1, "ped1": 2}
    with pytest.raises(IndexError):
        t[3]


def test_reference_state_rules() -> None:
    r = RefStateRules(comfort_decel_mps2=4.0, stop_margin_m=5.0, slow_headway_s=2.0, slow_ttc_s=4.0)
    assert r.decide(gap_m=None, speed_mps=20.0) == RefState.SAFE
    # Standing obstacle at 10 m/s: stop distance 12.5 + 5 = 17.5 m; slow to 37.5 m or TTC 4 s (40 m).
    assert r.decide(gap_m=17.5, speed_mps=10.0) == RefState.STOP
    assert r.decide(gap_m=39.0, speed_mps=10.0) == RefState.SLOW
    assert r.decide(gap_m=41.0, speed_mps=10.0) == RefState.SAFE
    # The same gap behind a car doing 8 m/s: (100 - 64) / 8 + 5 = 9.5 m to stop; headway 29.5 m.
    assert r.decide(gap_m=17.5, speed_mps=10.0, obstacle_speed_mps=8.0) == RefState.SLOW
    assert r.decide(gap_m=9.0, speed_mps=10.0, obstacle_speed_mps=8.0) == RefState.STOP
    assert r.decide(gap_m=30.0, speed_mps=10.0, obstacle_speed_mps=10.0) == RefState.SAFE
    # Standing still, something within the margin: STOP.
    assert r.decide(gap_m=4.0, speed_mps=0.0) == RefState.STOP


def test_ground_truth_is_a_pure_function_of_the_steps(make_sim) -> None:
    def trace() -> list[GroundTruth]:
        sim = make_sim("cut_in")
        sim.set_control("ego0", steering_rad=0.01, throttle=0.3, brake=0.0)
        out = []
        for _ in range(20):
            run_until(sim, sim.sim_time_ns / 1e9 + 0.25)
            out.append(sim.ground_truth())
        return out

    a, b = trace(), trace()
    assert a == b
    assert np.ptp([g.entity("cutter1").y_m for g in a]) > 3.0
