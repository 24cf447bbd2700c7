"""The OpenCV baseline on real simulator images: ranging, states, lane keeping and a
closed loop in-process (no transport)."""

from __future__ import annotations

import ast
import math
from collections.abc import Iterator
from dataclasses import dataclass, replace
from pathlib import Path

import cv2
import numpy as np
import pytest

from hil.adapters.wire.messages import CameraInfo, DrivingState, Frame, ImageEncoding, Inference, ObjectClass
from hil.targets import cv_baseline
from hil.targets.cv_baseline import CvBaseline

LANE_Y = -1.85  # world y of the ego lane's centre in the stopped_car scenario
CAMERA_AHEAD_OF_BUMPER_M = 0.05


@dataclass(frozen=True)
class Shot:
    rgb: np.ndarray
    camera: CameraInfo
    gap_m: float


@pytest.fixture(scope="module")
def sim_mod() -> Iterator[object]:
    from hil.scenarios.gl import select_backend

    select_backend()  # before the first import of mujoco
    from hil.scenarios import sim

    yield sim


def _world(gap_m: float, speed_mps: float = 0.0, lateral_offset_m: float = 0.0):
    from hil.scenarios import get
    from hil.scenarios.world import CameraSpec

    return get("stopped_car").build(
        params={"gap_m": gap_m, "ego_speed_mps": speed_mps, "lateral_offset_m": lateral_offset_m},
        seed=0, camera=CameraSpec(), physics_step_s=0.002)


def _camera(sim) -> CameraInfo:
    k = sim.intrinsics()
    spec = sim.world.camera
    return CameraInfo(k.fx, k.fy, k.cx, k.cy, spec.mount_height_m, spec.pitch_rad)


def _shot(sim_mod, *, gap_m: float, lateral_offset_m: float = 0.0, ego_dx_m: float = 0.0,
          ego_dy_m: float = 0.0, ego_dyaw_rad: float = 0.0) -> Shot:
    import mujoco

    with sim_mod.Simulation(_world(gap_m, lateral_offset_m=lateral_offset_m)) as sim:
        sim.data.qpos[sim.model.joint("ego0/x").qposadr[0]] = ego_dx_m
        sim.data.qpos[sim.model.joint("ego0/y").qposadr[0]] = ego_dy_m
        sim.data.qpos[sim.model.joint("ego0/yaw").qposadr[0]] = ego_dyaw_rad
        mujoco.mj_forward(sim.model, sim.data)
        rgb = sim.render("ego0").copy()
        gap = sim.ground_truth().egos[0].gap_m
        return Shot(rgb, _camera(sim), gap if gap is not None else math.inf)


def _frame(rgb: np.ndarray, camera: CameraInfo, encoding: ImageEncoding, *, speed_mps: float = 0.0,
           frame_id: int = 0) -> Frame:
    if encoding == ImageEncoding.JPEG:
        ok, buf = cv2.imencode(".jpg", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
        assert ok
        data = buf.tobytes()
    elif encoding == ImageEncoding.BGR8:
        data = np.ascontiguousarray(rgb[:, :, ::-1]).tobytes()
    else:
        data = rgb.tobytes()
    return Frame(vehicle_id=0, frame_id=frame_id, sim_time_ns=0, t0_ns=0, t_tx_ns=0, width=rgb.shape[1],
                 height=rgb.shape[0], encoding=encoding, camera=camera, ego_speed_mps=speed_mps, data=data)


# -- perception --------------------------------------------------------------


@pytest.mark.parametrize("gap_m", [15.0, 30.0, 45.0])
@pytest.mark.parametrize("lateral_offset_m", [-0.8, 0.0, 0.8])
def test_stopped_car_is_ranged_within_ten_percent(sim_mod, gap_m: float, lateral_offset_m: float) -> None:
    shot = _shot(sim_mod, gap_m=gap_m, lateral_offset_m=lateral_offset_m)
    true_x = shot.gap_m - CAMERA_AHEAD_OF_BUMPER_M
    for encoding in (ImageEncoding.RGB8, ImageEncoding.BGR8, ImageEncoding.JPEG):
        inf = CvBaseline().infer(_frame(shot.rgb, shot.camera, encoding))
        assert len(inf.objects) == 1, (encoding, inf.objects)
        obj = inf.objects[0]
        assert obj.cls == ObjectClass.VEHICLE and 0.0 < obj.confidence <= 1.0
        x0, y0, x1, y1 = obj.box_px
        assert 0 <= x0 < x1 <= 320 and 0 <= y0 < y1 <= 240
        x, y, z = obj.position_m
        assert abs(x / true_x - 1.0) < 0.10, (encoding, x, true_x)
        assert abs(y - lateral_offset_m) < 0.5, (encoding, y, lateral_offset_m)
        assert z == 0.0


@pytest.mark.parametrize("gap_m", [1.0, 3.0, 5.0])
def test_close_car_cut_by_the_image_border_means_stop(sim_mod, gap_m: float) -> None:
    # The scenario's smallest gap is 15 m: drive the ego closer by its joint. Standing
    # still, anything within the 6 m stop margin means STOP.
    shot = _shot(sim_mod, gap_m=15.0, ego_dx_m=15.0 - gap_m)
    assert shot.gap_m == pytest.approx(gap_m)
    inf = CvBaseline().infer(_frame(shot.rgb, shot.camera, ImageEncoding.JPEG, speed_mps=0.0))
    assert len(inf.objects) == 1
    x = inf.objects[0].position_m[0]
    if gap_m >= 3.0:
        assert abs(x / (gap_m - CAMERA_AHEAD_OF_BUMPER_M) - 1.0) < 0.10
    else:  # the bottom edge is out of the image: the lowest road row bounds it (2.1 m)
        assert x < 2.2
    assert inf.state == DrivingState.STOP and inf.control.brake >= 0.3
    assert inf.control.brake == 1.0 or gap_m > 4.0


def test_no_vehicle_beyond_range_or_out_of_view(sim_mod) -> None:
    # At 150 m the car is ~2.5 x 2 px, under the detection floor (area >= 8 px).
    far = _shot(sim_mod, gap_m=150.0)
    # Yawed 0.8 rad (46 deg; the half field of view is 37.6 deg) the car leaves
    # the image: road, verge, sky and markings at an angle must give nothing.
    away = _shot(sim_mod, gap_m=30.0, ego_dyaw_rad=0.8)
    for shot in (far, away):
        for encoding in (ImageEncoding.RGB8, ImageEncoding.JPEG):
            inf = CvBaseline().infer(_frame(shot.rgb, shot.camera, encoding, speed_mps=10.0))
            assert inf.objects == () and inf.state == DrivingState.SAFE


def test_other_saturated_colours_are_vehicles_and_verge_is_not(sim_mod) -> None:
    shot = _shot(sim_mod, gap_m=20.0)
    red = np.all(shot.rgb == shot.rgb[125, 160], axis=-1)  # the car's flat-lit rear face
    assert red.sum() > 200
    for paint in ((230, 200, 20), (235, 120, 20), (140, 40, 200)):  # yellow, orange, purple
        img = shot.rgb.copy()
        img[red] = paint
        inf = CvBaseline().infer(_frame(img, shot.camera, ImageEncoding.RGB8))
        assert len(inf.objects) == 1, paint
        assert abs(inf.objects[0].position_m[0] / (shot.gap_m - 0.05) - 1.0) < 0.10
    img = shot.rgb.copy()
    img[red] = (64, 115, 51)  # verge green: indistinguishable from the grass by colour
    assert CvBaseline().infer(_frame(img, shot.camera, ImageEncoding.RGB8)).objects == ()


# -- decision and longitudinal control ---------------------------------------


@pytest.mark.parametrize(("gap_m", "speed_mps", "state"), [
    (15.0, 10.0, DrivingState.STOP),   # stop distance 18.5 m
    (30.0, 10.0, DrivingState.SLOW),   # within 18.5 + 2 s * 10 m/s
    (45.0, 10.0, DrivingState.SAFE),   # 38.5 m and TTC 4.5 s: clear
    (15.0, 5.0, DrivingState.SLOW),    # stop 9.1 m, slow 19.1 m
    (30.0, 3.0, DrivingState.SAFE),
    (15.0, 0.0, DrivingState.SAFE),    # standing still, 15 m away
])
def test_driving_state_from_images(sim_mod, gap_m: float, speed_mps: float, state: DrivingState) -> None:
    shot = _shot(sim_mod, gap_m=gap_m)
    ai = CvBaseline(cruise_speed_mps=12.0)
    inf = ai.infer(_frame(shot.rgb, shot.camera, ImageEncoding.JPEG, speed_mps=speed_mps))
    assert inf.state == state
    c = inf.control
    assert 0.0 <= c.throttle <= 1.0 and 0.0 <= c.brake <= 1.0 and not (c.throttle and c.brake)
    if state == DrivingState.STOP:
        assert c.brake >= 0.3 and c.throttle == 0.0
    if state == DrivingState.SAFE:
        assert c.brake == 0.0 and c.throttle > 0.0


def test_decide_and_longitudinal_rules() -> None:
    ai = CvBaseline(cruise_speed_mps=10.0)
    assert ai.stop_distance_m(8.0) == pytest.approx(14.0)
    assert ai.decide(None, 20.0) == DrivingState.SAFE
    assert ai.decide(14.0, 8.0) == DrivingState.STOP
    assert ai.decide(29.9, 8.0) == DrivingState.SLOW   # 14 + 2 s * 8 m/s
    assert ai.decide(31.9, 8.0) == DrivingState.SLOW   # TTC under 4 s
    assert ai.decide(32.1, 8.0) == DrivingState.SAFE
    assert ai.decide(5.0, 0.0) == DrivingState.STOP
    assert ai.longitudinal(DrivingState.SAFE, None, 4.0) == (1.0, 0.0)
    assert ai.longitudinal(DrivingState.SAFE, None, 12.0) == (0.0, 0.0)
    # STOP: the deceleration needed to halt 3 m short, over 8 m/s^2, at least 0.3.
    assert ai.longitudinal(DrivingState.STOP, 20.0, 10.0) == (0.0, pytest.approx(100 / 34 / 8))
    assert ai.longitudinal(DrivingState.STOP, 8.0, 12.0) == (0.0, 1.0)
    assert ai.longitudinal(DrivingState.STOP, 6.0, 0.0) == (0.0, 0.3)   # hold when stopped
    assert ai.longitudinal(DrivingState.STOP, 3.5, 0.5) == (0.0, 1.0)
    throttle, brake = ai.longitudinal(DrivingState.SLOW, 20.0, 9.0)
    assert throttle == 0.0 and 0.0 < brake <= 1.0
    throttle, brake = ai.longitudinal(DrivingState.SLOW, 40.0, 2.0)
    assert throttle > 0.0 and brake == 0.0


# -- lane keeping ------------------------------------------------------------


@pytest.mark.parametrize(("dy_m", "dyaw_rad", "sign"), [
    (-0.6, 0.0, +1),   # right of the lane centre: steer left
    (0.6, 0.0, -1),
    (0.0, -0.05, +1),  # heading right of the lane: steer back left
    (0.0, 0.05, -1),
    (0.0, 0.0, 0),
])
def test_lane_keeping_steers_back(sim_mod, dy_m: float, dyaw_rad: float, sign: int) -> None:
    shot = _shot(sim_mod, gap_m=80.0, ego_dy_m=dy_m, ego_dyaw_rad=dyaw_rad)
    for encoding in (ImageEncoding.RGB8, ImageEncoding.JPEG):
        steer = CvBaseline().infer(_frame(shot.rgb, shot.camera, encoding, speed_mps=8.0)).control.steering_rad
        if sign == 0:
            assert abs(steer) < 0.005
        else:
            assert sign * steer > 0.01 and abs(steer) <= 0.5


def test_steering_decays_without_markings(sim_mod) -> None:
    shot = _shot(sim_mod, gap_m=80.0, ego_dy_m=-0.6)
    ai = CvBaseline()
    first = ai.infer(_frame(shot.rgb, shot.camera, ImageEncoding.RGB8, speed_mps=8.0)).control.steering_rad
    blank = np.full_like(shot.rgb, 82)  # bare road, no markings
    steers = [ai.infer(_frame(blank, shot.camera, ImageEncoding.RGB8, speed_mps=8.0)).control.steering_rad
              for _ in range(10)]
    assert first > 0.01
    assert all(0 <= b < a for a, b in zip([first, *steers], steers))
    assert steers[-1] < 0.2 * first


def test_warm_up_leaves_no_trace_in_what_the_ai_answers(sim_mod) -> None:
    """Served, the baseline runs once on noise before its HELLO (OpenCV's and numpy's
    first calls stay off the run's first frame); what it then answers is what a fresh
    one answers, frame for frame, steering filter included (the bare road first: with
    no markings the filter answers with what it held)."""
    shots = [_shot(sim_mod, gap_m=30.0, ego_dy_m=-0.6), _shot(sim_mod, gap_m=15.0, ego_dyaw_rad=0.05)]
    bare_road = _frame(np.full_like(shots[0].rgb, 82), shots[0].camera, ImageEncoding.RGB8, speed_mps=8.0)
    frames = [bare_road] + [_frame(sh.rgb, sh.camera, enc, speed_mps=8.0, frame_id=i + 1) for i, (sh, enc) in
                            enumerate((sh, enc) for sh in shots for enc in (ImageEncoding.RGB8, ImageEncoding.JPEG))]
    warmed = CvBaseline()
    warmed.warm_up()
    fresh = CvBaseline()
    assert [warmed.infer(f) for f in frames] == [fresh.infer(f) for f in frames]


# -- frames and the package rule -----------------------------------------------


def test_bad_frames_raise_value_error() -> None:
    cam = CameraInfo(200.0, 200.0, 16.0, 12.0, 1.3)
    rgb = np.zeros((24, 32, 3), np.uint8)
    short = _frame(rgb, cam, ImageEncoding.RGB8)
    short = replace(short, data=short.data[:-1])
    with pytest.raises(ValueError, match="bytes of raw pixels"):
        CvBaseline().infer(short)
    garbage = replace(short, encoding=ImageEncoding.JPEG, data=b"not a jpeg")
    with pytest.raises(ValueError, match="JPEG"):
        CvBaseline().infer(garbage)


def test_imports_only_what_the_wire_carries() -> None:
    tree = ast.parse(Path(cv_baseline.__file__).read_text())
    top: set[str] = set()
    for node in tree.body:
        if isinstance(node, ast.Import):
            top.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            top.add(node.module or "")
    assert top <= {"__future__", "argparse", "math", "sys", "collections.abc", "cv2", "numpy",
                   "hil.adapters.wire.messages"}
    every = {n.module for n in ast.walk(tree) if isinstance(n, ast.ImportFrom)}
    assert not any(m and m.split(".")[0] in ("scenarios", "harness", "timing") for m in every)


def test_main_serves_the_baseline(tmp_path: Path) -> None:
    # The real program as a child process on the local transport.
    import sys

    from hil.adapters.link import open_link
    from hil.adapters.wire.messages import Estimate
    from hil.timing.clock import MonotonicClock

    link = open_link("local", command=[sys.executable, "-m", "hil.targets.cv_baseline", "--name", "cv-test",
                                       "--cruise-speed", "7.5"],
                     vehicle_id=0, clock=MonotonicClock(), log_path=tmp_path / "t.log")
    try:
        hello = link.open(hello_timeout_s=30)
        assert hello.target_name == "cv-test"
        link.send_frame(frame_id=0, sim_time_ns=0, t0_ns=0, width=320, height=240, encoding=ImageEncoding.RGB8,
                        camera=CameraInfo(207.8, 207.8, 160.0, 120.0, 1.3), ego_speed_mps=0.0,
                        data=bytes(320 * 240 * 3))
        r = link.recv(timeout_s=10)
        while r is not None and not isinstance(r.msg, Estimate):
            r = link.recv(timeout_s=10)
        assert r is not None, (tmp_path / "t.log").read_text()
        # Standing still with a clear road: the baseline accelerates towards 7.5 m/s.
        assert r.msg.frame_id == 0 and r.msg.control.throttle > 0
    finally:
        link.close()


def test_main_started_by_hand_says_why(monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    monkeypatch.delenv("HIL_LOCAL_FD", raising=False)
    assert cv_baseline.main([]) == 2
    err = capsys.readouterr().err
    assert err.startswith("python -m hil.targets.cv_baseline: HIL_LOCAL_FD is not set") and err.count("\n") == 1, err


# -- closed loop -----------------------------------------------------------------


@dataclass(frozen=True)
class LoopResult:
    final_gap_m: float
    final_speed_mps: float
    max_lateral_dev_m: float
    final_lateral_dev_m: float
    collisions: int
    states: tuple[DrivingState, ...]


def run_closed_loop(sim_mod, *, gap_m: float = 45.0, speed_mps: float = 8.0, duration_s: float = 15.0,
                    steps_per_frame: int = 25, encoding: ImageEncoding = ImageEncoding.JPEG,
                    start_dy_m: float = 0.0) -> LoopResult:
    """Render every ``steps_per_frame`` physics steps, infer, apply the control;
    the ego starts ``start_dy_m`` left of its lane centre."""
    import mujoco

    ai = CvBaseline()
    states: list[DrivingState] = []
    collisions = 0
    max_dev = 0.0
    with sim_mod.Simulation(_world(gap_m, speed_mps)) as sim:
        sim.data.qpos[sim.model.joint("ego0/y").qposadr[0]] = start_dy_m
        mujoco.mj_forward(sim.model, sim.data)
        cam = _camera(sim)
        n_steps = round(duration_s / sim.world.physics_step_s)
        for k in range(n_steps):
            if k % steps_per_frame == 0:
                rgb = sim.render("ego0")
                inf: Inference = ai.infer(_frame(rgb, cam, encoding, speed_mps=sim.speed_mps("ego0"),
                                                 frame_id=k // steps_per_frame))
                c = inf.control
                sim.set_control("ego0", steering_rad=c.steering_rad, throttle=c.throttle, brake=c.brake)
                states.append(inf.state)
                collisions += len(sim.ground_truth().collisions)
                max_dev = max(max_dev, abs(sim.pose("ego0")[1] - LANE_Y))
            sim.step()
        truth = sim.ground_truth()
        collisions += len(truth.collisions)
        return LoopResult(truth.egos[0].gap_m or math.inf, sim.speed_mps("ego0"), max_dev,
                          abs(sim.pose("ego0")[1] - LANE_Y), collisions, tuple(states))


@pytest.mark.slow
def test_closed_loop_stops_behind_the_car_in_lane(sim_mod) -> None:
    r = run_closed_loop(sim_mod)
    assert r.collisions == 0
    assert r.final_speed_mps < 0.3
    assert 1.0 <= r.final_gap_m <= 12.0
    assert r.max_lateral_dev_m < 0.5
    assert r.states[0] == DrivingState.SAFE and r.states[-1] == DrivingState.STOP


@pytest.mark.slow
def test_closed_loop_returns_to_the_lane_centre(sim_mod) -> None:
    r = run_closed_loop(sim_mod, gap_m=150.0, speed_mps=10.0, duration_s=6.0, start_dy_m=-0.6)
    assert r.collisions == 0
    assert r.final_lateral_dev_m < 0.1
    assert r.max_lateral_dev_m < 0.65  # no overshoot past the start
