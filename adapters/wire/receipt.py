"""Receipt stamps on a stream socket: each message stamped with the arrival of its
own last byte, and with how far that stamp can be from the truth.

A stream carries messages back to back, and one read may return the end of one
message and the start of the next: stamped per read, several messages would share
one stamp, each inheriting the arrival of bytes that are not its own. So the reader
here never reads past the end of the current message (``StreamDecoder.wanted``: the
header, then exactly the payload): every read completes at most one message, and
the read that completes it stamps it.

Two ways to stamp (PROTOCOL.md sections 10.1 and 10.5):

* **kernel** (TCP): ``SO_TIMESTAMPNS`` gives each read the kernel's receive time of
  the last segment it took bytes from, mapped onto the reader's clock with a paired
  reading of both clocks. Linux merges a segment into the previous one when that one
  is still unread (``tcp_try_coalesce``), and the merged segment carries the newer
  arrival: the stamp of a message that waited while later bytes came is then the
  arrival of those later bytes. After each message the reader peeks at the next
  byte: nothing waiting, or a byte with another stamp, means the message's segment
  ended with it and the stamp is its own (uncertainty 0); the same stamp means the
  true arrival lies between the last instant the reader knew the bytes had not yet
  come and the stamp.
* **plain** (a Unix socket, or kernel stamps off): the clock read right after the
  read that completes the message. A read that had to wait for its bytes returns as
  they arrive (uncertainty 0: the wake-up latency is this method's floor); a read
  that found them already waiting (the reader was late) knows only that they came
  after the reader last found the socket empty, so that span is the uncertainty.

Either way the stamp is never earlier than the truth: the uncertainty is one-sided,
the truth lies in ``[t_rx_ns - uncertainty_ns, t_rx_ns]``. Standard library only.
"""

from __future__ import annotations

import socket
import struct
import time
from dataclasses import dataclass
from typing import Generic, TypeVar

from hil.adapters.wire.messages import Message
from hil.adapters.wire.stream import StreamDecoder
from hil.common.errors import ProtocolError
from hil.timing.clock import Clock

SO_TIMESTAMPNS = getattr(socket, "SO_TIMESTAMPNS", 35)  # Linux; SCM_TIMESTAMPNS is the same value
_TIMESPEC = struct.Struct("@qq")  # struct timespec on 64-bit Linux
_CMSG_SIZE = socket.CMSG_SPACE(_TIMESPEC.size)
_PEEK = socket.MSG_PEEK | socket.MSG_DONTWAIT
READ_BYTES = 1 << 20  # the largest single read (a bigger payload takes several)

R = TypeVar("R")


class RealtimeMapper:
    """Maps ``CLOCK_REALTIME`` readings (kernel receive stamps) onto ``clock``.

    Each mapping reads ``clock``, the realtime clock and ``clock`` again, and takes
    the realtime reading to sit midway (µs-level error); of up to three such brackets
    the tightest, so a reader preempted between two reads (a loaded host) does not
    shift the mapping by half the time it waited. A realtime step between two reads
    is picked up at the next read.
    """

    TIGHT_NS = 2_000  # a bracket this narrow needs no second try

    def __init__(self, clock: Clock) -> None:
        self.clock = clock

    def now_pair(self) -> tuple[int, int]:
        """(``clock`` now, ``clock`` minus realtime), both ns."""
        width, offset, b = 1 << 62, 0, 0
        for _ in range(3):
            a = self.clock.now_ns()
            r = time.time_ns()
            b = self.clock.now_ns()
            if b - a < width:
                width, offset = b - a, (a + b) // 2 - r
            if width <= self.TIGHT_NS:
                break
        return b, offset

    def map(self, realtime_ns: int) -> tuple[int, int]:
        """(``realtime_ns`` on ``clock``, ``clock`` now); the mapped time is never
        later than now."""
        now, offset = self.now_pair()
        return min(realtime_ns + offset, now), now


def _kernel_ns(ancdata: list[tuple[int, int, bytes]]) -> int | None:
    for level, kind, data in ancdata:
        if level == socket.SOL_SOCKET and kind == SO_TIMESTAMPNS and len(data) >= _TIMESPEC.size:
            sec, nsec = _TIMESPEC.unpack_from(data)
            return int(sec * 1_000_000_000 + nsec)
    return None


def recv_stamped(sock: socket.socket, view: memoryview, flags: int = 0) -> tuple[int, int | None]:
    """One ``recvmsg_into``: (bytes read, kernel receive time in ns of
    ``CLOCK_REALTIME`` or None when the kernel gave none).

    Raises:
        OSError: the socket failed (``BlockingIOError`` with ``MSG_DONTWAIT`` and
            nothing to read).
    """
    n, ancdata, _flags, _addr = sock.recvmsg_into([view], _CMSG_SIZE, flags)
    return n, _kernel_ns(ancdata)


def enable_kernel_stamps(sock: socket.socket) -> None:
    """Ask the kernel to stamp what ``sock`` receives (``SO_TIMESTAMPNS``)."""
    sock.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)


@dataclass(frozen=True)
class Receipt(Generic[R]):
    """What one call of ``StreamReader.next`` completed: at most one message (and the
    errors or side records completed by the same bytes), stamped on the reader's
    clock; the truth lies in ``[t_rx_ns - uncertainty_ns, t_rx_ns]``."""

    items: list[Message | ProtocolError | R]
    t_rx_ns: int
    uncertainty_ns: int
    nbytes: int  # bytes read for it
    kernel: bool  # stamped by the kernel (else by the clock after the read)


@dataclass
class ReaderStats:
    kernel_stamps: int = 0  # messages stamped with the kernel's receive time
    fallback_stamps: int = 0  # messages stamped when the read returned (no kernel stamp on the read)
    uncertain: int = 0  # messages whose true arrival is known only to a span (uncertainty > 0)
    uncertainty_max_ns: int = 0  # the widest such span
    wake_delay_max_ns: int = 0  # longest time from the kernel's receipt to the reader having the bytes


class StreamReader(Generic[R]):
    """Reads a blocking stream socket one message at a time, each stamped alone.

    Args:
        sock: a connected stream socket in blocking mode.
        clock: the clock of the stamps.
        decoder: the stream decoder (one with side records for the local
            transport's notices); a fresh one by default.
        kernel_stamps: stamp with ``SO_TIMESTAMPNS`` (the caller enables it on the
            socket, before the first byte can arrive).
        uncertainty: work out each stamp's uncertainty (one more non-blocking call
            per message; a target, whose stamps carry none, turns it off).
        stats: count into this (a transport's own subclass), else a fresh one.
        not_before_ns: on ``clock``, an instant before any byte of this stream
            arrived (when the connection was made; default: now).
    """

    def __init__(self, sock: socket.socket, clock: Clock, *, decoder: StreamDecoder[R] | None = None,
                 kernel_stamps: bool = False, uncertainty: bool = True, stats: ReaderStats | None = None,
                 not_before_ns: int | None = None) -> None:
        self.sock = sock
        self.clock = clock
        self.decoder: StreamDecoder[R] = decoder if decoder is not None else StreamDecoder()
        self.kernel_stamps = kernel_stamps
        self.uncertainty = uncertainty
        self.stats = stats if stats is not None else ReaderStats()
        self._mapper = RealtimeMapper(clock)
        self._buf = bytearray(READ_BYTES)
        self._view = memoryview(self._buf)
        self._peek = memoryview(bytearray(1))
        # The bytes not yet read arrived after this (on `clock`).
        self._lower_ns = clock.now_ns() if not_before_ns is None else not_before_ns

    def next(self) -> Receipt[R] | None:
        """The next message (or bad bytes reported), read and stamped; None at end of
        stream.

        Raises:
            OSError: the socket failed.
        """
        nbytes = 0
        while True:
            want = min(self.decoder.wanted(), READ_BYTES)
            n, kernel_ns, waited = self._read(want)
            if n == 0:
                return None
            nbytes += n
            t_read = self.clock.now_ns()
            if waited and not self.kernel_stamps:  # woken by these bytes: later ones came after
                self._lower_ns = max(self._lower_ns, t_read)
            items = self.decoder.feed(self._view[:n])
            if items:
                break
        return self._stamp(items, nbytes, kernel_ns, waited, t_read)

    def _read(self, want: int) -> tuple[int, int | None, bool]:
        """(bytes, kernel stamp, whether the read had to wait for them). Plain stamps
        try without blocking first, to know whether the bytes were already waiting;
        kernel stamps do not need to (the peek after each message tells)."""
        view = self._view[:want]
        if not self.kernel_stamps and self.uncertainty:
            before = self.clock.now_ns()
            try:
                return self.sock.recv_into(view, want, socket.MSG_DONTWAIT), None, False
            except BlockingIOError:
                self._lower_ns = max(self._lower_ns, before)  # nothing waited at `before`
            return self.sock.recv_into(view, want), None, True
        if not self.kernel_stamps:
            return self.sock.recv_into(view, want), None, True
        n, kernel_ns = recv_stamped(self.sock, view)
        return n, kernel_ns, True

    def _stamp(self, items: list[Message | ProtocolError | R], nbytes: int, kernel_ns: int | None, waited: bool,
               t_read: int) -> Receipt[R]:
        st = self.stats
        if kernel_ns is not None:
            t_rx, now = self._mapper.map(kernel_ns)
            st.kernel_stamps += 1
            st.wake_delay_max_ns = max(st.wake_delay_max_ns, now - t_rx)
            exact = not self.uncertainty or self._segment_ends_here(kernel_ns)
        else:
            t_rx = t_read
            st.fallback_stamps += self.kernel_stamps
            exact = waited and not self.kernel_stamps  # a kernel-mode read may have found its bytes waiting
        uncertainty = 0 if exact else max(0, t_rx - self._lower_ns)
        if uncertainty:
            st.uncertain += 1
            st.uncertainty_max_ns = max(st.uncertainty_max_ns, uncertainty)
        else:
            self._lower_ns = max(self._lower_ns, t_rx)  # later bytes came no earlier than these
        return Receipt(items, t_rx, uncertainty, nbytes, kernel_ns is not None)

    def _segment_ends_here(self, kernel_ns: int) -> bool:
        """Whether the segment that held the message's last byte held nothing after
        it: nothing more to read, or the next byte carries another receipt time."""
        before = self.clock.now_ns()
        try:
            n, next_ns = recv_stamped(self.sock, self._peek, _PEEK)
        except BlockingIOError:
            self._lower_ns = max(self._lower_ns, before)
            return True
        except OSError:
            return True  # the next read reports it
        return n == 0 or (next_ns is not None and next_ns != kernel_ns)


__all__ = ["READ_BYTES", "SO_TIMESTAMPNS", "ReaderStats", "RealtimeMapper", "Receipt", "StreamReader",
           "enable_kernel_stamps", "recv_stamped"]
