"""Clocks. Logic takes a ``Clock`` and never calls ``time.*`` itself, so tests can
skew, step and freeze time.

All readings are integer nanoseconds.
"""

from __future__ import annotations

import time
from typing import Protocol


class Clock(Protocol):
    """A source of integer-nanosecond timestamps."""

    def now_ns(self) -> int:
        """Current reading in nanoseconds."""
        ...


class MonotonicClock:
    """The harness clock: ``time.monotonic_ns()``."""

    def now_ns(self) -> int:
        return time.monotonic_ns()

    def sleep_until_ns(self, deadline_ns: int, *, spin_ns: int = 200_000) -> None:
        """Sleep until ``deadline_ns`` on this clock: OS sleep, then spin the last
        ``spin_ns`` (default 200 µs), which hits deadlines within ~1 µs where a plain
        sleep oversleeps ~80 µs."""
        remaining = deadline_ns - time.monotonic_ns()
        if remaining > spin_ns:
            time.sleep((remaining - spin_ns) / 1e9)
        while time.monotonic_ns() < deadline_ns:
            pass


class RealtimeClock:
    """This host's wall clock, ``time.time_ns()`` (CLOCK_REALTIME: ns since the Unix
    epoch; it may step). The clock a ROS 2 node stamps with when it does not use sim time."""

    def now_ns(self) -> int:
        return time.time_ns()


class ManualClock:
    """A clock that moves only when told to (tests and lockstep replays)."""

    def __init__(self, start_ns: int = 0) -> None:
        self._now_ns = start_ns

    def now_ns(self) -> int:
        return self._now_ns

    def advance_ns(self, delta_ns: int) -> None:
        if delta_ns < 0:
            raise ValueError(f"a clock advances forwards; got delta_ns={delta_ns}")
        self._now_ns += delta_ns

    def set_ns(self, value_ns: int) -> None:
        """Jump to ``value_ns`` (may go backwards: a clock step)."""
        self._now_ns = value_ns


class OffsetClock:
    """Another clock seen through a fixed offset and a rate error, the way a target's
    clock differs from the harness clock: ``base + offset_ns + (base - epoch) * skew_ppm * 1e-6``.
    """

    def __init__(self, base: Clock, *, offset_ns: int = 0, skew_ppm: float = 0.0) -> None:
        self._base = base
        self._offset_ns = offset_ns
        self._skew = skew_ppm * 1e-6
        self._epoch_ns = base.now_ns()

    def now_ns(self) -> int:
        b = self._base.now_ns()
        return b + self._offset_ns + int((b - self._epoch_ns) * self._skew)
