"""The render workers' warm-up before a real-time start (``engine.render_warm_ms``): a
GPU that idled while the targets started is awake for the first frames. Here (Mesa's
llvmpipe) "auto" warms nothing; asked for, the warm-up renders no frame of the run."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

from hil.harness.config.loading import parse_config
from hil.harness.engine.pool import WARM_NS, warm_lead_ns as warm_ns
from hil.harness.run.driver import execute, prepare_out_dir
from tests.conftest import GL_BACKEND


def _run(tmp_path: Path, warm: str | int) -> dict:
    cfg = parse_config({
        "name": "warm", "duration_s": 1.5, "progress": False, "seed": 1,
        "scenario": {"name": "lead_brake", "params": {"brake_at_s": 1.0}},
        "target": {"command": [sys.executable, "-m", "hil.targets.echo", "--throttle", "0.2"]},
        "engine": {"render_warm_ms": warm},
    })
    return execute(cfg, out_dir=prepare_out_dir(tmp_path / f"run-{warm}"), gl_backend=GL_BACKEND,
                   install_signal_handlers=False).summary


def test_auto_warms_on_a_gpu_only() -> None:
    assert warm_ns("auto", ["NVIDIA H200/PCIe/SSE2"] * 3) == WARM_NS
    assert warm_ns("auto", ["llvmpipe (LLVM 15.0.6, 256 bits)", ""]) == 0
    assert warm_ns("auto", [""]) == 0  # unknown: not warmed
    assert warm_ns(0, ["NVIDIA H200/PCIe/SSE2"]) == 0 and warm_ns(120, [""]) == 120_000_000


@pytest.mark.parametrize("warm", ["auto", 250])
def test_the_warm_up_comes_before_the_first_step_and_renders_no_frame_of_the_run(tmp_path: Path,
                                                                                  warm: str | int) -> None:
    s = _run(tmp_path, warm)
    rt = s["realtime"]
    assert rt["renderer"], rt  # the workers' GL_RENDERER, read from their context
    assert rt["render_warm_ms"] == (0.0 if warm == "auto" and "llvmpipe" in rt["renderer"] else 250.0)
    # The camera instants are paced from after the warm-up: every one of them rendered
    # and sent once (20 fps, 1.5 s), none late, none dropped.
    v = s["vehicles"]["ego0"]
    assert v["frames_sent"] == 30 and v["dropped"] == 0, v
    assert rt["camera"]["late_frames"] == 0 and rt["achieved_factor"] > 0.95, rt
    if warm == 250:
        assert s["harness_cost"]["start_s"] >= 0.25  # the warm-up is start-up
