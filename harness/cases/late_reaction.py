"""Late reactions: the AI decided to stop in time, its brake came too late.

A ``late_reaction`` mismatch names the most direct consequence of latency: a
collision, or a near miss (the route gap to the obstacle ahead under
``near_miss_m``), although the AI already believed STOP and commanded a brake in
time. Judged per contact of an ego with the entity ahead of it (sim time ``t_c``),
over the ego's decisions (estimates that were applied), in frame order:

1. the *decision* is the first frame of the unbroken run of STOP beliefs (with a
   brake command) ending at the last frame captured at or before ``t_c``; none: no
   late reaction (the AI did not believe STOP: perception, or ``collision_while_safe``);
2. *decided in time*: at that frame's capture ``t0`` the ego could still stop before
   the obstacle at ``avoid_decel_mps2``: route gap ≥ (v² − u²) / (2 a), with v the
   ego's speed and u the obstacle's speed along the route (no obstacle in the path
   yet counts as in time);
3. *applied too late*: at contact the control had not been applied yet, or when it
   was applied (``t_apply``) the gap was already under that stopping distance.

The event carries the evidence (both instants' gap, speeds and stopping distance,
the decision's sim times) and the latency that made the difference: ``t_apply − t0``
in sim time (at least ``t_c − t0`` when the control was still in flight) against the
budget, the time after ``t0`` at which stopping stopped being possible (from the
ego's truth at each camera tick; ``None`` when not seen).

A contact is judged once a frame captured after it has been decided (earlier ones
are settled then: controls apply in frame order), or at :meth:`finish`.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

from hil.adapters.wire.messages import DrivingState

HISTORY = 600  # decisions and truth ticks kept per ego (30 s of frames at 20 fps): bounded
REPEAT_NS = 2_000_000_000  # a contact with the same entity within this belongs to the same one


@dataclass(frozen=True)
class EgoView:
    """The ego's route truth at one instant: gap to the obstacle ahead (m, ``None``:
    path clear), which one, the ego's and the obstacle's speed along the route (m/s)."""

    sim_time_ns: int
    gap_m: float | None
    obstacle: str | None
    speed_mps: float
    obstacle_speed_mps: float

    def stop_distance_m(self, decel_mps2: float) -> float:
        """Distance (m) the ego needs to match the obstacle's speed at ``decel_mps2``."""
        u = max(0.0, self.obstacle_speed_mps)
        return max(0.0, self.speed_mps ** 2 - u * u) / (2 * decel_mps2)

    def to_json(self, decel_mps2: float) -> dict[str, object]:
        return {"sim_time_ns": self.sim_time_ns, "gap_m": _r(self.gap_m), "obstacle": self.obstacle,
                "speed_mps": _r(self.speed_mps), "obstacle_speed_mps": _r(self.obstacle_speed_mps),
                "stop_distance_m": _r(self.stop_distance_m(decel_mps2))}


@dataclass(frozen=True)
class Decision:
    """One applied estimate: its belief and brake, the ego's truth at capture and at
    apply (``None``: not seen), its frame's sim times (ns)."""

    frame_id: int
    state: DrivingState
    brake: float
    at_t0: EgoView
    at_apply: EgoView | None


@dataclass(frozen=True)
class LateReaction:
    """The verdict on one contact (see the module docstring)."""

    other: str
    contact: str  # "collision" | "near_miss"
    sim_time_ns: int
    frame_id: int
    latency_ns: int
    applied_before_contact: bool
    budget_ns: int | None
    evidence: dict[str, object]


@dataclass
class _Contact:
    other: str
    contact: str
    sim_time_ns: int
    at_contact: EgoView | None
    measured: float  # N (collision) or m (near miss)


class LateReactionJudge:
    """One ego's contacts against its decisions (see the module docstring)."""

    def __init__(self, *, decel_mps2: float, near_miss_m: float) -> None:
        self.decel = decel_mps2
        self.near_miss_m = near_miss_m
        self._decisions: deque[Decision] = deque(maxlen=HISTORY)
        self._truth: deque[EgoView] = deque(maxlen=HISTORY)
        self._pending: list[_Contact] = []
        self._last_contact: dict[str, tuple[int, _Contact]] = {}

    def on_truth(self, view: EgoView) -> None:
        """The ego's truth at a camera tick: kept for the budget; a near miss noted."""
        self._truth.append(view)
        if (view.gap_m is not None and view.obstacle is not None and view.gap_m < self.near_miss_m
                and view.speed_mps - max(0.0, view.obstacle_speed_mps) > 0.1):
            self._note(_Contact(view.obstacle, "near_miss", view.sim_time_ns, view, view.gap_m))

    def on_collision(self, *, other: str, sim_time_ns: int, force_n: float) -> None:
        at = self._truth[-1] if self._truth else None
        self._note(_Contact(other, "collision", sim_time_ns, at, force_n))

    def _note(self, c: _Contact) -> None:
        last = self._last_contact.get(c.other)
        if last is not None and c.sim_time_ns - last[0] < REPEAT_NS:
            prev = last[1]
            if c.contact == "collision" and prev.contact == "near_miss" and prev in self._pending:
                prev.contact, prev.measured = "collision", c.measured  # the near miss was not one
            self._last_contact[c.other] = (c.sim_time_ns, prev)
            return
        self._last_contact[c.other] = (c.sim_time_ns, c)
        self._pending.append(c)

    def on_decision(self, d: Decision) -> list[tuple[_Contact, LateReaction | None]]:
        """Record an applied estimate; judge the contacts it settles."""
        self._decisions.append(d)
        ready = [c for c in self._pending if d.at_t0.sim_time_ns > c.sim_time_ns]
        return self._judge(ready)

    def finish(self) -> list[tuple[_Contact, LateReaction | None]]:
        return self._judge(list(self._pending))

    def _judge(self, ready: list[_Contact]) -> list[tuple[_Contact, LateReaction | None]]:
        out = []
        for c in ready:
            self._pending.remove(c)
            out.append((c, self.judge(c)))
        return out

    def judge(self, c: _Contact) -> LateReaction | None:
        before = [d for d in self._decisions if d.at_t0.sim_time_ns <= c.sim_time_ns]
        if not before or not _stopping(before[-1]):
            return None
        i = len(before) - 1
        while i > 0 and _stopping(before[i - 1]):
            i -= 1
        d = before[i]
        if c.at_contact is not None and c.at_contact.obstacle not in (None, c.other):
            return None  # not the entity ahead: the ego's brake was not what could avoid it
        t0, a = d.at_t0, d.at_apply
        # The gap to the nearest entity ahead bounds the gap to the one hit.
        in_time = t0.gap_m is None or t0.gap_m >= t0.stop_distance_m(self.decel)
        applied = a is not None and a.sim_time_ns <= c.sim_time_ns
        too_late = (a is None or not applied
                    or (a.gap_m is not None and a.gap_m < a.stop_distance_m(self.decel)))
        if not (in_time and too_late):
            return None
        latency = (a.sim_time_ns if a is not None and applied else c.sim_time_ns) - t0.sim_time_ns
        budget = next((v.sim_time_ns - t0.sim_time_ns for v in self._truth
                       if v.sim_time_ns >= t0.sim_time_ns and v.gap_m is not None
                       and v.gap_m < v.stop_distance_m(self.decel)), None)
        ev = {"contact": c.contact, "other": c.other, "contact_sim_time_ns": c.sim_time_ns,
              "contact_measured": _r(c.measured), "decision_frame_id": d.frame_id,
              "belief": {"state": d.state.name, "brake": _r(d.brake)},
              "sim_time_t0_ns": t0.sim_time_ns, "sim_time_apply_ns": a.sim_time_ns if a is not None else None,
              "latency_sim_ns": latency, "applied_before_contact": applied, "budget_ns": budget,
              "avoid_decel_mps2": self.decel, "truth_t0": t0.to_json(self.decel),
              "truth_apply": a.to_json(self.decel) if a is not None else None,
              "truth_contact": c.at_contact.to_json(self.decel) if c.at_contact is not None else None}
        return LateReaction(c.other, c.contact, c.sim_time_ns, d.frame_id, latency, applied, budget, ev)


def _stopping(d: Decision) -> bool:
    return d.state == DrivingState.STOP and d.brake > 0


def _r(x: float | None) -> float | None:
    return None if x is None else round(float(x), 4)
