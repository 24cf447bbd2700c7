"""Recordings made before the recording's encoder changed (the standard library's
JSON, tests/harness/record/fixtures/run_before_orjson) hold the same values as today's and
every reader still takes them: the run folder, ``hil compare``, the report and a
lockstep replay of their latencies."""

from __future__ import annotations

import json
import shutil
import sys
from pathlib import Path

import pytest

from hil.harness.cli.main import main as hil_main
from hil.harness.config.loading import parse_config
from hil.harness.record.run_folder import read_run
from hil.harness.report.run_report import write_report
from hil.harness.run.driver import execute, prepare_out_dir
from tests.conftest import GL_BACKEND, read_mcap

OLD = Path(__file__).parent / "fixtures" / "run_before_orjson"
# Fields a record gained after the fixture was made (each with the change that added it):
# the render worker of a frame (the Perfetto timeline), each estimate's own receipt
# stamp's uncertainty (per-message stamps). Nothing else may appear or go.
ADDED = {"/ego0/pipeline": {"render_worker", "t0p_uncertainty_ns"}}


def _cfg(**extra: object) -> dict[str, object]:
    """The fixture's own run (its config.json), for this build."""
    cfg = json.loads((OLD / "config.json").read_text())
    cfg.update(progress=False, **extra)
    cfg["target"]["command"] = [sys.executable, "-m", "hil.targets.echo", "--throttle", "0.2"]
    return cfg


@pytest.fixture(scope="module")
def new(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = prepare_out_dir(tmp_path_factory.mktemp("now") / "run")
    execute(parse_config(_cfg()), out_dir=out, gl_backend=GL_BACKEND, install_signal_handlers=False)
    return out


def test_the_same_run_records_the_same_values_as_before(new: Path) -> None:
    old, now = read_mcap(OLD / "run.mcap"), read_mcap(new / "run.mcap")
    # Lockstep with one seed: the truth is the same to the bit, whatever spells it.
    for topic in ("/ground_truth", "/ego0/truth"):
        assert [d for _, d in now[topic]] == [d for _, d in old[topic]], topic
    for topic in ("/ego0/pipeline", "/ego0/estimate", "/events", "/ego0/latency", "/scene", "/tf"):
        assert len(now[topic]) == len(old[topic]), topic
        added = ADDED.get(topic, set())
        assert [sorted(set(d) - added) for _, d in now[topic]] == [sorted(d) for _, d in old[topic]], topic


def test_every_reader_takes_a_recording_made_before(new: Path, tmp_path: Path,
                                                    capsys: pytest.CaptureFixture[str]) -> None:
    old_run, new_run = read_run(OLD), read_run(new)
    assert not old_run.truncated and old_run.vehicles == ["ego0"] == new_run.vehicles
    assert len(old_run.pipeline["ego0"]) == len(new_run.pipeline["ego0"]) == 20
    assert len(old_run.camera_times["ego0"]) == 20 and old_run.summary is not None
    # hil compare: the old run as the baseline of the new one, and of itself.
    assert hil_main(["compare", str(OLD), str(OLD)]) == 0, capsys.readouterr().out
    assert hil_main(["compare", str(OLD), str(new)]) in (0, 1)
    out = capsys.readouterr().out
    assert "end_to_end" in out and "error" not in out.lower()
    # The report of the old folder, written today.
    folder = tmp_path / "old"
    shutil.copytree(OLD, folder)
    write_report(folder)
    assert "lead_brake" in (folder / "report.html").read_text()


def test_a_lockstep_replay_takes_its_latencies_from_a_recording_made_before(tmp_path: Path) -> None:
    cfg = _cfg(lockstep={"latency": {"kind": "recorded", "path": str(OLD)}})
    r = execute(parse_config(cfg), out_dir=prepare_out_dir(tmp_path / "replay"), gl_backend=GL_BACKEND,
                install_signal_handlers=False)
    old = {d["frame_id"]: d for _, d in read_mcap(OLD / "run.mcap")["/ego0/pipeline"]}
    got = {d["frame_id"]: d for _, d in read_mcap(r.mcap_path)["/ego0/pipeline"]}
    assert r.summary["ended_by"] == "duration"
    applied = [f for f, d in old.items() if d["status"] == "ok" and f in got and got[f]["status"] == "ok"]
    assert len(applied) >= 15
    for f in applied:  # the replay applies each control after the recorded sim-time latency
        was = old[f]["sim_time_apply_ns"] - old[f]["sim_time_ns"]
        now = got[f]["sim_time_apply_ns"] - got[f]["sim_time_ns"]
        assert now >= was, (f, was, now)
