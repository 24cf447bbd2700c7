"""A render worker that fails mid-run ends the run early, saying what failed: the
run's outputs are kept and every frame sent is accounted for."""

from __future__ import annotations

import sys
from pathlib import Path

from hil.harness.config.loading import parse_config
from hil.harness.run.driver import execute, prepare_out_dir
from tests.conftest import GL_BACKEND, read_mcap


def test_a_failing_render_worker_ends_the_run_and_says_why(tmp_path: Path) -> None:
    cfg = parse_config({
        "name": "render-fails", "duration_s": 5.0, "progress": False,
        "target": {"command": [sys.executable, "-m", "hil.targets.echo"]},
        "engine": {"faults": {"render_fail_at_frame": 6}},
    })
    r = execute(cfg, out_dir=prepare_out_dir(tmp_path / "run"), gl_backend=GL_BACKEND, install_signal_handlers=False)
    s = r.summary
    assert "render worker" in s["ended_by"] and "frame 6 of ego0" in s["ended_by"], s["ended_by"]
    assert "InjectedRenderFault" in s["ended_by"]
    assert s["sim_time_s"] < 4.0  # it ended early, not at its duration
    v = s["vehicles"]["ego0"]
    assert v["frames_sent"] == 5  # the frames rendered before the failure
    assert v["estimates_applied"] + v["dropped"] + v["stale"] == v["frames_sent"]
    assert len(read_mcap(r.mcap_path)["/ego0/pipeline"]) == 5
    assert (tmp_path / "run" / "summary.json").exists()
