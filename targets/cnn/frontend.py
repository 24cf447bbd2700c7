"""The decode part of a batch (``--decode-workers N|auto``, ``--decode-pool
process|thread``): in the target's process (0 workers, as before) or on a pool
(``hil.targets.cnn.pool``), and ``auto``, which measures before serving.

``auto`` (a shared target only: a batch of one frame has nothing to spread) times a
batch of ``max_batch`` synthetic 320 x 240 JPEG frames decoded in process and on a
process pool of one worker per core this process may use, at start, and takes the
pool when it decodes the batch at least ``AUTO_GAIN`` faster (``pool_pays``), else
decodes in process; the target's log says what it measured and chose. The
threshold is on the decode alone, not on the whole batch: served, the pool gains
more than it does alone (on 2 cores, 16 vehicles at 20 fps: 16 frames dropped of
1,280 against 256 in process, ``bench/README.md``), because in process the decode's
Python parts wait for the interpreter lock that the vehicles' reader threads hold.
For the same reason the pool is of processes: ``--decode-pool thread`` runs one all
the same (``bench_shared.py`` measures both).
"""

from __future__ import annotations

import math
import os
import statistics
import sys
import time
from collections.abc import Callable, Collection, Sequence

import cv2
import numpy as np

from hil.adapters.wire.messages import CameraInfo, Frame, ImageEncoding
from hil.targets.cnn.pool import NETS, Layout, Pool, PoolError, ProcessPool, ThreadPool, prepare_into

AUTO_GAIN = 0.2  # the pool must decode a batch this much faster than the process alone
POOL_KINDS = ("process", "thread")


def parse_workers(text: str) -> int | None:
    """``--decode-workers``: a count >= 0, or ``auto`` (None).

    Raises:
        ValueError: neither (named in the message)."""
    if text.strip().lower() == "auto":
        return None
    if not text.strip().isdigit() or int(text) > 256:
        raise ValueError(f"--decode-workers {text!r}: expected 0 (decode in process), a count up to 256, or auto")
    return int(text)


def make_pool(kind: str, workers: int, *, slots: int, layout: Layout = NETS) -> Pool:
    """Raises: ValueError: an unknown kind. PoolError, OSError: it cannot start."""
    if kind == "process":
        return ProcessPool(workers, slots=slots, layout=layout)
    if kind == "thread":
        return ThreadPool(workers, slots=slots, layout=layout)
    raise ValueError(f"--decode-pool {kind!r}: expected {' or '.join(POOL_KINDS)}")


class Frontend:
    """Decodes batches in process or on ``workers`` workers of ``kind``; a pool per
    layout, the nets' (``NETS``) started here, a frame layout on first use. A pool
    that breaks is closed, reported once, and its batches decoded in process."""

    def __init__(self, workers: int = 0, *, kind: str = "process", slots: int = 16,
                 log: Callable[[str], None] | None = None, pool: Pool | None = None) -> None:
        if kind not in POOL_KINDS:
            raise ValueError(f"--decode-pool {kind!r}: expected {' or '.join(POOL_KINDS)}")
        self.workers, self.kind, self.slots = workers, kind, slots
        self._log = log or (lambda text: print(text, file=sys.stderr, flush=True))
        self._pools: dict[Layout, Pool] = {}
        self._broken = False
        if pool is not None:
            self._pools[pool.layout] = pool
        elif workers > 0:
            self._pools[NETS] = make_pool(kind, workers, slots=slots)

    def describe(self) -> str:
        """``in process``, ``2 processes`` or ``2 threads``."""
        if self.workers == 0 or self._broken:
            return "in process"
        return f"{self.workers} {'processes' if self.kind == 'process' else 'threads'}"

    @property
    def pids(self) -> list[int]:
        return [pid for p in self._pools.values() if isinstance(p, ProcessPool) for pid in p.pids]

    def prepare(self, frames: Sequence[Frame], names: Collection[str], layout: Layout = NETS) -> dict[str, np.ndarray]:
        """The outputs ``names`` of ``layout`` for ``frames`` (n x shape uint8 arrays,
        valid until the next call).

        Raises:
            ProtocolError, ValueError: a frame does not decode (the first in order).
        """
        pool = self._pool(layout) if len(frames) <= self.slots else None
        if pool is not None:
            try:
                return pool.prepare(frames, names)
            except PoolError as err:
                self._broken = True
                self.close()
                self._log(f"cnn: decode pool stopped ({err}); decoding in process from now on")
        views = {name: np.empty((len(frames), *shape), np.uint8) for name, shape in layout.outputs if name in names}
        for i, f in enumerate(frames):
            prepare_into(views, i, f, names)
        return views

    def _pool(self, layout: Layout) -> Pool | None:
        if self.workers == 0 or self._broken:
            return None
        pool = self._pools.get(layout)
        if pool is None:
            try:
                pool = self._pools[layout] = make_pool(self.kind, self.workers, slots=self.slots, layout=layout)
            except (PoolError, OSError) as err:
                self._broken = True
                self._log(f"cnn: no decode pool for {layout.spec()} ({err}); decoding in process")
                return None
        return pool

    def close(self) -> None:
        """End every pool's workers. Idempotent."""
        pools, self._pools = list(self._pools.values()), {}
        for p in pools:
            p.close()


def synthetic_frames(n: int, *, width: int = 320, height: int = 240) -> list[Frame]:
    """``n`` JPEG frames of a plain road scene (sky, road, lane marks, a box), for
    timing: what the decoder does with them is what it does with a camera's."""
    rng = np.random.default_rng(0)
    frames = []
    for i in range(n):
        img = np.empty((height, width, 3), np.uint8)
        img[: height // 2] = np.linspace(235, 170, height // 2, dtype=np.uint8)[:, None, None]
        img[height // 2:] = (87, 82, 82)
        img[height // 2:, width // 2 - 2: width // 2 + 2] = 230
        x = 40 + 8 * i % (width - 80)
        img[height // 2 - 20: height // 2 + 10, x: x + 40] = (40, 40, 160)
        noisy = cv2.add(img, rng.integers(0, 6, img.shape, dtype=np.uint8))
        ok, jpeg = cv2.imencode(".jpg", noisy, (cv2.IMWRITE_JPEG_QUALITY, 85))
        if not ok:  # pragma: no cover - OpenCV always encodes a plain image
            raise RuntimeError("cannot encode a synthetic frame")
        f = height / 2 / math.tan(math.radians(30))  # 60 degrees vertical field of view
        cam = CameraInfo(f, f, width / 2, height / 2, 1.3, 0.0)
        frames.append(Frame(0, i, 0, 0, 0, width, height, ImageEncoding.JPEG, cam, 8.0, jpeg.tobytes()))
    return frames


def _median_ms(fn: Callable[[], object], reps: int) -> float:
    fn()  # warm-up
    times = []
    for _ in range(reps):
        t0 = time.perf_counter_ns()
        fn()
        times.append((time.perf_counter_ns() - t0) / 1e6)
    return statistics.median(times)


def pool_pays(in_process_ms: float, pool_ms: float) -> bool:
    """The pool decodes a batch at least ``AUTO_GAIN`` faster than the process alone."""
    return pool_ms <= (1.0 - AUTO_GAIN) * in_process_ms


def auto_frontend(*, slots: int, kind: str = "process", cores: int | None = None,
                  log: Callable[[str], None] | None = None, reps: int = 5) -> Frontend:
    """``--decode-workers auto`` (module docstring): a pool of ``cores`` workers
    (default: the cores this process may use) or none, by measurement."""
    say = log or (lambda text: print(text, file=sys.stderr, flush=True))
    cores = len(os.sched_getaffinity(0)) if cores is None else cores
    frames = synthetic_frames(slots)
    inline = Frontend(0, slots=slots, log=say)
    # Rounded as printed, so the choice follows from the figures the line shows.
    t_in = round(_median_ms(lambda: inline.prepare(frames, NETS.names), reps), 2)
    what = f"a batch of {slots} synthetic 320x240 JPEG frames decodes in {t_in:.2f} ms in process"
    if cores < 2:
        say(f"cnn: --decode-workers auto: {what}; one core: in process")
        return inline
    try:
        pooled = Frontend(cores, kind=kind, slots=slots, log=say)
    except (PoolError, OSError) as err:
        say(f"cnn: --decode-workers auto: {what}; no pool ({err}): in process")
        return inline
    t_pool = round(_median_ms(lambda: pooled.prepare(frames, NETS.names), reps), 2)
    use = pool_pays(t_in, t_pool)
    say(f"cnn: --decode-workers auto: {what}, {t_pool:.2f} ms on {pooled.describe()}: "
        + (pooled.describe() if use else "in process"))
    if use:
        return pooled
    pooled.close()
    return inline
