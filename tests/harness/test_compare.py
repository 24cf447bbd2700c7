"""``hil compare``: identical runs pass, added inference latency fails on p50/p99,
tolerances are overridable, and bad inputs give one line with exit code 2."""

from __future__ import annotations

import copy
import json
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

from harness.cli import main as hil_main
from harness.compare import Tolerance, Tolerances, Verdict, compare, parse_tolerances
from harness.config import parse_config
from harness.run import execute, prepare_out_dir
from tests.conftest import GL_BACKEND

ROOT = Path(__file__).resolve().parents[2]


def _run(root: Path, name: str, infer_ms: float) -> Path:
    out = prepare_out_dir(root / name)
    cfg = parse_config({
        "name": name, "duration_s": 1.5, "progress": False,
        "scenario": {"name": "stopped_car", "params": {"gap_m": 40.0, "ego_speed_mps": 6.0}},
        "target": {"command": [sys.executable, "-m", "targets.echo", "--infer-ms", str(infer_ms)]}})
    execute(cfg, out_dir=out, gl_backend=GL_BACKEND, install_signal_handlers=False)
    return out


@pytest.fixture(scope="module")
def runs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("compare")
    return {"base": _run(root, "base", 0), "slow": _run(root, "slow", 30)}


def _verdicts(checks: list[Any]) -> dict[tuple[str, str, str], Verdict]:
    return {(c.vehicle, c.stage, c.metric): c.verdict for c in checks}


def test_identical_runs_pass(runs: dict[str, Path], capsys: pytest.CaptureFixture[str]) -> None:
    assert hil_main(["compare", str(runs["base"]), str(runs["base"] / "summary.json")]) == 0
    out = capsys.readouterr().out
    assert "ok: all 25 checks within their limits" in out
    assert "end_to_end" in out and "REGRESSION" not in out


def test_added_inference_latency_fails_on_p50_and_p99(runs: dict[str, Path],
                                                     capsys: pytest.CaptureFixture[str]) -> None:
    assert hil_main(["compare", str(runs["base"]), str(runs["slow"])]) == 1
    out = capsys.readouterr().out
    assert "REGRESSION" in out
    base = json.loads((runs["base"] / "summary.json").read_text())
    slow = json.loads((runs["slow"] / "summary.json").read_text())
    v = _verdicts(compare(base, slow))
    for stage in ("inference", "target_total", "end_to_end", "to_apply"):
        assert v[("ego0", stage, "p50")] == Verdict.REGRESSION, stage
    for stage in ("inference", "target_total"):  # the target's own clock: no scheduling noise of the harness
        assert v[("ego0", stage, "p99")] == Verdict.REGRESSION, stage
    # The other way round it is an improvement, not a failure.
    assert hil_main(["compare", str(runs["slow"]), str(runs["base"]), "--stage", "inference",
                     "--stage", "end_to_end", "--drop-rate-abs", "1"]) == 0
    assert "better" in capsys.readouterr().out


def test_tolerance_flags_and_file_override_the_defaults(runs: dict[str, Path], tmp_path: Path,
                                                       capsys: pytest.CaptureFixture[str]) -> None:
    base, slow = str(runs["base"]), str(runs["slow"])
    # Drops are not the subject here (a loaded machine can skip a frame of the slow target).
    loose = ["--p50-abs-ms", "1000", "--p99-abs-ms", "1000", "--std-abs-ms", "1000", "--drop-rate-abs", "1"]
    assert hil_main(["compare", base, slow, *loose]) == 0
    # --stage checks that stage alone (plus the vehicle's drop rate).
    assert hil_main(["compare", base, slow, "--stage", "end_to_end", *loose]) == 0
    assert "all 4 checks within their limits" in capsys.readouterr().out
    tol = tmp_path / "tol.yaml"
    tol.write_text("p50: {abs_ms: 1000}\np99: {abs_ms: 1000}\nstd: {abs_ms: 1000}\ndrop_rate: {abs: 1}\n")
    assert hil_main(["compare", base, slow, "--tolerances", str(tol)]) == 0
    # A flag wins over the file; a per-stage override wins over both.
    assert hil_main(["compare", base, slow, "--tolerances", str(tol), "--p50-abs-ms", "0.5"]) == 1
    tol.write_text("p50: {abs_ms: 1000}\np99: {abs_ms: 1000}\nstd: {abs_ms: 1000}\ndrop_rate: {abs: 1}\n"
                   "stages:\n  inference: {p99: {rel: 0, abs_ms: 1}}\n")
    assert hil_main(["compare", base, slow, "--tolerances", str(tol), "--failures-only"]) == 1
    out = capsys.readouterr().out
    assert "inference" in out and "1 of 25 checks failed (ego0 inference p99)" in out


def _summary(**vehicles: dict[str, Any]) -> dict[str, Any]:
    def stage(p50: float) -> dict[str, Any]:
        return {"count": 100, "p50_ms": p50, "p90_ms": p50 * 1.2, "p99_ms": p50 * 1.5, "max_ms": p50 * 2,
                "std_ms": p50 / 10}

    out: dict[str, Any] = {"schema_version": 1, "ended_by": "duration", "vehicles": {}}
    for name, v in vehicles.items():
        out["vehicles"][name] = {"drop_rate": v.get("drop_rate", 0.0),
                                 "latency_ms": {s: stage(p) for s, p in v["stages"].items()}}
    return out


def test_missing_and_new_vehicles_and_stages() -> None:
    base = _summary(ego0={"stages": {"end_to_end": 10.0, "inference": 5.0}}, ego1={"stages": {"end_to_end": 10.0}})
    run = _summary(ego0={"stages": {"end_to_end": 10.0, "uplink": 1.0}}, ego2={"stages": {"end_to_end": 10.0}})
    v = _verdicts(compare(base, run))
    assert v[("ego1", "-", "vehicle")] == Verdict.MISSING          # missing in the run: fails
    assert v[("ego2", "-", "vehicle")] == Verdict.NEW              # new in the run: information
    assert v[("ego0", "inference", "stage")] == Verdict.MISSING
    assert v[("ego0", "uplink", "stage")] == Verdict.NEW
    assert v[("ego0", "end_to_end", "p99")] == Verdict.OK
    assert [c.verdict.fails for c in compare(base, run)].count(True) == 2
    # No samples in the run for a stage the baseline has: fails too.
    run["vehicles"]["ego0"]["latency_ms"]["end_to_end"] = {"count": 0}
    assert _verdicts(compare(base, run))[("ego0", "end_to_end", "p50")] == Verdict.MISSING


def test_limits_drop_rate_and_early_end() -> None:
    base = _summary(ego0={"stages": {"end_to_end": 10.0}})
    run = copy.deepcopy(base)
    e2e = run["vehicles"]["ego0"]["latency_ms"]["end_to_end"]
    e2e["p50_ms"] = 11.0  # +10 %: exactly at max(10 %, 0.5 ms)
    e2e["p99_ms"] = 15.0 + 3.01  # limit max(20 % of 15, 2) = 3 ms
    run["vehicles"]["ego0"]["drop_rate"] = 0.011
    checks = {(c.stage, c.metric): c for c in compare(base, run)}
    assert checks[("end_to_end", "p50")].verdict == Verdict.OK
    assert checks[("end_to_end", "p99")].verdict == Verdict.REGRESSION
    assert checks[("end_to_end", "p99")].limit == pytest.approx(18.0)
    assert checks[("-", "drop_rate")].verdict == Verdict.REGRESSION
    run["ended_by"] = "target of ego0 is gone: exited with code 3"
    assert any(c.metric == "ended_by" and c.verdict.fails for c in compare(base, run))
    tol = Tolerances(p99=Tolerance(0.0, 5.0), drop_rate=Tolerance(0.0, 0.05))
    checks = {(c.stage, c.metric): c for c in compare(base, run, tol)}
    assert checks[("end_to_end", "p99")].verdict == Verdict.OK
    assert checks[("-", "drop_rate")].verdict == Verdict.OK


def test_tolerances_file_errors_name_the_key(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from timing.errors import ConfigError

    with pytest.raises(ConfigError, match=r"p99\.rel: got 'x'"):
        parse_tolerances({"p99": {"rel": "x"}})
    with pytest.raises(ConfigError, match="unknown key 'p95'"):
        parse_tolerances({"p95": {"rel": 0.1}})
    with pytest.raises(ConfigError, match=r"stages\.transport: unknown metric 'max'"):
        parse_tolerances({"stages": {"transport": {"max": {"abs_ms": 1}}}})
    assert parse_tolerances({"p99": {"rel": 0.3}}).p99 == Tolerance(0.3, 2.0)  # partial: keeps abs_ms


def _one_line_error(argv: list[str], capsys: pytest.CaptureFixture[str], *needles: str) -> None:
    assert hil_main(argv) == 2
    err = capsys.readouterr().err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1 and "Traceback" not in err, err
    for n in needles:
        assert n in lines[0], lines[0]


def test_bad_inputs_give_one_line_and_exit_2(runs: dict[str, Path], tmp_path: Path,
                                             capsys: pytest.CaptureFixture[str]) -> None:
    base = str(runs["base"])
    _one_line_error(["compare", base, str(tmp_path / "nowhere")], capsys, "nowhere", "no such file")
    _one_line_error(["compare", str(tmp_path), base], capsys, str(tmp_path), "no summary.json", "not a run folder")

    text = tmp_path / "text" / "summary.json"
    text.parent.mkdir()
    text.write_text("hello, not JSON\n")
    _one_line_error(["compare", base, str(text.parent)], capsys, str(text), "not a run summary")

    cut = tmp_path / "cut.json"
    full = (runs["base"] / "summary.json").read_text()
    cut.write_text(full[: len(full) // 3])
    _one_line_error(["compare", str(cut), base], capsys, str(cut), "truncated JSON")

    other = tmp_path / "other.json"
    other.write_text('{"name": "something else"}')
    _one_line_error(["compare", base, str(other)], capsys, str(other), "without a 'vehicles' mapping")

    binary = tmp_path / "bin.json"
    binary.write_bytes(b"\x89MCAP0\r\n\xff\xfe\x00")
    _one_line_error(["compare", base, str(binary)], capsys, str(binary), "not UTF-8")

    killed = tmp_path / "killed"
    killed.mkdir()
    shutil.copy(runs["base"] / "run.mcap", killed / "run.mcap")
    _one_line_error(["compare", base, str(killed)], capsys, "killed", "no summary.json", "did not finish")

    _one_line_error(["compare", base, base, "--tolerances", str(tmp_path / "tol.yaml")], capsys,
                    "tol.yaml", "not found")
    _one_line_error(["compare", base, base, "--p99-rel", "-1"], capsys, "--p99-rel", ">= 0")


def test_cli_subprocess_exit_codes(runs: dict[str, Path]) -> None:
    def hil(*args: str) -> subprocess.CompletedProcess[str]:
        return subprocess.run([sys.executable, "-m", "harness.cli", *args], cwd=ROOT, capture_output=True,
                              text=True, timeout=60, check=False)

    p = hil("compare", str(runs["base"]), str(runs["slow"]))
    assert p.returncode == 1 and "REGRESSION" in p.stdout and "Traceback" not in p.stderr
    p = hil("compare", str(runs["base"]), "/nonexistent/run")
    assert p.returncode == 2 and p.stderr.count("\n") == 1 and "/nonexistent/run" in p.stderr
