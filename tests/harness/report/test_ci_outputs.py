"""What CI systems read (issue 25 item 4): ``--junit FILE`` and ``--json FILE`` on
``run``, ``compare`` (tests/harness/check/test_compare.py), ``search``, ``study``,
``calibrate`` and ``target-check``, read back by an independent parser
(tests/harness/junit_check.py); a testcase fails exactly when its check makes the
command's exit code non-zero."""

from __future__ import annotations

import copy
import json
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
import yaml

from hil.harness.check.ci_cases import of_calibrate
from hil.harness.report.ci_cases import of_run, run_figures
from hil.harness.vocab.figures import RunFigures
from hil.harness.report.ci_outputs import CiCase, CiReport, write_junit
from tests.adapters.tcp.pair import tcp_echo
from tests.adapters.zenoh.pair import free_port
from tests.conftest import GL_BACKEND
from tests.harness.junit_check import read_junit

ROOT = Path(__file__).resolve().parents[3]


def hil(*args: str, timeout: float = 120) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "hil.harness.cli.main", *args], cwd=ROOT, capture_output=True,
                          text=True, timeout=timeout, env=dict(os.environ, MUJOCO_GL=GL_BACKEND), check=False)


def _agree(junit: Path, js: Path, exit_code: int) -> tuple[dict[str, Any], dict[str, Any]]:
    """The two files agree with each other and with the exit code; returns (cases, json)."""
    (suite,) = read_junit(junit)
    doc = json.loads(js.read_text())
    assert doc["exit_code"] == exit_code and doc["passed"] == (exit_code == 0)
    assert suite.properties["exit_code"] == str(exit_code)
    assert [c["name"] for c in doc["checks"]] == list(suite.cases)
    for c in doc["checks"]:
        case = suite.cases[c["name"]]
        assert case.failed == c["fails_command"], c["name"]
        assert case.properties["ok"] == ("true" if c["ok"] else "false")
    assert any(c.failed for c in suite.cases.values()) == (exit_code != 0)
    return suite.cases, doc


@pytest.fixture(scope="module")
def late_run(tmp_path_factory: pytest.TempPathFactory) -> tuple[subprocess.CompletedProcess[str], Path]:
    # Every answer takes 120 ms: every frame misses the 100 ms budget; --fail-on deadline.
    root = tmp_path_factory.mktemp("ci")
    p = hil("run", "hil_configs/demo.yaml", "--no-progress", "--out", str(root / "run"), "--set", "duration_s=1.5",
            "--set", 'target.command=["{python}","-m","hil.targets.echo","--infer-ms","120"]',
            "--fail-on", "deadline", "--junit", str(root / "run.xml"), "--json", str(root / "run.json"))
    return p, root


def test_run_writes_one_testcase_per_verdict_check(late_run: tuple[subprocess.CompletedProcess[str], Path]) -> None:
    p, root = late_run
    assert p.returncode == 3, p.stdout + p.stderr
    cases, doc = _agree(root / "run.xml", root / "run.json", 3)
    s = json.loads((root / "run" / "summary.json").read_text())
    assert list(cases) == ["completed", *(c["name"] for c in s["verdict"]["checks"])]
    dl = cases["deadline"]
    b = s["vehicles"]["ego0"]["budgets"]["end_to_end"]
    assert dl.failed and dl.message.startswith("missed: ego0: ") and dl.classname == "hil.run.demo"
    assert dl.properties["measured"] == str(float(b["over"])) and dl.properties["in_fail_on"] == "true"
    assert dl.properties["details.vehicles.ego0.end_to_end.over"] == str(b["over"])
    assert not cases["completed"].failed and cases["completed"].properties["ended_by"] == "duration"
    # Figures of the run travel as suite properties, equal to summary.json's.
    (suite,) = read_junit(root / "run.xml")
    e2e = s["vehicles"]["ego0"]["latency_ms"]["end_to_end"]
    assert suite.properties["ego0.end_to_end.p99_ms"] == str(e2e["p99_ms"])
    assert suite.properties["run_dir"] == str(root / "run")
    assert doc["details"]["verdict"] == s["verdict"]


def test_a_failed_check_not_in_fail_on_is_a_warning_not_a_failure(
        late_run: tuple[subprocess.CompletedProcess[str], Path], tmp_path: Path) -> None:
    # The same run without --fail-on exits 0; its JUnit file must agree: the missed
    # deadline is a passed testcase saying ok=false, with the headline in system-out.
    _, root = late_run
    s = json.loads((root / "run" / "summary.json").read_text())
    s = copy.deepcopy(s)
    s["verdict"].update(fail_on=[], fails_run=[])
    report = of_run(RunFigures.from_json(s), run_dir=root / "run", exit_code=0)
    write_junit(report, tmp_path / "warn.xml")
    (suite,) = read_junit(tmp_path / "warn.xml")
    dl = suite.cases["deadline"]
    assert not dl.failed and dl.properties["ok"] == "false" and dl.properties["fails_command"] == "false"
    assert dl.system_out is not None and dl.system_out.startswith("warning: missed: ego0: ")
    assert not any(c.failed for c in suite.cases.values())
    # An early end is exit 1: the completed case fails.
    s["ended_by"] = "target of ego0 is gone: exited with code 3"
    write_junit(of_run(RunFigures.from_json(s), run_dir=root / "run", exit_code=1), tmp_path / "early.xml")
    (suite,) = read_junit(tmp_path / "early.xml")
    assert suite.cases["completed"].failed and "ended early: target of ego0 is gone" in suite.cases["completed"].message


def test_run_figures_are_the_summarys() -> None:
    s = {"realtime": {"mode": "realtime", "kept_realtime": True, "achieved_factor": 1.0, "late_steps": 0,
                      "camera": {"late_frames": 2}},
         "vehicles": {"ego1": {"frames_sent": 10, "dropped": 1, "drop_rate": 0.1,
                               "latency_ms": {"end_to_end": {"count": 9, "p50_ms": 3.5, "p99_ms": 9.25},
                                              "transport": {"count": 0}}}}}
    f = run_figures(RunFigures.from_json(s))
    assert f["ego1.end_to_end.p99_ms"] == 9.25 and f["ego1.dropped"] == 1 and f["realtime.late_frames"] == 2
    assert not any(k.startswith("ego1.transport") for k in f)


def test_output_files_are_checked_before_any_work(tmp_path: Path) -> None:
    for argv in (["run", "hil_configs/demo.yaml", "--out", str(tmp_path / "r")],
                 ["compare", str(tmp_path), str(tmp_path)], ["study", "hil_configs/study.yaml"],
                 ["calibrate"], ["search", "hil_configs/search.yaml"]):
        p = hil(*argv, "--junit", str(tmp_path / "no" / "such" / "x.xml"), timeout=60)
        assert p.returncode == 2, (argv, p.stdout, p.stderr)
        assert p.stderr.strip().splitlines() == [f"hil: error: --junit {tmp_path}/no/such/x.xml: folder "
                                                 f"{tmp_path}/no/such does not exist"], argv
    assert not (tmp_path / "r").exists()
    p = hil("target-check", "tcp://127.0.0.1:1", "--json", str(tmp_path))
    assert p.returncode == 2 and "--json" in p.stderr and "is a folder" in p.stderr


def test_target_check_cases_are_its_rows(tmp_path: Path) -> None:
    from hil.harness.check import target_check

    address = f"127.0.0.1:{free_port()}"
    with tcp_echo(tmp_path / "t.log", ["--bad-stamps", "backwards"], listen=address):
        code = target_check.main([f"tcp://{address}", "--timeout", "3", "--junit", str(tmp_path / "tc.xml"),
                                  "--json", str(tmp_path / "tc.json")])
    assert code == 1
    cases, _ = _agree(tmp_path / "tc.xml", tmp_path / "tc.json", 1)
    assert cases["frame RGB8 -> estimate"].failed and "t_rx (offset 24)" in cases["frame RGB8 -> estimate"].message
    assert not cases["bye ends the session"].failed
    assert cases["clock sync burst"].properties["section"].startswith("PROTOCOL.md §")


def test_calibration_cases_fail_where_the_calibration_fails(tmp_path: Path) -> None:
    from hil.harness.check.calibrate import Calibration
    from hil.harness.check.calibrate_checks import Check
    from hil.harness.check.calibrate_faults import Cause, FaultCheck, Other

    cal = Calibration("local", checks=[Check("clock offset", 0.01, 0.0, 0.01, 0.05, True, "ms"),
                                       Check("inference p50", 5.2, 5.0, 0.2, 0.1, False, "ms")],
                      faults=[FaultCheck("spike", 12, ("latency_spike",), True)],
                      others=[Other("frame 40", "jitter", (40,), Cause.FALSE, "jitter at frame 40: nothing injected")])
    assert not cal.passed
    write_junit(of_calibrate(cal, out=tmp_path, exit_code=1), tmp_path / "cal.xml")
    (suite,) = read_junit(tmp_path / "cal.xml")
    failed = {n for n, c in suite.cases.items() if c.failed}
    assert failed == {"inference p50", "jitter frame 40"}
    assert suite.cases["inference p50"].properties["bound"] == "0.1"
    assert suite.cases["spike at frame 12"].properties["flagged_by"] == '["latency_spike"]'


def test_junit_values_are_escaped_and_never_nan(tmp_path: Path) -> None:
    weird = 'a <b> & "c"\nd'
    report = CiReport("run", weird, [CiCase(weird, False, weird, {"x": float("nan"), "y": None, "z": [1, 2]})], 1)
    write_junit(report, tmp_path / "w.xml")
    (suite,) = read_junit(tmp_path / "w.xml")
    case = suite.cases[weird]
    assert case.failed and case.message == weird
    assert case.properties["x"] == "nan" and case.properties["y"] == "" and case.properties["z"] == "[1, 2]"
    assert json.loads(json.dumps(report.to_json(), allow_nan=False))["checks"][0]["properties"]["x"] is None


SPEC = {"name": "ci-search", "seed": 3, "episodes": 2,
        "run": {"mode": "lockstep", "duration_s": 1.0, "scenario": {"name": "stopped_car"},
                "target": {"command": ["{python}", "-m", "hil.targets.echo"]}},
        "params": {"gap_m": [15, 30]}, "strategy": {"kind": "random"}}


@pytest.mark.slow
def test_search_writes_one_testcase_per_episode(tmp_path: Path) -> None:
    spec = tmp_path / "spec.yaml"
    spec.write_text(yaml.safe_dump(SPEC))
    p = hil("search", str(spec), "--out", str(tmp_path / "c"), "--workers", "1", "--no-progress",
            "--junit", str(tmp_path / "s.xml"), "--json", str(tmp_path / "s.json"), timeout=300)
    assert p.returncode == 0, p.stdout + p.stderr
    cases, doc = _agree(tmp_path / "s.xml", tmp_path / "s.json", 0)
    assert list(cases) == ["complete", "e00000", "e00001"]
    assert cases["e00000"].properties["status"] == "ok" and 15 <= float(cases["e00000"].properties["params.gap_m"]) <= 30
    assert doc["details"]["summary"]["episodes"]["ran"] == 2


@pytest.mark.slow
def test_study_writes_one_testcase_per_point(tmp_path: Path) -> None:
    out = tmp_path / "study"
    p = hil("study", "hil_configs/study.yaml", "--vehicles", "1", "--placement", "replicated", "--duration", "1",
            "--out", str(out), "--junit", str(tmp_path / "st.xml"), "--json", str(tmp_path / "st.json"), timeout=300)
    assert p.returncode == 0, p.stdout + p.stderr
    assert "study: 1 of 1 points done (" in p.stdout and ", done: replicated-n1-fps" in p.stdout  # item 9
    cases, _ = _agree(tmp_path / "st.xml", tmp_path / "st.json", 0)
    point = json.loads((out / "results.json").read_text())["points"][0]
    assert list(cases) == [f"replicated-n1-fps{point['fps']:g}"]
    case = next(iter(cases.values()))
    assert case.properties["total_fps"] == str(point["total_fps"]) and case.properties["status"] == "ok"
