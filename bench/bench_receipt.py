"""What reading one message per read costs: the harness's receive path before and
after ``hil.adapters.wire.receipt`` (each message stamped with its own arrival), on the
same sockets, in the same run, next to the raw floor.

Run: ``.venv/bin/python bench/bench_receipt.py`` (about 20 s; ``--rounds``,
``--block``). Prints a markdown table. Not part of the test suite.

A child process answers each 1-byte ping with a message: an ESTIMATE (80 bytes, what
the harness reads per frame), or a raw 320x240 FRAME (230 504 bytes, what a target
reads). Timed: from the ping's send to the message decoded and stamped in this
process, read in one of three ways (interleaved blocks, so drift hits all alike):

* **raw floor**: ``recv_into`` of the known length, no decoding, no stamp;
* **before**: the read path as it was: ``recvmsg_into`` a 1 MiB buffer, feed the
  stream decoder, one stamp per read (the kernel's on TCP, mapped; the clock after
  the read on a Unix socket);
* **after**: ``StreamReader.next``: the header, then exactly the payload, and on TCP
  a non-blocking peek at the next byte to know whether the stamp is exact; on a Unix
  socket a non-blocking attempt before each blocking read.
"""

from __future__ import annotations

import argparse
import os
import socket
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from hil.adapters.wire import protocol  # noqa: E402
from hil.adapters.wire.messages import CameraInfo, Control, DrivingState, Estimate, Frame, ImageEncoding  # noqa: E402
from hil.adapters.wire.receipt import (RealtimeMapper, StreamReader, enable_kernel_stamps,  # noqa: E402
                                       recv_stamped)
from hil.adapters.wire.stream import StreamDecoder  # noqa: E402
from hil.timing.clock import MonotonicClock  # noqa: E402

MESSAGES = {
    b"e": protocol.encode(Estimate(0, 1, DrivingState.SAFE, Control(0.0, 0.3, 0.0), (), 1, 2, 3, 4)),
    b"f": protocol.encode(Frame(0, 1, 0, 0, 0, 320, 240, ImageEncoding.RGB8, CameraInfo(277.0, 277.0, 160.0, 120.0,
                                                                                       1.3), 0.0, bytes(230400))),
}


def child(fd: int) -> None:
    s = socket.socket(fileno=fd)
    while kind := s.recv(1):
        s.sendall(MESSAGES[kind])


def pair(kind: str) -> tuple[socket.socket, subprocess.Popen[bytes]]:
    """Our end (TCP with kernel stamps on, or a Unix socket pair) and the child."""
    if kind == "unix":
        ours, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_STREAM)
    else:
        with socket.create_server(("127.0.0.1", 0)) as server:
            theirs = socket.create_connection(server.getsockname()[:2])
            ours, _ = server.accept()
        for s in (ours, theirs):
            s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        enable_kernel_stamps(ours)
    for s in (ours, theirs):
        s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4 << 20)
        s.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 4 << 20)
    proc = subprocess.Popen([sys.executable, __file__, "--child", str(theirs.fileno())], pass_fds=[theirs.fileno()])
    theirs.close()
    return ours, proc


Way = Callable[[bytes], None]  # one ping, then read the answer the way under test


def raw(sock: socket.socket) -> Way:
    buf = memoryview(bytearray(1 << 20))

    def once(kind: bytes) -> None:
        sock.sendall(kind)
        need, got = len(MESSAGES[kind]), 0
        while got < need:
            got += sock.recv_into(buf[: need - got])

    return once


def before(sock: socket.socket, *, kernel: bool) -> Way:
    """The read loop of TcpLink / LocalLink before one message per read."""
    clock = MonotonicClock()
    mapper = RealtimeMapper(clock)
    dec: StreamDecoder[object] = StreamDecoder()
    buf = bytearray(1 << 20)
    view = memoryview(buf)

    def once(kind: bytes) -> None:
        sock.sendall(kind)
        while True:
            if kernel:
                n, k = recv_stamped(sock, view)
                t = mapper.map(k)[0] if k is not None else clock.now_ns()
            else:
                n = sock.recv_into(view)
                t = clock.now_ns()
            del t
            if dec.feed(view[:n]):
                return

    return once


def after(sock: socket.socket, *, kernel: bool) -> Way:
    reader: StreamReader[object] = StreamReader(sock, MonotonicClock(), kernel_stamps=kernel)

    def once(kind: bytes) -> None:
        sock.sendall(kind)
        r = reader.next()
        assert r is not None and len(r.items) == 1

    return once


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--rounds", type=int, default=20, help="interleaved rounds (default 20)")
    p.add_argument("--block", type=int, default=50, help="round trips per way per round (default 50)")
    p.add_argument("--child", type=int, help=argparse.SUPPRESS)
    a = p.parse_args(argv)
    if a.child is not None:
        child(a.child)
        return 0
    rows: list[tuple[str, str, str, list[int]]] = []
    procs = []
    try:
        for kind in ("tcp", "unix"):
            ways: list[tuple[str, Way]] = []
            for name, make in (("raw floor", lambda s, kernel: raw(s)), ("before: per read", before),
                               ("after: one message per read", after)):
                sock, proc = pair(kind)
                procs.append((sock, proc))
                ways.append((name, make(sock, kernel=kind == "tcp")))
            for what, code in (("ESTIMATE 80 B", b"e"), ("FRAME 230 504 B", b"f")):
                samples: dict[str, list[int]] = {name: [] for name, _ in ways}
                for _ in range(5):
                    for _name, way in ways:
                        way(code)  # warm up
                for _ in range(a.rounds):
                    for name, way in ways:
                        for _ in range(a.block):
                            t = time.perf_counter_ns()
                            way(code)
                            samples[name].append(time.perf_counter_ns() - t)
                rows += [(kind, what, name, samples[name]) for name, _ in ways]
    finally:
        for sock, proc in procs:
            sock.close()
            proc.wait(10)
    print("## Receive path: one message per read vs per read (µs, round trip ping -> message decoded)\n")
    print(f"{os.cpu_count()} CPUs; {a.rounds} interleaved rounds of {a.block}; load "
          f"{os.getloadavg()[0]:.2f} at the end.\n")
    print("| socket | message | read | p50 | p99 | p50 / before | p50 − before |")
    print("| --- | --- | --- | ---: | ---: | ---: | ---: |")
    base: dict[tuple[str, str], float] = {}
    for kind, what, name, xs in rows:
        p50, p99 = float(np.percentile(xs, 50)) / 1e3, float(np.percentile(xs, 99)) / 1e3
        if name.startswith("before"):
            base[(kind, what)] = p50
    for kind, what, name, xs in rows:
        p50, p99 = float(np.percentile(xs, 50)) / 1e3, float(np.percentile(xs, 99)) / 1e3
        b = base[(kind, what)]
        print(f"| {kind} | {what} | {name} | {p50:.1f} | {p99:.1f} | {p50 / b:.2f} | {p50 - b:+.1f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
