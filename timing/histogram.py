"""Streaming per-stage latency statistics in fixed memory.

Each stage gets an HdrHistogram covering 1 µs .. 60 s at 3 significant digits
(~136 KiB, values recorded in whole µs; sub-µs values land in the 0 bucket), plus
exact count / min / max / mean / std kept alongside in ns (Welford), so only the
percentiles carry the histogram's 0.1 % quantisation. Histograms merge, so
per-vehicle or per-worker statistics combine into one.

Negative durations are never recorded (counted in ``rejected``); durations beyond
60 s are recorded as 60 s and counted in ``overflow``.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

import numpy as np

from hil.common.errors import HilError
from hil.timing.anomaly import is_sane
from hil.timing.records import PipelineRecord

LOWEST_US = 1
HIGHEST_US = 60_000_000
SIGNIFICANT_DIGITS = 3
MAX_STAGES = 64
PENDING = 256  # values (µs) a stage holds before they go into its histogram at once


def _new_histogram() -> Any:
    try:
        from hdrh.histogram import HdrHistogram
    except ImportError as err:  # pragma: no cover - depends on the install
        raise HilError("streaming latency statistics need the 'hdrhistogram' package: "
                       "pip install 'hdrhistogram>=0.10'") from err
    return HdrHistogram(LOWEST_US, HIGHEST_US, SIGNIFICANT_DIGITS)


def values_at_percentiles(h: Any, percentiles: Iterable[float]) -> list[int]:
    """``h.get_value_at_percentile(q)`` for each ``q``, in one pass over the counts with
    numpy: the library walks its 17,408 buckets in Python for each (0.4-0.7 ms a call
    here), which was most of a shard's finish (every stage of every vehicle)."""
    cum = np.cumsum(np.ctypeslib.as_array(h.counts)[:h.counts_len], dtype=np.int64)
    out = []
    for q in percentiles:
        i = int(np.searchsorted(cum, h.get_target_count_at_percentile(q), side="left"))
        if i >= h.counts_len:
            out.append(0)
            continue
        v = h.get_value_from_index(i)
        out.append(h.get_highest_equivalent_value(v) if q else h.get_lowest_equivalent_value(v))
    return out


def record_values(h: Any, us: np.ndarray) -> None:
    """``h.record_value(v)`` for each ``v`` of ``us`` (non-negative whole µs, int64),
    at once: the same bucket arithmetic as the library's, on arrays (its per-value
    Python call, ~1 µs, ran for a dozen stages and splits of every frame)."""
    if us.size == 0:
        return
    # bit length of (v | mask): frexp's exponent, exact for integers below 2**53
    pow2ceiling = np.frexp((us | h.sub_bucket_mask).astype(np.float64))[1].astype(np.int64)
    bucket = pow2ceiling - h.unit_magnitude - (h.sub_bucket_half_count_magnitude + 1)
    sub = us >> (bucket + h.unit_magnitude)
    idx = ((bucket + 1) << h.sub_bucket_half_count_magnitude) + (sub - h.sub_bucket_half_count)
    ok = (idx >= 0) & (idx < h.counts_len)
    if not ok.all():
        idx, us = idx[ok], us[ok]
        if us.size == 0:
            return
    np.add.at(np.ctypeslib.as_array(h.counts)[:h.counts_len], idx, 1)
    h.total_count += int(us.size)
    h.min_value = min(h.min_value, int(us.min()))
    h.max_value = max(h.max_value, int(us.max()))


@dataclass
class _Moments:
    """Exact running count, min, max, mean and sum of squared deviations (ns)."""

    count: int = 0
    mean: float = 0.0
    m2: float = 0.0
    lo: int = 0
    hi: int = 0

    def add(self, values_ns: np.ndarray) -> None:
        n = int(values_ns.size)
        if n == 0:
            return
        f = values_ns.astype(np.float64)
        other = _Moments(n, float(f.mean()), float(((f - f.mean()) ** 2).sum()),
                         int(values_ns.min()), int(values_ns.max()))
        self.merge(other)

    def add_one(self, value_ns: int) -> None:
        """Welford's update for one value (no numpy: this runs once per stage per frame)."""
        self.count += 1
        if self.count == 1:
            self.mean, self.m2, self.lo, self.hi = float(value_ns), 0.0, value_ns, value_ns
            return
        d = value_ns - self.mean
        self.mean += d / self.count
        self.m2 += d * (value_ns - self.mean)
        self.lo, self.hi = min(self.lo, value_ns), max(self.hi, value_ns)

    def merge(self, o: _Moments) -> None:
        if o.count == 0:
            return
        if self.count == 0:
            self.count, self.mean, self.m2, self.lo, self.hi = o.count, o.mean, o.m2, o.lo, o.hi
            return
        n = self.count + o.count
        d = o.mean - self.mean
        self.mean += d * o.count / n
        self.m2 += o.m2 + d * d * self.count * o.count / n
        self.count, self.lo, self.hi = n, min(self.lo, o.lo), max(self.hi, o.hi)


class StageHistograms:
    """Per-stage streaming latency histograms; bounded memory (≤ 64 stages)."""

    def __init__(self) -> None:
        self._hist: dict[str, Any] = {}
        self._moments: dict[str, _Moments] = {}
        self._pending: dict[str, list[int]] = {}  # µs values not yet in their histogram
        self.rejected = 0
        self.overflow = 0
        self.excluded_records = 0

    def stages(self) -> list[str]:
        """Stage names recorded so far."""
        return list(self._hist)

    def _slot(self, stage: str) -> tuple[Any, _Moments]:
        if stage not in self._hist:
            if len(self._hist) >= MAX_STAGES:
                raise ValueError(f"more than {MAX_STAGES} stages; got new stage {stage!r}: "
                                 "stage names must come from a fixed set (hil.timing.records.STAGES)")
            self._hist[stage], self._moments[stage] = _new_histogram(), _Moments()
            self._pending[stage] = []
        return self._hist[stage], self._moments[stage]

    def _settle(self, stage: str | None = None) -> None:
        """Put the pending values of ``stage`` (None: of every stage) into their histogram."""
        for name in (stage,) if stage is not None else tuple(self._pending):
            p = self._pending.get(name)
            if p:
                record_values(self._hist[name], np.array(p, dtype=np.int64))
                p.clear()

    def record(self, stage: str, value_ns: int) -> bool:
        """Record one duration (ns). Returns False (and counts it in ``rejected``)
        for a negative value. Raises ValueError beyond ``MAX_STAGES`` stage names."""
        value_ns = int(value_ns)
        if value_ns < 0:
            self.rejected += 1
            return False
        _hist, moments = self._slot(stage)
        us = (value_ns + 500) // 1000
        if us > HIGHEST_US:
            self.overflow += 1
            us = HIGHEST_US
        pending = self._pending[stage]
        pending.append(us)
        if len(pending) >= PENDING:
            self._settle(stage)
        moments.add_one(value_ns)
        return True

    def record_many(self, stage: str, values_ns: Iterable[int] | np.ndarray) -> int:
        """Record a batch of durations (ns); returns how many were recorded."""
        a = np.asarray(values_ns, dtype=np.int64).ravel()
        bad = a < 0
        if bad.any():
            self.rejected += int(bad.sum())
            a = a[~bad]
        if a.size == 0:
            return 0
        hist, moments = self._slot(stage)  # its pending values may stay: counts add in any order
        us = (a + 500) // 1000
        over = us > HIGHEST_US
        if over.any():
            self.overflow += int(over.sum())
            us = np.minimum(us, HIGHEST_US)
        record_values(hist, us)
        moments.add(a)
        return int(a.size)

    def record_record(self, rec: PipelineRecord) -> bool:
        """Record every sync-free stage of a record; an insane record (see
        ``hil.timing.anomaly.is_sane``) is skipped and counted in ``excluded_records``."""
        if not is_sane(rec)[0]:
            self.excluded_records += 1
            return False
        for stage, v in rec.stages_ns().items():
            self.record(stage, v)
        return True

    def percentiles_ms(self, stage: str) -> dict[str, float | int]:
        """``count`` and p50/p90/p99/max/min/mean/std in ms (percentiles from the
        histogram, ±0.1 %; the rest exact). An unknown or empty stage gives
        ``{"count": 0}``."""
        m = self._moments.get(stage)
        if m is None or m.count == 0:
            return {"count": 0}
        self._settle(stage)
        out: dict[str, float | int] = {"count": m.count}
        for q, us in zip((50, 90, 99), values_at_percentiles(self._hist[stage], (50, 90, 99)), strict=True):
            out[f"p{q}_ms"] = round(us / 1e3, 4)
        out.update(max_ms=round(m.hi / 1e6, 4), min_ms=round(m.lo / 1e6, 4),
                   mean_ms=round(m.mean / 1e6, 4), std_ms=round(math.sqrt(m.m2 / m.count) / 1e6, 4))
        return out

    def summary_ms(self) -> dict[str, dict[str, float | int]]:
        """``percentiles_ms`` of every stage."""
        return {s: self.percentiles_ms(s) for s in self._hist}

    def merge(self, other: StageHistograms) -> None:
        """Add ``other``'s values into this one (``other`` is unchanged).
        Raises ValueError beyond ``MAX_STAGES`` stage names."""
        self._settle()
        other._settle()  # its counts, not its values: unchanged
        for stage, h in other._hist.items():
            mine, moments = self._slot(stage)
            mine.add(h)
            moments.merge(other._moments[stage])
        self.rejected += other.rejected
        self.overflow += other.overflow
        self.excluded_records += other.excluded_records
