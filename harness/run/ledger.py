"""The frame ledger: where each frame of a run stands between its render and its
settled record.

A frame is *rendering* from its camera instant until its ``FrameReady``; *in flight*
from ``send_frame`` until its estimate arrives (or its timeout: dropped). An answered
frame whose control went to the physics is *applying* until the physics confirms it
(``Applied``, with ``t_apply``); records of the same vehicle settled meanwhile (a
stale estimate, a drop) are *held behind* it, so the analysis sees each vehicle's
records in receipt order. In lockstep the controls of one camera instant wait in
``lockstep_controls`` for the next ``Advance``.

Changed under its shard's lock; :meth:`busy` and :meth:`in_flight` may be read
without it (counts, never an iteration). Nothing here blocks, sends or records: the
shard does, with what the ledger answers. Vehicles are their ids (``vi``).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple

from hil.adapters.wire.messages import Estimate
from hil.harness.engine.messages import ApplyControl
from hil.harness.run.vehicle_state import InFlight, VehicleRun


class Answer(NamedTuple):
    """A frame in flight and the estimate that answered it, received at ``t0p_ns``;
    ``rest``: the other frames of its frame set the same ESTIMATE answered (a target
    that answers per set), settled with it."""

    v: VehicleRun
    fl: InFlight
    m: Estimate
    t0p_ns: int
    rest: tuple[InFlight, ...] = ()


Task = tuple[Callable[..., None], tuple[Any, ...]]  # an analysis task: fn(*args)


class FrameLedger:
    """In-flight frames, controls being applied and the records held behind them."""

    def __init__(self) -> None:
        # (vi, steps) of frames whose camera instant came and whose FrameReady did not
        # yet, and of frames ready before their instant's world state (the worker has
        # the job from the physics directly; its pipe may overtake the physics's ring).
        self._rendering: set[tuple[int, int, int]] = set()  # (vi, steps, camera)
        self._ready_early: set[tuple[int, int, int]] = set()
        self.lockstep_controls: list[ApplyControl] = []
        self._in_flight: dict[int, dict[int, InFlight]] = {}
        self._n_in_flight = 0
        self._applying: dict[tuple[int, int], Answer] = {}
        self._applying_of: dict[int, int] = {}  # vi -> how many of its controls are applying
        self._behind: dict[int, list[Task]] = {}
        self._last_applied: dict[int, int] = {}

    # -- rendering -------------------------------------------------------------------

    def capturing(self, steps: int, caps: list[tuple[int, int]]) -> None:
        """The world state of camera instant ``steps``: cameras ``caps`` (ego ``vi``,
        camera of its rig) are rendering. States come in order, so a frame ready early
        for an instant before this one never meets its state (lost on a full ring):
        forgotten."""
        early = self._ready_early
        for vi, cam in caps:
            key = (vi, steps, cam)
            if key in early:
                early.discard(key)
            else:
                self._rendering.add(key)
        if early:
            self._ready_early = {k for k in early if k[1] > steps}

    def rendered(self, vi: int, steps: int, cam: int = 0) -> None:
        """Ego ``vi``'s frame of instant ``steps`` (camera ``cam`` of its rig) is ready."""
        key = (vi, steps, cam)
        if key in self._rendering:
            self._rendering.discard(key)
        else:
            self._ready_early.add(key)

    # -- in flight -----------------------------------------------------------------

    def sent(self, vi: int, fl: InFlight) -> None:
        self._in_flight.setdefault(vi, {})[fl.frame_id] = fl
        self._n_in_flight += 1

    def answer(self, vi: int, frame_id: int) -> InFlight | None:
        """The in-flight frame an estimate answers (no longer in flight), or None."""
        mine = self._in_flight.get(vi)
        fl = None if mine is None else mine.pop(frame_id, None)
        if fl is not None:
            self._n_in_flight -= 1
        return fl

    def answer_set(self, vi: int, set_id: int, cameras: int) -> list[InFlight]:
        """The in-flight frames of the frame set ``set_id`` (frame ids ``set_id`` ..
        ``set_id + cameras - 1``) one ESTIMATE answers, taken out in camera order."""
        mine = self._in_flight.get(vi)
        if not mine:
            return []
        out = [fl for fid in range(set_id, set_id + cameras) if (fl := mine.pop(fid, None)) is not None]
        self._n_in_flight -= len(out)
        return out

    def receipt_uncertainty(self, vi: int, frame_id: int, ns: int) -> None:
        """The answer to an in-flight frame was stamped to within ``ns`` (a span)."""
        fl = self._in_flight.get(vi, {}).get(frame_id)
        if fl is not None:
            fl.t0p_uncertainty_ns = ns

    def in_flight(self, vi: int | None = None) -> bool:
        """Any frame in flight (of ``vi``, or of any vehicle)."""
        if vi is not None:
            return bool(self._in_flight.get(vi))
        return self._n_in_flight > 0

    def busy(self) -> bool:
        """Frames rendering or in flight."""
        return bool(self._rendering) or self._n_in_flight > 0

    def oldest_t0_ns(self) -> int | None:
        t0s = [fl.t0_ns for mine in self._in_flight.values() for fl in mine.values()]
        return min(t0s) if t0s else None

    def expired(self, now_ns: int, timeout_ns: int) -> list[tuple[int, InFlight]]:
        """Frames in flight longer than ``timeout_ns``, taken out (in frame order)."""
        out = []
        for vi, mine in self._in_flight.items():
            if mine:
                for fid in [f for f, fl in mine.items() if now_ns - fl.t0_ns > timeout_ns]:
                    out.append((vi, mine.pop(fid)))
        self._n_in_flight -= len(out)
        return out

    def take_all(self) -> list[tuple[int, InFlight]]:
        """Every frame in flight, taken out (by vehicle, in frame order)."""
        out = []
        for vi, mine in self._in_flight.items():
            out += [(vi, mine.pop(fid)) for fid in sorted(mine)]
        self._n_in_flight = 0
        return out

    # -- applying --------------------------------------------------------------------

    def apply(self, a: Answer) -> bool:
        """Note ``a``'s control as sent to the physics; False (nothing noted) when an
        answer to a later frame of the vehicle was applied already (stale)."""
        vi, fid = a.v.vehicle_id, a.m.frame_id
        if fid <= self._last_applied.get(vi, -1):
            return False
        self._last_applied[vi] = fid
        self._applying[(vi, fid)] = a
        self._applying_of[vi] = self._applying_of.get(vi, 0) + 1
        return True

    def cancel(self, vi: int, frame_id: int) -> Answer:
        """The control could not be sent after all."""
        return self._take(vi, frame_id)  # type: ignore[return-value]

    def applied(self, vi: int, frame_id: int) -> tuple[Answer | None, list[Answer], list[Task]]:
        """The physics applied it: its answer (None if unknown); the vehicle's earlier
        answers still applying, whose confirmations were lost (the physics applies a
        vehicle's controls in order, and its ring to this process may drop when this
        process falls behind), in frame order; and, once the vehicle has nothing else
        applying, the tasks held behind it (in order)."""
        a = self._take(vi, frame_id)
        if a is None:
            return None, [], []
        lost = [self._take(v, f) for v, f in sorted(k for k in self._applying if k[0] == vi and k[1] < frame_id)]
        released = [] if self._applying_of.get(vi) else self._behind.pop(vi, [])
        return a, [x for x in lost if x is not None], released

    def hold(self, vi: int, task: Task) -> bool:
        """Keep ``task`` behind the vehicle's controls being applied; False when none
        is (the caller runs it now)."""
        if not self._applying_of.get(vi):
            return False
        self._behind.setdefault(vi, []).append(task)
        return True

    def unconfirmed(self) -> tuple[list[Answer], list[Task]]:
        """Everything still applying (in vehicle and frame order) and every task held
        behind it, taken out: the physics will never confirm them."""
        answers = [self._applying[k] for k in sorted(self._applying)]
        self._applying.clear()
        self._applying_of.clear()
        held, self._behind = self._behind, {}
        return answers, [t for tasks in held.values() for t in tasks]

    def _take(self, vi: int, frame_id: int) -> Answer | None:
        a = self._applying.pop((vi, frame_id), None)
        if a is not None:
            self._applying_of[vi] -= 1
        return a
