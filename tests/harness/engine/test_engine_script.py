"""The engine's children never import the caller's main script: a user script that
calls ``execute`` at module level, without an ``if __name__ == "__main__"`` guard,
runs once and works (spawned children would otherwise run it again)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from tests.conftest import GL_BACKEND

ROOT = Path(__file__).resolve().parents[3]

SCRIPT = """
import sys
from pathlib import Path
from hil.harness.config.loading import parse_config
from hil.harness.run.driver import execute, prepare_out_dir
print("script body ran", flush=True)
cfg = parse_config({"name": "script", "mode": "lockstep", "duration_s": 0.5, "progress": False,
                    "target": {"command": [sys.executable, "-m", "hil.targets.echo"]}})
r = execute(cfg, out_dir=prepare_out_dir(Path(sys.argv[1])), gl_backend=sys.argv[2],
            install_signal_handlers=False)
print("frames", r.summary["vehicles"]["ego0"]["frames_sent"], flush=True)
"""


@pytest.mark.slow
def test_unguarded_user_script_runs_once(tmp_path):
    script = tmp_path / "user_script.py"
    script.write_text(SCRIPT)
    env = dict(os.environ, MUJOCO_GL=GL_BACKEND, PYTHONPATH=str(ROOT))
    p = subprocess.run([sys.executable, str(script), str(tmp_path / "run"), GL_BACKEND], cwd=tmp_path, env=env,
                       capture_output=True, text=True, timeout=180, check=False)
    assert p.returncode == 0, p.stderr[-3000:]
    assert p.stdout.count("script body ran") == 1, p.stdout
    assert "frames 10" in p.stdout, p.stdout
    assert json.loads((tmp_path / "run" / "summary.json").read_text())["ended_by"] == "duration"
