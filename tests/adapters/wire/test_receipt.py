"""Every message's receipt stamp is the arrival of its own last byte, with injected
truth on real sockets: TCP loopback (kernel stamps) and a Unix socket pair (the
local transport's; clock after the read). Two messages in one segment, a message
split over segments, and a reader that comes late: each stamp is no earlier than
the message's truth and within its stated uncertainty of it.

The truth of a message is the instant its last byte was handed to the kernel: on
loopback the receiving socket has it before ``send`` returns (the softirq runs in
the sender's call), so it lies in [clock before send, clock after send]."""

from __future__ import annotations

import contextlib
import socket
import time
from collections.abc import Iterator
from dataclasses import dataclass

import pytest

from hil.adapters.tcp.link import TcpLink
from hil.adapters.tcp.options import TcpOptions
from hil.adapters.wire import protocol
from hil.adapters.wire.messages import SyncResponse
from hil.adapters.wire.receipt import Receipt, StreamReader, enable_kernel_stamps
from hil.timing.clock import MonotonicClock

SLACK_NS = 2_000_000  # the kernel may run the receive a little after send() returns on a loaded machine
GAP_S = 0.03  # between the parts a test sends apart: far above SLACK_NS


@dataclass
class Truth:
    seq: int
    before_ns: int  # clock before the send that carried the message's last byte
    after_ns: int  # clock after it


@contextlib.contextmanager
def stream(kind: str) -> Iterator[tuple[socket.socket, socket.socket]]:
    """(sender, receiver): TCP loopback with kernel stamps on, or a Unix socket pair."""
    if kind == "unix":
        a, b = socket.socketpair(socket.AF_UNIX, socket.SOCK_STREAM)
    else:
        with socket.create_server(("127.0.0.1", 0)) as server:
            a = socket.create_connection(server.getsockname()[:2])
            b, _ = server.accept()
        a.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        enable_kernel_stamps(b)
    with a, b:
        yield a, b


def msg(seq: int) -> bytes:
    return protocol.encode(SyncResponse(1, seq, 10, 20, 30))


def send(sock: socket.socket, data: bytes, clock: MonotonicClock) -> tuple[int, int]:
    before = clock.now_ns()
    sock.sendall(data)
    return before, clock.now_ns()


def reader_for(kind: str, sock: socket.socket, clock: MonotonicClock) -> StreamReader[object]:
    return StreamReader(sock, clock, kernel_stamps=kind == "tcp")


def warm_up(kind: str, a: socket.socket, reader: StreamReader[object]) -> None:
    """The kernel turns stamping on a moment after a socket asks: wait until it does."""
    if kind != "tcp":
        return
    for seq in range(10_000, 10_500):
        a.sendall(msg(seq))
        if reader.next().kernel:  # type: ignore[union-attr]
            return
    pytest.fail("the kernel never stamped a read")


def check(truths: list[Truth], receipts: list[Receipt[object]]) -> None:
    by_seq = {t.seq: t for t in truths}
    got = []
    for r in receipts:
        (m,) = r.items  # one message per read
        assert isinstance(m, SyncResponse)
        got.append(m.seq)
        t = by_seq[m.seq]
        where = (f"seq {m.seq}: stamp {(r.t_rx_ns - t.before_ns) / 1e6:+.3f} ms after the send began, "
                 f"send took {(t.after_ns - t.before_ns) / 1e6:.3f} ms, uncertainty {r.uncertainty_ns / 1e6:.3f} ms")
        assert r.t_rx_ns >= t.before_ns - 200_000, where  # never before its truth (paired clock reads: µs)
        assert r.t_rx_ns - r.uncertainty_ns <= t.after_ns + SLACK_NS, where  # the truth is within the stated span
    assert got == [t.seq for t in truths]


@pytest.mark.parametrize("kind", ["tcp", "unix"])
def test_two_messages_in_one_segment_each_keep_their_own_arrival(kind):
    clock = MonotonicClock()
    with stream(kind) as (a, b):
        reader = reader_for(kind, b, clock)
        warm_up(kind, a, reader)
        before, after = send(a, msg(1) + msg(2), clock)  # one write, one segment
        receipts = [reader.next(), reader.next()]
    assert all(r is not None and len(r.items) == 1 for r in receipts)
    check([Truth(1, before, after), Truth(2, before, after)], receipts)  # type: ignore[arg-type]


@pytest.mark.parametrize("kind", ["tcp", "unix"])
def test_a_message_split_over_segments_is_stamped_at_its_last_byte(kind):
    clock = MonotonicClock()
    with stream(kind) as (a, b):
        reader = reader_for(kind, b, clock)
        warm_up(kind, a, reader)
        whole = msg(3)
        send(a, whole[:40], clock)  # part of the header...
        time.sleep(GAP_S)  # the gap under test, not a wait for an event
        before, after = send(a, whole[40:], clock)  # ... and the rest, 30 ms later
        receipts = [reader.next()]
    check([Truth(3, before, after)], receipts)  # type: ignore[list-item]
    assert receipts[0].t_rx_ns >= before - 200_000  # type: ignore[union-attr]  # not the first part's arrival


@pytest.mark.parametrize("kind", ["tcp", "unix"])
def test_a_late_reader_never_gives_a_message_a_later_arrival_without_saying_so(kind):
    """Three messages 30 ms apart wait in the socket, then one reader comes: each stamp
    is its own arrival, or says how much earlier the arrival may have been (TCP merges a
    waiting segment with later ones; a Unix socket has no receive time at all)."""
    clock = MonotonicClock()
    with stream(kind) as (a, b):
        reader = reader_for(kind, b, clock)
        warm_up(kind, a, reader)
        truths = []
        for seq in (4, 5, 6):
            truths.append(Truth(seq, *send(a, msg(seq), clock)))
            time.sleep(GAP_S)  # the sender's pace under test
        receipts = [reader.next() for _ in truths]
    check(truths, receipts)  # type: ignore[arg-type]


_SENDER = """
import json, os, socket, sys, time
sock = socket.socket(fileno=int(sys.argv[1]))
parts = [bytes.fromhex(h) for h in sys.argv[2:]]
sys.stdin.readline()  # go
out = []
for i, part in enumerate(parts):
    before = time.monotonic_ns()
    sock.sendall(part)
    out.append((before, time.monotonic_ns()))
    time.sleep(0.02 if i == 0 else 0.03)
print(json.dumps(out), flush=True)
"""


def test_tcp_link_stamps_each_message_alone_while_its_reader_is_held_up():
    """End to end through ``TcpLink``: while the link's reader thread waits for the
    interpreter lock (this thread spins 150 ms), a sender process sends message 0, then
    message 1, and 30 ms later message 2 and 3 in one write. Before one message per
    read, the reader read 1, 2 and 3 in one read and gave message 1 the arrival of 2
    and 3, 30 ms late, as if exact; now each stamp is its own arrival or says by how
    much it may be late."""
    import json
    import subprocess
    import sys
    import threading

    from hil.adapters.wire.messages import ClockId, Hello

    clock = MonotonicClock()
    with socket.create_server(("127.0.0.1", 0)) as server:
        link = TcpLink(vehicle_id=1, clock=clock,
                       options=TcpOptions(connect="127.0.0.1:%d" % server.getsockname()[1], heartbeat_idle_s=0))
        opener = threading.Thread(target=lambda: link.open(hello_timeout_s=5))
        opener.start()
        c, _ = server.accept()
    with c:
        c.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        c.sendall(protocol.encode(Hello("raw", protocol.VERSION, ClockId.MONOTONIC, 1)))
        opener.join(5)
        for seq in range(100, 600):  # until the kernel stamps this socket's reads
            c.sendall(msg(seq))
            link.sync_exchange(timeout_s=0.01)
            if link.tcp_stats.kernel_stamps:
                break
        link.sync_samples()
        parts = [msg(0), msg(1), msg(2) + msg(3)]
        sender = subprocess.Popen([sys.executable, "-c", _SENDER, str(c.fileno()), *(p.hex() for p in parts)],
                                  pass_fds=[c.fileno()], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
        try:
            old = sys.getswitchinterval()
            sys.setswitchinterval(1.0)  # no forced hand-over of the interpreter lock while we spin
            try:
                sender.stdin.write("go\n")  # type: ignore[union-attr]
                sender.stdin.flush()  # type: ignore[union-attr]
                end = time.monotonic_ns() + 150_000_000
                while time.monotonic_ns() < end:
                    pass
            finally:
                sys.setswitchinterval(old)
            out, _ = sender.communicate(timeout=10)
        finally:
            if sender.poll() is None:
                sender.kill()
                sender.wait()
        sent = json.loads(out)
        truths = [Truth(0, *sent[0]), Truth(1, *sent[1]), Truth(2, *sent[2]), Truth(3, *sent[2])]
        got = {}
        deadline = time.monotonic() + 5
        while len(got) < 4 and time.monotonic() < deadline:
            r = link._sync_rx.get(timeout=1)  # noqa: SLF001 - the SYNC_RESPONSEs received, with their stamps
            if r.msg.seq < 4:
                got[r.msg.seq] = r
        link.close()
    for t in truths:
        r = got[t.seq]
        where = (f"seq {t.seq}: stamp {(r.t_rx_ns - t.before_ns) / 1e6:+.3f} ms after its send began, "
                 f"uncertainty {r.rx_uncertainty_ns / 1e6:.3f} ms")
        assert r.t_rx_ns >= t.before_ns - 200_000, where
        assert r.t_rx_ns - r.rx_uncertainty_ns <= t.after_ns + SLACK_NS, where
