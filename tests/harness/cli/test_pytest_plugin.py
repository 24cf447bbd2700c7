"""The ``hil_run`` pytest fixture: a user's test runs a config and asserts a budget;
an over-budget assertion says what, measured, budget, by how much."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from importlib.metadata import entry_points
from pathlib import Path
from typing import Any

import pytest

from hil.harness.cli.pytest_plugin import HilRunner, HilRunResult
from tests.conftest import GL_BACKEND
from tests.harness.junit_check import read_junit

USER_TEST = '''
import sys

CONFIG = {
    "name": "budget", "duration_s": 1.0,
    "scenario": {"name": "stopped_car", "params": {"gap_m": 40.0, "ego_speed_mps": 6.0}},
    "target": {"command": [sys.executable, "-m", "hil.targets.echo", "--infer-ms", "5"]},
}


def test_within_budget(hil_run):
    result = hil_run("cfg.yaml", overrides=["duration_s=1"])
    assert (result.run_dir / "run.mcap").is_file() and result.summary["ended_by"] == "duration"
    result.assert_budget(vehicle="ego0", stage="end_to_end", p99_ms=400)
    result.assert_budget(stage="inference", p50_ms=50, max_ms=400)
    result.assert_no_drops()


def test_over_budget(hil_run):
    result = hil_run(CONFIG)
    result.assert_budget(vehicle="ego0", stage="inference", p50_ms=1.0)
'''

CFG_YAML = '''
name: budget
duration_s: 3.0
scenario: {name: stopped_car, params: {gap_m: 40.0, ego_speed_mps: 6.0}}
target: {command: ["{python}", "-m", "hil.targets.echo", "--infer-ms", "5"]}
'''


def test_fixture_in_a_users_test_session(tmp_path: Path) -> None:
    (tmp_path / "test_user.py").write_text(USER_TEST)
    (tmp_path / "cfg.yaml").write_text(CFG_YAML)
    registered = any(e.value == "hil.harness.cli.pytest_plugin" for e in entry_points(group="pytest11"))
    plugin = [] if registered else ["-p", "hil.harness.cli.pytest_plugin"]  # installed: the entry point loads it
    env = dict(os.environ, MUJOCO_GL=GL_BACKEND)
    p = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", *plugin,
                        "--rootdir", str(tmp_path), str(tmp_path / "test_user.py"),
                        "--junitxml", str(tmp_path / "junit.xml"), "--hil-keep-runs", str(tmp_path / "artifacts")],
                       cwd=tmp_path, env=env, capture_output=True, text=True, timeout=120, check=False)
    out = p.stdout + p.stderr
    assert p.returncode == 1, out
    assert "1 failed, 1 passed" in out, out
    assert "latency budget exceeded:" in out, out
    assert "ego0 inference p50 = " in out and "> budget 1.000 ms (over by" in out, out
    assert "run folder: " in out, out
    assert "PytestWarning" not in out and "incompatible with junit_family" not in out, out
    # Each run's figures are properties of its test in pytest's JUnit file, failed test
    # included; each run folder is kept under --hil-keep-runs for CI artifacts.
    (suite,) = read_junit(tmp_path / "junit.xml")
    for test, name in (("test_within_budget", "hil-1-cfg"), ("test_over_budget", "hil-1-config")):
        case = suite.cases[test]
        assert case.failed == (test == "test_over_budget")
        kept = tmp_path / "artifacts" / f"test_user.py_{test}" / name
        assert case.properties["hil.1.run_dir"] == str(kept)
        assert (kept / "run.mcap").is_file() and (kept / "report.html").is_file()
        s = json.loads((kept / "summary.json").read_text())
        for stage in ("end_to_end", "inference"):
            for k in ("count", "p50_ms", "p99_ms", "max_ms"):
                assert case.properties[f"hil.1.ego0.{stage}.{k}"] == str(s["vehicles"]["ego0"]["latency_ms"][stage][k])
        assert case.properties["hil.1.ego0.dropped"] == str(s["vehicles"]["ego0"]["dropped"])
        assert case.properties["hil.1.verdict.passed"] == str(s["verdict"]["passed"])
        assert case.properties["hil.1.ended_by"] == "duration"
    assert f"run folder: {tmp_path / 'artifacts'}" in out  # the failure names the kept copy


def _result(e2e: dict[str, Any], *, dropped: int = 0) -> HilRunResult:
    return HilRunResult(Path("/runs/x"), {"ended_by": "duration", "vehicles": {"ego0": {
        "frames_sent": 100, "dropped": dropped, "drop_rate": dropped / 100,
        "latency_ms": {"end_to_end": e2e, "transport": {"count": 0}}}}})


def test_assert_budget_message() -> None:
    r = _result({"count": 100, "p50_ms": 40.0, "p99_ms": 93.2, "max_ms": 120.0})
    r.assert_budget(vehicle="ego0", stage="end_to_end", p50_ms=50, p99_ms=100)
    with pytest.raises(AssertionError) as err:
        r.assert_budget(vehicle="ego0", stage="end_to_end", p50_ms=50, p99_ms=80, max_ms=100)
    msg = str(err.value)
    assert "ego0 end_to_end p99 = 93.200 ms > budget 80.000 ms (over by 13.200 ms, +16.5 %, 100 frames)" in msg
    assert "ego0 end_to_end max = 120.000 ms > budget 100.000 ms" in msg
    assert "p50" not in msg and "/runs/x" in msg
    with pytest.raises(AssertionError, match=r"no latency samples for ego0 transport \(stages with samples: "
                                             r"end_to_end\)"):
        r.assert_budget(stage="transport", p99_ms=1)
    with pytest.raises(AssertionError, match=r"no vehicle 'ego9' in the run \(vehicles: ego0\)"):
        r.assert_budget(vehicle="ego9", p99_ms=1)
    with pytest.raises(TypeError, match="at least one budget"):
        r.assert_budget(vehicle="ego0")


def test_assert_no_drops_message() -> None:
    _result({"count": 1, "p50_ms": 1.0}).assert_no_drops()
    with pytest.raises(AssertionError, match=r"ego0: 3 of 100 frames dropped \(rate 0.0300 > 0.0000\)"):
        _result({"count": 1, "p50_ms": 1.0}, dropped=3).assert_no_drops()
    _result({"count": 1, "p50_ms": 1.0}, dropped=3).assert_drop_rate(0.05)


def test_config_mistake_fails_the_test_in_one_line(tmp_path: Path) -> None:
    runner = HilRunner(tmp_path)
    with pytest.raises(pytest.fail.Exception) as err:
        runner({"camera": {"fps": 0}})
    assert "hil_run:" in str(err.value) and "camera.fps" in str(err.value)
    assert err.value.pytrace is False
    with pytest.raises(pytest.fail.Exception, match="config file not found"):
        runner(tmp_path / "missing.yaml")


def test_packaged_configs_resolve_from_any_working_directory(tmp_path: Path, monkeypatch) -> None:
    from hil.common.errors import ConfigError
    from hil.harness.cli.pytest_plugin import _resolve

    monkeypatch.chdir(tmp_path)  # a user's project: no hil_configs/ of its own
    found = _resolve("hil_configs/regression.yaml", tmp_path)
    assert found.is_file() and found.parent.name == "hil_configs", found
    (tmp_path / "hil_configs").mkdir()
    (tmp_path / "hil_configs" / "regression.yaml").write_text("name: mine\n")
    assert _resolve("hil_configs/regression.yaml", tmp_path) == tmp_path / "hil_configs" / "regression.yaml"
    with pytest.raises(ConfigError, match=r"config file not found: nope.yaml \(looked in "):
        _resolve("nope.yaml", tmp_path)


def _readme_block(marker: str) -> str:
    text = (Path(__file__).resolve().parents[3] / "README.md").read_text()
    blocks = text.split("```")
    return next(b.split("\n", 1)[1] for b in blocks[1::2] if marker in b)


@pytest.mark.slow
def test_the_readme_fixture_sample_runs_as_shown(tmp_path: Path) -> None:
    # Exactly the README's test, in a project folder of its own (not the checkout).
    (tmp_path / "test_readme.py").write_text(_readme_block("def test_my_ai_budget(hil_run)"))
    registered = any(e.value == "hil.harness.cli.pytest_plugin" for e in entry_points(group="pytest11"))
    plugin = [] if registered else ["-p", "hil.harness.cli.pytest_plugin"]
    p = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", *plugin,
                        "--rootdir", str(tmp_path), str(tmp_path / "test_readme.py")],
                       cwd=tmp_path, env=dict(os.environ, MUJOCO_GL=GL_BACKEND), capture_output=True, text=True,
                       timeout=300, check=False)
    assert p.returncode == 0, p.stdout + p.stderr
    assert "1 passed" in p.stdout
    # The README's sample failure names the folder the fixture really makes.
    sample = _readme_block("AssertionError: latency budget exceeded")
    assert "/hil-1-regression " in sample, sample
