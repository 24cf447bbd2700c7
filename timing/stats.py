"""Latency statistics: exact percentiles from recorded values and a bounded rolling
window for live display. Inputs are integer nanoseconds; outputs milliseconds."""

from __future__ import annotations

from collections import deque
from collections.abc import Iterable

import numpy as np

PERCENTILES = (50, 90, 99)


def summarize_ns(values_ns: Iterable[int]) -> dict[str, float | int]:
    """Exact summary of durations: count, p50/p90/p99/max/min/mean/std in ms.

    An empty input gives ``{"count": 0}``.
    """
    a = np.fromiter(values_ns, dtype=np.int64)
    if a.size == 0:
        return {"count": 0}
    ms = a.astype(np.float64) / 1e6
    p = np.percentile(ms, PERCENTILES)
    out: dict[str, float | int] = {"count": int(a.size)}
    for q, v in zip(PERCENTILES, p):
        out[f"p{q}_ms"] = round(float(v), 4)
    out.update(max_ms=round(float(ms.max()), 4), min_ms=round(float(ms.min()), 4),
               mean_ms=round(float(ms.mean()), 4), std_ms=round(float(ms.std()), 4))
    return out


class RollingWindow:
    """The last ``size`` values (ns) for live p50/p99 display; bounded memory."""

    def __init__(self, size: int = 512) -> None:
        self._values: deque[int] = deque(maxlen=size)

    def add(self, value_ns: int) -> None:
        self._values.append(value_ns)

    def percentile_ms(self, q: float) -> float | None:
        if not self._values:
            return None
        return float(np.percentile(np.fromiter(self._values, np.int64), q)) / 1e6


class RateMeter:
    """Events per second over a sliding time window (harness clock, ns)."""

    def __init__(self, window_ns: int = 2_000_000_000) -> None:
        self._window_ns = window_ns
        self._times: deque[int] = deque()

    def add(self, t_ns: int) -> None:
        self._times.append(t_ns)

    def rate_hz(self, now_ns: int) -> float:
        while self._times and self._times[0] < now_ns - self._window_ns:
            self._times.popleft()
        if len(self._times) < 2:
            return 0.0
        span = max(now_ns - self._times[0], 1)
        return (len(self._times) - 1) * 1e9 / span
