"""Process plumbing shared by the engine's children: die with the parent, ask for a
real-time scheduling class, and pump a child's pipe into the run's event queue."""

from __future__ import annotations

import ctypes
import os
import queue
import signal
import threading
from multiprocessing.connection import Connection
from typing import Any

_PR_SET_PDEATHSIG = 1
_PR_SET_TIMERSLACK = 29
_F_SETPIPE_SZ = 1031


def _prctl(option: int, arg: int) -> bool:
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        return int(libc.prctl(option, arg, 0, 0, 0)) == 0
    except (OSError, AttributeError):  # not Linux
        return False


def die_with_parent(expected_parent: int | None = None) -> None:
    """Have the kernel SIGKILL this process when its parent dies (Linux), so a
    killed run never leaves workers behind. Exits at once if the parent is already
    gone (``expected_parent`` given and no longer our parent)."""
    _prctl(_PR_SET_PDEATHSIG, int(signal.SIGKILL))
    if expected_parent is not None and os.getppid() != expected_parent:
        os._exit(1)


def preexec_die_with_parent() -> None:
    """For ``subprocess.Popen(preexec_fn=...)``: the target dies with the harness."""
    _prctl(_PR_SET_PDEATHSIG, int(signal.SIGKILL))


def ask_realtime(priority: int) -> str:
    """Ask for SCHED_FIFO at ``priority`` (0: don't) and 1 ns timer slack; returns
    what was granted, in words, for the summary."""
    _prctl(_PR_SET_TIMERSLACK, 1)
    if priority <= 0:
        return "normal (real-time class not requested)"
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
    except (PermissionError, OSError, AttributeError) as err:
        return f"normal (SCHED_FIFO refused: {getattr(err, 'strerror', None) or err})"
    return f"SCHED_FIFO priority {priority}"


def lower_thread_priority(nice: int = 10) -> None:
    """Make the calling thread yield the CPU to the run's latency-critical threads
    (Linux: a thread's nice value is its own; raising it needs no privilege). The
    analysis and recording threads call this, so the loop thread that moves frames
    and controls is served first when the cores are busy."""
    try:
        import threading

        os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), nice)
    except (OSError, AttributeError):
        pass


def widen_pipe(conn: Connection, size: int = 1 << 20) -> None:
    """Let a pipe hold ``size`` bytes, so a child never blocks on a busy reader."""
    try:
        import fcntl
        fcntl.fcntl(conn.fileno(), _F_SETPIPE_SZ, size)
    except (OSError, ImportError, AttributeError):
        pass


class Pump:
    """A daemon thread that moves every message of ``conn`` into ``out``, and
    ``ChildGone(name)`` when the child's end closes."""

    def __init__(self, conn: Connection, out: queue.Queue[Any], *, name: str) -> None:
        self._conn, self._out, self.name = conn, out, name
        self._thread = threading.Thread(target=self._run, name=f"pump-{name}", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        from hil.adapters.process import prioritise_this_thread
        from hil.harness.engine.messages import ChildGone

        prioritise_this_thread()  # world states and frames are on the capture path
        while True:
            try:
                msg = self._conn.recv()
            except (EOFError, OSError):
                self._out.put(ChildGone(self.name))
                return
            self._out.put(msg)

    def join(self, timeout_s: float) -> None:
        self._thread.join(timeout_s)
