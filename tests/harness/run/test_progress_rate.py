"""The live table's rows are computed at most every ``PROGRESS_NS``, not at every 20 ms
tick of the loop (each row set is every vehicle's percentiles: a lockstep run of 16
vehicles spent a quarter of its loop thread's CPU on rows nobody saw)."""

from __future__ import annotations

from hil.harness.run.driver import _progress_every
from hil.harness.run.vehicle_state import PROGRESS_NS
from hil.timing.clock import ManualClock


def test_rows_at_most_every_progress_interval() -> None:
    clock = ManualClock(1_000)
    shown: list[int] = []
    tick = _progress_every(PROGRESS_NS, clock, shown.append)
    for _ in range(100):  # 2 s of 20 ms ticks
        tick()
        clock.advance_ns(20_000_000)
    assert shown[0] == 1_000  # the first tick shows at once
    assert len(shown) == 8  # 2 s at most every 0.25 s (a tick lands on each 260 ms)
    assert all(b - a >= PROGRESS_NS for a, b in zip(shown, shown[1:]))
