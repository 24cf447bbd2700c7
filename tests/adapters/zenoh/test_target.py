"""``hil target NAME --transport zenoh`` as a person on a bench starts it: it says
where it listens, its clock and capabilities, and serves harness after harness
until stopped (issue 14, item 15)."""

from __future__ import annotations

import os
import select
import signal
import subprocess
import sys

import pytest

from tests.adapters.zenoh.pair import ROOT, SKIP_REASON, end_process, free_port, zenoh_link

pytestmark = pytest.mark.skipif(SKIP_REASON is not None, reason=SKIP_REASON or "")


def _first_line(proc: subprocess.Popen[str], timeout_s: float) -> str:
    assert proc.stderr is not None
    ready, _, _ = select.select([proc.stderr], [], [], timeout_s)  # waits on the pipe, bounded
    assert ready, "the target printed nothing at startup"
    return proc.stderr.readline()


@pytest.mark.slow
def test_hil_target_announces_itself_and_serves_run_after_run():

    port = free_port()
    proc = subprocess.Popen([sys.executable, "-m", "hil.harness.cli.main", "target", "echo", "--transport", "zenoh",
                             "--listen", f"tcp/127.0.0.1:{port}"], cwd=ROOT, stdin=subprocess.DEVNULL,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                            env=dict(os.environ, PYTHONUNBUFFERED="1"))
    try:
        line = _first_line(proc, 30)
        assert f"echo: zenoh target listening on tcp/127.0.0.1:{port}" in line, line
        assert "keys hil/v0/*" in line and "clock MONOTONIC" in line and "capabilities:" in line, line
        assert "run after run" in line, line
        for run in range(2):  # the second harness finds the target still there
            link = zenoh_link(port)
            try:
                assert link.open(hello_timeout_s=20).target_name == "echo", run
                assert link.sync_exchange(timeout_s=2.0) is not None, run
            finally:
                link.close()
            assert proc.poll() is None, f"the target exited after run {run + 1}"
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=10) == 0
    finally:
        end_process(proc)  # type: ignore[arg-type]
        if proc.stderr is not None:
            proc.stderr.close()


@pytest.mark.slow
def test_once_serves_one_harness():
    port = free_port()
    proc = subprocess.Popen([sys.executable, "-m", "hil.harness.cli.main", "target", "echo", "--transport", "zenoh",
                             "--listen", f"tcp/127.0.0.1:{port}", "--once"], cwd=ROOT, stdin=subprocess.DEVNULL,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        assert "serving one run" in _first_line(proc, 30)
        with zenoh_link(port) as link:
            link.open(hello_timeout_s=20)
        rc = proc.wait(timeout=10)
        assert rc == 0, proc.stderr.read() if proc.stderr is not None else rc
    finally:
        end_process(proc)  # type: ignore[arg-type]
        if proc.stderr is not None:
            proc.stderr.close()


# The target of ``hil target echo --transport zenoh``, with a SIGTERM sent to itself while
# it makes the endpoint for the next harness: the one moment the endpoint the signal stops
# is not the one served next.
_BETWEEN = """
import os, signal, sys
import hil.adapters.zenoh.target as zt
made = zt.fresh_endpoint
def fresh_endpoint(base, done):
    os.kill(os.getpid(), signal.SIGTERM)
    return made(base, done)
zt.fresh_endpoint = fresh_endpoint
from hil.harness.cli.main import main
sys.exit(main(["target", "echo", "--transport", "zenoh", "--listen", sys.argv[1]]))
"""


# A shared target (one session, a thread per vehicle) with the SIGTERM landing while the
# vehicle's thread makes its endpoint, before that endpoint is the one a SIGTERM stops.
_SHARED_BETWEEN = """
import os, signal, sys, time
from hil.adapters.batching import BatchedEndpoint, BatchScheduler
from hil.adapters.zenoh.options import ZenohOptions
from hil.adapters.zenoh.shared_target import serve_shared
sched = BatchScheduler(lambda frames: [], window_ns=1_000_000)
made = []
def make_endpoint():
    made.append(1)
    if len(made) == 2:  # the first is for the startup line; this one is vehicle 0's
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(0.5)  # the main thread's handler runs before this endpoint is current
    return BatchedEndpoint(sched, target_name="shared")
serve_shared(sched, make_endpoint, vehicles=[0], options=ZenohOptions(listen=(sys.argv[1],)), keep_serving=True)
"""


@pytest.mark.slow
@pytest.mark.parametrize("script", [_BETWEEN, _SHARED_BETWEEN], ids=["own", "shared"])
def test_a_sigterm_while_the_next_endpoint_is_made_ends_the_target(script):
    # Before: the SIGTERM stopped the endpoint before (the harness's that had left, or
    # none), and the target served the new one until the next signal (a run-after-run
    # test waited 10 s). The own target gets its signal once a harness has left.
    port = free_port()
    proc = subprocess.Popen([sys.executable, "-c", script, f"tcp/127.0.0.1:{port}"], cwd=ROOT,
                            stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                            env=dict(os.environ, PYTHONUNBUFFERED="1"))
    try:
        assert "run after run" in _first_line(proc, 30)
        if script is _BETWEEN:
            link = zenoh_link(port)
            try:
                assert link.open(hello_timeout_s=20).target_name == "echo"
            finally:
                link.close()  # the harness leaves: the target makes the next endpoint
        assert proc.wait(timeout=10) == 0
    finally:
        end_process(proc)  # type: ignore[arg-type]
        if proc.stderr is not None:
            proc.stderr.close()
