"""Long work shows progress and the time left (issue 25 item 9): ``hil train``
(tests/targets/test_cnn_train.py), ``hil study`` (tests/harness/report/test_ci_outputs.py)
and ``hil compare`` over long runs, through ``WorkProgress`` and ``time_left``."""

from __future__ import annotations

import io

import numpy as np
from rich.console import Console

from hil.common.eta import time_left
from hil.harness.report.progress import WorkProgress
from hil.harness.check.gate import Method, Tolerances, compare, samples_checks
from hil.harness.check.gate_samples import RunSamples, VehicleSamples


def test_time_left_at_the_pace_so_far() -> None:
    assert time_left(0, 10, 5.0) == "estimating the time left"
    assert time_left(2, 10, 10.0) == "about 40 s left"
    assert time_left(1, 10, 60.0) == "about 9.0 min left"
    assert time_left(1, 1000, 60.0) == "about 16.6 h left"
    assert time_left(10, 10, 99.0) == "done"


def test_lines_in_a_log_and_a_bar_on_a_terminal() -> None:
    now = [100.0]
    log = Console(file=io.StringIO(), width=200)
    with WorkProgress(log, what="study", total=4, unit="points", clock=lambda: now[0]) as p:
        now[0] += 30
        p.advance(note="replicated-n1-fps20")
        now[0] += 90
        p.advance(note="replicated-n2-fps20")
    assert log.file.getvalue().splitlines() == [
        "study: 1 of 4 points done (0:30), about 1.5 min left: replicated-n1-fps20",
        "study: 2 of 4 points done (2:00), about 2.0 min left: replicated-n2-fps20"]
    quiet = Console(file=io.StringIO(), width=200)
    with WorkProgress(quiet, what="judging", total=3, lines=False) as p:
        p.advance()
    assert quiet.file.getvalue() == ""  # compare in a CI log: no progress lines
    term = Console(file=io.StringIO(), width=120, force_terminal=True)
    with WorkProgress(term, what="judging", total=3, lines=False) as p:
        p.advance(note="ego0 end_to_end")
        p._bar.refresh()
    out = term.file.getvalue()
    assert "judging" in out and "ego0 end_to_end" in out and "0:00:0" in out  # elapsed and remaining


def test_compare_reports_each_check_it_judges() -> None:
    rng = np.random.default_rng(0)

    def samples(shift: float) -> RunSamples:
        x = {s: 3.0 + shift + rng.gamma(20.0, 0.01, 120) for s in ("inference", "end_to_end")}
        return RunSamples({"ego0": VehicleSamples(x, np.zeros(120))})

    def summary() -> dict:
        st = {"count": 120, "p50_ms": 3.2, "p99_ms": 3.5, "std_ms": 0.05}
        return {"ended_by": "duration", "vehicles": {"ego0": {"drop_rate": 0.0,
                                                              "latency_ms": {"inference": st, "end_to_end": st}}}}

    xb, xr = samples(0.0), samples(1.0)
    calls = []
    checks = compare(summary(), summary(), base_samples=xb, run_samples=xr, on_judged=lambda: calls.append(1))
    judged = [c for c in checks if c.method is Method.SAMPLES]
    assert len(calls) == len(judged) == samples_checks(xb, xr, Tolerances()) == 1 + 2 * 4
    assert samples_checks(xb, xr, Tolerances(only_stages=("inference",))) == 1 + 4
