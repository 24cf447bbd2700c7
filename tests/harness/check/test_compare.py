"""``hil compare``: runs of one build pass, added inference latency fails, the
verdict comes from the per-frame samples with its uncertainty (load noise that moves
p50/p99 of an unchanged build does not fail; a shift of every frame does), tolerances
are overridable, and bad inputs give one line with exit code 2."""

from __future__ import annotations

import copy
import os
import json
import re
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from hil.harness.cli.main import main as hil_main
from hil.harness.config.loading import parse_config
from hil.harness.check.gate import Method, Tolerance, Tolerances, Verdict, compare, load_run, parse_tolerances
from hil.harness.check.gate_samples import RunSamples, VehicleSamples
from hil.harness.run.driver import execute, prepare_out_dir
from tests.conftest import GL_BACKEND
from hil.timing.stats import summarize_ns

ROOT = Path(__file__).resolve().parents[3]


def _run(root: Path, name: str, infer_ms: float) -> Path:
    out = prepare_out_dir(root / name)
    cfg = parse_config({
        "name": name, "duration_s": 1.5, "progress": False,
        "scenario": {"name": "stopped_car", "params": {"gap_m": 40.0, "ego_speed_mps": 6.0}},
        "target": {"command": [sys.executable, "-m", "hil.targets.echo", "--infer-ms", str(infer_ms)]}})
    execute(cfg, out_dir=out, gl_backend=GL_BACKEND, install_signal_handlers=False)
    return out


@pytest.fixture(scope="module")
def runs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("compare")
    return {"base": _run(root, "base", 0), "slow": _run(root, "slow", 30), "again": _run(root, "again", 0)}


def _verdicts(checks: list[Any]) -> dict[tuple[str, str, str], Verdict]:
    return {(c.vehicle, c.stage, c.metric): c.verdict for c in checks}


def test_identical_runs_pass(runs: dict[str, Path], capsys: pytest.CaptureFixture[str]) -> None:
    assert hil_main(["compare", str(runs["base"]), str(runs["base"] / "summary.json")]) == 0
    out = capsys.readouterr().out
    assert re.search(r"ok: all \d+ checks within their limits", out)
    assert "end_to_end" in out and "REGRESSION" not in out
    assert "judged from per-frame samples" in out and "P(worse)" in out and "95 % interval" in out


def test_two_runs_of_one_build_pass(runs: dict[str, Path], capsys: pytest.CaptureFixture[str]) -> None:
    assert hil_main(["compare", str(runs["base"]), str(runs["again"])]) == 0, capsys.readouterr().out
    (sb, xb), (sr, xr) = load_run(runs["base"]), load_run(runs["again"])
    checks = compare(sb, sr, base_samples=xb, run_samples=xr)
    judged = [c for c in checks if c.method is Method.SAMPLES]
    assert len(judged) >= 4 * 7 + 1  # p1/p50/p99/std of every stage with samples, and the drop rate
    for c in judged:
        assert c.ci is not None and c.ci[0] <= c.run - c.baseline <= c.ci[1] and 0 <= (c.p_worse or 0) <= 1


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
    loose = ["--p1-abs-ms", "1000", "--p50-abs-ms", "1000", "--p99-abs-ms", "1000", "--std-abs-ms", "1000",
             "--drop-rate-abs", "1"]
    assert hil_main(["compare", base, slow, *loose]) == 0
    # --stage checks that stage alone (plus the vehicle's drop rate).
    assert hil_main(["compare", base, slow, "--stage", "end_to_end", *loose]) == 0
    assert "all 5 checks within their limits" in capsys.readouterr().out  # drop rate, p1, p50, p99, std
    tol = tmp_path / "tol.yaml"
    loose_file = ("p1: {abs_ms: 1000}\np50: {abs_ms: 1000}\np99: {abs_ms: 1000}\nstd: {abs_ms: 1000}\n"
                  "drop_rate: {abs: 1}\n")
    tol.write_text(loose_file)
    assert hil_main(["compare", base, slow, "--tolerances", str(tol)]) == 0
    # A flag wins over the file; a per-stage override wins over both.
    assert hil_main(["compare", base, slow, "--tolerances", str(tol), "--p50-abs-ms", "0.5"]) == 1
    tol.write_text(loose_file + "stages:\n  inference: {p99: {rel: 0, abs_ms: 1}}\n")
    assert hil_main(["compare", base, slow, "--tolerances", str(tol), "--failures-only"]) == 1
    out = capsys.readouterr().out
    assert "inference" in out and re.search(r"1 of \d+ checks failed \(ego0 inference p99\)", out), out
    # Summaries alone (--point): the figures compared as points, as before.
    assert hil_main(["compare", base, slow, "--point", *loose]) == 0
    assert "point" in capsys.readouterr().out


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
    from hil.common.errors import ConfigError

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

    killed = tmp_path / "killed"  # a killed baseline is no baseline (a killed RUN: the test below)
    killed.mkdir()
    shutil.copy(runs["base"] / "run.mcap", killed / "run.mcap")
    _one_line_error(["compare", str(killed), base], capsys, "killed", "no summary.json", "did not finish")

    _one_line_error(["compare", base, base, "--tolerances", str(tmp_path / "tol.yaml")], capsys,
                    "tol.yaml", "not found")
    _one_line_error(["compare", base, base, "--p99-rel", "-1"], capsys, "--p99-rel", ">= 0")


def test_a_run_killed_before_its_summary_is_a_regression_not_bad_input(runs: dict[str, Path], tmp_path: Path,
                                                                        capsys: pytest.CaptureFixture[str]) -> None:
    # The README: a RUN that ended early is a regression. A SIGKILLed run has run.mcap
    # and no summary.json: it was refused as bad input (exit 2, and no JUnit case).
    killed = tmp_path / "killed"
    killed.mkdir()
    shutil.copy(runs["base"] / "run.mcap", killed / "run.mcap")
    junit = tmp_path / "gate.xml"
    assert hil_main(["compare", str(runs["base"]), str(killed), "--junit", str(junit)]) == 1
    out = capsys.readouterr().out
    assert "ended early: did not finish (no summary.json" in out and "REGRESSION" in out, out
    assert "note:" not in out  # no "scenario differs: ... run None" for a summary it has not
    assert "did not finish" in junit.read_text()


def test_cli_subprocess_exit_codes(runs: dict[str, Path]) -> None:
    def hil(*args: str) -> subprocess.CompletedProcess[str]:
        return subprocess.run([sys.executable, "-m", "hil.harness.cli.main", *args], cwd=ROOT, capture_output=True,
                              text=True, timeout=60, check=False)

    p = hil("compare", str(runs["base"]), str(runs["slow"]))
    assert p.returncode == 1 and "REGRESSION" in p.stdout and "Traceback" not in p.stderr
    p = hil("compare", str(runs["base"]), "/nonexistent/run")
    assert p.returncode == 2 and p.stderr.count("\n") == 1 and "/nonexistent/run" in p.stderr


# --- the statistics, on synthetic per-frame samples --------------------------------------


def _frames(seed: int, n: int, *, shift_ms: float = 0.0, disturbed: float = 0.1, load_ms: float = 1.0) -> np.ndarray:
    """End-to-end samples (ms, frame order) of a pipeline whose own work takes ~3.3 ms
    (+ ``shift_ms``): a fraction ``disturbed`` of the frames, in bursts of 8, is
    slowed by the machine's load (gamma, mean ``load_ms``)."""
    rng = np.random.default_rng(seed)
    work = 3.3 + shift_ms + rng.gamma(20.0, 0.01, n)
    bursts = -(-n // 8)
    burst = np.repeat(rng.permutation(bursts) < round(disturbed * bursts), 8)[:n]
    return work + burst * rng.gamma(4.0, load_ms / 4, n)


def _pair(base: np.ndarray, run: np.ndarray) -> tuple[dict[str, Any], RunSamples, dict[str, Any], RunSamples]:
    def one(x: np.ndarray) -> tuple[dict[str, Any], RunSamples]:
        summary = {"schema_version": 1, "ended_by": "duration", "vehicles": {"ego0": {
            "drop_rate": 0.0, "latency_ms": {"end_to_end": summarize_ns((x * 1e6).astype(np.int64).tolist())}}}}
        return summary, RunSamples({"ego0": VehicleSamples({"end_to_end": x}, np.zeros(x.size))})

    return (*one(base), *one(run))


def _by_metric(checks: list[Any]) -> dict[str, Any]:
    return {c.metric: c for c in checks if c.stage == "end_to_end"}


def test_load_that_moves_p50_and_p99_of_an_unchanged_build_does_not_fail() -> None:
    # The same build twice, the second time on a busier machine: 70 % of its frames
    # are slowed (3 ms on average) instead of 10 % (1 ms). p50 grows ~+60 %, p99 more;
    # the floor (p1), what the build itself takes, stays.
    sb, xb, sr, xr = _pair(_frames(1, 160), _frames(2, 160, disturbed=0.7, load_ms=3.0))
    point = _by_metric(compare(sb, sr))
    assert point["p50"].verdict == Verdict.REGRESSION  # what the gate said before: a false alarm
    checks = compare(sb, sr, base_samples=xb, run_samples=xr)
    v = _by_metric(checks)
    assert all(c.method is Method.SAMPLES and not c.verdict.fails for c in checks), \
        [(c.metric, c.verdict, c.p_worse) for c in checks]
    assert abs(v["p1"].run - v["p1"].baseline) < 0.3
    # p50 is over its limit and does not fail: it says so, and why, never a plain "ok".
    p50 = v["p50"]
    assert p50.run - p50.baseline > 1.0 and p50.run > p50.limit
    assert p50.verdict == Verdict.NOT_SIGNIFICANT and not p50.verdict.fails
    assert p50.reason == (f"over the limit but not significant (P(worse) {p50.p_worse * 100:.1f} % < "
                          f"{p50.need * 100:.2f} %)")


def test_a_row_over_its_limit_is_never_printed_ok(capsys: pytest.CaptureFixture[str]) -> None:
    from rich.console import Console

    from hil.harness.check.gate_render import outcome_lines, render

    sb, xb, sr, xr = _pair(_frames(1, 160), _frames(2, 160, disturbed=0.7, load_ms=3.0))
    checks = compare(sb, sr, base_samples=xb, run_samples=xr)
    over = [c for c in checks if c.run is not None and c.limit is not None and c.run > c.limit]
    assert over and not any(c.verdict.fails for c in checks)
    console = Console(width=250, no_color=True)
    console.print(render(checks))
    for line in outcome_lines(checks):
        console.print(line)
    out = capsys.readouterr().out
    for c in over:
        row = next(ln for ln in out.splitlines() if re.search(rf"│ {c.stage}\s+│ {c.metric}\s+│", ln))
        assert "over, not significant" in row and not re.search(r"│ ok\s+│", row), row
        # The reason with the numbers: values, change, limit, P(worse) against what it needs.
        assert (f"ego0 end_to_end {c.metric} {c.baseline:.3f} → {c.run:.3f} ms, " in out
                and f"limit ≤ {c.limit:.3f} ms: over the limit but not "
                    f"significant (P(worse) {c.p_worse * 100:.1f} % < {c.need * 100:.2f} %)" in out), out
    assert "all " not in out.splitlines()[-1] and f"{len(over)} over" in out.splitlines()[-1]


@pytest.mark.parametrize(("argv", "tol_yaml", "needle"), [
    (["--stage", "nosuch"], None, "--stage: unknown stage 'nosuch' (valid: render, capture_to_send, transport"),
    (["--stage", "end_to_end", "--stage", "end-to-end"], None, "unknown stage 'end-to-end'"),
    ([], "stages:\n  nosuch: {p99: {abs_ms: 5}}\n", "tolerances error at stages: unknown stage 'nosuch'"),
    ([], "skip_stages: [transprot]\n", "tolerances error at skip_stages: unknown stage 'transprot' (valid:"),
    ([], "only_stages: [nosuch]\n", "only_stages: unknown stage 'nosuch'"),
    ([], "p99: {rel: 0.2}\np95: {rel: 0.1}\n", "unknown key 'p95' (valid keys: p1, p50, p99, std, drop_rate"),
])
def test_a_typo_never_switches_the_gate_off(runs: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                            argv: list[str], tol_yaml: str | None, needle: str) -> None:
    # Before: `--stage nosuch` checked the drop rate alone and printed "ok: all 1 checks".
    if tol_yaml is not None:
        (tmp_path / "tol.yaml").write_text(tol_yaml)
        argv = [*argv, "--tolerances", str(tmp_path / "tol.yaml")]
    _one_line_error(["compare", str(runs["base"]), str(runs["slow"]), *argv], capsys, needle)


def test_a_stage_the_baseline_never_measured_is_refused() -> None:
    from hil.common.errors import ConfigError
    from hil.harness.check.gate import check_selection

    base = _summary(ego0={"stages": {"end_to_end": 10.0, "inference": 5.0}})
    base["vehicles"]["ego0"]["latency_ms"]["transport"] = {"count": 0}
    check_selection(base, Tolerances(only_stages=("end_to_end", "inference")))
    with pytest.raises(ConfigError, match=r"--stage transport: the baseline has no samples of this stage, so "
                                          r"nothing would be checked \(its stages with samples: inference, end_to_end\)"):
        check_selection(base, Tolerances(only_stages=("end_to_end", "transport")))


def test_every_frame_2ms_slower_fails_with_near_certainty() -> None:
    sb, xb, sr, xr = _pair(_frames(1, 160), _frames(2, 160, shift_ms=2.0))
    v = _by_metric(compare(sb, sr, base_samples=xb, run_samples=xr))
    assert v["p1"].verdict == Verdict.REGRESSION
    assert v["p1"].p_worse >= v["p1"].need >= 0.99 and v["p1"].ci[0] > 1.0
    # ... also on a busier machine (the load would hide it in p50 and p99).
    sb, xb, sr, xr = _pair(_frames(3, 160), _frames(4, 160, shift_ms=2.0, disturbed=0.7, load_ms=3.0))
    assert _by_metric(compare(sb, sr, base_samples=xb, run_samples=xr))["p1"].verdict == Verdict.REGRESSION


def test_a_tiny_change_passes_however_sure_and_a_fall_is_better() -> None:
    # 20,000 frames each, no run-to-run noise (a quiet machine): +0.1 ms on every frame
    # is surely real, and within its allowance.
    sb, xb, sr, xr = _pair(_frames(5, 20_000), _frames(6, 20_000, shift_ms=0.1))
    zero = {"rel": 0, "abs_ms": 0}
    quiet = parse_tolerances({"noise": {"p1": zero, "p50": zero, "p99": zero, "std": zero}})
    v = _by_metric(compare(sb, sr, quiet, base_samples=xb, run_samples=xr))
    assert v["p50"].ci[0] > 0.05 and v["p50"].verdict == Verdict.OK and v["p50"].p_worse < 0.01
    sb, xb, sr, xr = _pair(_frames(1, 160, shift_ms=2.0), _frames(2, 160))
    assert _by_metric(compare(sb, sr, base_samples=xb, run_samples=xr))["p1"].verdict == Verdict.BETTER
    # Same inputs, same seed: the same verdicts and numbers.
    a = compare(sb, sr, base_samples=xb, run_samples=xr)
    assert a == compare(sb, sr, base_samples=xb, run_samples=xr)


def test_run_to_run_noise_comes_from_the_tolerances(tmp_path: Path) -> None:
    sb, xb, sr, xr = _pair(_frames(1, 160), _frames(2, 160, disturbed=0.7, load_ms=3.0))
    zero = {"rel": 0, "abs_ms": 0}
    quiet = parse_tolerances({"noise": {"p50": zero, "p99": zero, "std": zero}})
    assert _by_metric(compare(sb, sr, quiet, base_samples=xb, run_samples=xr))["p50"].verdict == Verdict.REGRESSION
    from hil.common.errors import ConfigError

    assert parse_tolerances({"noise": {"p50": 0.1}}).noise_of("p50") == Tolerance(0.1, 1.0)  # a number sets rel
    with pytest.raises(ConfigError, match=r"noise\.p50: got -1"):
        parse_tolerances({"noise": {"p50": -1}})
    with pytest.raises(ConfigError, match="noise: unknown metric 'p90'"):
        parse_tolerances({"noise": {"p90": 0.1}})
    # Per stage: the harness's own stages move more between runs (defaults), and any can be set.
    assert Tolerances().noise_of("p1", "render").rel > Tolerances().noise_of("p1", "end_to_end").rel
    t = parse_tolerances({"stages": {"end_to_end": {"noise": {"p50": zero}, "p99": {"abs_ms": 5}}}})
    assert t.noise_of("p50", "end_to_end") == Tolerance(0, 0)
    assert t.noise_of("p50", "inference") == Tolerances().noise_of("p50")
    assert _by_metric(compare(sb, sr, t, base_samples=xb, run_samples=xr))["p50"].verdict == Verdict.REGRESSION
    with pytest.raises(ConfigError, match=r"stages\.render\.noise\.p1: got 'x'"):
        parse_tolerances({"stages": {"render": {"noise": {"p1": "x"}}}})


# --- the README's example is what the command prints ----------------------------------


def _readme_example() -> list[str]:
    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    block = next(b for b in readme.split("```")[1::2] if b.lstrip().startswith("$ hil compare"))
    return block.strip("\n").splitlines()


def _cell_shape(cell: str) -> str:
    """A table cell or line with its numbers (and their sign, ratio or inequality form) blurred."""
    s = re.sub(r"[<>]?[+-]?\d+(\.\d+)?", "9", cell.strip())
    return s.replace("(×9)", "(9 %)")


def _shape(lines: list[str]) -> dict[str, Any]:
    head = next(ln for ln in lines if ln.startswith("┃"))
    rows = [[c.strip() for c in ln.strip("│").split("│")] for ln in lines if ln.startswith("│")]
    return {"title": next(ln.strip() for ln in lines if ln.startswith("latency regression check")),
            "header": [c.strip() for c in head.strip("┃").split("┃")],
            "rows": {tuple(r[:3]): [_cell_shape(c) for c in r[3:9]] for r in rows},
            "verdicts": {r[9] for r in rows},
            "judged": [_cell_shape(ln) for ln in lines if "checks judged" in ln or "run-to-run noise" in ln],
            "over": [ln.partition(": ") for ln in lines if "over the limit but not significant" in ln],
            "last": _cell_shape(lines[-1])}


def test_the_readme_compare_example_is_what_the_command_prints(runs: dict[str, Path]) -> None:
    example = _readme_example()
    argv = example[0].removeprefix("$ hil ").split()
    assert argv[:3] == ["compare", "runs/base", "runs/slow"]
    p = subprocess.run([sys.executable, "-m", "hil.harness.cli.main", "compare", str(runs["base"]), str(runs["slow"]),
                        *argv[3:]], cwd=ROOT, capture_output=True, text=True, timeout=120, check=False,
                       env={**os.environ, "COLUMNS": "400"})
    assert p.returncode == 1 and not p.stderr, p.stderr
    printed = [ln.rstrip() for ln in p.stdout.splitlines() if not ln.startswith("note: ")]
    want, got = _shape(example[1:]), _shape(printed)
    assert got["title"] == want["title"] and got["header"] == want["header"]
    assert got["rows"].keys() == want["rows"].keys()  # the same checks, in the README as printed
    for key, cells in want["rows"].items():
        # Figures with units, changes, intervals, limits, P(worse): the same form (the numbers are this machine's).
        assert got["rows"][key] == cells, (key, got["rows"][key])
    from hil.harness.check.gate import Verdict

    assert want["verdicts"] <= {v.value for v in Verdict} and got["verdicts"] <= {v.value for v in Verdict}
    assert got["judged"] == want["judged"]
    # The lines under the table: the check with its numbers, then the reason, in the same form.
    numbers = re.compile(r"ego\d+ (\w+ )?\w+ [\d.]+ → [\d.]+ (ms|%), [+-][\d.]+ (ms \(([+-][\d.]+ %|×\d+)\)|pp), "
                         r"limit ≤ [\d.]+ (ms|%)")
    assert want["over"] and {_cell_shape(r) for _, _, r in got["over"]} <= {_cell_shape(r) for _, _, r in want["over"]}
    for head, _, _ in want["over"] + got["over"]:
        assert numbers.fullmatch(head), head
    assert re.sub(r"\(.*\)", "", got["last"]) == re.sub(r"\(.*\)", "", want["last"])
    # Every row over its limit that did not fail has its line with the numbers under the table.
    rows = [ln for ln in printed if ln.startswith("│") and "over, not significant" in ln]
    assert len(rows) == sum("over the limit but not significant" in ln for ln in printed)


def test_junit_and_json_have_one_case_per_check(runs: dict[str, Path], tmp_path: Path,
                                                capsys: pytest.CaptureFixture[str]) -> None:
    from tests.harness.junit_check import read_junit

    junit, js = tmp_path / "c.xml", tmp_path / "c.json"
    code = hil_main(["compare", str(runs["base"]), str(runs["slow"]), "--stage", "inference", "--stage", "transport",
                     "--junit", str(junit), "--json", str(js)])
    assert code == 1
    (sb, xb), (sr, xr) = load_run(runs["base"]), load_run(runs["slow"])
    from hil.harness.check.gate_tolerances import Tolerances as Tol

    checks = compare(sb, sr, Tol(only_stages=("inference", "transport")), base_samples=xb, run_samples=xr)
    (suite,) = read_junit(junit)
    doc = json.loads(js.read_text())
    assert doc["exit_code"] == 1 and not doc["passed"] and suite.properties["exit_code"] == "1"
    assert len(suite.cases) == len(checks) == len(doc["checks"])
    for c in checks:
        case = suite.cases[f"{c.vehicle} {c.stage} {c.metric}".replace(" - ", " ")]
        assert case.failed == c.verdict.fails and case.properties["verdict"] == c.verdict.value
        assert case.properties["limit"] == str(c.limit) and case.properties["p_worse"] == str(c.p_worse)
        if c.verdict.fails:
            assert case.message.endswith(": REGRESSION") and f"limit ≤ {c.limit:.3f} ms" in case.message
        if c.verdict is Verdict.NOT_SIGNIFICANT:  # passes, and says why
            assert not case.failed and "over the limit but not significant (P(worse)" in (case.system_out or "")
