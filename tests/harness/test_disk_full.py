"""A disk that fills during a run: the run ends early with a clear reason, the
summary and the report are still written (a reserve kept on the disk is released
for them), and what was recorded stays readable."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from tests.conftest import GL_BACKEND

ROOT = Path(__file__).resolve().parents[2]


@pytest.mark.slow
def test_disk_filling_during_the_run_ends_it_and_keeps_the_summary(tmp_path):
    if os.geteuid() != 0:
        pytest.skip("needs root to mount a small tmpfs")
    disk = tmp_path / "disk"
    disk.mkdir()
    # 3 MiB: room for the start-up probe (1 MiB, freed) and the reserve (2 MiB); raw
    # 640x480 frames (~300 KB/s after compression) fill the rest within seconds.
    if subprocess.run(["mount", "-t", "tmpfs", "-o", "size=3m", "tmpfs", str(disk)], check=False,
                      capture_output=True).returncode != 0:
        pytest.skip("cannot mount a tmpfs here")
    try:
        out = disk / "run"
        env = dict(os.environ, MUJOCO_GL=GL_BACKEND)
        p = subprocess.run([sys.executable, "-m", "hil.harness.cli.main", "run", "hil_configs/demo.yaml", "--no-progress",
                            "--out", str(out), "--set", "duration_s=40",
                            "--set", "camera.encoding=raw", "--set", "camera.width=640", "--set", "camera.height=480"],
                           cwd=ROOT, env=env, capture_output=True, text=True, timeout=180, check=False)
        assert p.returncode == 1, (p.returncode, p.stdout[-2000:], p.stderr[-2000:])
        assert "Traceback" not in p.stderr + p.stdout, p.stderr[-3000:]
        s = json.loads((out / "summary.json").read_text())
        assert "recording failed" in s["ended_by"], s["ended_by"]
        assert s["sim_time_s"] < 35, "the run should end soon after the disk filled"
        assert (out / "report.html").stat().st_size > 0
        assert not (out / ".hil-reserve").exists()
    finally:
        subprocess.run(["umount", str(disk)], check=False)
