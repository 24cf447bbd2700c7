"""``hil cases`` says which cases a lockstep replay can bring back; ``hil replay``
refuses a wall-clock timing case with one line instead of a replay that cannot
reproduce it (issue 12 defect 7)."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

from hil.harness.cases.casebook import read_cases
from hil.harness.cases.replayable import Reproducibility, reproducibility
from hil.harness.cli.main import main as hil_main
from hil.harness.config.loading import parse_config
from hil.harness.run.driver import execute, prepare_out_dir
from tests.conftest import GL_BACKEND


def test_kinds() -> None:
    assert reproducibility("mismatch.state_mismatch") is Reproducibility.REPLAY
    assert reproducibility("mismatch.collision_while_safe") is Reproducibility.REPLAY
    for kind in ("deadline_miss", "latency_spike", "jitter", "clock_step", "sync_lost", "frame_rate_floor"):
        assert reproducibility(kind) is Reproducibility.REAL_TIME_ONLY, kind


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    # A blind AI (SAFE, throttle) in lockstep, and a deadline no frame can meet: a
    # mismatch case (replayable) and a deadline-miss case (real time only).
    out = prepare_out_dir(tmp_path_factory.mktemp("replayable") / "run")
    cfg = parse_config({
        "name": "replayable", "duration_s": 2.0, "progress": False, "mode": "lockstep",
        "scenario": {"name": "stopped_car", "params": {"gap_m": 15.0, "ego_speed_mps": 10.0}},
        "target": {"command": [sys.executable, "-m", "hil.targets.echo", "--throttle", "0.3"]},
        "timing": {"thresholds": {"deadline_ms": {"end_to_end": 0.01}}},
        "corner_cases": {"on_anomalies": ["deadline_miss"]}})
    execute(cfg, out_dir=out, gl_backend=GL_BACKEND, install_signal_handlers=False)
    return out


def test_cases_say_which_replay_and_replay_refuses_a_timing_case(run_dir: Path, capsys: pytest.CaptureFixture[str],
                                                               monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("COLUMNS", "240")
    rows, _ = read_cases(run_dir)
    timing = [r for r in rows if r["kind"] == "deadline_miss"]
    mismatch = [r for r in rows if r["kind"].startswith("mismatch.")]
    assert timing and mismatch, [r["kind"] for r in rows]
    assert hil_main(["cases", str(run_dir)]) == 0
    out = capsys.readouterr().out
    rows_out = {ln.split("│")[1].strip(): ln for ln in out.splitlines() if ln.count("│") > 8}
    assert " no " in rows_out[str(timing[0]["id"])] and " yes " in rows_out[str(mismatch[0]["id"])], out
    assert "real time only" in out
    assert hil_main(["replay", str(run_dir), str(timing[0]["id"])]) == 2
    err = capsys.readouterr().err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1 and "wall-clock timing anomaly" in lines[0] and "Traceback" not in err, err
    assert not (run_dir / "replays").exists(), "nothing was replayed"
