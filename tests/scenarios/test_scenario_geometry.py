"""Paths, speed profiles and scripts: the closed-form geometry everything moves on
(no MuJoCo)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from hil.scenarios.motion import (
                                  LaneChange,
                                  LateralProfile,
                                  Script,
                                  SpeedChange,
                                  SpeedProfile,
                                  )
from hil.scenarios.path import Path
from hil.scenarios.road import RoadSpec, road_xml
from hil.scenarios.visibility import pixel_boxes, silhouette_area


def s_curve() -> Path:
    return Path.start(-30.0, 0.0, 0.0).line(70.0).arc(150.0, math.radians(45)).line(30.0).arc(
        150.0, -math.radians(45)).line(100.0)


def test_arc_geometry_is_exact() -> None:
    quarter = Path.start(0.0, 0.0, 0.0).arc(10.0, math.pi / 2)
    assert quarter.length_m == pytest.approx(5 * math.pi)
    x, y, h = quarter.end_pose
    assert (x, y, h) == pytest.approx((10.0, 10.0, math.pi / 2))
    # A right turn mirrors it.
    x, y, h = Path.start(0.0, 0.0, 0.0).arc(10.0, -math.pi / 2).end_pose
    assert (x, y, h) == pytest.approx((10.0, -10.0, -math.pi / 2))
    # Every point of the arc is 10 m from the centre (0, 10).
    px, py, _ = quarter.pose_at(np.linspace(0, quarter.length_m, 50))
    assert np.allclose(np.hypot(px, py - 10.0), 10.0)


def test_projection_inverts_pose_with_lateral_offsets() -> None:
    path = s_curve()
    s = np.linspace(1.0, path.length_m - 1.0, 200)
    x, y, h = path.pose_at(s)
    for lateral in (-3.0, -0.5, 0.0, 2.0):
        ps, pl = path.project(x - lateral * np.sin(h), y + lateral * np.cos(h))
        assert np.allclose(ps, s, atol=1e-6)
        assert np.allclose(pl, lateral, atol=1e-6)


def test_beyond_the_ends_the_path_runs_straight_on() -> None:
    path = Path.start(0.0, 0.0, 0.0).arc(20.0, math.pi / 2)
    ex, ey, eh = path.end_pose
    x, y, h = path.pose_at(path.length_m + 5.0)
    assert (float(x), float(y), float(h)) == pytest.approx((ex + 5 * math.cos(eh), ey + 5 * math.sin(eh), eh))
    assert float(path.project(-7.0, 0.0)[0]) == pytest.approx(-7.0)


@pytest.mark.parametrize("heading", [0.0, 0.7, -2.9])
def test_a_straight_line_poses_as_the_general_formula(heading: float) -> None:
    """One straight segment takes a shortcut (the ground truth asks an ego's lane for
    poses at every camera instant): the same values to the bit as the general formula,
    before the start too; past the end, where the formula restarts from the end pose, the
    general one."""
    line = Path.start(3.5, -20.0, heading).line(700.0)
    general = Path.start(3.5, -20.0, heading).line(700.0)
    object.__setattr__(general, "_line", None)
    rng = np.random.default_rng(3)
    for s in (rng.uniform(-50, 700, 64), np.array([0.0, 700.0, -1e-9]), rng.uniform(-50, 760, 64)):
        for fast, slow in zip(line.pose_at(s), general.pose_at(s), strict=True):
            assert fast.shape == s.shape and np.array_equal(fast, slow)


def test_offset_path_is_parallel() -> None:
    path = s_curve()
    left = path.offset(1.85)
    s = np.linspace(0.0, left.length_m, 300)
    x, y, _ = left.pose_at(s)
    _, lateral = path.project(x, y)
    assert np.allclose(lateral, 1.85, atol=1e-6)
    # The inside of the left arc is shorter, the outside of the right arc longer: they cancel.
    assert left.length_m == pytest.approx(path.length_m)


def test_speed_profile_brakes_to_a_stop() -> None:
    p = SpeedProfile(12.0, (SpeedChange(4.0, 0.0, 6.0),))
    assert float(p.speed_at(3.9)) == pytest.approx(12.0)
    assert float(p.speed_at(5.0)) == pytest.approx(6.0)
    assert float(p.speed_at(6.0)) == pytest.approx(0.0)
    assert float(p.speed_at(60.0)) == 0.0
    # 48 m cruising, then v^2 / (2 a) = 12 m braking.
    assert float(p.distance_at(100.0)) == pytest.approx(48.0 + 12.0)
    t = np.linspace(0.0, 10.0, 1001)
    d = p.distance_at(t)
    assert np.all(np.diff(d) >= 0)
    assert np.allclose(np.diff(d) / np.diff(t), (p.speed_at(t[1:]) + p.speed_at(t[:-1])) / 2, atol=1e-9)


def test_a_later_change_overrides_one_under_way() -> None:
    p = SpeedProfile(0.0, (SpeedChange(0.0, 10.0, 1.0), SpeedChange(3.0, 1.0, 2.0)))
    assert float(p.speed_at(3.0)) == pytest.approx(3.0)   # accelerating at 1 m/s^2 until 3 s
    assert float(p.speed_at(4.0)) == pytest.approx(1.0)   # then braking at 2 m/s^2 to 1 m/s
    assert float(p.speed_at(9.0)) == pytest.approx(1.0)


def test_lane_change_is_smooth_and_complete() -> None:
    lat = LateralProfile(3.7, (LaneChange(2.0, -3.7, 3.0),))
    off, rate = lat.at(np.array([0.0, 2.0, 3.5, 5.0, 9.0]))
    assert off == pytest.approx([3.7, 3.7, 1.85, 0.0, 0.0])
    assert rate[0] == rate[1] == rate[3] == 0.0 and rate[2] < 0


def test_script_velocity_matches_its_motion() -> None:
    script = Script(s_curve(), SpeedProfile(10.0, (SpeedChange(5.0, 4.0, 2.0),)), s0_m=20.0,
                    lateral=LateralProfile(0.0, (LaneChange(1.0, 3.7, 2.0),)))
    t = np.linspace(0.0, 15.0, 3001)
    st = script.state_at(t)
    dt = t[1] - t[0]
    # Central differences (off only at the kinks of the speed profile, where braking starts).
    for pos, vel in ((st.x_m, st.vx_mps), (st.y_m, st.vy_mps)):
        err = np.abs(np.gradient(pos, dt) - vel)[1:-1]
        assert np.percentile(err, 99) < 0.01 and err.max() < 0.2
    # Heading turns into the lane change, then back to the path's.
    assert st.heading_rad[500] > 0.01 and abs(st.heading_rad[-1] - float(s_curve().pose_at(
        20.0 + script.speed.distance_at(15.0))[2])) < 1e-9


def test_road_markings_follow_the_curve() -> None:
    road = RoadSpec(path=s_curve(), lanes=2, lane_width_m=3.7)
    xml = "\n".join(road_xml(road))
    assert xml.count("/edge") >= 2 * 100 // 2  # chords of at most 2 m along both arcs
    # Every dash centre lies on the lane boundary (the centre line here).
    import re

    pos = np.array([[float(v) for v in m.group(1).split()[:2]]
                    for m in re.finditer(r'name="road/dash\d+" type="box" pos="([^"]+)"', xml)])
    assert len(pos) > 30
    _, lateral = road.centre.project(pos[:, 0], pos[:, 1])
    assert np.abs(lateral).max() < 0.01  # chords sag a few mm off the arc


def test_marking_gaps_leave_the_junction_bare() -> None:
    road = RoadSpec(path=Path.straight(-100.0, 0.0, 0.0, 200.0), marking_gaps=((95.0, 105.0),))
    import re

    xml = "\n".join(road_xml(road))
    for m in re.finditer(r'name="road/(edge|dash)\d+" type="box" pos="([^ ]+) [^"]+" euler="[^"]+" size="([^ ]+)', xml):
        x, half = float(m.group(2)), float(m.group(3))
        assert x + half <= -5.0 + 1e-6 or x - half >= 5.0 - 1e-6, (m.group(0), x, half)


def test_silhouette_of_a_box_seen_square_on() -> None:
    # A 2 m x 2 m face 10 m ahead of a camera looking along world +x (MuJoCo camera:
    # looks along its -z, image up +y): f = 100 px -> a 20 x 20 px square.
    cam_mat = np.array([[0.0, 0.0, -1.0], [-1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])  # columns: cam x, y, z in world
    area, truncated = silhouette_area(np.array([11.0, 0.0, 0.0]), np.eye(3), np.array([1.0, 1.0, 1.0]),
                                      np.zeros(3), cam_mat, 100.0, 100.0, 160.0, 120.0, 320, 240)
    assert area == pytest.approx(400.0) and not truncated
    # Seen off-axis a side face shows too: the hull of all eight corners.
    area, _ = silhouette_area(np.array([11.0, 5.0, 0.0]), np.eye(3), np.ones(3), np.zeros(3), cam_mat,
                              100.0, 100.0, 160.0, 120.0, 320, 240)
    near = (100 * 6 / 10 - 100 * 4 / 10) * 20.0  # the near face, 20 x 20 px at 10 m
    assert area > near
    # A thin plate 11 m ahead, centred on the image's left border: half of it is clipped off.
    area, truncated = silhouette_area(np.array([11.0, 1.6 * 11, 0.0]), np.eye(3), np.array([1e-6, 1.0, 1.0]),
                                      np.zeros(3), cam_mat, 100.0, 100.0, 160.0, 120.0, 320, 240)
    side = 100 * 2 / 11
    assert area == pytest.approx(side * side / 2, rel=1e-4) and truncated
    # Behind the camera: nothing.
    assert silhouette_area(np.array([-11.0, 0.0, 0.0]), np.eye(3), np.ones(3), np.zeros(3), cam_mat,
                           100.0, 100.0, 160.0, 120.0, 320, 240) == (0.0, True)


def test_pixel_boxes_bound_each_entity() -> None:
    ids = np.full((6, 8), -1)
    ids[1:3, 2:5] = 0
    ids[4, 7] = 3
    assert pixel_boxes(ids, [0, 3]) == [(2, 1, 5, 3), (7, 4, 8, 5)]


def test_vehicle_bank_follows_the_same_rules_as_one_vehicle() -> None:
    from hil.scenarios.vehicle import VehicleBank, VehicleLimits, VehicleState, step_command

    lim = VehicleLimits()
    rng = np.random.default_rng(0)
    bank = VehicleBank(lim, [0.0, 5.0, 12.0])
    one = [VehicleState(speed_mps=v) for v in (0.0, 5.0, 12.0)]
    measured = np.array([0.0, 5.0, 12.0])
    for k in range(2000):
        if k % 50 == 0:  # a new command every 0.1 s, sometimes out of range
            for i in range(3):
                steer, thr, brk = rng.uniform(-1, 1), rng.uniform(-0.2, 1.2), rng.uniform(-0.2, 1.2) * (k % 150 == 0)
                bank.set_command(i, steering_rad=steer, throttle=thr, brake=brk)
                one[i].cmd_steer_rad, one[i].cmd_throttle, one[i].cmd_brake = steer, thr, brk
        v, w = bank.step(measured, 0.002)
        ref = [step_command(s, lim, measured_speed_mps=float(m), dt_s=0.002) for s, m in zip(one, measured)]
        assert np.allclose(v, [r[0] for r in ref], atol=1e-9) and np.allclose(w, [r[1] for r in ref], atol=1e-9)
        measured = v - 0.01  # a servo lagging a little behind
    assert np.ptp(v) > 0.5 and np.abs(bank.steer_rad).max() <= lim.max_steer_rad
