"""``hil`` as a user meets it: one-line errors with exit code 2 for mistakes, and a
run that is stopped (Ctrl-C, SIGTERM) still leaves a finalized MCAP."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests.conftest import GL_BACKEND, read_mcap

ROOT = Path(__file__).resolve().parents[2]


def hil(*args: str, timeout: float = 60) -> subprocess.CompletedProcess[str]:
    env = dict(os.environ, MUJOCO_GL=GL_BACKEND)
    return subprocess.run([sys.executable, "-m", "harness.cli", *args], cwd=ROOT, env=env,
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


def test_target_command_missing(tmp_path):
    assert_one_line_error(hil("run", "hil_configs/demo.yaml", "--set", "target.command=[/no/such/ai]",
                              "--out", str(tmp_path / "r")), "not found", "/no/such/ai")


def test_target_exits_at_once(tmp_path):
    p = hil("run", "hil_configs/demo.yaml", "--out", str(tmp_path / "r"), "--set",
            'target.command=["{python}", "-c", "import sys; print(\'no model file\'); sys.exit(4)"]')
    assert_one_line_error(p, "exited with code 4", "no model file")


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_stopped_run_finalizes_mcap(tmp_path, sig):
    out = tmp_path / "r"
    env = dict(os.environ, MUJOCO_GL=GL_BACKEND)
    proc = subprocess.Popen([sys.executable, "-m", "harness.cli", "run", "hil_configs/demo.yaml", "--out", str(out),
                             "--no-progress", "--set", "duration_s=60", "--set",
                             'target.command=["{python}", "-m", "targets.echo"]'],
                            cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        # Wait (bounded) until the run is recording: its target has answered frames.
        deadline = time.monotonic() + 60
        log = out / "target-ego0.log"
        mcap = out / "run.mcap"
        while time.monotonic() < deadline and not (mcap.exists() and mcap.stat().st_size > 200_000):
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
            "--set", 'target.command=["{python}", "-m", "targets.echo", "--clock-offset-s", "2.5"]')
    assert p.returncode == 0, p.stderr
    assert "ego0" in p.stdout and "synced" in p.stdout
    assert "+2500.0" in p.stdout.replace("\u202f", "")  # offset shown in ms: +2500.0xx ms
