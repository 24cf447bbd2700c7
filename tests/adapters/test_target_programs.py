"""Every transport's target behaves like the Zenoh one, as real processes: one start-up
line (where, clock, capabilities, access), run after run until SIGTERM (``--once``:
one), one line per session (who, frames, how it ended), and a user mistake or an
unusable transport is one line and exit 2, never a traceback."""

from __future__ import annotations

import contextlib
import os
import queue
import signal
import socket
import subprocess
import sys
import threading
import time
import uuid
from collections.abc import Iterator, Sequence

import pytest

from hil.adapters.sdk import Endpoint
from hil.adapters.tcp.link import TcpLink
from hil.adapters.tcp.options import TcpOptions
from hil.adapters.wire.messages import Control, DrivingState, Inference
from hil.timing.clock import MonotonicClock
from tests.adapters.test_conformance import next_estimate, send_frame
from tests.adapters.zenoh.pair import ROOT, free_port
from tests.targets import c_build


class Lines:
    """A target process whose stderr lines arrive on a queue as they are written."""

    def __init__(self, argv: Sequence[str], env: dict[str, str] | None = None) -> None:
        self.proc = subprocess.Popen(list(argv), cwd=ROOT, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                                     stderr=subprocess.PIPE, text=True,
                                     env=dict(os.environ if env is None else env, PYTHONUNBUFFERED="1"))
        self.lines: queue.Queue[str] = queue.Queue()
        self.seen: list[str] = []
        threading.Thread(target=self._pump, daemon=True).start()

    def _pump(self) -> None:
        assert self.proc.stderr is not None
        for line in self.proc.stderr:
            self.lines.put(line.rstrip("\n"))

    def expect(self, text: str, timeout_s: float = 30.0) -> str:
        """The next line containing ``text`` (waiting for it)."""
        deadline = time.monotonic() + timeout_s
        while (left := deadline - time.monotonic()) > 0:
            try:
                line = self.lines.get(timeout=left)
            except queue.Empty:
                break
            self.seen.append(line)
            if text in line:
                return line
        raise AssertionError(f"no line with {text!r} in {timeout_s:g} s; got {self.seen}")

    def end(self) -> int:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
        try:
            return self.proc.wait(timeout=10)
        finally:
            if self.proc.poll() is None:
                self.proc.kill()
                self.proc.wait()


@contextlib.contextmanager
def target(argv: Sequence[str], env: dict[str, str] | None = None) -> Iterator[Lines]:
    t = Lines(argv, env)
    try:
        yield t
    finally:
        t.end()


def _one_session(address: str) -> None:
    link = TcpLink(vehicle_id=3, clock=MonotonicClock(), options=TcpOptions(connect=address))
    try:
        link.open(hello_timeout_s=20)
        send_frame(link, 1)
        assert next_estimate(link)[0].frame_id == 1
    finally:
        link.close()


HIL = [sys.executable, "-m", "hil.harness.cli.main"]


@pytest.mark.parametrize("program", ["hil target echo", "c"])
def test_a_listening_tcp_target_serves_run_after_run_until_sigterm(program):
    address = f"127.0.0.1:{free_port()}"
    if program == "c":
        if c_build.unavailable():
            pytest.skip(str(c_build.unavailable()))
        argv = [str(c_build.build().plain), "--transport", "tcp", "--listen", address]
        name = "c-reference"
    else:
        argv = [*HIL, "target", "echo", "--transport", "tcp", "--listen", address]
        name = "echo"
    env = {k: v for k, v in os.environ.items() if k not in ("HIL_SESSION", "HIL_SESSION_TOKEN")}
    with target(argv, env) as t:
        start = t.expect("target listening on")
        assert start.startswith(f"{name}: tcp target listening on {address}") and "clock MONOTONIC" in start
        assert "protocol v1" in start and "access: no token" in start and "run after run" in start, start
        for n in (1, 2):  # the second run finds it listening still (it used to serve one and exit)
            _one_session(address)
            line = t.expect(f"session {n} with 127.0.0.1:")
            assert "vehicle 3: 1 frames, 1 estimates" in line and "ended: the harness said BYE" in line, line
        t.proc.send_signal(signal.SIGTERM)
        assert t.proc.wait(timeout=10) == 0


def test_a_zenoh_target_prints_a_line_per_session_as_tcp_and_can_ones_do():
    # The README: a hand-started target prints one line per session (who, frames and
    # estimates, how it ended); the zenoh one printed its startup line alone.
    from tests.adapters.zenoh.pair import zenoh_link

    port = free_port()
    with target([*HIL, "target", "echo", "--transport", "zenoh", "--listen", f"tcp/127.0.0.1:{port}"]) as t:
        assert "zenoh target" in t.expect("run after run")
        for n in (1, 2):
            link = zenoh_link(port)
            try:
                link.open(hello_timeout_s=20)
                send_frame(link, n)
                assert next_estimate(link)[0].frame_id == n
            finally:
                link.close()
            line = t.expect(f"session {n} with the harness on")
            assert "vehicle 0: 1 frames, 1 estimates" in line and "ended: the harness said BYE" in line, line
        t.proc.send_signal(signal.SIGTERM)
        assert t.proc.wait(timeout=15) == 0


def test_once_serves_one_run():
    address = f"127.0.0.1:{free_port()}"
    with target([*HIL, "target", "echo", "--transport", "tcp", "--listen", address, "--once"]) as t:
        assert "serving one run" in t.expect("target listening on")
        _one_session(address)
        t.expect("session 1 with")
        assert t.proc.wait(timeout=10) == 0


def test_a_dialling_tcp_target_dials_again_after_each_run():
    address = f"127.0.0.1:{free_port()}"
    with target([*HIL, "target", "echo", "--transport", "tcp", "--connect", address]) as t:
        assert "dialling the harness at" in t.expect("tcp target")
        for n in (1, 2):
            link = TcpLink(vehicle_id=0, clock=MonotonicClock(), options=TcpOptions(listen=address))
            try:
                link.open(hello_timeout_s=20)
                send_frame(link, 5)
                assert next_estimate(link)[0].frame_id == 5
            finally:
                link.close()
            assert "ended: the harness said BYE" in t.expect(f"session {n} with")


@pytest.mark.parametrize("program", ["echo", "c"])
def test_a_port_in_use_is_one_line_and_exit_2(program):
    with socket.create_server(("127.0.0.1", 0)) as taken:
        address = f"127.0.0.1:{taken.getsockname()[1]}"
        if program == "c":
            if c_build.unavailable():
                pytest.skip(str(c_build.unavailable()))
            argv = [str(c_build.build().plain), "--transport", "tcp", "--listen", address]
        else:
            argv = [*HIL, "target", "echo", "--transport", "tcp", "--listen", address]
        p = subprocess.run(argv, cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert p.returncode == 2, p.stderr
    lines = p.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in p.stderr, p.stderr
    assert f"cannot listen on {address}" in lines[0] and "in use" in lines[0], lines


def test_a_zenoh_port_in_use_is_one_line_without_rust_source_paths():
    pytest.importorskip("zenoh")
    with socket.create_server(("127.0.0.1", 0)) as taken:
        port = taken.getsockname()[1]
        p = subprocess.run([*HIL, "target", "echo", "--transport", "zenoh", "--listen", f"tcp/127.0.0.1:{port}"],
                           cwd=ROOT, capture_output=True, text=True, timeout=60)
    lines = p.stderr.strip().splitlines()
    assert p.returncode == 2 and len(lines) == 1, p.stderr
    assert "Address already in use" in lines[0] and ".rs:" not in lines[0] and ".cargo" not in lines[0], lines


@pytest.mark.parametrize("argv, says", [
    (["target", "echo"], "HIL_LOCAL_FD is not set"),  # was a 20-line traceback
    (["target", "echo", "--bogus"], "unrecognized arguments: --bogus (see hil target echo --help)"),
    (["target", "cv", "--transport", "tcp", "--listen", "nohost"], "listen='nohost': expected host:port"),
    (["--bogus"], "(see hil --help)"),  # was "(see hil hil --help)"
    (["target-check", "tcp://127.0.0.1:1", "--bogus"], "(see hil target-check --help)"),
])
def test_user_mistakes_are_one_line_and_exit_2(argv, says):
    env = {k: v for k, v in os.environ.items() if k != "HIL_LOCAL_FD"}
    p = subprocess.run([*HIL, *argv], cwd=ROOT, capture_output=True, text=True, timeout=60, env=env)
    lines = p.stderr.strip().splitlines()
    assert p.returncode == 2 and len(lines) == 1 and "Traceback" not in p.stderr, p.stderr
    assert says in lines[0], lines


def test_a_can_target_announces_itself_and_serves_run_after_run():
    """On a python-can virtual bus (one process: the bus lives in it), two harnesses
    one after the other, then SIGTERM."""
    pytest.importorskip("can")
    pytest.importorskip("isotp")
    if threading.current_thread() is not threading.main_thread():
        pytest.skip("signals need the main thread")
    import can

    from hil.adapters.can.link import CanLink
    from hil.adapters.can.options import CanOptions
    from hil.adapters.can.target import serve_endpoint

    channel = f"hil-programs-{uuid.uuid4().hex}"
    virtual = CanOptions(interface="virtual", channel=channel)
    bus = can.Bus(interface="virtual", channel=channel, fd=True, ignore_config=True)
    said: queue.Queue[str] = queue.Queue()
    served: list[int] = []
    lines: list[str] = []

    def harnesses() -> None:
        try:
            for fid in (1, 2):
                link = CanLink(vehicle_id=0, clock=MonotonicClock(), options=virtual)
                try:
                    link.open(hello_timeout_s=10)
                    send_frame(link, fid)
                    served.append(next_estimate(link)[0].frame_id)
                finally:
                    link.close()
                while f"session {fid} " not in (line := said.get(timeout=10)):  # its session line, then the next
                    lines.append(line)
                lines.append(line)
        finally:
            os.kill(os.getpid(), signal.SIGTERM)  # however it went: the target must stop

    t = threading.Thread(target=harnesses, daemon=True)
    t.start()
    ep = Endpoint(lambda frame: Inference(DrivingState.SAFE, Control()), target_name="can-echo")
    try:
        serve_endpoint(ep, options=virtual, bus=bus, keep_serving=True, announce=said.put)
    finally:
        t.join(timeout=20)
        bus.shutdown()
    lines += list(said.queue)
    assert served == [1, 2], lines
    assert lines[0].startswith(f"can-echo: can target on virtual channel {channel}, vehicle 0") and \
        "run after run" in lines[0], lines
    assert "session 1 with the harness on" in lines[1] and "1 frames, 1 estimates" in lines[1], lines
    assert "session 2 " in lines[2] and "the harness said BYE" in lines[2], lines
    assert len(lines) == 3, lines  # waiting for a third harness when SIGTERM came: no session to report
