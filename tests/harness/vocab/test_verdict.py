"""The verdict a user sees: per-frame budgets, every check with its figures, the
terminal shows it first, ``--fail-on`` fails a run with exit 3, and the summary's
event counts are what ``/events`` holds."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from collections import Counter
from pathlib import Path
from typing import Any, get_args

import numpy as np
import pytest

from hil.harness.vocab.figures import VerdictFigures
from hil.harness.vocab.verdict import CheckName, checks, parse_fail_on, stage_budgets, verdict_json
from hil.harness.config.loading import parse_config
from hil.harness.config.model import VerdictName
from tests.conftest import GL_BACKEND, read_mcap

ROOT = Path(__file__).resolve().parents[3]


def hil(*args: str, timeout: float = 180) -> subprocess.CompletedProcess[str]:
    env = dict(os.environ, MUJOCO_GL=GL_BACKEND, COLUMNS="160")
    return subprocess.run([sys.executable, "-m", "hil.harness.cli.main", *args], cwd=ROOT, env=env,
                          capture_output=True, text=True, timeout=timeout, check=False)


def test_the_config_knows_every_check_by_name() -> None:
    assert set(get_args(VerdictName)) == {c.value for c in CheckName}
    cfg = parse_config({"verdict": {"fail_on": ["deadline", "collision"], "drop_fraction": 0.01}})
    assert cfg.verdict.fail_on == ["deadline", "collision"]
    with pytest.raises(Exception, match="verdict.fail_on"):
        parse_config({"verdict": {"fail_on": ["deadlines"]}})
    assert parse_fail_on("deadline, drop,deadline") == (CheckName.DEADLINE, CheckName.DROP)
    with pytest.raises(ValueError, match="valid: realtime, deadline, drop, collision, mismatch, anomaly"):
        parse_fail_on("deadline,nosuch")


def test_budgets_count_every_frame_over_its_stage_budget() -> None:
    ms = 1_000_000
    b = stage_budgets({"end_to_end": np.array([50, 99, 100, 101, 250]) * ms, "inference": np.array([], np.int64)},
                      {"end_to_end": 100.0, "inference": 20.0, "uplink": 5.0})
    assert b["end_to_end"] == {"budget_ms": 100.0, "frames": 5, "over": 2, "fraction": 0.4, "worst_ms": 250.0}
    assert b["inference"]["frames"] == 0 and b["inference"]["worst_ms"] is None
    assert b["uplink"]["frames"] == 0  # budgeted but never measured: said, not passed silently


def _summary(**over: Any) -> dict[str, Any]:
    v = {"frames_sent": 40, "frames_accounted": 40, "dropped": 0, "anomalies": {}, "mismatches": {}, "anomaly_causes": {},
         "budgets": {"end_to_end": {"budget_ms": 100.0, "frames": 40, "over": 0, "fraction": 0.0, "worst_ms": 9.5}}}
    s: dict[str, Any] = {"realtime": {"mode": "realtime", "kept_realtime": True, "lagging": [], "camera": {}},
                         "collisions": [], "vehicles": {"ego0": v}, "corner_cases": {"written": 0}}
    for k, val in over.items():
        if k in v:
            v[k] = val
        else:
            s[k] = val
    return s


def test_a_clean_run_passes_every_check_and_says_so() -> None:
    cs = checks(_summary())
    assert [c.name for c in cs] == list(CheckName) and all(c.ok for c in cs)
    assert cs[1].headline == ("met: 0 of 40 frames over budget (largest: ego0 end_to_end 0 of 40 over 100 ms, "
                              "worst 9.5 ms)")
    assert verdict_json(_summary())["passed"] is True


def test_with_no_frame_over_budget_the_largest_is_the_worst_frame() -> None:
    # Every vehicle met its budget (0 over each): the headline names the one whose worst
    # frame came nearest, not the first vehicle.
    s = _summary()
    s["vehicles"]["ego1"] = {**s["vehicles"]["ego0"], "budgets": {"end_to_end": {
        "budget_ms": 100.0, "frames": 40, "over": 0, "fraction": 0.0, "worst_ms": 33.5}}}
    s["vehicles"]["ego2"] = {**s["vehicles"]["ego0"], "budgets": {"end_to_end": {
        "budget_ms": 100.0, "frames": 40, "over": 0, "fraction": 0.0, "worst_ms": 21.9}}}
    assert checks(s)[1].headline == ("met: 0 of 120 frames over budget (largest: ego1 end_to_end 0 of 40 over "
                                     "100 ms, worst 33.5 ms)")


def test_every_frame_over_budget_is_a_missed_deadline_with_its_numbers() -> None:
    s = _summary(budgets={"end_to_end": {"budget_ms": 100.0, "frames": 40, "over": 40, "fraction": 1.0,
                                         "worst_ms": 121.3}}, dropped=2)
    v = verdict_json(s, fail_on=[CheckName.DEADLINE])
    by = {c["name"]: c for c in v["checks"]}
    assert by["deadline"]["ok"] is False
    assert by["deadline"]["headline"] == "missed: ego0: 40 of 40 frames over 100 ms end_to_end (worst 121.3 ms)"
    assert by["drop"]["ok"] is False and "2 of 40 frames" in by["drop"]["headline"]
    assert v["failed"] == ["deadline", "drop"] and v["fails_run"] == ["deadline"]
    # An allowance: 5 % of frames may miss, 10 % may drop.
    s2 = _summary(budgets={"end_to_end": {"budget_ms": 100.0, "frames": 40, "over": 2, "fraction": 0.05,
                                          "worst_ms": 101.0}}, dropped=4)
    assert verdict_json(s2, deadline_miss_fraction=0.05, drop_fraction=0.1)["passed"] is True
    assert verdict_json(s2)["failed"] == ["deadline", "drop"]


def test_collisions_mismatches_and_anomalies_are_named() -> None:
    s = _summary(collisions=[{"a": "ego0", "b": "car1", "sim_time_ns": 3_250_000_000, "closing_speed_mps": 4.04}],
                 mismatches={"state_mismatch/latency": 2, "missed_object/perception": 1},
                 anomalies={"latency_spike": 3, "dropped_frame": 1},
                 anomaly_causes={"harness": {"latency_spike": 2}}, corner_cases={"written": 1})
    by = {c.name: c for c in checks(s)}
    assert by[CheckName.COLLISION].headline == "1 collision: ego0 and car1 at 3.25 s, 4.0 m/s"
    assert by[CheckName.MISMATCH].headline == ("3: 2 state_mismatch (latency), 1 missed_object (perception); "
                                               "1 corner case written (of every kind: hil cases lists them)")
    assert by[CheckName.ANOMALY].headline == "4: 3 latency spike (2 caused by the harness), 1 dropped frame"
    # A collision between two scripted cars is not the AI's.
    assert checks(_summary(collisions=[{"a": "car1", "b": "car2"}]))[3].ok


def test_lockstep_has_no_real_time_to_keep() -> None:
    c = checks(_summary(realtime={"mode": "lockstep", "kept_realtime": True}))[0]
    assert c.ok and c.headline.startswith("not applicable")


@pytest.mark.slow
def test_a_run_over_budget_says_so_first_and_fails_on_request(tmp_path: Path) -> None:
    # Every answer takes 120 ms: every answered frame misses the 100 ms budget.
    out = tmp_path / "run"
    p = hil("run", "hil_configs/demo.yaml", "--no-progress", "--out", str(out), "--set", "duration_s=2",
            "--set", 'target.command=["{python}","-m","hil.targets.echo","--infer-ms","120"]',
            "--fail-on", "deadline,collision")
    assert p.returncode == 3, p.stdout + p.stderr
    s = json.loads((out / "summary.json").read_text())
    b = s["vehicles"]["ego0"]["budgets"]["end_to_end"]
    applied = s["vehicles"]["ego0"]["estimates_applied"]
    assert b["budget_ms"] == 100.0 and b["over"] == b["frames"] == applied > 0 and b["worst_ms"] > 120
    v = s["verdict"]
    assert "deadline" in v["failed"] and v["fails_run"] == ["deadline"] and v["fail_on"] == ["deadline", "collision"]
    lines = p.stdout.splitlines()
    first = next(i for i, ln in enumerate(lines) if ln.startswith("verdict:"))
    table = next(i for i, ln in enumerate(lines) if ln.startswith("demo:"))
    assert first < table  # the verdict before the figures
    dl = next(ln for ln in lines if ln.split()[1:2] == ["deadline"])  # its check's line
    assert "FAIL" in dl and f"{applied} of {applied} frames over 100 ms end_to_end" in dl
    assert "the run fails on: deadline (--fail-on): exit 3" in p.stdout
    assert "warnings only" not in lines[first]
    # The report's first screen is the same verdict.
    html = (out / "report.html").read_text()
    assert html.index('id="verdict"') < html.index('id="run"')
    assert f"missed: ego0: {applied} of {applied} frames over 100 ms end_to_end" in html
    assert "FAILED (fails the run)" in html
    assert "; the run fails on deadline (--fail-on)" in html  # its first line says so, as the terminal's last
    # 20 frames a second were sent: the rate is per the loop's steps, not its drain of
    # the last 120 ms answers after them (18.3 a second was said of such a run).
    assert s["vehicles"]["ego0"]["frames_per_s"] >= 19.5, (s["vehicles"]["ego0"]["frames_per_s"], s["wall_time_s"])
    warned = [n for n in v["failed"] if n not in v["fails_run"]]  # the terminal's "warn", amber here
    assert ('<span class="soft">warning</span>' in html) == bool(warned), warned
    # The summary's event counts are what /events holds, vehicle by vehicle and kind by kind.
    events = Counter((d["vehicle"], d["kind"]) for _, d in read_mcap(out / "run.mcap")["/events"])
    assert s["events"]["unrecorded"] == 0 and s["events"]["published"] == sum(events.values())
    for name, vs in s["vehicles"].items():
        assert vs["events"] == {k: n for (veh, k), n in events.items() if veh == name}
        # Every anomaly count is its kind's count on /events.
        for kind, n in vs["anomalies"].items():
            assert vs["events"][kind] == n
    assert s["events"]["run"] == {k: n for (veh, k), n in events.items() if veh is None}
    # A typo never switches the gate off.
    bad = hil("run", "hil_configs/demo.yaml", "--fail-on", "deadlines", "--out", str(tmp_path / "bad"))
    assert bad.returncode == 2 and "Traceback" not in bad.stderr
    assert bad.stderr.strip().splitlines() == [
        "hil: error: --fail-on: unknown verdict 'deadlines'; valid: realtime, deadline, drop, collision, "
        "mismatch, anomaly"]


def test_the_verdicts_first_line_says_when_failed_checks_are_only_warnings() -> None:
    # "1 check(s) failed: mismatch" over a run that exits 0 read as a fault of the tool
    # (the demo's usual perception mismatch is a warning: not in --fail-on).
    def head(failed: tuple[str, ...], fail_on: tuple[str, ...]) -> str:
        return VerdictFigures(not failed, failed, fail_on, tuple(n for n in failed if n in fail_on), {}, ()).headline

    assert head((), ()) == "all checks passed"
    assert head(("mismatch",), ()) == ("1 check failed: mismatch (warnings only: none is in --fail-on, so the run "
                                       "does not fail on them)")
    assert head(("mismatch",), ("deadline",)).endswith("so the run does not fail on them)")
    # One that fails the run says so (the report had no other line saying it; the
    # terminal ends with "the run fails on: ... exit 3").
    assert head(("deadline", "mismatch"), ("deadline",)) == ("2 checks failed: deadline, mismatch; the run fails on "
                                                             "deadline (--fail-on)")


def test_an_old_summary_says_what_it_cannot_judge() -> None:
    s = _summary()
    del s["vehicles"]["ego0"]["budgets"]
    c = checks(s)[1]
    assert c.ok and c.headline.startswith("not measured: this summary has no per-frame budgets")
