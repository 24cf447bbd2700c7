"""A camera rig in the recording and the report (issue 31): every camera's images on
its own topic, its calibration and its mount on ``/tf`` as MuJoCo renders it, and the
report's per-camera table agreeing with ``summary.json``."""

from __future__ import annotations

import math
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from hil.harness.config.loading import dump_config, parse_config
from hil.harness.record.foxglove_out import optical_quaternion
from hil.harness.record.rig_views import optical_axes, quaternion, rig_views
from hil.harness.record.run_folder import read_run
from hil.harness.report.run_report import write_report
from hil.harness.run.driver import RunResult, build_world, execute, prepare_out_dir
from hil.scenarios.world import camera_name
from tests.conftest import GL_BACKEND, read_mcap

SURROUND = ("front", "front_left", "front_right", "back", "back_left", "back_right")


def _matrix(q: dict[str, float]) -> np.ndarray:
    x, y, z, w = q["x"], q["y"], q["z"], q["w"]
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def test_each_cameras_tf_is_the_orientation_mujoco_renders_it_with() -> None:
    from hil.scenarios.sim import Simulation

    cfg = parse_config({"camera": {"rig": [
        {"name": "front", "yaw_deg": 20, "pitch_deg": 5},
        {"name": "back", "forward_m": -2.0, "yaw_deg": 180, "pitch_deg": 10},
        {"name": "side", "lateral_m": 0.8, "yaw_deg": 90, "pitch_deg": -4, "roll_deg": 30}]}})
    views = rig_views(dump_config(cfg)["camera"])
    assert views is not None and [c.name for c in views] == [None, "back", "side"]
    ts = {"sec": 0, "nsec": 0}
    world, _ = build_world(cfg)
    with Simulation(world) as sim:
        body = sim.model.body("ego0").id
        r_body = sim.data.xmat[body].reshape(3, 3)
        for k, view in enumerate(views):
            cam = sim.model.camera(camera_name("ego0", k)).id
            mj = r_body.T @ sim.data.cam_xmat[cam].reshape(3, 3)  # MuJoCo: x right, y up, looks along -z
            optical = np.column_stack([mj[:, 0], -mj[:, 1], -mj[:, 2]])
            tfs = view.transforms("ego0", ts)
            rot = np.eye(3)
            for tf in tfs:  # the chain from the vehicle to the optical frame
                rot = rot @ _matrix(tf["rotation"])
            assert tfs[-1]["child_frame_id"] == ("ego0/camera" if k == 0 else f"ego0/camera/{view.name}")
            np.testing.assert_allclose(rot, optical, atol=1e-5)
            offset = sum(np.array([tf["translation"][a] for a in "xyz"]) for tf in tfs)  # a turn about z only, before
            np.testing.assert_allclose(offset, sim.model.cam_pos[cam], atol=1e-3)


def test_the_quaternion_of_an_unturned_camera_is_the_single_cameras() -> None:
    for pitch in (-0.5, 0.0, 0.2):
        assert quaternion(optical_axes(0.0, pitch)) == pytest.approx(optical_quaternion(pitch))
    assert rig_views({"rig": "front", "width": 320, "height": 240, "fovy_deg": 60}) is None


@pytest.fixture(scope="module")
def surround(tmp_path_factory: pytest.TempPathFactory) -> tuple[RunResult, dict[str, list[Any]]]:
    cfg = {"mode": "lockstep", "duration_s": 1.0, "progress": False, "seed": 3, "detector": {"enabled": False},
           "camera": {"rig": "surround6", "fps": 10, "width": 96, "height": 64},
           "target": {"command": [sys.executable, "-m", "hil.targets.echo", "--cameras", "set"]}}
    r = execute(parse_config(cfg), out_dir=prepare_out_dir(tmp_path_factory.mktemp("rig") / "run"),
                gl_backend=GL_BACKEND, install_signal_handlers=False)
    return r, read_mcap(r.mcap_path)


def test_every_rig_camera_is_recorded_on_its_own_topic_with_its_calibration(surround: Any) -> None:
    _r, m = surround
    topics = ["/ego0/camera"] + [f"/ego0/camera/{n}" for n in SURROUND[1:]]
    stamps = []
    for k, topic in enumerate(topics):
        images = m[topic]
        assert len(images) == 10, topic
        assert {d["frame_id"] for _, d in images} == {topic[1:]}  # its own optical frame
        stamps.append(sorted(msg.publish_time for msg, _ in images))
    # One trigger line in lockstep: each camera's k-th image is the k-th frame set's,
    # captured at the same sim instant; its t0 (render done) is its own.
    recs = [d for _, d in m["/ego0/pipeline"]]
    for k in range(6):
        assert stamps[k] == sorted(d["t0_ns"] for d in recs if d["camera"] == k)
    for k, name in enumerate(SURROUND):
        topic = "/ego0/camera_info" + (f"/{name}" if k else "")
        calib = [d for _, d in m[topic]]
        assert calib and {d["frame_id"] for d in calib} == {"ego0/camera" + (f"/{name}" if k else "")}
        fy = calib[0]["K"][4]
        fovy = 2 * math.degrees(math.atan(32 / fy))
        assert fovy == pytest.approx(90.0 if name == "back" else 60.0)  # surround6's back camera is wider
    children = {d["child_frame_id"] for _, d in m["/tf"]}
    assert {"ego0/camera_ground", "ego0/camera"} | {f"ego0/camera/{n}" for n in SURROUND[1:]} <= children


def test_the_report_has_the_rig_table_agreeing_with_the_summary(surround: Any) -> None:
    r, _m = surround
    run = read_run(r.out_dir)
    assert run.vehicles == ["ego0"] and len(run.camera_times["ego0"]) == 10  # camera 0's images
    html = write_report(r.out_dir).read_text()
    v = r.summary["vehicles"]["ego0"]
    assert "<h4>Camera rig</h4>" in html
    for name, c in v["cameras"].items():
        row = (f"<tr><td>{name}</td><td class=n>{c['frames']}</td><td class=n>{c['late_frames']}</td>"
               f"<td class=n>{c['missing_in_sets']}</td><td class=n>{c['render_p50_ms']:.3f}</td>")
        assert row in html, name
    rig = v["rig"]
    assert rig["sets"] == 10 == rig["complete"]
    assert f"<tr><th>frame sets</th><td>{rig['sets']}</td></tr>" in html
    assert f"<td>{rig['e2e_from_last_capture_ms_p50']:.3f}</td>" in html


def test_the_shipped_rig_layout_is_current_and_names_topics_the_rig_run_writes(surround: Any) -> None:
    pytest.importorskip("foxglove.layouts")
    import json
    import re

    from hil.harness.record.foxglove_layout import build_layout

    _r, m = surround
    root = Path(__file__).resolve().parents[3]
    shipped = json.loads((root / "hil_configs" / "foxglove_layout_surround6.json").read_text())
    assert shipped == json.loads(build_layout(["ego0"], rig_cameras=SURROUND[1:])), (
        "regenerate: python -m hil.harness.record.foxglove_layout --rig surround6 ego0")
    named = set(re.findall(r'"(/[a-z0-9_/]+?)(?:\.[a-z_.]+)?"', json.dumps(shipped)))
    assert {f"/ego0/camera/{n}" for n in SURROUND[1:]} <= named
    assert named - {"/log"} <= set(m), named - set(m)  # /log: the clean run has no event
