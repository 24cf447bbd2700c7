"""Scenarios: MuJoCo world building, entities and their scripted motion, vehicle
dynamics, cameras and ground truth.

A scenario is a registered factory: ``build(params, seed, camera, physics_step_s)``
returns a ``WorldSpec``; nothing touches the simulator in a constructor. Look one up
with ``get(name)``; an unknown name lists the valid ones. ``catalog.describe()`` is
the listing ``hil scenarios`` prints.

Modules: ``path`` (straight and arc paths), ``motion`` (speed profiles, lane changes,
scripts), ``road`` and ``world`` (MJCF), ``params``/``registry``/``library`` (the
typed scenario library), ``vehicle`` (ego dynamics), ``sim`` (the MuJoCo simulation),
``render`` (cameras and segmentation), ``visibility`` (boxes, silhouettes),
``ground_truth`` (records and the reference state), ``gl`` (headless GL backend).
"""

from __future__ import annotations

# Import for the side effect of registering the built-in library.
from hil.scenarios import library as _library  # noqa: F401  (registration)
from hil.scenarios.registry import ScenarioDef, get, names, register

__all__ = ["ScenarioDef", "get", "names", "register"]
