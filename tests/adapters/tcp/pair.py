"""TCP pair for the conformance suite: the echo target as a separate process listening
on a free port of 127.0.0.1, and a ``TcpLink`` that connects to it."""

from __future__ import annotations

import contextlib
import os
import subprocess
import sys
from collections.abc import Iterator, Sequence
from pathlib import Path

from hil.adapters.link import Link
from hil.adapters.tcp.link import TcpLink
from hil.adapters.tcp.options import TcpOptions
from hil.timing.clock import MonotonicClock
from tests.adapters.zenoh.pair import ROOT, end_process, free_port

SKIP_REASON: str | None = None


@contextlib.contextmanager
def tcp_echo(log_path: Path, args: Sequence[str] = (), *, listen: str | None = None,
             connect: str | None = None, env: dict[str, str] | None = None) -> Iterator[subprocess.Popen[bytes]]:
    """``python -m hil.targets.echo --transport tcp (--listen|--connect) ADDRESS *args``
    (environment ``env``, default this one), ended by PID on exit (it normally leaves by
    itself on the harness's BYE)."""
    where = ["--listen", listen] if listen else ["--connect", str(connect)]
    with open(log_path, "ab") as log:
        proc = subprocess.Popen([sys.executable, "-m", "hil.targets.echo", "--transport", "tcp", *where, *args],
                                cwd=ROOT, env=dict(os.environ if env is None else env, PYTHONUNBUFFERED="1"),
                                stdin=subprocess.DEVNULL, stdout=log, stderr=log)
        try:
            yield proc
        finally:
            end_process(proc)


@contextlib.contextmanager
def tcp_pair(tmp_path: Path, echo_args: list[str]) -> Iterator[Link]:
    address = f"127.0.0.1:{free_port()}"
    with tcp_echo(tmp_path / "target.log", echo_args, listen=address):
        link = TcpLink(vehicle_id=0, clock=MonotonicClock(), options=TcpOptions(connect=address))
        try:
            link.open(hello_timeout_s=20)
            yield link
        finally:
            link.close()


PAIR_FACTORY = tcp_pair
