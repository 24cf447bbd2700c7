"""Latency statistics: exact percentiles from recorded values and a bounded rolling
window for live display. Inputs are integer nanoseconds; outputs milliseconds.

Exact figures over a run of any length need every value, but not in memory:
:class:`SpillColumn` keeps a fixed block of int64 values and appends full blocks to
one unlinked temporary file per process (:class:`SpillFile`), read back when the
figures are computed. A column that grows in memory instead (``array``, ``list``)
reallocates as it grows, and the freed blocks stayed resident: a 10-minute run grew
its process by ~0.5 MB/min (bench/bench_soak.py, issue 14).
"""

from __future__ import annotations

import os
import tempfile
import threading
from collections import deque
from collections.abc import Iterable, Iterator

import numpy as np

PERCENTILES = (50, 90, 99)


def summarize_ns(values_ns: Iterable[int]) -> dict[str, float | int]:
    """Exact summary of durations: count, p50/p90/p99/max/min/mean/std in ms.

    An empty input gives ``{"count": 0}``.
    """
    if isinstance(values_ns, SpillColumn):
        a = values_ns.to_numpy()
    elif isinstance(values_ns, np.ndarray):
        a = values_ns.astype(np.int64, copy=False)
    else:
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


class SpillFile:
    """One unlinked temporary file that many :class:`SpillColumn` append blocks to
    (a file per column would cost a descriptor each: 64 vehicles hold ~700 columns).

    Args:
        directory: where the file lives (default: ``tempfile``'s, ``$TMPDIR``).
    """

    def __init__(self, directory: str | None = None) -> None:
        self._directory = directory
        self._file: int | None = None  # an os-level descriptor, opened at the first block
        self._size = 0
        self._lock = threading.Lock()

    def write(self, block: np.ndarray) -> int:
        """Append ``block``'s bytes; returns the offset they start at.

        Raises:
            OSError: the file cannot be created or written (a full disk).
        """
        data = block.tobytes()
        with self._lock:
            if self._file is None:
                fd, path = tempfile.mkstemp(prefix="hil-spill-", dir=self._directory)
                os.unlink(path)  # gone with the process, whatever way it ends
                self._file = fd
            offset = self._size
            done = 0
            while done < len(data):
                done += os.pwrite(self._file, data[done:], offset + done)
            self._size += len(data)
            return offset

    def read(self, offset: int, count: int) -> np.ndarray:
        """``count`` int64 values written at ``offset``."""
        with self._lock:
            assert self._file is not None
            data = os.pread(self._file, count * 8, offset)
        return np.frombuffer(data, dtype=np.int64)

    def close(self) -> None:
        with self._lock:
            if self._file is not None:
                os.close(self._file)
                self._file = None


_DEFAULT_SPILL: SpillFile | None = None
_DEFAULT_LOCK = threading.Lock()


def _forget_default_spill() -> None:
    global _DEFAULT_SPILL
    _DEFAULT_SPILL = None  # a forked child must not append at the parent's offsets


os.register_at_fork(after_in_child=_forget_default_spill)


def default_spill() -> SpillFile:
    """The process's shared spill file (created on first use; a forked child gets its
    own for the columns it makes)."""
    global _DEFAULT_SPILL
    with _DEFAULT_LOCK:
        if _DEFAULT_SPILL is None:
            _DEFAULT_SPILL = SpillFile()
        return _DEFAULT_SPILL


class SpillColumn:
    """An int64 column of any length in bounded memory (module docstring): ``block``
    values in memory, the rest in a :class:`SpillFile`. Append from one thread.

    A block that cannot be spilled (``OSError``: a full disk) stays in memory instead,
    counted in ``spill_failures`` (the first error in ``spill_error``): the figures
    stay exact and in order, memory grows.
    """

    def __init__(self, block: int = 1024, spill: SpillFile | None = None) -> None:
        if block < 1:
            raise ValueError(f"block={block}: expected >= 1")
        self._buf = np.empty(block, dtype=np.int64)
        self._n = 0
        self._spill = spill
        self._blocks: list[int | np.ndarray] = []  # full blocks: an offset in the spill file, or kept here
        self.spill_failures = 0
        self.spill_error: str | None = None  # the first failure, e.g. "OSError: [Errno 28] No space left on device"

    def append(self, value: int) -> None:
        self._buf[self._n] = value
        self._n += 1
        if self._n == len(self._buf):
            self._flush()

    def _flush(self) -> None:
        if self._spill is None:
            self._spill = default_spill()
        try:
            self._blocks.append(self._spill.write(self._buf))
        except OSError as err:
            self.spill_failures += 1
            if self.spill_error is None:
                self.spill_error = f"{type(err).__name__}: {err}"
            self._blocks.append(self._buf.copy())
        self._n = 0

    def __len__(self) -> int:
        return len(self._blocks) * len(self._buf) + self._n

    def __bool__(self) -> bool:
        return len(self) > 0

    def to_numpy(self) -> np.ndarray:
        """Every value, in the order appended (a new array)."""
        block = len(self._buf)
        parts = [b if isinstance(b, np.ndarray) else self._spill.read(b, block)  # type: ignore[union-attr]
                 for b in self._blocks]
        parts.append(self._buf[:self._n])
        return np.concatenate(parts)

    def __iter__(self) -> Iterator[int]:
        return iter(self.to_numpy().tolist())


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
