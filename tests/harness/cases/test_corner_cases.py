"""Corner cases in whole runs: an AI that sees nothing and says SAFE drives into a
stopped car; the detector must say what it got wrong, keep the history, index it,
and replay it."""

from __future__ import annotations

import json
import os
import sqlite3
import subprocess
import sys
from pathlib import Path

import pytest

from hil.harness.cases.windows import write_case_windows
from hil.harness.config.loading import parse_config
from hil.harness.run.driver import execute, prepare_out_dir
from tests.conftest import GL_BACKEND, read_mcap

ROOT = Path(__file__).resolve().parents[3]


def blind_run(out: Path):
    cfg = {"name": "blind", "seed": 3, "mode": "lockstep", "duration_s": 4.0, "progress": False,
           "scenario": {"name": "stopped_car", "params": {"gap_m": 20.0, "ego_speed_mps": 8.0}},
           "target": {"command": [sys.executable, "-m", "hil.targets.echo", "--throttle", "0.3"]},
           "corner_cases": {"history_s": 2.0, "after_s": 0.5}}
    return execute(parse_config(cfg), out_dir=prepare_out_dir(out), gl_backend=GL_BACKEND,
                   install_signal_handlers=False)


@pytest.fixture(scope="module")
def blind(tmp_path_factory):
    return blind_run(tmp_path_factory.mktemp("cases") / "run")


def hil(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "hil.harness.cli.main", *args], cwd=ROOT, capture_output=True, text=True,
                          timeout=300, env=dict(os.environ, MUJOCO_GL=GL_BACKEND))


def test_blind_ai_mismatches_are_found(blind):
    v = blind.summary["vehicles"]["ego0"]
    kinds = v["mismatches"]
    assert kinds.get("missed_object/perception", 0) >= 1
    assert kinds.get("state_mismatch/perception", 0) == 2
    assert kinds.get("collision_while_safe/perception", 0) == 1
    assert v["outcome"]["collisions"] >= 1  # contacts (a bounce counts twice); one corner case
    events = [d for _, d in read_mcap(blind.mcap_path)["/events"] if d["kind"].startswith("mismatch.")]
    crit = [e for e in events if e["kind"].removeprefix("mismatch.") == "state_mismatch"]
    # SAFE against SLOW first (warning), then against STOP: reported again, critical.
    assert [e["severity"] for e in crit] == ["warning", "critical"]


def test_cases_are_indexed_with_their_history(blind):
    db = blind.out_dir / "corner_cases.sqlite"
    assert write_case_windows(blind.out_dir) == []  # cut from the finished run.mcap
    rows = sqlite3.connect(db).execute(
        "SELECT id, run, scenario, seed, params, config_hash, vehicle, kind, mcap_path, window_start_ns,"
        " window_end_ns, messages FROM cases").fetchall()
    assert len(rows) == blind.summary["corner_cases"]["written"] >= 3
    for _id, run, scenario, seed, params, chash, vehicle, kind, path, lo, hi, n in rows:
        assert (run, scenario, seed, vehicle) == ("blind", "stopped_car", 3, "ego0")
        assert json.loads(params)["gap_m"] == 20.0 and chash == blind.summary["config_hash"]
        assert path == f"corner_cases/case-{_id:04d}.mcap"
        window = read_mcap(blind.out_dir / path)
        assert window["/ego0/camera"], "the window holds the frames before the trigger"
        assert window["/ego0/pipeline"] and window["/ground_truth"]
        assert any(d["kind"] == kind for _, d in window["/events"])
        assert all(lo <= d["sim_time_ns"] <= hi for _, d in window["/ground_truth"])
        assert n == sum(len(v) for v in window.values())


def test_hil_cases_lists_and_survives_a_corrupt_row(blind, tmp_path):
    p = hil("cases", str(blind.out_dir))
    assert p.returncode == 0, p.stderr
    assert "collision_while_safe" in p.stdout and "perception" in p.stdout
    # A copy of the run with one corrupt row: reported and skipped, the rest listed.
    import shutil

    copy = tmp_path / "copy"
    shutil.copytree(blind.out_dir, copy)
    con = sqlite3.connect(copy / "corner_cases.sqlite")
    con.execute("UPDATE cases SET params = 'not json{' WHERE id = 1")
    con.commit()
    con.close()
    p = hil("cases", str(copy))
    assert p.returncode == 0 and "unreadable row skipped" in p.stdout and "Traceback" not in p.stderr


def test_hil_cases_bad_input(tmp_path):
    p = hil("cases", str(tmp_path / "nothing"))
    assert p.returncode == 2 and "no such run folder" in p.stderr and "Traceback" not in p.stderr
    (tmp_path / "run.mcap").write_text("not mcap")
    (tmp_path / "corner_cases.sqlite").write_text("garbage, not sqlite")
    p = hil("cases", str(tmp_path))
    assert p.returncode == 2 and "not a corner-case database" in p.stderr


@pytest.mark.slow
def test_replay_reproduces_the_collision(blind):
    rows = sqlite3.connect(blind.out_dir / "corner_cases.sqlite").execute(
        "SELECT id FROM cases WHERE kind = 'mismatch.collision_while_safe'").fetchall()
    (case_id,), = rows
    p = hil("replay", str(blind.out_dir), str(case_id))
    assert p.returncode == 0, (p.stdout, p.stderr)
    assert "reproduced" in p.stdout and "not reproduced" not in p.stdout
