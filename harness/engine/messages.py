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

What the physics process sends goes through shared-memory rings it never waits on
(``hil.harness.engine.rings``), as bytes: :func:`encode` and :func:`decode` are that
codec (fixed little-endian headers, the state vectors as float64, the rare parts
(collisions, the lateness histogram) as JSON; no pickle).
"""

from __future__ import annotations

import json
import struct
from typing import Any, NamedTuple

import numpy as np

from hil.scenarios.ground_truth import Collision

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
    capture at it; ``collisions`` began since the previous one; ``unrendered`` are
    those of ``vis`` whose render worker could not take the job (it fell behind)."""

    vis: tuple[int, ...]
    t_state_ns: int
    steps: int
    qpos: np.ndarray
    qvel: np.ndarray
    collisions: tuple[Any, ...]  # hil.scenarios.ground_truth.Collision
    unrendered: tuple[int, ...] = ()
    masks: tuple[int, ...] = ()  # of each of ``vis``: the bit mask of its rig's cameras that capture (empty: 1 each)

    def cameras(self, i: int) -> int:
        """The camera bit mask of ``vis[i]``."""
        return self.masks[i] if self.masks else 1


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
    """Render the cameras of egos ``vis`` in the world of ``steps`` (camera instant
    ``t_state_ns``)."""

    steps: int
    qpos: np.ndarray
    qvel: np.ndarray
    vis: tuple[int, ...]
    t_state_ns: int
    masks: tuple[int, ...] = ()  # of each of ``vis``: its rig's cameras to render (bit k: camera k; empty: 1 each)


# -- render worker <-> run ------------------------------------------------------------------


class WorkerReady(NamedTuple):
    """A render worker is ready; ``renderer``: its OpenGL renderer (``GL_RENDERER``;
    empty where it could not be read)."""

    pid: int
    renderer: str = ""


class Warm(NamedTuple):
    """Render every camera of the worker again and again until ``until_ns`` (the run's
    start): a GPU that idled while the targets started leaves its idle state before the
    first frame, not during the first second (``engine.render_warm_ms``)."""

    until_ns: int


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
    camera: int = 0  # the camera of the vehicle's rig (0: the first or only one)


class CameraTruthReady(NamedTuple):
    """What ``vehicle``'s camera ``camera`` showed at ``steps`` (segmentation boxes)."""

    vehicle: str
    steps: int
    truth: Any  # hil.scenarios.ground_truth.CameraTruth
    camera: int = 0  # the camera of the vehicle's rig (0: the first or only one)


class WorkerFailed(NamedTuple):
    text: str


class StopWorker(NamedTuple):
    """Leave (the run is over)."""


# -- the run process's own -------------------------------------------------------------------


class ChildGone(NamedTuple):
    """The pipe of child ``name`` (``"physics"``, ``"render-<w>"``) closed."""

    name: str


# -- the ring codec -----------------------------------------------------------------------------

_KIND = struct.Struct("<B")
_STATE = struct.Struct("<BqqHHHIHB")   # kind, t_state_ns, steps, len(vis), nq, nv, len(collisions), len(unrendered), masks?
_APPLIED = struct.Struct("<BiqqqHH")   # kind, vi, frame_id, t_apply_ns, steps, nq, nv
_JOB = struct.Struct("<BqqHHHB")       # kind, t_state_ns, steps, len(vis), nq, nv, masks?
_FINISHED = struct.Struct("<Bq")       # kind, steps
_DONE = struct.Struct("<BqHHII")       # kind, steps, nq, nv, len(lateness JSON), len(collisions JSON)
_K_STATE, _K_APPLIED, _K_JOB, _K_FINISHED, _K_DONE = 1, 2, 3, 4, 5


def _f64(a: np.ndarray) -> bytes:
    return np.ascontiguousarray(a, np.float64).tobytes()


def _collisions_json(cs: tuple[Any, ...]) -> bytes:
    return json.dumps([c.to_json() for c in cs], separators=(",", ":")).encode() if cs else b""


def _collisions(b: bytes) -> tuple[Collision, ...]:
    return tuple(Collision(**d) for d in json.loads(b)) if b else ()


def encode(msg: WorldState | Applied | RenderJob | Finished | Done) -> bytes:
    """``msg`` as the bytes a ring carries.

    Raises:
        TypeError: a message of another kind.
    """
    match msg:
        case WorldState():
            coll = _collisions_json(msg.collisions)
            return b"".join((_STATE.pack(_K_STATE, msg.t_state_ns, msg.steps, len(msg.vis), msg.qpos.size,
                                         msg.qvel.size, len(coll), len(msg.unrendered), bool(msg.masks)),
                             np.asarray(msg.vis + msg.unrendered, "<u2").tobytes(), _masks(msg.masks),
                             _f64(msg.qpos), _f64(msg.qvel), coll))
        case Applied():
            return b"".join((_APPLIED.pack(_K_APPLIED, msg.vi, msg.frame_id, msg.t_apply_ns, msg.steps,
                                           msg.qpos.size, msg.qvel.size), _f64(msg.qpos), _f64(msg.qvel)))
        case RenderJob():
            return b"".join((_JOB.pack(_K_JOB, msg.t_state_ns, msg.steps, len(msg.vis), msg.qpos.size,
                                       msg.qvel.size, bool(msg.masks)),
                             np.asarray(msg.vis, "<u2").tobytes(), _masks(msg.masks), _f64(msg.qpos),
                             _f64(msg.qvel)))
        case Finished():
            return _FINISHED.pack(_K_FINISHED, msg.steps)
        case Done():
            lat = json.dumps(msg.lateness, separators=(",", ":")).encode()
            coll = _collisions_json(msg.collisions)
            return b"".join((_DONE.pack(_K_DONE, msg.steps, msg.qpos.size, msg.qvel.size, len(lat), len(coll)),
                             _f64(msg.qpos), _f64(msg.qvel), lat, coll))
    raise TypeError(f"no ring encoding for {type(msg).__name__}")


def _masks(masks: tuple[int, ...]) -> bytes:
    return np.asarray(masks, "<u4").tobytes()


def _read_masks(b: bytes, at: int, n: int, present: int) -> tuple[tuple[int, ...], int]:
    """The camera masks of ``n`` egos at ``at`` (when ``present``), and where they end."""
    if not present:
        return (), at
    return tuple(np.frombuffer(b, "<u4", n, at).tolist()), at + 4 * n


def _vectors(b: bytes, at: int, nq: int, nv: int) -> tuple[np.ndarray, np.ndarray, int]:
    qpos = np.frombuffer(b, np.float64, nq, at)
    at += 8 * nq
    qvel = np.frombuffer(b, np.float64, nv, at)
    return qpos, qvel, at + 8 * nv


def decode(b: bytes) -> WorldState | Applied | RenderJob | Finished | Done:
    """A ring record back as its message (the vectors are read-only views of ``b``).

    Raises:
        ValueError: an unknown kind (not one of ours).
    """
    kind = b[0]
    if kind == _K_STATE:
        _, t_state, steps, n_vis, nq, nv, n_coll, n_un, has_masks = _STATE.unpack_from(b)
        at = _STATE.size
        ids = np.frombuffer(b, "<u2", n_vis + n_un, at).tolist()
        masks, at = _read_masks(b, at + 2 * (n_vis + n_un), n_vis, has_masks)
        qpos, qvel, at = _vectors(b, at, nq, nv)
        return WorldState(tuple(ids[:n_vis]), t_state, steps, qpos, qvel, _collisions(b[at:at + n_coll]),
                          tuple(ids[n_vis:]), masks)
    if kind == _K_APPLIED:
        _, vi, frame_id, t_apply, steps, nq, nv = _APPLIED.unpack_from(b)
        qpos, qvel, _ = _vectors(b, _APPLIED.size, nq, nv)
        return Applied(vi, frame_id, t_apply, steps, qpos, qvel)
    if kind == _K_JOB:
        _, t_state, steps, n_vis, nq, nv, has_masks = _JOB.unpack_from(b)
        vis = tuple(np.frombuffer(b, "<u2", n_vis, _JOB.size).tolist())
        masks, at = _read_masks(b, _JOB.size + 2 * n_vis, n_vis, has_masks)
        qpos, qvel, _ = _vectors(b, at, nq, nv)
        return RenderJob(steps, qpos, qvel, vis, t_state, masks)
    if kind == _K_FINISHED:
        return Finished(_FINISHED.unpack_from(b)[1])
    if kind == _K_DONE:
        _, steps, nq, nv, n_lat, n_coll = _DONE.unpack_from(b)
        qpos, qvel, at = _vectors(b, _DONE.size, nq, nv)
        lateness = json.loads(b[at:at + n_lat])
        return Done(lateness, steps, qpos, qvel, _collisions(b[at + n_lat:at + n_lat + n_coll]))
    raise ValueError(f"not an engine ring record (kind {kind})")


__all__ = ["Advance", "Applied", "ApplyControl", "CameraTruthReady", "ChildGone", "Done", "Exit", "Finished",
           "FrameReady", "Halt", "PhysicsReady", "RenderJob", "Start", "StopWorker", "WorkerFailed", "WorkerReady",
           "WorldState", "decode", "encode"]
