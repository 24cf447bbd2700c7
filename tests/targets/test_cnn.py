"""The CNN target's parts: ranging from boxes, decisions and overrides, commands,
nets and weights, and the rule that it sees only what the wire carries."""

from __future__ import annotations

import ast
import json
import math
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from hil.adapters.wire.messages import (CameraInfo, DetectedObject, DrivingState, Frame, ImageEncoding,  # noqa: E402
                                        ObjectClass)
from hil.targets.cnn import commands, geometry, models  # noqa: E402
from hil.targets.cnn.cli import main  # noqa: E402
from hil.targets.cnn.decision import Policy, decide, in_path, path_y  # noqa: E402
from hil.targets.cnn.target import CnnTarget  # noqa: E402
from hil.targets.cv_baseline import CvBaseline  # noqa: E402

CAM = CameraInfo(207.846, 207.846, 160.0, 120.0, 1.3, 0.0)  # 320 x 240, 60 deg, 1.3 m
PKG = Path(models.__file__).resolve().parent


def _project_box(x_m: float, y_m: float, w_m: float, h_m: float, bottom_m: float) -> tuple[float, ...]:
    """Box (px) of a camera-facing rectangle ``x_m`` ahead, centred ``y_m`` left."""
    u0 = CAM.cx - (y_m + w_m / 2) * CAM.fx / x_m
    u1 = CAM.cx - (y_m - w_m / 2) * CAM.fx / x_m
    v_top = CAM.cy + (CAM.mount_height_m - bottom_m - h_m) * CAM.fy / x_m
    v_bot = CAM.cy + (CAM.mount_height_m - bottom_m) * CAM.fy / x_m
    return (u0, v_top, u1, v_bot)


def _frame(rgb: np.ndarray, *, speed_mps: float = 8.0, frame_id: int = 0) -> Frame:
    return Frame(0, frame_id, 0, 0, 0, rgb.shape[1], rgb.shape[0], ImageEncoding.RGB8, CAM, speed_mps,
                 rgb.tobytes())


def _road(height: int = 240, width: int = 320) -> np.ndarray:
    img = np.empty((height, width, 3), np.uint8)
    img[: height // 2] = (170, 200, 235)
    img[height // 2:] = (82, 82, 87)
    return img


# -- position from a box -----------------------------------------------------------


@pytest.mark.parametrize("cls,w,h,bottom", [(ObjectClass.VEHICLE, 1.8, 1.4, 0.1),
                                            (ObjectClass.PEDESTRIAN, 0.5, 1.75, 0.0),
                                            (ObjectClass.OBSTACLE, 0.7, 0.7, 0.0)])
@pytest.mark.parametrize("x_m,y_m", [(8.0, 0.0), (20.0, -1.0), (40.0, 2.0)])
def test_position_from_a_prior_sized_box(cls, w, h, bottom, x_m, y_m):
    pos = geometry.estimate_position(_project_box(x_m, y_m, w, h, bottom), cls, CAM, 320, 240)
    assert pos is not None
    assert pos[0] == pytest.approx(x_m, rel=0.02) and pos[1] == pytest.approx(y_m, abs=0.05) and pos[2] == 0.0


def test_ground_contact_wins_when_the_size_is_off():
    # A van 2 m wide and 2.3 m tall, and a 0.4 m obstacle: the size priors are off, the
    # bottom edge is not (the height alone would say 7.3 m for the van, 21 m for the obstacle).
    van = geometry.estimate_position(_project_box(12.0, 0.0, 2.0, 2.3, 0.1), ObjectClass.VEHICLE, CAM, 320, 240)
    small = geometry.estimate_position(_project_box(12.0, 0.0, 0.4, 0.4, 0.0), ObjectClass.OBSTACLE, CAM, 320, 240)
    assert van is not None and small is not None
    assert abs(van[0] / 12.0 - 1) < 0.1 and abs(small[0] / 12.0 - 1) < 0.05


def test_box_cut_by_the_bottom_border_is_no_farther_than_the_lowest_road_row():
    pos = geometry.estimate_position((60.0, 90.0, 260.0, 240.0), ObjectClass.VEHICLE, CAM, 320, 240)
    assert pos is not None and pos[0] <= geometry.ground_x(CAM, 240.0, 0.1) + 1e-9
    assert geometry.estimate_position((10.0, 5.0, 5.0, 30.0), ObjectClass.VEHICLE, CAM, 320, 240) is None


# -- decision --------------------------------------------------------------------------


def _obj(x: float, y: float, cls: ObjectClass = ObjectClass.VEHICLE) -> DetectedObject:
    return DetectedObject(cls, 0.9, (0.0, 0.0, 1.0, 1.0), (x, y, 0.0))


def test_path_follows_the_steering_and_widens_for_pedestrians():
    p = Policy()
    assert path_y(20.0, 0.0) == 0.0 and path_y(20.0, 0.05) > 0.0 > path_y(20.0, -0.05)
    assert in_path(_obj(20.0, 1.8), 0.0, p) and not in_path(_obj(20.0, 2.0), 0.0, p)
    assert not in_path(_obj(20.0, 1.6, ObjectClass.OBSTACLE), 0.0, p)
    assert in_path(_obj(20.0, 1.6, ObjectClass.PEDESTRIAN), 0.0, p)
    # A car in the lane on a left bend sits left of straight ahead: in the path when steering left.
    bend = path_y(30.0, 0.03)
    assert in_path(_obj(30.0, bend), 0.03, p) and not in_path(_obj(30.0, bend), -0.03, p)


def test_the_rules_are_the_baselines():
    rules, p = CvBaseline(), Policy()
    for d, v in ((14.0, 8.0), (29.9, 8.0), (32.1, 8.0), (None, 5.0), (5.0, 0.0)):
        got = decide(rules, p, distance_m=d, uncertain_m=None, speed_mps=v, steering_low_confidence=False)
        assert got.state == rules.decide(d, v)
        assert (got.throttle, got.brake) == rules.longitudinal(got.state, d, v)


def test_uncertain_detection_slows_down_but_never_stops():
    rules, p = CvBaseline(), Policy()
    slow = decide(rules, p, distance_m=None, uncertain_m=10.0, speed_mps=8.0, steering_low_confidence=False)
    assert slow.state == DrivingState.SLOW and slow.brake > 0 and slow.distance_m == 10.0
    far = decide(rules, p, distance_m=None, uncertain_m=80.0, speed_mps=8.0, steering_low_confidence=False)
    assert far.state == DrivingState.SAFE  # too far away to matter
    stop = decide(rules, p, distance_m=8.0, uncertain_m=5.0, speed_mps=8.0, steering_low_confidence=False)
    assert stop.state == DrivingState.STOP


def test_unsure_steering_slows_to_the_low_confidence_speed():
    rules, p = CvBaseline(cruise_speed_mps=10.0), Policy()
    fast = decide(rules, p, distance_m=None, uncertain_m=None, speed_mps=8.0, steering_low_confidence=True)
    assert fast.state == DrivingState.SLOW and fast.throttle == 0.0 and fast.brake == pytest.approx(0.25 * 4.0)
    slow = decide(rules, p, distance_m=None, uncertain_m=None, speed_mps=2.0, steering_low_confidence=True)
    assert slow.state == DrivingState.SLOW and slow.throttle == pytest.approx(0.6) and slow.brake == 0.0


def test_policy_checks_its_thresholds():
    with pytest.raises(ValueError, match="det_uncertain"):
        Policy(det_confidence=0.2, det_uncertain=0.3)


# -- commands --------------------------------------------------------------------------


def test_command_parsing():
    assert commands.parse("swap detector cv") == commands.Swap("detector", "cv")
    assert commands.parse("  SWAP steering CNN ") == commands.Swap("steering", "cnn")
    assert commands.parse("status") == commands.Status()
    for bad, word in (("swap lidar cv", "slot"), ("swap detector yolo", "model"), ("reboot", "unknown command")):
        with pytest.raises(commands.CommandError, match=word):
            commands.parse(bad)


# -- nets and weights ------------------------------------------------------------------


def test_shipped_weights_are_small_and_documented():
    wdir = models.WEIGHTS_DIR
    total = sum(f.stat().st_size for f in wdir.iterdir() if f.is_file())
    assert total <= 5 * 1024 * 1024, total
    card = (wdir / "MODEL_CARD.md").read_text()
    metrics = json.loads((wdir / "metrics.json").read_text())
    for word in ("Data", "Training", "Metrics", "AP50", "Steering error"):
        assert word in card
    assert metrics["seed"] == 0 and metrics["detector"]["map50"] >= 0.8


def test_loading_checks_files(tmp_path):
    with pytest.raises(FileNotFoundError, match="hil train"):
        models.load("detector", tmp_path / "none.pt")
    torch.save({"something": torch.zeros(3)}, tmp_path / "bad.pt")
    with pytest.raises(ValueError, match="not a detector weights file"):
        models.load("detector", tmp_path / "bad.pt")
    models.save(models.SteeringNet(), tmp_path / "steer.pt", {})
    with pytest.raises(ValueError, match="do not fit"):
        models.load("detector", tmp_path / "steer.pt")
    with pytest.raises(ValueError, match="kind"):
        models.load("lidar")


def test_batchnorm_folding_keeps_the_outputs():
    torch.manual_seed(0)
    net = models.Detector()
    for m in net.modules():  # non-trivial statistics
        if isinstance(m, torch.nn.BatchNorm2d):
            m.running_mean.uniform_(-0.5, 0.5)
            m.running_var.uniform_(0.5, 2.0)
    net.eval()
    x = torch.rand(2, 3, 120, 160) * 255
    with torch.no_grad():
        before = net(x)
        after = models.fold_batchnorm(net)(x)
    assert not any(isinstance(m, torch.nn.BatchNorm2d) for m in net.modules())
    assert torch.allclose(before, after, atol=1e-4)


def test_decode_keeps_peaks_above_the_threshold_and_drops_duplicates():
    out = torch.full((7, 30, 40), -10.0)
    out[3:5] = math.log(16.0)  # 16 x 16 px boxes
    out[5:7] = 0.5
    out[0, 10, 20] = 3.0   # vehicle, 0.95
    out[0, 10, 21] = 2.0   # its neighbour: not a local maximum
    out[1, 10, 21] = 2.5   # a pedestrian 4 px to the right: IoU 0.6 with the vehicle, dropped
    out[2, 25, 5] = -1.0   # obstacle, 0.27
    dets = models.decode(out, threshold=0.25)
    assert [(d.cls, round(d.confidence, 2)) for d in dets] == [(0, 0.95), (2, 0.27)]
    assert dets[0].box == pytest.approx((74.0, 34.0, 90.0, 50.0))
    assert models.decode(out, threshold=0.5)[-1].cls == 0


# -- the target --------------------------------------------------------------------------


@pytest.fixture(scope="module")
def target() -> CnnTarget:
    torch.set_num_threads(1)
    return CnnTarget()


def test_empty_road_is_safe_and_every_output_is_valid(target):
    inf = target.infer(_frame(_road()))
    c = inf.control
    assert inf.state == DrivingState.SAFE and inf.objects == ()
    assert abs(c.steering_rad) <= 0.5 and 0 <= c.throttle <= 1 and c.brake == 0.0


def test_models_swap_and_status(target):
    assert target.command("swap detector cv").startswith("ok detector=cv steering=cnn")
    assert target.command("swap steering cv").startswith("ok detector=cv steering=cv")
    runs = target.stats.baseline_runs
    target.infer(_frame(_road(), frame_id=7))
    assert target.stats.baseline_runs == runs + 1  # one baseline run serves both slots
    reply = target.command("swap detector cnn")
    assert reply.endswith("after_frame=7")
    target.command("swap steering cnn")
    status = target.command("status")
    assert status.startswith("ok detector=cnn steering=cnn") and "total_p50_ms=" in status
    assert target.command("swap detector yolo").startswith("error: unknown model")


def test_low_confidence_falls_back_and_is_counted(target):
    unsure = CnnTarget(policy=Policy(steer_error_max_rad=1e-9, det_confidence=1.0, det_uncertain=1e-3))
    frame = _frame(_road(), speed_mps=8.0)
    inf = unsure.infer(frame)
    assert unsure.stats.steering_low_confidence == 1 and unsure.stats.baseline_runs == 1
    assert inf.state == DrivingState.SLOW and inf.control.brake > 0  # slowing towards 4 m/s
    assert inf.control.steering_rad == CvBaseline().infer(frame).control.steering_rad


def test_bad_model_names_and_frames(target):
    with pytest.raises(ValueError, match="unknown model"):
        CnnTarget(detector="yolo")
    short = replace(_frame(_road()), data=b"\0" * 10)
    with pytest.raises(Exception):
        target.infer(short)


def test_main_started_by_hand_says_why(monkeypatch, capsys):
    monkeypatch.delenv("HIL_LOCAL_FD", raising=False)
    assert main(["--threads", "1"]) == 2
    assert "cnn: HIL_LOCAL_FD" in capsys.readouterr().err
    assert main(["--weights", "/nonexistent"]) == 2
    assert "hil train" in capsys.readouterr().err


# -- it sees only what the wire carries ---------------------------------------------------


def test_imports_only_what_the_wire_carries():
    for path in sorted(PKG.glob("*.py")):
        tree = ast.parse(path.read_text())
        mods = {a.name for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names}
        mods |= {n.module or "" for n in ast.walk(tree) if isinstance(n, ast.ImportFrom)}
        roots = {m.removeprefix("hil.").split(".")[0] for m in mods}  # hil.adapters.x -> adapters
        assert not roots & {"scenarios", "harness", "mujoco", "urllib", "requests", "http", "socket"}, path
        # The decode pool's worker processes, pipes and shared memory (never a socket),
        # and torchvision's GPU JPEG decoder where it imports.
        pool = {"os", "mmap", "select", "signal", "statistics", "struct", "subprocess", "concurrent", "torchvision"}
        assert roots <= {"__future__", "argparse", "math", "sys", "threading", "time", "collections",
                         "dataclasses", "pathlib", "typing", "cv2", "numpy", "torch", "adapters", "targets", "common",
                         *pool}, (path, roots)
        assert "hub" not in path.read_text().replace("github", ""), path  # no torch.hub downloads


def test_serving_loads_nothing_of_the_simulator_or_the_harness():
    code = ("import sys; from hil.targets.cnn.target import CnnTarget; CnnTarget(); "
            "bad = [m for m in sys.modules if m.split('.')[0] in ('scenarios', 'harness', 'mujoco')]; "
            "print(bad); sys.exit(1 if bad else 0)")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stdout + proc.stderr
