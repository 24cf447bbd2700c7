"""The engine's messages: one typed record per kind, between our own processes.

Physics, render workers and the run process exchange these over ``multiprocessing``
pipes (never over a target's wire). Each kind is a ``NamedTuple``: typed fields by
name, matched by class (``match msg: case FrameReady(): ...``), and as cheap to send
as the positional tuples they replace (they pickle as a class reference and a tuple).
Times are harness-clock (``time.monotonic_ns``) nanoseconds; ``steps`` counts
physics steps from the start; ``vi`` is an ego's index in ``Simulation.egos``.

run -> physics                      physics -> run
``Start``, ``ApplyControl``,         ``PhysicsReady``, ``WorldState`` (camera instant),
``Advance`` (lockstep), ``Halt``,    ``Applied`` (a control, with ``t_apply``),
``Exit``                             ``Finished``, ``Done``

physics -> render worker            render worker -> run
``RenderJob``                        ``WorkerReady``, ``FrameReady``, ``CameraTruthReady``,
                                     ``WorkerFailed``; run -> worker: ``StopWorker``

``ChildGone`` is what the run's pump reports when a child's pipe closes.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import numpy as np

# -- run -> physics ---------------------------------------------------------------


class Start(NamedTuple):
    """Begin stepping; real time is paced from ``wall_start_ns``."""

    wall_start_ns: int


class ApplyControl(NamedTuple):
    """An estimate's control for ego ``vi``, from the answer to frame ``frame_id``."""

    vi: int
    frame_id: int
    steering_rad: float
    throttle: float
    brake: float


class Advance(NamedTuple):
    """Lockstep: apply ``controls`` (in order), then step up to ``to_step``."""

    to_step: int
    controls: tuple[ApplyControl, ...]


class Halt(NamedTuple):
    """Stop stepping (controls still apply until ``Exit``)."""


class Exit(NamedTuple):
    """Send ``Done`` and leave."""


# -- physics -> run -----------------------------------------------------------------


class PhysicsReady(NamedTuple):
    """The physics process is up; ``scheduling`` says, in words, what class it got."""

    scheduling: str


class WorldState(NamedTuple):
    """The world at a camera instant (``t_state_ns``): ``vis`` are the egos that
    capture at it; ``collisions`` began since the previous one."""

    vis: tuple[int, ...]
    t_state_ns: int
    steps: int
    qpos: np.ndarray
    qvel: np.ndarray
    collisions: tuple[Any, ...]  # hil.scenarios.ground_truth.Collision


class Applied(NamedTuple):
    """Frame ``frame_id``'s control was applied to ego ``vi`` at ``t_apply_ns``;
    the world at that instant."""

    vi: int
    frame_id: int
    t_apply_ns: int
    steps: int
    qpos: np.ndarray
    qvel: np.ndarray


class Finished(NamedTuple):
    """The physics has taken its last step (``steps`` in all)."""

    steps: int


class Done(NamedTuple):
    """The physics's last word: its lateness histogram (``LatenessHistogram.to_json``
    plus ``span_ns``) and the final state."""

    lateness: dict[str, Any]
    steps: int
    qpos: np.ndarray
    qvel: np.ndarray
    collisions: tuple[Any, ...]


# -- physics -> render worker -----------------------------------------------------------


class RenderJob(NamedTuple):
    """Render ``vehicles``' cameras in the world of ``steps`` (camera instant
    ``t_state_ns``)."""

    steps: int
    qpos: np.ndarray
    qvel: np.ndarray
    vehicles: tuple[str, ...]
    t_state_ns: int


# -- render worker <-> run ------------------------------------------------------------------


class WorkerReady(NamedTuple):
    pid: int


class FrameReady(NamedTuple):
    """A rendered, encoded frame of ``vehicle`` in its shared-memory ``slot``
    (``nbytes`` long, wire ``encoding``); ``t0_ns`` when the pixels were ready."""

    vehicle: str
    steps: int
    t_state_ns: int
    speed_mps: float
    t0_ns: int
    t_encoded_ns: int
    slot: int
    nbytes: int
    encoding: int


class CameraTruthReady(NamedTuple):
    """What ``vehicle``'s camera showed at ``steps`` (segmentation boxes)."""

    vehicle: str
    steps: int
    truth: Any  # hil.scenarios.ground_truth.CameraTruth


class WorkerFailed(NamedTuple):
    text: str


class StopWorker(NamedTuple):
    """Leave (the run is over)."""


# -- the run process's own -------------------------------------------------------------------


class ChildGone(NamedTuple):
    """The pipe of child ``name`` (``"physics"``, ``"render-<w>"``) closed."""

    name: str


__all__ = ["Advance", "Applied", "ApplyControl", "CameraTruthReady", "ChildGone", "Done", "Exit", "Finished",
           "FrameReady", "Halt", "PhysicsReady", "RenderJob", "Start", "StopWorker", "WorkerFailed", "WorkerReady",
           "WorldState"]
