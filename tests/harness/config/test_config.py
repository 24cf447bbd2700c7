"""hil.harness.config.model: loading, overrides, one-line errors, canonical hash."""

from __future__ import annotations

import hashlib
import json
import re
from pathlib import Path

import pydantic
import pytest

from hil.harness.config.loading import config_hash, dump_config, load_config, parse_config
from hil.harness.config.model import Encoding, Mode, RunConfig, Transport
from hil.common.errors import ConfigError, HilError

DEMO = Path(__file__).resolve().parents[3] / "hil_configs" / "demo.yaml"


@pytest.fixture
def write(tmp_path: Path):
    def _write(text: str, name: str = "run.yaml") -> Path:
        path = tmp_path / name
        path.write_text(text, encoding="utf-8")
        return path

    return _write


def config_error(path: Path, *, overrides: tuple[str, ...] = ()) -> str:
    with pytest.raises(ConfigError) as info:
        load_config(path, overrides=overrides)
    message = str(info.value)
    assert "\n" not in message
    return message


def test_demo_loads_with_its_documented_values() -> None:
    cfg = load_config(DEMO)
    assert cfg.name == "demo"
    assert cfg.seed == 7
    assert cfg.mode is Mode.REALTIME
    assert cfg.duration_s == 15.0
    assert cfg.scenario.name == "stopped_car"
    assert cfg.scenario.params == {"gap_m": 45.0, "ego_speed_mps": 8.0}
    assert (cfg.camera.width, cfg.camera.height, cfg.camera.fps) == (320, 240, 20.0)
    assert cfg.camera.encoding is Encoding.JPEG
    assert cfg.target.transport is Transport.LOCAL
    assert cfg.target.command == ["{python}", "-m", "hil.targets.cv_baseline"]
    assert cfg.target.estimate_timeout_s == 0.5
    assert cfg.camera_period_steps == 25


def test_empty_mapping_and_empty_file_give_the_defaults(write) -> None:
    cfg = load_config(write("{}\n"))
    assert cfg == RunConfig()
    assert load_config(write("", name="empty.yaml")) == cfg
    assert cfg.name == "run" and cfg.seed == 0 and cfg.mode is Mode.REALTIME
    assert cfg.duration_s == 20.0 and cfg.physics_step_s == 0.002
    assert cfg.camera.fps == 20.0 and cfg.camera.encoding is Encoding.JPEG
    assert cfg.target.args == [] and cfg.target.startup_timeout_s == 15.0
    assert cfg.recording.queue_size == 4096 and cfg.recording.images is True
    assert cfg.progress is True
    assert cfg.camera_period_steps == 25


def test_overrides_parse_values_as_yaml_and_create_param_keys() -> None:
    cfg = load_config(
        DEMO,
        overrides=(
            "camera.fps=10",
            "camera.shadows=true",
            "mode=lockstep",
            "target.args=[--threshold, '0.4']",
            "scenario.params.lead_decel_mps2=3",
            "scenario.params.gap_m=40",
            "recording.images=false",
        ),
    )
    assert cfg.camera.fps == 10.0 and cfg.camera_period_steps == 50
    assert cfg.camera.shadows is True
    assert cfg.mode is Mode.LOCKSTEP
    assert cfg.target.args == ["--threshold", "0.4"]
    assert cfg.scenario.params == {"gap_m": 40.0, "ego_speed_mps": 8.0, "lead_decel_mps2": 3.0}
    assert cfg.recording.images is False


def test_override_creates_a_missing_section(write) -> None:
    cfg = load_config(write("{}"), overrides=("scenario.params.gap_m=30",))
    assert cfg.scenario.params == {"gap_m": 30.0}


def test_unknown_key_names_its_path_and_lists_the_valid_keys(write) -> None:
    message = config_error(write("camera:\n  fpss: 10\n"))
    assert "unknown key 'fpss' at camera" in message
    assert "valid keys: width, height, fovy_deg, fps," in message
    assert "did you mean 'fps'" in message


def test_unknown_top_level_key_from_an_override(write) -> None:
    message = config_error(write("{}"), overrides=("sed=3",))
    assert "unknown key 'sed' at <root>" in message
    assert "seed" in message and "override 'sed=3'" in message


def test_wrong_type_names_the_path_and_the_value(write) -> None:
    path = write("camera:\n  width: wide\n")
    message = config_error(path)
    assert message.startswith(f"{path}: config error at camera.width:")
    assert "got 'wide'; expected a valid integer" in message


def test_out_of_range_names_the_bound(write) -> None:
    message = config_error(write("duration_s: -1\n"))
    assert "config error at duration_s: got -1; expected greater than 0" in message


def test_camera_antialias_reaches_the_world_and_is_bounded(write) -> None:
    from hil.harness.run.driver import build_world

    assert load_config(write("{}")).camera.antialias == 4  # MuJoCo's own default, as before the setting
    world, _ = build_world(load_config(write("camera:\n  antialias: 0\n")))
    assert world.camera.antialias == 0
    assert "config error at camera.antialias: got 17; expected less than or equal to 16" in config_error(
        write("camera:\n  antialias: 17\n"))


def test_bool_is_not_a_number(write) -> None:
    message = config_error(write("seed: true\n"))
    assert "at seed: got True" in message


def test_enum_error_lists_the_valid_values(write) -> None:
    message = config_error(write("mode: fast\n"))
    assert "at mode: got 'fast'; expected 'realtime' or 'lockstep'" in message


@pytest.mark.parametrize("where", ["thresholds", "vehicles", "override"])
def test_a_deadline_for_an_unknown_stage_is_refused(write, where) -> None:
    # `deadline_ms: {end_to_endd: 5}` ran and judged nothing (README walkthrough).
    if where == "override":
        message = config_error(write(""), overrides=("timing.vehicles={ego0: {deadline_ms: {inferance: 5}}}",))
        assert "timing.vehicles.ego0.deadline_ms" in message and "'inferance'" in message, message
        return
    text = ("timing:\n  thresholds: {deadline_ms: {end_to_endd: 5, uplink: 3}}\n" if where == "thresholds" else
            "timing:\n  vehicles: {ego0: {deadline_ms: {end_to_endd: 5}}}\n")
    message = config_error(write(text))
    assert "deadline_ms" in message and "'end_to_endd'" in message and "end_to_end, to_apply" in message, message
    cfg = load_config(write("timing:\n  thresholds: {deadline_ms: {uplink: 3, to_apply: 90}}\n", "ok.yaml"))
    assert cfg.timing.thresholds_for("ego0").deadline_ms["uplink"] == 3


def test_long_bad_value_is_truncated(write) -> None:
    message = config_error(write(f"camera:\n  width: {'x' * 500}\n"))
    got = message.split("got ", 1)[1].split(";", 1)[0]
    assert len(got) <= 60 and got.endswith("...")


def test_several_errors_report_the_first_and_count_the_rest(write) -> None:
    message = config_error(write("seed: -1\ncamera: {width: 1}\nfoo: 2\n"))
    assert "at seed: got -1" in message
    assert "(+2 more: " in message


def test_missing_file(tmp_path: Path) -> None:
    missing = tmp_path / "nope.yaml"
    assert config_error(missing) == f"config file not found: {missing}"


def test_directory_is_not_a_config(tmp_path: Path) -> None:
    assert "is a directory" in config_error(tmp_path)


def test_yaml_syntax_error_names_line_and_column(write) -> None:
    path = write("name: ok\ncamera:\n  width: [320, 240\n  fps: 20\n")
    message = config_error(path)
    assert message.startswith(f"{path}: YAML syntax error at line 4, column ")
    assert "expected ',' or ']'" in message


def test_top_level_must_be_a_mapping(write) -> None:
    message = config_error(write("- a\n- b\n"))
    assert "at <root>: got ['a', 'b']; expected a mapping" in message


def test_section_must_be_a_mapping(write) -> None:
    assert "at camera: got 5; expected a mapping" in config_error(write("camera: 5\n"))


def test_camera_period_mismatch_suggests_values_that_work(write) -> None:
    message = config_error(write("camera: {fps: 30}\n"))
    assert "config error at camera.fps: got 30.0; expected" in message
    assert "whole multiple of physics_step_s" in message
    fps_part = re.search(r"use camera\.fps one of ([0-9., ]+)", message)
    step_part = re.search(r"use physics_step_s one of ([0-9., ]+)", message)
    assert fps_part and step_part
    fps_values = [float(v) for v in fps_part[1].strip(" ,").split(", ")]
    steps = [float(v) for v in step_part[1].strip(" ,").split(", ")]
    assert len(fps_values) == 6 and 25.0 in fps_values
    for fps in fps_values:
        cfg = load_config(write("camera: {fps: 30}\n"), overrides=(f"camera.fps={fps}",))
        assert cfg.camera_period_steps * cfg.physics_step_s == pytest.approx(1 / fps)
    for step in steps:
        load_config(write("camera: {fps: 30}\n"), overrides=(f"physics_step_s={step}",))


@pytest.mark.parametrize(("fps", "step"), [(20, 0.0013), (240, 0.05), (7, 0.002), (144, 0.001)])
def test_every_suggestion_validates(fps: float, step: float) -> None:
    with pytest.raises(ConfigError) as info:
        parse_config({"camera": {"fps": fps}, "physics_step_s": step})
    message = str(info.value)
    fps_text = re.search(r"use camera\.fps one of ([0-9., ]+)", message)[1]
    for text in fps_text.strip(" ,").split(", "):
        parse_config({"camera": {"fps": float(text)}, "physics_step_s": step})
    step_text = re.search(r"use physics_step_s one of ([0-9., ]+)", message)
    for text in step_text[1].strip(" ,").split(", ") if step_text else []:
        parse_config({"camera": {"fps": fps}, "physics_step_s": float(text)})


@pytest.mark.parametrize("override", ["camera.fps", "=3", "camera..fps=3", ".fps=3", "fps.=3"])
def test_malformed_override_is_named(write, override: str) -> None:
    message = config_error(write("{}"), overrides=(override,))
    assert f"malformed override {override!r}" in message


@pytest.mark.parametrize(
    ("text", "override", "expected"),
    [
        ("{}", "seed.x=3", "seed is 0, not a mapping"),  # through a default
        ("seed: 4\n", "seed.x=3", "seed is 4, not a mapping"),
        ("camera: {fps: 20}\n", "camera.fps.y=1", "camera.fps is 20, not a mapping"),
    ],
)
def test_override_through_a_non_mapping_is_named(
    write, text: str, override: str, expected: str
) -> None:
    message = config_error(write(text), overrides=(override,))
    assert f"override {override!r}: cannot set {override.split('=')[0]}" in message
    assert expected in message


def test_error_from_an_override_names_the_override(write) -> None:
    message = config_error(write("{}"), overrides=("scenario.params.gap_m=far",))
    assert "at scenario.params.gap_m: got 'far'" in message
    assert "(set by override 'scenario.params.gap_m=far')" in message


def test_config_error_is_a_hil_error(write) -> None:
    with pytest.raises(HilError):
        load_config(write("seed: -1\n"))


def test_config_hash_is_stable_and_tracks_every_field() -> None:
    cfg = load_config(DEMO)
    digest = config_hash(cfg)
    assert re.fullmatch(r"[0-9a-f]{64}", digest)
    assert config_hash(load_config(DEMO)) == digest
    assert config_hash(RunConfig.model_validate(dump_config(cfg))) == digest
    assert config_hash(load_config(DEMO, overrides=("seed=8",))) != digest
    assert config_hash(load_config(DEMO, overrides=("scenario.params.gap_m=46",))) != digest
    assert config_hash(load_config(DEMO, overrides=("camera.antialias=0",))) != digest


def test_a_field_added_later_leaves_the_hash_of_a_config_at_its_default_as_it_was() -> None:
    # camera.antialias came after runs recorded their config hash: the demo, which does
    # not set it, hashes as its dump without the field did (its baselines stay alike).
    doc = dump_config(load_config(DEMO))
    assert doc["camera"].pop("antialias") == 4
    before = hashlib.sha256(json.dumps(doc, sort_keys=True, separators=(",", ":")).encode()).hexdigest()
    assert config_hash(load_config(DEMO)) == before


def test_dump_config_is_json_able_with_enum_values() -> None:
    dumped = dump_config(load_config(DEMO))
    assert dumped["mode"] == "realtime"
    assert dumped["camera"]["encoding"] == "jpeg"
    assert dumped["target"]["transport"] == "local"
    assert type(dumped["mode"]) is str


def test_config_is_frozen() -> None:
    cfg = load_config(DEMO)
    with pytest.raises(pydantic.ValidationError):
        cfg.seed = 3  # type: ignore[misc]
    with pytest.raises(pydantic.ValidationError):
        cfg.camera.fps = 10  # type: ignore[misc]


def test_each_default_has_one_home() -> None:
    # The config's sections take their defaults from the models that use them (issue 27 item 4).
    from hil.harness.config.detector import DetectorSettings
    from hil.harness.config.timing import SyncSettings, ThresholdsConfig
    from hil.timing.anomaly import Thresholds
    from hil.timing.sync import SyncConfig

    assert SyncSettings().to_sync_config() == SyncConfig()
    assert ThresholdsConfig().apply(Thresholds()) == Thresholds()
    import hil.harness.cases.detector as detector

    assert not hasattr(detector, "DetectorConfig")  # the detector takes the config's model itself
    assert detector.CornerCaseDetector("ego0").cfg == DetectorSettings()
