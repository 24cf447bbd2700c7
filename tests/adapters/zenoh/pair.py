"""Zenoh pair for the conformance suite: the echo target as a separate process
listening on a free port of 127.0.0.1, and a ``ZenohLink`` connected to it."""

from __future__ import annotations

import contextlib
import os
import signal
import socket
import subprocess
import sys
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

from hil.adapters.link import Link
from hil.timing.clock import MonotonicClock

try:
    import zenoh  # noqa: F401
except ImportError:
    SKIP_REASON: str | None = "eclipse-zenoh is not installed (pip install eclipse-zenoh==1.10.2)"
else:
    SKIP_REASON = None

ROOT = Path(__file__).resolve().parents[3]


def free_port() -> int:
    """A TCP port of 127.0.0.1 that was free a moment ago."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _ctrl_c_as_usual() -> None:
    # A suite started in the background by a non-interactive shell ignores SIGINT, and
    # children inherit that: the target would never see the Ctrl-C a test sends it.
    signal.signal(signal.SIGINT, signal.SIG_DFL)


@contextlib.contextmanager
def echo_target(log_path: Path, port: int, args: Sequence[str] = ()) -> Iterator[subprocess.Popen[bytes]]:
    """``python -m hil.targets.echo --transport zenoh --listen tcp/127.0.0.1:PORT *args``,
    ended by PID on exit (it normally leaves by itself on the harness's BYE)."""
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    with open(log_path, "ab") as log:
        proc = subprocess.Popen([sys.executable, "-m", "hil.targets.echo", "--transport", "zenoh",
                                 "--listen", f"tcp/127.0.0.1:{port}", *args],
                                cwd=ROOT, env=env, stdin=subprocess.DEVNULL, stdout=log, stderr=log,
                                preexec_fn=_ctrl_c_as_usual)
        try:
            yield proc
        finally:
            end_process(proc)


def end_process(proc: subprocess.Popen[bytes], grace_s: float = 3.0) -> None:
    if proc.poll() is not None:
        return
    try:
        proc.wait(timeout=grace_s)
        return
    except subprocess.TimeoutExpired:
        proc.terminate()
    try:
        proc.wait(timeout=grace_s)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


def zenoh_link(port: int, **options: Any) -> Link:
    """A Zenoh link (vehicle 0, not open) connecting to 127.0.0.1:``port``;
    ``options``: ``ZenohOptions``' others."""
    from hil.adapters.zenoh.link import ZenohLink
    from hil.adapters.zenoh.options import ZenohOptions

    return ZenohLink(vehicle_id=0, clock=MonotonicClock(),
                     options=ZenohOptions(connect=[f"tcp/127.0.0.1:{port}"], **options))


@contextlib.contextmanager
def zenoh_pair(tmp_path: Path, echo_args: list[str]) -> Iterator[Link]:
    port = free_port()
    with echo_target(tmp_path / "target.log", port, echo_args):
        link = zenoh_link(port)
        try:
            link.open(hello_timeout_s=20)
            yield link
        finally:
            link.close()


PAIR_FACTORY = zenoh_pair
