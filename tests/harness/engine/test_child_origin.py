"""The engine's children come from a fork server with the engine's modules imported
(hil.harness.engine.procs): each takes the cores and nice value of the thread that
started it, as a spawned child inherited them, and dies with the run process."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

from hil.harness.engine.procs import Origin, child_context

ROOT = Path(__file__).resolve().parents[3]


def _report(origin: Origin, conn: Connection) -> None:
    origin.adopt()
    conn.send((sorted(os.sched_getaffinity(0)), os.getpriority(os.PRIO_PROCESS, 0), os.getppid(),
               "hil.harness.engine.render" in sys.modules))


def test_a_child_takes_the_cores_and_nice_of_the_thread_that_starts_it() -> None:
    ctx = child_context()
    cores = sorted(os.sched_getaffinity(0))
    got: dict[str, Any] = {}

    def starter() -> None:  # affinity and nice are the thread's own: the test's thread keeps its
        tid = threading.get_native_id()
        os.sched_setaffinity(0, {cores[0]})
        base = os.getpriority(os.PRIO_PROCESS, tid)
        os.setpriority(os.PRIO_PROCESS, tid, min(19, base + 2))
        a, b = ctx.Pipe(duplex=False)
        p = ctx.Process(target=_report, args=(Origin.here(), b), daemon=True)
        p.start()
        b.close()
        got["child"] = a.recv() if a.poll(60) else None
        got["nice"] = min(19, base + 2)
        p.join(10)

    t = threading.Thread(target=starter)
    t.start()
    t.join(90)
    assert got.get("child") is not None, "the child never answered"
    child_cores, nice, ppid, preloaded = got["child"]
    assert child_cores == [cores[0]] and nice == got["nice"]
    if ctx.get_start_method() == "forkserver":
        assert ppid != os.getpid()  # a fork of the server, which imported the engine's modules
        assert preloaded


def _park(origin: Origin) -> None:
    origin.adopt()
    print("adopted", os.getpid(), flush=True)
    time.sleep(120)


def park_in_a_child() -> None:
    """A run process in small: one engine child, parked; prints the server's PID."""
    from multiprocessing import forkserver

    p = child_context().Process(target=_park, args=(Origin.here(),), daemon=True)
    p.start()
    print("server", getattr(forkserver._forkserver, "_forkserver_pid", None), flush=True)  # type: ignore[attr-defined]
    time.sleep(120)


def _running(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except (OSError, IndexError):
        return False
    return state != "Z"


def test_killing_the_run_process_ends_the_server_and_its_children() -> None:
    p = subprocess.Popen([sys.executable, "-c", "from tests.harness.engine.test_child_origin import "
                          "park_in_a_child; park_in_a_child()"], cwd=ROOT, stdout=subprocess.PIPE, text=True)
    try:
        assert p.stdout is not None
        pids: dict[str, int] = {}
        deadline = time.monotonic() + 60
        while len(pids) < 2 and time.monotonic() < deadline:
            line = p.stdout.readline().split()
            if len(line) == 2 and line[1].isdigit():
                pids[line[0]] = int(line[1])
        assert set(pids) == {"server", "adopted"}, pids
        assert all(_running(pid) for pid in pids.values())
        p.send_signal(signal.SIGKILL)
        p.wait(10)
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline and any(_running(pid) for pid in pids.values()):
            time.sleep(0.05)
        assert not [name for name, pid in pids.items() if _running(pid)]
    finally:
        if p.poll() is None:
            p.kill()
            p.wait(10)


def test_where_the_server_cannot_start_the_children_are_spawned(tmp_path: Path) -> None:
    # The server's socket lives in the temporary folder: a path past AF_UNIX's 108 bytes
    # cannot be bound (a real failure, as a full or odd temporary folder would be).
    deep = tmp_path / ("x" * 60) / ("y" * 60)
    deep.mkdir(parents=True)
    code = ("from hil.harness.engine.procs import Origin, child_context\n"
            "from tests.harness.engine.test_child_origin import _report\n"
            "ctx = child_context()\n"
            "a, b = ctx.Pipe(duplex=False)\n"
            "p = ctx.Process(target=_report, args=(Origin.here(), b)); p.start(); b.close()\n"
            "print(ctx.get_start_method(), a.recv()[2] == __import__('os').getpid()); p.join(10)\n")
    p = subprocess.run([sys.executable, "-c", code], cwd=ROOT, env=dict(os.environ, TMPDIR=str(deep)),
                       capture_output=True, text=True, timeout=120)
    assert p.returncode == 0, p.stderr[-2000:]
    assert p.stdout.split() == ["spawn", "True"]  # spawned: its parent is the caller itself
