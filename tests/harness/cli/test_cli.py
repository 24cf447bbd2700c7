"""``hil`` as a user meets it: one-line errors with exit code 2 for mistakes, and a
run that is stopped (Ctrl-C, SIGTERM) still leaves a finalized MCAP."""

from __future__ import annotations

import argparse
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests.conftest import GL_BACKEND, read_mcap, recording_started

ROOT = Path(__file__).resolve().parents[3]


def hil(*args: str, timeout: float = 60) -> subprocess.CompletedProcess[str]:
    env = dict(os.environ, MUJOCO_GL=GL_BACKEND)
    return subprocess.run([sys.executable, "-m", "hil.harness.cli.main", *args], cwd=ROOT, env=env,
                          capture_output=True, text=True, timeout=timeout, check=False)


def assert_one_line_error(p: subprocess.CompletedProcess[str], *needles: str) -> None:
    assert p.returncode == 2, (p.returncode, p.stdout, p.stderr)
    assert "Traceback" not in p.stderr + p.stdout
    lines = [ln for ln in p.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1, p.stderr
    for n in needles:
        assert n in lines[0], lines[0]


def test_version():
    p = hil("--version")
    assert p.returncode == 0 and p.stdout.startswith("hil ")


def test_a_reader_that_leaves_early_gets_no_traceback():
    # hil scenarios --json | head -c 1: the pipe is closed before hil has written.
    p = subprocess.Popen([sys.executable, "-m", "hil.harness.cli.main", "scenarios", "--json"], cwd=ROOT,
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    assert p.stdout is not None and p.stderr is not None
    p.stdout.close()
    err = p.stderr.read().decode()
    assert p.wait(timeout=60) == 1 and err == "", err


def _command_help(parser: argparse.ArgumentParser, name: str) -> str:
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return str(sub.choices[name].format_help())


def test_every_command_has_the_same_help_alone_as_among_all():
    # hil builds only the parser of the command it is given (a quicker start) ...
    from hil.harness.cli.parser import _PARSERS, build_parser

    every = build_parser()
    for name in _PARSERS:
        assert _command_help(build_parser(name), name) == _command_help(every, name), name
    # ... and imports no other command's module for it.
    code = ("import sys; from hil.harness.cli.parser import build_parser; build_parser('run'); "
            "print(sorted(m for m in sys.modules if m.startswith(('hil.harness.check', 'hil.harness.search', "
            "'hil.harness.study', 'hil.training', 'hil.harness.report.rosbag2'))))")
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]", out.stdout


def test_missing_config(tmp_path):
    assert_one_line_error(hil("run", str(tmp_path / "nope.yaml")), "not found", "nope.yaml")


def test_yaml_syntax_error(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("name: x\ncamera: [1, 2\n")
    assert_one_line_error(hil("run", str(bad)), "bad.yaml", "line")


def test_unknown_key(tmp_path):
    cfg = tmp_path / "c.yaml"
    cfg.write_text("camera:\n  fpss: 10\n")
    assert_one_line_error(hil("run", str(cfg)), "fpss", "camera")


def test_unknown_scenario_lists_valid_ones(tmp_path):
    assert_one_line_error(hil("run", "hil_configs/demo.yaml", "--set", "scenario.name=nowhere",
                              "--out", str(tmp_path / "r")), "nowhere", "stopped_car")


def test_parameter_out_of_range(tmp_path):
    assert_one_line_error(hil("run", "hil_configs/demo.yaml", "--set", "scenario.params.gap_m=5000",
                              "--out", str(tmp_path / "r")), "gap_m", "[15, 150]")


def test_a_physics_core_this_machine_has_not_is_refused_before_anything(tmp_path):
    # It ran unpinned, with exit 0, said only in summary.json's scheduling line.
    core = max(os.sched_getaffinity(0)) + 1
    assert_one_line_error(hil("run", "hil_configs/demo.yaml", "--set", f"engine.physics_cpu={core}",
                              "--out", str(tmp_path / "r")), "engine.physics_cpu", f"core {core} is not one")
    assert not (tmp_path / "r").exists()


def test_target_command_missing(tmp_path):
    assert_one_line_error(hil("run", "hil_configs/demo.yaml", "--set", "target.command=[/no/such/ai]",
                              "--out", str(tmp_path / "r")), "not found", "/no/such/ai")


def test_target_exits_at_once(tmp_path):
    p = hil("run", "hil_configs/demo.yaml", "--out", str(tmp_path / "r"), "--set",
            'target.command=["{python}", "-c", "import sys; print(\'no model file\'); sys.exit(4)"]')
    assert_one_line_error(p, "exited with code 4", "no model file")
    # The half-made folder says so (issue 14 item 11), and the same --out can be used again.
    assert "exited with code 4" in (tmp_path / "r" / "FAILED").read_text()
    assert not (tmp_path / "r" / "summary.json").exists()


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_stopped_run_finalizes_mcap(tmp_path, sig):
    out = tmp_path / "r"
    env = dict(os.environ, MUJOCO_GL=GL_BACKEND)
    proc = subprocess.Popen([sys.executable, "-m", "hil.harness.cli.main", "run", "hil_configs/demo.yaml", "--out", str(out),
                             "--no-progress", "--set", "duration_s=60", "--set",
                             'target.command=["{python}", "-m", "hil.targets.echo"]'],
                            cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        # Wait (bounded) until the run is recording: its target has answered frames.
        deadline = time.monotonic() + 60
        log = out / "target-ego0.log"
        mcap = out / "run.mcap"
        while time.monotonic() < deadline and not recording_started(mcap):
            if proc.poll() is not None:
                break
            time.sleep(0.05)
        assert proc.poll() is None, proc.communicate()
        proc.send_signal(sig)
        stdout, stderr = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 1, (stdout, stderr)
    assert "Traceback" not in stderr
    assert "ended early" in stdout and signal.Signals(sig).name in stdout
    msgs = read_mcap(mcap)
    assert msgs["/ego0/pipeline"], "nothing recorded"
    assert (out / "summary.json").exists() and log.exists()


def test_clock_shows_synced_targets():
    p = hil("clock", "hil_configs/demo.yaml", "--bursts", "2", "--set", "timing.sync.interval_s=0.1",
            "--set", 'target.command=["{python}", "-m", "hil.targets.echo", "--clock-offset-s", "2.5"]')
    assert p.returncode == 0, p.stderr
    assert "ego0" in p.stdout and "synced" in p.stdout
    assert "+2500.0" in p.stdout.replace("\u202f", "")  # offset shown in ms: +2500.0xx ms


@pytest.mark.parametrize("n", ["0", "-1"])
def test_clock_refuses_a_count_of_bursts_below_one(n):
    # `--bursts -1` (and 0) ran until Ctrl-C (README walkthrough).
    assert_one_line_error(hil("clock", "hil_configs/demo.yaml", "--bursts", n), "--bursts", f"(got {n})")


# --- a newcomer's first hour (issue 14, items 14, 17, 18) ----------------------------


def test_target_help_lists_the_targets():
    p = hil("target", "--help")
    assert p.returncode == 0, p.stderr
    assert "usage: hil target {cnn|cv|echo}" in p.stdout and "hil target cv --transport zenoh" in p.stdout
    bare = hil("target")
    assert bare.returncode == 2 and "usage: hil target" in bare.stderr and "Traceback" not in bare.stderr


@pytest.mark.parametrize("name", ["cv", "echo"])
def test_target_name_help_names_the_hil_command(name):
    p = hil("target", name, "--help")
    assert p.returncode == 0, p.stderr
    assert p.stdout.startswith(f"usage: hil target {name} ") and "--transport" in p.stdout


def test_switching_scenario_by_name_says_how_to_reset_its_params(tmp_path):
    p = hil("run", "hil_configs/demo.yaml", "--set", "scenario.name=cut_in", "--out", str(tmp_path / "r"))
    assert_one_line_error(p, "gap_m", "unknown parameter of scenario 'cut_in'", "--set 'scenario.params={}'")


def test_final_table_fits_80_columns_without_cut_headers():
    from rich.console import Console

    from hil.harness.cli.progress import final_table

    s = {"name": "demo", "sim_time_s": 15.0, "wall_time_s": 15.2,
         "realtime": {"mode": "realtime", "achieved_factor": 1.0, "late_steps": 1900},
         "vehicles": {"ego0": {"frames_sent": 300, "estimates_applied": 299, "dropped": 1, "frames_per_s": 19.9,
                               "latency_ms": {"end_to_end": {"p50_ms": 12.3, "p99_ms": 40.1, "max_ms": 62.0}},
                               "outcome": {"min_gap_m": 5.2, "collisions": 0}}}}
    console = Console(width=80, record=True, force_terminal=False)
    console.print(final_table(s))
    text = console.export_text()
    assert "…" not in text, text
    for word in ("vehicle", "frames", "applied", "dropped", "fps", "e2e", "p50", "p99", "max", "gap", "collisions",
                 "ego0", "300", "299", "19.9", "12.3", "40.1", "62.0", "5.20"):
        assert word in text, (word, text)
    assert max(len(line.rstrip()) for line in text.splitlines()) <= 80
    # The run's line wraps at the console's width, not at the table's (~64).
    head = [line.rstrip() for line in text.splitlines()[:2]]
    assert head == ["demo: 15.00 s simulated in 15.20 s (realtime, real-time factor 1.00, late steps", "1900)"], text


def test_realtime_warning_says_what_was_not_kept():
    from hil.harness.cli.main import realtime_warning

    rt = {"mode": "realtime", "requested_factor": 1.0, "achieved_factor": 1.0, "late_steps": 1900,
          "late_tolerance_ms": 10.0, "max_lateness_ms": 62.0, "kept_realtime": False}
    text = realtime_warning(rt, sim_steps=7500)
    assert text is not None and "factor 1.00 of 1" not in text
    assert "1900 of 7500 physics steps ran more than 10 ms late (worst 62.0 ms)" in text and "lockstep" in text
    assert "camera pipeline" not in text
    slow = realtime_warning(dict(rt, achieved_factor=0.5), sim_steps=7500)
    assert slow is not None and "0.50x wall-clock speed where 1x was asked" in slow
    assert realtime_warning(dict(rt, kept_realtime=True), sim_steps=7500) is None
    cams = realtime_warning(dict(rt, lagging=["camera"], camera={"late_frames": 7, "frames": 40, "tolerance_ms": 50.0,
                                                                 "worst_lag_ms": 81.25}), sim_steps=7500)
    assert cams is not None and "physics" not in cams
    assert "the camera pipeline lagged: 7 of 40 frames left more than 50 ms after their camera instant" in cams
    assert "(worst 81.2 ms)" in cams or "(worst 81.3 ms)" in cams
