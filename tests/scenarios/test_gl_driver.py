"""The GL driver's settings the harness chooses where the user has not
(``hil.scenarios.gl.GL_DRIVER_DEFAULTS``): a render worker waiting for the GPU sleeps
instead of spinning on the cores the shards need."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

_SHOW = ("import os; from hil.scenarios.gl import select_backend; select_backend(); "
         "print(repr(os.environ.get('__GL_YIELD')))")


def _yield_after_select(env_yield: str | None) -> str:
    env = {k: v for k, v in os.environ.items() if k != "__GL_YIELD"}
    if env_yield is not None:
        env["__GL_YIELD"] = env_yield
    env.setdefault("MUJOCO_GL", "egl")  # no probe needed: the choice is the setting under test
    out = subprocess.run([sys.executable, "-c", _SHOW], env=env, capture_output=True, text=True, check=True)
    return out.stdout.strip()


@pytest.mark.parametrize(("given", "after"), [(None, "'USLEEP'"), ("NOTHING", "'NOTHING'"), ("", "''")])
def test_select_backend_sets_gl_yield_only_where_the_user_left_it_unset(given: str | None, after: str) -> None:
    assert _yield_after_select(given) == after


_EARLY = ("import os; from hil.scenarios import gl; gl.start_probe(); early = gl._early; "
          "print(early is not None, gl.select_backend(), early.returncode, gl._early is None); "
          "gl.start_probe(); late = gl._early; print(late); "  # MUJOCO_GL is set now: nothing started
          "os.environ.pop('MUJOCO_GL'); gl.start_probe(); p = gl._early; gl.cancel_probe(); "
          "print(p.poll() is not None, gl._early is None)")


def test_an_early_probe_is_the_one_select_backend_reads_and_cancel_ends_it(gl_backend) -> None:
    # hil run starts the probe before loading its config and modules: select_backend
    # reads that child's outcome (no second probe); a command that ends first kills it.
    env = {k: v for k, v in os.environ.items() if k != "MUJOCO_GL"}
    out = subprocess.run([sys.executable, "-c", _EARLY], env=env, capture_output=True, text=True, check=True,
                         timeout=120)
    first, second, third = out.stdout.split("\n")[:3]
    started, chosen, code, read = first.split()
    assert started == "True" and chosen == gl_backend and read == "True"
    assert (code == "0") == (gl_backend == "egl")  # the EGL probe's own outcome was the one read
    assert second == "None"
    assert third == "True True"


@pytest.mark.parametrize("argv, early", [
    (["calibrate", "hil_configs/calibrate.yaml"], True), (["replay", "runs/x", "c1"], True),
    (["search", "hil_configs/search.yaml"], True), (["search", "merge", "out", "a"], False),
    (["search", "report", "c"], False), (["calibrate", "--help"], False), (["cases", "runs/x"], False),
    (["report", "runs/x"], False), ([], False)])
def test_the_commands_that_render_start_the_gl_probe_first(argv: list[str], early: bool) -> None:
    from hil.harness.cli.main import _renders

    assert _renders(argv) is early


@pytest.mark.parametrize(("value", "why"), [("bogus", "not a backend MuJoCo renders with here"),
                                          ("disable", "not a backend MuJoCo renders with here"),
                                          ("glx", "needs a display and none is set ($DISPLAY)")])
def test_a_mujoco_gl_that_cannot_render_is_one_line_not_a_traceback(tmp_path, value: str, why: str) -> None:
    root = Path(__file__).resolve().parents[2]
    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY")}
    p = subprocess.run([sys.executable, "-m", "hil.harness.cli.main", "run", "hil_configs/demo.yaml", "--out",
                        str(tmp_path / "run"), "--no-progress"], cwd=root, env=dict(env, MUJOCO_GL=value),
                       capture_output=True, text=True, timeout=120)
    assert p.returncode == 2, p.stderr[-2000:]
    assert p.stderr.strip().splitlines() == [f"hil: error: MUJOCO_GL={value}: {why}; "
                                             "use egl or osmesa (headless), or unset it to let hil choose"]
    assert not (tmp_path / "run").exists()
