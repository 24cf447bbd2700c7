"""Scenarios: MuJoCo world building, vehicle dynamics and ground truth.

A scenario is a registered factory: ``build(params, seed, camera, physics_step_s)``
returns a ``WorldSpec``; nothing touches the simulator in a constructor. Look one up
with ``get(name)``; an unknown name lists the valid ones.
"""

from __future__ import annotations

from scenarios.registry import ScenarioDef, get, names, register

# Import for the side effect of registering the built-in library.
from scenarios import library as _library  # noqa: F401  (registration)

__all__ = ["ScenarioDef", "get", "names", "register"]
