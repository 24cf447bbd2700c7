"""Choosing MuJoCo's headless OpenGL backend.

MuJoCo reads ``MUJOCO_GL`` once, when ``mujoco`` is first imported, so the choice
must be made before that. ``select_backend()`` keeps a backend the user set, else
probes EGL then OSMesa in a short-lived child process (a failed GL init can abort
the process that tries it) and sets the variable.
"""

from __future__ import annotations

import os
import subprocess
import sys

from hil.common.errors import SimulationError

_PROBE = (
    "import os, sys; os.environ['MUJOCO_GL'] = sys.argv[1]; "
    "import mujoco; "
    "m = mujoco.MjModel.from_xml_string('<mujoco><worldbody><geom size=\"1\"/></worldbody></mujoco>'); "
    "r = mujoco.Renderer(m, 16, 16); d = mujoco.MjData(m); r.update_scene(d); r.render(); r.close()"
)

# Set (where the user has not) before the GL driver loads. NVIDIA's driver spins on the CPU
# while it waits for the GPU (``__GL_YIELD`` unset: ``sched_yield`` in a loop; NOTHING: a
# bare spin); USLEEP sleeps instead. Render workers serve the capture path at a raised
# priority, so their spin took the cores the shards needed to forward the frames
# (bench/README, "start-up burst"). Mesa ignores it. ``__GL_YIELD=`` (empty) gives the
# driver's own choice back.
GL_DRIVER_DEFAULTS = {"__GL_YIELD": "USLEEP"}
# What MUJOCO_GL may say for hil to render: headless first; glfw and glx need a display.
USER_BACKENDS = ("egl", "osmesa", "glfw", "glx")

INSTALL_HINT = (
    "install Mesa's EGL (Debian: apt-get install libegl1 libegl-mesa0 libgl1-mesa-dri) "
    "or OSMesa (apt-get install libosmesa6)"
)


_early: subprocess.Popen[str] | None = None  # the EGL probe start_probe() started, not yet read


def _spawn(backend: str) -> subprocess.Popen[str]:
    return subprocess.Popen([sys.executable, "-c", _PROBE, backend], stdin=subprocess.DEVNULL,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _outcome(proc: subprocess.Popen[str], timeout_s: float) -> str | None:
    try:
        _, err = proc.communicate(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.communicate()
        return f"probe timed out after {timeout_s:g} s"
    if proc.returncode == 0:
        return None
    lines = [ln for ln in err.strip().splitlines() if ln.strip()]
    return lines[-1] if lines else f"exit code {proc.returncode}"


def probe(backend: str, *, timeout_s: float = 30.0) -> str | None:
    """Try to render one tiny image with ``backend``; return None on success or the
    last line of the failure."""
    return _outcome(_spawn(backend), timeout_s)


def _driver_defaults() -> None:
    for name, value in GL_DRIVER_DEFAULTS.items():
        os.environ.setdefault(name, value)  # inherited by the probe, the render workers, the floors


def start_probe() -> None:
    """Start the EGL probe of :func:`select_backend` now, in its child, where it will be
    needed (``MUJOCO_GL`` unset, ``mujoco`` not imported), so that it runs while the
    caller loads its config and modules (~0.5 s of a command's start). Pair with
    :func:`cancel_probe` for the paths that never select."""
    global _early
    if _early is None and not os.environ.get("MUJOCO_GL", "").strip() and "mujoco" not in sys.modules:
        _driver_defaults()  # as select_backend's own probe inherits them
        _early = _spawn("egl")


def cancel_probe() -> None:
    """End an early probe nothing read (a command that stopped before rendering)."""
    global _early
    proc, _early = _early, None
    if proc is not None and proc.poll() is None:
        proc.kill()
    if proc is not None:
        proc.communicate()


def select_backend() -> str:
    """Set ``MUJOCO_GL`` to a working headless backend and return its name (and the GL
    driver's settings of ``GL_DRIVER_DEFAULTS`` the user left unset).

    Raises:
        SimulationError: ``MUJOCO_GL`` names no backend MuJoCo renders with,
            neither EGL nor OSMesa works (with the install hint), or ``mujoco`` was
            already imported with another backend.
    """
    _driver_defaults()
    chosen = os.environ.get("MUJOCO_GL", "").strip().lower()
    if chosen:
        if chosen not in USER_BACKENDS:  # MuJoCo's own refusal is a traceback at its import
            raise SimulationError(f"MUJOCO_GL={chosen}: not a backend MuJoCo renders with here; "
                                  f"use {' or '.join(USER_BACKENDS[:2])} (headless), or unset it to let hil choose")
        if chosen in USER_BACKENDS[2:] and not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
            # Else a render worker fails to start behind GLFW's warnings, after the run began.
            raise SimulationError(f"MUJOCO_GL={chosen}: needs a display and none is set ($DISPLAY); use "
                                  f"{' or '.join(USER_BACKENDS[:2])} (headless), or unset it to let hil choose")
        return chosen
    if "mujoco" in sys.modules:
        raise SimulationError("mujoco was imported before a GL backend was chosen; call select_backend() first")
    global _early
    failures = []
    for backend in ("egl", "osmesa"):
        early = _early if backend == "egl" else None  # start_probe()'s, started earlier
        if early is not None:
            _early = None
        err = probe(backend) if early is None else _outcome(early, 30.0)
        if err is None:
            os.environ["MUJOCO_GL"] = backend
            return backend
        failures.append(f"{backend}: {err}")
    raise SimulationError(f"no headless OpenGL backend works ({'; '.join(failures)}); {INSTALL_HINT}")


def main() -> int:
    """``python -m hil.scenarios.gl``: say which backend works, or what to install."""
    try:
        print(f"MuJoCo headless rendering: {select_backend()}")
    except SimulationError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
