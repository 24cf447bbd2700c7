"""The run process's analysis thread: ground truth, timing analysis, the detector and
the recording calls run here, off the thread that moves frames and controls.

The threads that move frames and estimates post tasks into a bounded hand-off
(``hil.harness.engine.handoff``: drop-newest when full, every drop counted; no system
call while this thread is busy); tasks run in the order posted. With the
interpreter's switch interval lowered for the run, those threads get the
interpreter back within 0.1 ms of a frame or an estimate arriving, whatever
analysis is doing.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Any

from hil.harness.engine.handoff import Handoff

QUEUE_SIZE = 20_000


class AnalysisThread:
    """Runs posted callables in order on one daemon thread. ``close()`` runs what is
    queued, then stops (idempotent)."""

    def __init__(self, *, queue_size: int = QUEUE_SIZE) -> None:
        self._q: Handoff[tuple[Callable[..., Any], tuple[Any, ...]] | None] = Handoff(queue_size)
        self.dropped = 0
        self.errors: list[str] = []
        self.max_depth = 0
        self.cpu_ns = 0  # CPU time the thread used (set when it ends)
        self._closing = threading.Lock()  # held by close() until the queue is drained
        self._thread = threading.Thread(target=self._run, name="hil-analysis", daemon=True)
        self._thread.start()
        self._closed = False

    def post(self, fn: Callable[..., Any], *args: Any) -> None:
        """Queue ``fn(*args)``; once closed, run it here and now, after everything
        queued before (a late input must not overtake what the thread still has)."""
        if self._closed:
            with self._closing:
                fn(*args)
            return
        if not self._q.put((fn, args)):
            self.dropped += 1
            return
        depth = len(self._q)
        if depth > self.max_depth:
            self.max_depth = depth

    def _run(self) -> None:
        import time

        from hil.harness.engine.procs import lower_thread_priority

        lower_thread_priority()
        start = time.thread_time_ns()
        while True:
            item = self._q.get(1.0)
            if item is None:
                if self._closed and not len(self._q):  # close() puts a None; the queue ends with it
                    self.cpu_ns = time.thread_time_ns() - start
                    return
                continue
            fn, args = item
            try:
                fn(*args)
            except Exception as err:  # noqa: BLE001 - one bad task must not end the analysis
                if len(self.errors) < 20:
                    self.errors.append(f"{getattr(fn, '__name__', fn)}: {type(err).__name__}: {err}")

    def wait_idle(self, timeout_s: float = 60.0) -> None:
        """Block until every task posted so far has run."""
        done = threading.Event()
        self._q.put_always((done.set, ()))
        done.wait(timeout_s)

    def close(self, timeout_s: float = 120.0) -> None:
        if self._closed:
            return
        with self._closing:
            self._closed = True
            self._q.put_always(None)
            self._thread.join(timeout_s)
