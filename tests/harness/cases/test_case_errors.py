"""A corner case that cannot be written is never lost silently: the error reaches
``CaseRecorder.errors`` (then the summary), and ``hil run`` exits 1 (issue 14, item 8)."""

from __future__ import annotations

from pathlib import Path

from hil.harness.vocab.events import Event, EventKind
from hil.harness.cases.casebook import CaseRecorder
from hil.harness.cli.main import run_exit_code
from hil.harness.cli.parser import EXIT_EARLY, EXIT_OK
from hil.harness.record.recorder import Recorder


def test_an_unexpected_error_writing_a_case_is_reported(tmp_path: Path):
    # A seed beyond SQLite's INTEGER (the config refuses it now; a hand-made meta
    # still must not kill the writer thread and leave "written: 0, errors: []").
    meta = {"name": "r", "scenario": "stopped_car", "seed": 2**70, "config_hash": "x"}
    with Recorder(tmp_path / "run.mcap") as rec:
        cases = CaseRecorder(rec, tmp_path, run_meta=meta, history_s=0.5, after_s=0.1, trigger_kinds=set())
        cases.on_event(Event(EventKind.STATE_MISMATCH, 1, "ego0", sim_time_ns=1), 1_000_000_000)
        cases.on_event(Event(EventKind.TARGET_COMMAND, 2, "ego0"), 2_000_000_000)  # not a trigger
        cases.close()
    assert cases.cases_written == 0
    assert len(cases.errors) == 1 and "OverflowError" in cases.errors[0], cases.errors


def test_case_errors_make_the_run_exit_1():
    summary = {"ended_by": "duration", "corner_cases": {"written": 1, "errors": []}}
    assert run_exit_code(summary) == EXIT_OK
    summary["corner_cases"]["errors"] = ["case 2: OverflowError: Python int too large to convert to SQLite INTEGER"]
    assert run_exit_code(summary) == EXIT_EARLY
    assert run_exit_code({"ended_by": "stopped by SIGTERM"}) == EXIT_EARLY


def test_a_case_row_without_a_window_is_one_line(tmp_path: Path):
    # A row whose window columns are NULL (damaged or tampered): `hil cases --window`
    # ended in a TypeError traceback (issue 26, item 7); now one line, exit 2, no file cut.
    from tests.harness.cli.test_cli import assert_one_line_error, hil
    from tests.harness.cases.test_replay_trust import foreign_run

    run = foreign_run(tmp_path / "r", [])
    p = hil("cases", str(run), "--window", "1")
    assert_one_line_error(p, "case 1 has no window", "window_start_ns None")
    assert not (run / "corner_cases").exists()
