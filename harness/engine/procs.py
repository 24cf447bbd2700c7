"""Process plumbing shared by the engine's children: die with the parent, ask for a
real-time scheduling class, keep a core for the physics, and pump a child's pipe or
the physics's ring into the run's handlers."""

from __future__ import annotations

import contextlib
import ctypes
import os
import re
import signal
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from multiprocessing.connection import Connection
from typing import Any

from hil.common.errors import ConfigError

_PR_SET_PDEATHSIG = 1
_PR_SET_TIMERSLACK = 29
_F_SETPIPE_SZ = 1031


def _prctl(option: int, arg: int) -> bool:
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        return int(libc.prctl(option, arg, 0, 0, 0)) == 0
    except (OSError, AttributeError):  # not Linux
        return False


# A link's reader or a pump gets the interpreter back within this of a frame or an
# estimate arriving, even while the analysis and recording threads are busy (Python's
# default is 5 ms).
SWITCH_INTERVAL_S = 0.0001


@contextlib.contextmanager
def loop_process(*, collect: bool = True) -> Iterator[None]:
    """A process while its run loop goes (the run process's, each shard process's):
    Python's full garbage collection held off (a collection over a run's growing
    history stalled a loop for 60-80 ms; a shard's first one 36-60 ms here) after one
    now (``collect``; False: the caller just did), with what is alive frozen out of
    later ones, and the 0.1 ms switch interval. Restored after."""
    import gc
    import sys

    thresholds, switch = gc.get_threshold(), sys.getswitchinterval()
    if collect:
        gc.collect()
    gc.freeze()
    gc.set_threshold(thresholds[0], thresholds[1], 1_000_000)
    sys.setswitchinterval(SWITCH_INTERVAL_S)
    try:
        yield
    finally:
        sys.setswitchinterval(switch)
        gc.set_threshold(*thresholds)
        gc.unfreeze()


def _thread_cpu_clock(native_id: int) -> int:
    """Linux's CPU-time clock of the thread ``native_id`` (its kernel id), as glibc's
    ``pthread_getcpuclockid`` makes it. Unlike that call it names no ``pthread_t``
    that a thread ending meanwhile frees: a gone thread's clock is refused (EINVAL)."""
    return ((~native_id) << 3) | 6  # CPUCLOCK_SCHED | CPUCLOCK_PERTHREAD_MASK


def threads_cpu_ns(*, loop_ident: int | None = None) -> dict[int, tuple[str, int]]:
    """CPU time (ns) of each live Python thread of this process so far, by kernel
    thread id: ``(role, ns)``, the role being the thread's name without its ``-N``
    parts (``local-rx-3`` -> ``local-rx``, ``shard-0-rec`` -> ``shard-rec``), ``loop``
    for the thread ``loop_ident``.
    A thread that ends while this reads it is left out."""
    out: dict[int, tuple[str, int]] = {}
    for t in threading.enumerate():
        tid = t.native_id
        if tid is None:
            continue
        try:
            ns = time.clock_gettime_ns(_thread_cpu_clock(tid))
        except OSError:  # gone meanwhile (or not Linux)
            continue
        role = "loop" if t.ident == loop_ident else re.sub(r"-\d+(?=-|$)", "", t.name) or t.name
        out[tid] = (role, ns)
    return out


def cpu_by_role(before: dict[int, tuple[str, int]], after: dict[int, tuple[str, int]]) -> dict[str, int]:
    """CPU time (ns) each role's threads spent between two :func:`threads_cpu_ns`
    readings (a thread started in between counts from its start)."""
    out: dict[str, int] = {}
    for tid, (role, ns) in after.items():
        was = before.get(tid)
        out[role] = out.get(role, 0) + ns - (was[1] if was is not None and was[0] == role else 0)
    return out


class ThreadCpu:
    """Each thread's CPU time of this process between :meth:`start` and :meth:`mark_end`
    (read at the run's last step, while every thread still runs; without it, when
    :meth:`by_role` is called), by role; ``loop`` is the thread that called ``start``."""

    def __init__(self) -> None:
        self._loop: int | None = None
        self._start: dict[int, tuple[str, int]] = {}
        self._end: dict[int, tuple[str, int]] | None = None

    def start(self) -> None:
        self._loop = threading.get_ident()
        self._start = threads_cpu_ns(loop_ident=self._loop)

    def mark_end(self) -> None:
        self._end = threads_cpu_ns(loop_ident=self._loop)

    def by_role(self) -> dict[str, int]:
        return cpu_by_role(self._start, self._end or threads_cpu_ns(loop_ident=self._loop))


def stacks_on_sigusr2() -> None:
    """SIGUSR2 prints every thread's stack of this process on stderr and goes on: what
    a run that seems stuck is doing, without stopping it (README, "A run that seems stuck").
    Nothing where there is no standard error to print on (closed, or not a file)."""
    import faulthandler

    try:
        faulthandler.register(signal.SIGUSR2, all_threads=True)
    except (RuntimeError, ValueError, OSError):  # sys.stderr None, or without a file descriptor
        pass


def die_with_parent(expected_parent: int | None = None) -> None:
    """Have the kernel SIGKILL this process when its parent dies (Linux), so a
    killed run never leaves workers behind. Exits at once if the parent is already
    gone (``expected_parent`` given and no longer our parent). A harness child also
    prints its stacks on SIGUSR2 (``stacks_on_sigusr2``)."""
    stacks_on_sigusr2()
    _prctl(_PR_SET_PDEATHSIG, int(signal.SIGKILL))
    if expected_parent is not None and os.getppid() != expected_parent:
        os._exit(1)


# --- where the engine's children come from ------------------------------------------
# Spawned, each child started an interpreter and imported MuJoCo, numpy and our engine
# modules (~0.3 s of CPU a child, on the start of every run; 16 render workers pay it 16
# times). A fork server of the run process imports them once: each child is a fork of it
# (a clean process: no thread, no GL context; the GL backend was chosen before it
# started). What a spawned child took from the thread that started it (its cores, its
# nice value) and its parent-death tie are set by the child itself (:class:`Origin`).
ENGINE_MODULES = ["hil.harness.engine.physics", "hil.harness.engine.render"]


def child_context() -> Any:
    """The multiprocessing context the engine starts its children from: the fork server
    with :data:`ENGINE_MODULES` imported (Linux; started here if it is not running),
    else spawn (no fork server here, or it could not start: its socket lives in the
    temporary folder)."""
    import multiprocessing as mp

    if "forkserver" not in mp.get_all_start_methods():
        return mp.get_context("spawn")
    from multiprocessing import forkserver

    ctx = mp.get_context("forkserver")
    ctx.set_forkserver_preload(ENGINE_MODULES)
    try:
        forkserver.ensure_running()
    except OSError:
        return mp.get_context("spawn")
    return ctx


def start_child_server() -> None:
    """Start the fork server now, so that its imports overlap the caller's (``hil run``
    while it loads its config and modules). Only once the GL backend is chosen
    (``MUJOCO_GL`` set): the server imports MuJoCo, which fixes it; the GL driver's
    settings (``select_backend``) are set first, for its children to inherit. Idempotent.

    Raises:
        SimulationError: ``MUJOCO_GL`` names no backend MuJoCo renders with.
    """
    if os.environ.get("MUJOCO_GL", "").strip():
        from hil.scenarios.gl import select_backend

        select_backend()
        child_context()


def stop_child_server() -> None:
    """End this process's fork server at once, if it has one (a command's end: one that
    stopped before it ran anything does not leave it importing for nothing)."""
    import sys

    module = sys.modules.get("multiprocessing.forkserver")
    server = getattr(module, "_forkserver", None)
    pid = getattr(server, "_forkserver_pid", None)
    if server is None or not isinstance(pid, int):
        return
    with contextlib.suppress(OSError):
        os.kill(pid, signal.SIGKILL)
    with contextlib.suppress(OSError, ChildProcessError):
        server._stop()


@dataclass(frozen=True)
class Origin:
    """What an engine child takes from the thread that starts it (:meth:`here`) and
    applies first (:meth:`adopt`), however it was started: the run process's PID (to
    die with it), the cores and the nice value of that thread (the physics's own core
    kept off, ``nice`` of the caller)."""

    pid: int
    cores: frozenset[int] | None = None
    nice: int | None = None

    @classmethod
    def here(cls) -> Origin:
        try:
            cores: frozenset[int] | None = frozenset(os.sched_getaffinity(0))
        except AttributeError:  # not Linux
            cores = None
        try:
            nice: int | None = os.getpriority(os.PRIO_PROCESS, threading.get_native_id())
        except (AttributeError, OSError):
            nice = None
        return cls(os.getpid(), cores, nice)

    def adopt(self) -> None:
        """Die with the run process (SIGKILL when it is gone: directly where it is the
        parent; a fork server's children through the server, which ends when the run
        process does), exiting at once if it is already gone; then the run thread's
        cores and nice value. A harness child also prints its stacks on SIGUSR2."""
        parent = os.getppid()
        if parent != self.pid:  # forked by the fork server: it stays up while a client holds
            _release_server_tie()  # its "alive" pipe; only the run process may hold it
        die_with_parent(parent)  # exits if that parent is gone already
        if not _alive(self.pid):  # the run process, where the server is the parent
            os._exit(1)
        if self.cores:
            with contextlib.suppress(OSError):
                os.sched_setaffinity(0, self.cores)
        if self.nice is not None:
            with contextlib.suppress(OSError):  # a lower nice value than the server's needs the privilege
                if os.getpriority(os.PRIO_PROCESS, 0) != self.nice:
                    os.setpriority(os.PRIO_PROCESS, 0, self.nice)


def _release_server_tie() -> None:
    """Close this child's copy of the fork server's "alive" pipe (multiprocessing hands
    it to every child it forks): the server then ends when the run process does, and
    with it, by their parent-death signal, its children."""
    from multiprocessing import forkserver

    server = getattr(forkserver, "_forkserver", None)
    fd = getattr(server, "_forkserver_alive_fd", None)
    if isinstance(fd, int):
        with contextlib.suppress(OSError):
            os.close(fd)
        server._forkserver_alive_fd = None  # type: ignore[union-attr]


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # there, another user's
        pass
    return True


def preexec_die_with_parent() -> None:
    """For ``subprocess.Popen(preexec_fn=...)``: the target dies with the harness."""
    _prctl(_PR_SET_PDEATHSIG, int(signal.SIGKILL))


def ask_realtime(priority: int, *, fallback_nice: int = 0, cpu: int | None = None) -> str:
    """Ask for SCHED_FIFO at ``priority`` (0: don't) and 1 ns timer slack; without it
    (refused on a VM or without privileges, or not asked for), ask for nice
    ``fallback_nice`` instead (granted to root or where ``RLIMIT_NICE`` allows; 0:
    don't). With ``cpu``, run on that core only. Returns what was granted, in words,
    for the summary."""
    _prctl(_PR_SET_TIMERSLACK, 1)
    where = ""
    if cpu is not None:
        try:
            os.sched_setaffinity(0, {cpu})
            where = f", on core {cpu}"
        except (OSError, AttributeError) as err:
            where = f", core {cpu} refused ({getattr(err, 'strerror', None) or err})"
    if priority > 0:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
            return f"SCHED_FIFO priority {priority}{where}"
        except (PermissionError, OSError, AttributeError) as err:
            why = f"SCHED_FIFO refused: {getattr(err, 'strerror', None) or err}"
    else:
        why = "real-time class not requested"
    if fallback_nice < 0:
        try:
            os.setpriority(os.PRIO_PROCESS, 0, fallback_nice)
            return f"normal, nice {fallback_nice} ({why}){where}"
        except (PermissionError, OSError):
            why += f"; nice {fallback_nice} refused too"
    return f"normal ({why}){where}"


def physics_core(setting: str | int) -> int | None:
    """The core the physics keeps to itself under ``engine.physics_cpu``: ``"auto"``
    gives it the last core of this process's set when there are 4 or more (fewer
    cannot spare one: rendering needs them), ``"none"`` none, a number that core.

    Raises:
        ConfigError: a number that is not a core this process may run on (the
            physics would run unpinned, said only in ``summary.json``).
    """
    if setting == "none":
        return None
    try:
        cores = sorted(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        return setting if isinstance(setting, int) else None
    if isinstance(setting, int):
        if setting not in cores:
            raise ConfigError(f"engine.physics_cpu: core {setting} is not one this run may use here (cores "
                              f"{', '.join(map(str, cores))}); use one of them, auto or none")
        return setting
    return cores[-1] if len(cores) >= 4 else None


def keep_off_core(cpu: int | None) -> set[int] | None:
    """Keep the calling thread (the threads and children it starts from now on) off
    core ``cpu``, the physics's own (None: nothing to do). Returns the cores it had,
    for :func:`restore_affinity`."""
    if cpu is None:
        return None
    try:
        before = set(os.sched_getaffinity(0))
        if before - {cpu}:
            os.sched_setaffinity(0, before - {cpu})
        return before
    except (OSError, AttributeError):
        return None


def restore_affinity(cores: set[int] | None) -> None:
    """Undo :func:`keep_off_core` (None: nothing to undo)."""
    if cores:
        try:
            os.sched_setaffinity(0, cores)
        except (OSError, AttributeError):
            pass


def lower_thread_priority(by: int = 10) -> None:
    """Make the calling thread yield the CPU to the run's latency-critical threads:
    its nice value ``by`` above what it is, at most 19 (Linux: a thread's nice value is
    its own; raising it needs no privilege). The analysis and recording threads call
    this, so the loop thread that moves frames and controls is served first when the
    cores are busy."""
    try:
        import threading

        tid = threading.get_native_id()
        os.setpriority(os.PRIO_PROCESS, tid, min(19, os.getpriority(os.PRIO_PROCESS, tid) + by))
    except (OSError, AttributeError):
        pass


def end_child(p: Any, *, grace_s: float = 2.0) -> None:
    """Wait ``grace_s`` for a child process (``multiprocessing``) to leave as asked,
    then terminate it, then kill it."""
    p.join(grace_s)
    if p.is_alive():
        p.terminate()
        p.join(2.0)
    if p.is_alive():
        p.kill()
        p.join(2.0)


def widen_pipe(conn: Connection, size: int = 1 << 20) -> None:
    """Let a pipe hold ``size`` bytes, so a child never blocks on a busy reader."""
    try:
        import fcntl
        fcntl.fcntl(conn.fileno(), _F_SETPIPE_SZ, size)
    except (OSError, ImportError, AttributeError):
        pass


class Pump:
    """A daemon thread that hands every message of ``conn`` to ``deliver`` (on this
    thread: no further hand-off), and ``ChildGone(name)`` when the child's end closes."""

    def __init__(self, conn: Connection, deliver: Callable[[Any], None], *, name: str) -> None:
        self._conn, self._deliver, self.name = conn, deliver, name
        self._thread = threading.Thread(target=self._run, name=f"pump-{name}", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        from hil.adapters.process import prioritise_this_thread
        from hil.harness.engine.messages import ChildGone

        prioritise_this_thread()  # frames are on the capture path
        deliver = self._deliver
        while True:
            try:
                msg = self._conn.recv()
            except (EOFError, OSError):
                deliver(ChildGone(self.name))
                return
            deliver(msg)

    def join(self, timeout_s: float) -> None:
        self._thread.join(timeout_s)


class RingPump:
    """A daemon thread that decodes every record of a ring the physics writes
    (``hil.harness.engine.rings``) and hands it to ``deliver`` (on this thread), and
    ``ChildGone(name)`` when its producer's end closes. ``stall``: (step, seconds):
    once the world state of that step is read, stop reading that long
    (``engine.faults.stall_run_ms``)."""

    def __init__(self, ring: Any, deliver: Callable[[Any], None], *, name: str,
                 stall: tuple[int, float] | None = None) -> None:
        self._ring, self._deliver, self.name = ring, deliver, name
        self._stall = stall
        self._thread = threading.Thread(target=self._run, name=f"ring-{name}", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        import select

        from hil.adapters.process import prioritise_this_thread
        from hil.harness.engine.messages import ChildGone, decode

        prioritise_this_thread()
        ring, put, stall = self._ring, self._deliver, self._stall
        try:
            while True:
                select.select([ring.fileno()], [], [])
                for record in ring.read():
                    msg = decode(record)
                    put(msg)
                    if stall is not None and getattr(msg, "steps", -1) >= stall[0]:
                        time.sleep(stall[1])  # the injected fault: a stuck consumer
                        stall = None
                if ring.closed_by_producer:
                    break
        except (OSError, ValueError, AssertionError):  # closed under us: the run is over
            pass
        put(ChildGone(self.name))

    def join(self, timeout_s: float) -> None:
        self._thread.join(timeout_s)
