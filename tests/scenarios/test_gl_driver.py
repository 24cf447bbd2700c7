"""The GL driver's settings the harness chooses where the user has not
(``hil.scenarios.gl.GL_DRIVER_DEFAULTS``): a render worker waiting for the GPU sleeps
instead of spinning on the cores the shards need."""

from __future__ import annotations

import os
import subprocess
import sys

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
