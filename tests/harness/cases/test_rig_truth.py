"""Ground truth per camera of a rig (issue 31): every camera's visible boxes, the
detector judging a fused frame set against what any of its cameras showed, in the
rig's vehicle frame (PROTOCOL.md 4.3), and each camera's annotations in the
recording.

The world: ``cut_in`` with both cars standing (seed 0: the other car's speed draws
0), the other car behind the ego in the left lane, where surround6's back cameras
see it and its front camera does not.
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

import pytest

from hil.harness.config.loading import parse_config
from hil.harness.run.driver import RunResult, build_world, execute, prepare_out_dir
from tests.conftest import GL_BACKEND, read_mcap

SCENARIO = {"name": "cut_in", "params": {"ego_speed_mps": 0.0, "npc_speed_mps": 0.0, "start_ahead_m": -12.0,
                                         "cut_in_at_s": 20.0}}
BACK = 3  # surround6's back camera


def config(*target: str, **over: Any) -> dict[str, Any]:
    return {"mode": "lockstep", "duration_s": 1.0, "progress": False, "seed": 0, "scenario": SCENARIO,
            "camera": {"rig": "surround6", "fps": 10, "width": 160, "height": 120},
            "recording": {"images": False},
            "target": {"command": [sys.executable, "-m", "hil.targets.echo", "--cameras", "set", *target]}, **over}


def run(tmp: Path, *target: str) -> tuple[RunResult, dict[str, list[Any]]]:
    r = execute(parse_config(config(*target)), out_dir=prepare_out_dir(tmp / "run"), gl_backend=GL_BACKEND,
                install_signal_handlers=False)
    return r, read_mcap(r.mcap_path)


def behind_in_vehicle_frame() -> tuple[float, float]:
    """The other car's nearest face (its front right corner here) in the rig's vehicle
    frame: on the road under camera 0's mount, the vehicle's axes; both cars stand
    still and straight, so this is a corner of its footprint less the mount."""
    from hil.scenarios.sim import Simulation

    cfg = parse_config(config())
    world, _ = build_world(cfg)
    front = cfg.camera.cameras()[0]
    with Simulation(world) as sim:
        (ex, ey, eyaw), (cx, cy, cyaw) = sim.pose("ego0"), sim.pose("cutter1")
        length, width, _ = next(v.size_m for v in world.vehicles if v.name == "cutter1")
    assert eyaw == cyaw == 0.0 and front.yaw_deg == 0.0
    return cx + length / 2 - (ex + front.forward_m), cy - width / 2 - (ey + front.lateral_m)


@pytest.fixture(scope="module")
def seen(tmp_path_factory: pytest.TempPathFactory) -> tuple[RunResult, dict[str, list[Any]]]:
    x, y = behind_in_vehicle_frame()
    return run(tmp_path_factory.mktemp("seen"), "--object", f"vehicle:{x:.3f}:{y:.3f}:{BACK}")


def test_each_camera_has_its_own_truth_and_only_the_back_ones_see_the_car_behind(seen: Any) -> None:
    _r, m = seen
    front = [d for _, d in m["/ego0/truth"]]
    back = [d for _, d in m["/ego0/truth/back"]]
    assert len(front) == len(back) == 10
    assert not any(d["boxes"] for d in front)  # camera 0 (front) does not see it
    assert all([b["entity"] for b in d["boxes"]] == ["cutter1"] for d in back)
    assert {d["frame_id"] % 6 for d in back} == {BACK}  # the frame's own id: set id + camera
    assert all(b["path_s_m"] < 0 for d in back for b in d["boxes"])  # behind the ego's front
    assert {"/ego0/truth/front_left", "/ego0/truth/back_left", "/ego0/truth/back_right"} <= set(m)


def test_an_object_only_the_back_camera_sees_reported_where_it_is_is_no_mismatch(seen: Any) -> None:
    r, m = seen
    v = r.summary["vehicles"]["ego0"]
    assert v["estimates_applied"] == 60  # each frame of the ten sets
    assert v["mismatches"] == {}, v["mismatches"]
    assert not [d for _, d in m.get("/events", []) if d["kind"].startswith("mismatch.")]


def test_each_cameras_annotations_draw_its_own_truth_and_the_ai_boxes_in_it(seen: Any) -> None:
    _r, m = seen
    green = {"r": 0.15, "g": 0.95, "b": 0.25, "a": 1.0}
    back = [d for _, d in m["/ego0/annotations/back"]]
    assert len(back) == 10
    for d in back:  # the true box of the car behind, and the AI's (its object names camera 3)
        assert [p["outline_color"] == green for p in d["points"]] == [True, False]
    assert not any(d["points"] for _, d in m["/ego0/annotations"])  # camera 0: no truth, no AI box in it
    assert len(m["/ego0/annotations/front_left"]) == 10
    assert all(d["points"] and all(p["outline_color"] == green for p in d["points"])
               for _, d in m["/ego0/annotations/back_left"])  # it sees the car too; the AI named camera 3


def test_leaving_out_what_only_the_back_camera_sees_is_one_missed_object(tmp_path: Path) -> None:
    r, m = run(tmp_path, "--object", "pedestrian:60:0")  # sees nothing near: a far ghost only
    missed = [d for _, d in m["/events"] if d["kind"] == "mismatch.missed_object"]
    assert [(d["entity"], d["cause"]) for d in missed] == [("cutter1", "perception")]
    assert r.summary["vehicles"]["ego0"]["mismatches"]["missed_object/perception"] == 1
