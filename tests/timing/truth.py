"""Injected known truth for timing tests: a target clock with a known offset, skew
and step, a pipeline with known one-way delays and inference, and the stream of
sync samples, records and ticks a run's loop would hand the ``TimingObserver``, in
harness-time order.

Every value is integer ns. Nothing here reads a clock; the truth of each frame
(the true uplink and downlink on the harness clock) is returned beside the stream,
so a test compares what the harness reports against what happened instead of
tuning to one case.
"""

from __future__ import annotations

import heapq
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field

import numpy as np

from hil.timing.records import FrameStatus, PipelineRecord
from hil.timing.sync import SyncSample

MS = 1_000_000
US = 1_000
START_NS = 10**15


@dataclass(frozen=True, kw_only=True)
class TargetClock:
    """The target's clock as a function of harness time: a fixed offset, a rate error
    (ppm, from ``epoch_ns``) and an optional step of ``step_ns`` at harness instant
    ``step_at_ns``."""

    offset_ns: int = 2_500_000_000
    skew_ppm: float = 300.0
    epoch_ns: int = START_NS
    step_at_ns: int | None = None
    step_ns: int = 0

    def at(self, t_harness_ns: int) -> int:
        """The target clock's reading (ns) at a harness instant."""
        step = self.step_ns if self.step_at_ns is not None and t_harness_ns >= self.step_at_ns else 0
        return (t_harness_ns + self.offset_ns + round(self.skew_ppm * 1e-6 * (t_harness_ns - self.epoch_ns))
                + step)


@dataclass(frozen=True)
class Truth:
    """What really happened to one answered frame, on the harness clock (ns)."""

    uplink_ns: int
    downlink_ns: int


@dataclass(frozen=True, kw_only=True)
class Scenario:
    """A run to simulate. ``answers(frame_id, t0_ns)`` says whether the target answers
    a frame (default: all); ``sync_silent`` lists harness windows ``[a, b)`` in which
    no clock-sync probe is answered; ``handoff_ns`` is how long after ``t0'`` the loop
    hands a record over (it services its queue between physics steps)."""

    seconds: float = 10.0
    fps: float = 20.0
    clock: TargetClock = field(default_factory=TargetClock)
    uplink_ns: tuple[int, int] = (80 * US, 400 * US)
    downlink_ns: tuple[int, int] = (80 * US, 400 * US)
    inference_ns: int = 20 * MS
    handoff_ns: tuple[int, int] = (100 * US, 3 * MS)
    timeout_ns: int = 500 * MS
    sync_interval_ns: int = 1_000 * MS
    burst: int = 4
    warmup_samples: int = 8
    tick_ns: int = 2 * MS
    answers: Callable[[int, int], bool] | None = None
    sync_silent: tuple[tuple[int, int], ...] = ()
    seed: int = 0


Event = tuple[int, str, object]  # (harness time ns, "sync" | "record" | "tick", payload)


def simulate(sc: Scenario) -> tuple[list[Event], dict[int, Truth]]:
    """The events of a run in harness-time order, and each answered frame's truth.
    The first frame is captured at ``START_NS``; the warm-up sync comes before it."""
    rng = np.random.default_rng(sc.seed)
    clk = sc.clock
    heap: list[tuple[int, int, int, str, object]] = []
    seq = 0

    def push(t: int, prio: int, kind: str, payload: object) -> None:
        nonlocal seq
        seq += 1
        heapq.heappush(heap, (t, prio, seq, kind, payload))

    def u(rng_pair: tuple[int, int]) -> int:
        return int(rng.integers(rng_pair[0], rng_pair[1] + 1))

    def exchange(t1: int, n: int) -> SyncSample | None:
        if any(a <= t1 < b for a, b in sc.sync_silent):
            return None
        up, down = u(sc.uplink_ns), u(sc.downlink_ns)
        t2h = t1 + up
        t3h = t2h + 20 * US
        return SyncSample(t1, clk.at(t2h), clk.at(t3h), t3h + down, n)

    n_sync = 0
    for k in range(sc.warmup_samples):
        s = exchange(START_NS - 500 * MS + k * MS, n_sync)
        n_sync += 1
        if s is not None:
            push(s.t4_ns, 0, "sync", s)
    end_ns = START_NS + int(sc.seconds * 1e9)
    t = START_NS
    while t < end_ns + sc.timeout_ns + 2 * sc.sync_interval_ns:  # the loop drains, then closes
        for j in range(sc.burst):
            s = exchange(t + j * 500 * US, n_sync)
            n_sync += 1
            if s is not None:
                push(s.t4_ns + 50 * US, 0, "sync", s)
        t += sc.sync_interval_ns

    truth: dict[int, Truth] = {}
    period = round(1e9 / sc.fps)
    busy_until = 0
    for i in range(int(sc.seconds * sc.fps)):
        t0 = START_NS + i * period
        t_tx = t0 + u((200 * US, 600 * US))
        if sc.answers is not None and not sc.answers(i, t0):
            push(t_tx + sc.timeout_ns, 1, "record",
                 PipelineRecord("ego", i, i * period, t0, t_tx, FrameStatus.DROPPED))
            continue
        rx = t_tx + u(sc.uplink_ns)
        start = max(rx + 50 * US, busy_until)
        end = start + sc.inference_ns
        reply = end + 30 * US
        busy_until = reply
        t0p = reply + u(sc.downlink_ns)
        handed = t0p + u(sc.handoff_ns)
        rec = PipelineRecord("ego", i, i * period, t0, t_tx, FrameStatus.OK, clk.at(rx), clk.at(start),
                             clk.at(end), clk.at(reply), t0p, handed, (i + 1) * period)
        truth[i] = Truth(rx - t_tx, t0p - reply)
        push(handed, 1, "record", rec)
    for tk in range(START_NS, end_ns, sc.tick_ns):  # the loop ticks while it steps physics
        push(tk, 2, "tick", tk - START_NS)
    return [(t, kind, payload) for t, _, _, kind, payload in _drain(heap)], truth


def _drain(heap: list[tuple[int, int, int, str, object]]) -> Iterator[tuple[int, int, int, str, object]]:
    while heap:
        yield heapq.heappop(heap)


def drive(observer: object, events: list[Event], *, vehicle: str = "ego") -> None:
    """Feed ``events`` to a ``TimingObserver`` the way the run loop does, then
    ``finish()`` it."""
    for t, kind, payload in events:
        if kind == "sync":
            observer.on_sync(vehicle, payload)  # type: ignore[attr-defined]
        elif kind == "record":
            observer.on_record(vehicle, payload, None)  # type: ignore[attr-defined]
        else:
            observer.on_tick(now_ns=t, sim_time_ns=payload)  # type: ignore[attr-defined]
    observer.finish()  # type: ignore[attr-defined]
