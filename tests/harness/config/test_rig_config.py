"""``camera.rig``: presets, a list of cameras, and one-line errors naming the field."""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from hil.common.errors import ConfigError
from hil.harness.config.loading import dump_config, load_config, parse_config
from hil.harness.run.driver import build_world
from hil.scenarios.world import build_mjcf
from tests.harness.cli.test_cli import assert_one_line_error, hil


def test_the_default_rig_is_the_camera_sections_one_camera_and_builds_the_same_world() -> None:
    cfg = parse_config({"camera": {"mount_height_m": 1.5, "pitch_deg": 3, "fovy_deg": 50}})
    (front,) = cfg.camera.cameras()
    assert cfg.camera.rig == "front" and cfg.rig_offset_steps == (0,)
    assert (front.height_m, front.pitch_deg, front.fovy_deg, front.width) == (1.5, 3.0, 50.0, 320)
    world, _ = build_world(cfg)
    assert world.camera.rig == ()  # no rig: the world of before rigs, byte for byte
    xml = build_mjcf(world)
    assert xml.count("<camera ") == 1 and 'name="ego0/camera"' in xml


def test_thresholds_for_a_vehicle_the_run_has_not_are_refused() -> None:
    # `timing.vehicles: {eg0: ...}` ran with the defaults for ego0 (README walkthrough).
    build_world(parse_config({"timing": {"vehicles": {"ego0": {"jitter_ms": 5}}}}))
    with pytest.raises(ConfigError, match=r"timing.vehicles.eg0: no such vehicle in this run \(its vehicles: ego0\)"):
        build_world(parse_config({"timing": {"vehicles": {"eg0": {"jitter_ms": 5}}}}))


def test_surround6_is_six_named_cameras_around_the_car() -> None:
    cfg = parse_config({"camera": {"rig": "surround6"}})
    cams = cfg.camera.cameras()
    assert [c.name for c in cams] == ["front", "front_left", "front_right", "back", "back_left", "back_right"]
    assert [c.yaw_deg for c in cams] == [0, 55, -55, 180, 110, -110]
    assert cams[3].fovy_deg > cams[0].fovy_deg  # the back camera is the wide one, as nuScenes'
    world, _ = build_world(cfg)
    xml = build_mjcf(world)
    assert xml.count("<camera ") == 6 and 'name="ego0/camera5"' in xml
    assert len(parse_config({"camera": {"rig": "front3"}}).camera.cameras()) == 3


def test_a_listed_rig_keeps_each_cameras_mount_size_and_offset() -> None:
    cfg = parse_config({"physics_step_s": 0.002, "camera": {"fps": 10, "rig": [
        {"name": "a"}, {"name": "b", "width": 160, "height": 120, "roll_deg": 90, "yaw_deg": 90, "offset_ms": 4}]}})
    a, b = cfg.camera.cameras()
    assert (a.width, b.width, b.height) == (320, 160, 120)
    assert cfg.rig_offset_steps == (0, 2)
    world, _ = build_world(cfg)
    assert world.camera.rig[1].roll_rad == pytest.approx(math.pi / 2)
    assert 'name="ego0/camera1"' in build_mjcf(world)
    assert dump_config(cfg)["camera"]["rig"][1]["offset_ms"] == 4.0


@pytest.mark.parametrize("rig,field,words", [
    ("foo", "camera.rig", "preset"),
    ([], "camera.rig", "1 to 32"),
    ([{"name": "a"}, {"name": "a"}], "camera.rig[1].name", "no other camera"),
    ([{"name": "a", "yaw_deg": 900}], "camera.rig[0].yaw_deg", "180"),
    ([{"name": "a"}, {"name": "b", "offset_ms": 3}], "camera.rig[1].offset_ms", "physics steps"),
    ([{"name": "a"}, {"name": "b", "offset_ms": 100}], "camera.rig[1].offset_ms", "camera period"),
    ([{"name": "a", "offset_ms": 4}, {"name": "b", "offset_ms": 2}], "camera.rig[1].offset_ms", "do not decrease"),
])
def test_a_bad_rig_is_one_line_naming_the_field(rig: object, field: str, words: str) -> None:
    with pytest.raises(ConfigError) as info:
        parse_config({"camera": {"fps": 10, "rig": rig}}, source="run.yaml")
    msg = str(info.value)
    assert "\n" not in msg and f"at {field}:" in msg and words in msg, msg


def test_a_dropped_camera_must_be_one_of_the_rig() -> None:
    with pytest.raises(ConfigError, match=r"engine\.faults\.drop_camera.*front, front_left"):
        parse_config({"camera": {"rig": "front3"}, "engine": {"faults": {"drop_camera": "back"}}})


def test_hil_run_refuses_a_bad_rig_with_exit_2(tmp_path: Path) -> None:
    cfg = tmp_path / "c.yaml"
    cfg.write_text("camera:\n  rig: [{name: a}, {name: a}]\n")
    assert_one_line_error(hil("run", str(cfg)), "camera.rig[1].name", "c.yaml")


def test_load_config_reads_a_rig_from_yaml(tmp_path: Path) -> None:
    p = tmp_path / "r.yaml"
    p.write_text("camera:\n  rig:\n    - {name: front}\n    - {name: back, yaw_deg: 180}\n")
    assert [c.name for c in load_config(p).camera.cameras()] == ["front", "back"]
