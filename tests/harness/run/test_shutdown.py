"""No process outlives its run: the physics process, the render workers and the
targets end with the harness whether it is killed (SIGKILL) in the middle of a run
or terminated (SIGTERM) while it waits for a target to start; shared memory goes too."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests.conftest import GL_BACKEND

ROOT = Path(__file__).resolve().parents[3]


def _children(pid: int) -> set[int]:
    """Every descendant of ``pid`` (from /proc)."""
    parent: dict[int, int] = {}
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                stat = (d / "stat").read_text()
            except OSError:
                continue
            parent[int(d.name)] = int(stat.rsplit(")", 1)[1].split()[1])
    out, todo = set(), [pid]
    while todo:
        p = todo.pop()
        kids = [c for c, pp in parent.items() if pp == p]
        out.update(kids)
        todo.extend(kids)
    return out


def _alive(pid: int) -> bool:
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return False
    return stat.rsplit(")", 1)[1].split()[0] != "Z"


def _wait_for(pred, timeout_s: float) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if pred():
            return True
        time.sleep(0.05)
    return pred()


def _start(out: Path, *sets: str) -> subprocess.Popen[str]:
    env = dict(os.environ, MUJOCO_GL=GL_BACKEND)
    args = [sys.executable, "-m", "hil.harness.cli.main", "run", "hil_configs/demo.yaml", "--no-progress", "--out", str(out)]
    for s in sets:
        args += ["--set", s]
    return subprocess.Popen(args, cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _wait_for_frames(p: subprocess.Popen[str], out: Path) -> None:
    """Until the run records frames: by then its loop runs and every child has started."""
    assert _wait_for(lambda: (out / "run.mcap").exists() and (out / "run.mcap").stat().st_size > 50_000, 90), \
        p.stderr.read() if p.poll() is not None and p.stderr else "no frames recorded"


def _shm() -> set[str]:
    return {p.name for p in Path("/dev/shm").glob("psm_*")}


@pytest.mark.slow
def test_sigkill_mid_run_leaves_no_process_and_no_shared_memory(tmp_path):
    before = _shm()
    out = tmp_path / "run"
    p = _start(out, "duration_s=60")
    try:
        _wait_for_frames(p, out)
        kids = _children(p.pid)
        names = {Path(f"/proc/{k}/cmdline").read_bytes().replace(b"\0", b" ")[:200] for k in kids if _alive(k)}
        assert len(kids) >= 3, names  # physics, a render worker, the target (and the resource tracker)
        p.send_signal(signal.SIGKILL)
        p.wait(10)
        assert _wait_for(lambda: not any(_alive(k) for k in kids), 10), \
            [k for k in kids if _alive(k)]
        assert _wait_for(lambda: not (_shm() - before), 10), _shm() - before
    finally:
        if p.poll() is None:
            p.kill()
            p.wait(10)


@pytest.mark.slow
def test_sigterm_while_waiting_for_the_target_ends_everything(tmp_path):
    out = tmp_path / "run"
    # A "target" that never says HELLO: the harness waits for it until SIGTERM.
    p = _start(out, 'target.command=["{python}", "-c", "import time; time.sleep(120)"]',
               "target.startup_timeout_s=60")
    try:
        assert _wait_for(lambda: any(b"time.sleep(120)" in _cmdline(k) for k in _children(p.pid)), 60), \
            p.stderr.read() if p.poll() is not None else "the target never started"
        kids = _children(p.pid)
        p.send_signal(signal.SIGTERM)
        code = p.wait(30)
        err = p.stderr.read()
        assert code == 1, err
        assert "Traceback" not in err and "interrupted" in err, err
        assert _wait_for(lambda: not any(_alive(k) for k in kids), 10), [k for k in kids if _alive(k)]
    finally:
        if p.poll() is None:
            p.kill()
            p.wait(10)


def _parent(pid: int) -> int | None:
    try:
        return int(Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[1])
    except (OSError, ValueError, IndexError):
        return None


def _cmdline(pid: int) -> bytes:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes()
    except OSError:
        return b""


@pytest.mark.slow
def test_a_render_worker_crashing_ends_the_run_cleanly(tmp_path):
    out = tmp_path / "run"
    p = _start(out, "duration_s=60")
    try:
        _wait_for_frames(p, out)
        kids = _children(p.pid)
        # The engine's children are forks of its fork server (hil.harness.engine.procs).
        server = [k for k in kids if b"multiprocessing.forkserver" in _cmdline(k) and _parent(k) == p.pid]
        workers = [k for k in kids if server and _parent(k) == server[0]]
        assert len(workers) >= 2, [_cmdline(k)[:120] for k in kids]  # physics + render worker(s)
        # The render worker is the one started first (the physics process starts last).
        victim = min(workers)
        os.kill(victim, signal.SIGKILL)
        code = p.wait(60)
        err = p.stderr.read()
        assert code == 1, err[-2000:]
        assert "Traceback" not in err, err[-3000:]
        s = __import__("json").loads((out / "summary.json").read_text())
        assert "ended unexpectedly" in s["ended_by"], s["ended_by"]
        assert _wait_for(lambda: not any(_alive(k) for k in kids), 10), [k for k in kids if _alive(k)]
    finally:
        if p.poll() is None:
            p.kill()
            p.wait(10)
