"""Ending a target process the harness started: by PID, politely first."""

from __future__ import annotations

import ctypes
import signal
import subprocess

_PR_SET_PDEATHSIG = 1


def prioritise_this_thread(by: int = 5) -> int | None:
    """Lower the calling thread's nice value by ``by`` from what it is (served first
    when the cores are busy): for threads that stamp receipts or move frames. Relative,
    so a harness started at ``nice -n 10`` stays below the user's other work. Needs
    CAP_SYS_NICE (root). Returns the nice value the thread had (for
    :func:`restore_thread_priority`), or None, changing nothing, without the privilege."""
    import os
    import threading

    tid = threading.get_native_id()
    try:
        before = os.getpriority(os.PRIO_PROCESS, tid)
        os.setpriority(os.PRIO_PROCESS, tid, max(-20, before - by))
    except (OSError, AttributeError):
        return None
    return before


def restore_thread_priority(nice: int) -> None:
    """Give the calling thread back the nice value :func:`prioritise_this_thread` returned."""
    import os
    import threading

    try:
        os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), nice)
    except (OSError, AttributeError):
        pass


def die_with_parent() -> None:
    """``preexec_fn`` for a target the harness starts: the kernel SIGKILLs it when the
    harness dies, even by SIGKILL, so no target outlives its run (Linux; elsewhere a
    no-op)."""
    try:
        ctypes.CDLL(None, use_errno=True).prctl(_PR_SET_PDEATHSIG, int(signal.SIGKILL), 0, 0, 0)
    except (OSError, AttributeError):
        pass


def end_process(proc: subprocess.Popen[bytes] | None, *, grace_s: float = 2.0, term_s: float = 2.0) -> None:
    """Wait ``grace_s`` for ``proc`` to leave on its own (it was told BYE), then
    SIGTERM, then after ``term_s`` SIGKILL. Returns once it has exited."""
    if proc is None or proc.poll() is not None:
        return
    try:
        proc.wait(timeout=grace_s)
    except subprocess.TimeoutExpired:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(timeout=term_s)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
