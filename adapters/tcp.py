"""The tcp transport: the local transport's stream framing over one TCP connection.

Messages travel back to back on the stream, exactly as on the local transport's
socket (PROTOCOL.md sections 8 and 10.5). Either side may listen: the harness
connects to a target that listens (``connect="10.0.0.5:7600"``), or listens for a
target that dials in (``listen="0.0.0.0:7600"``). Addresses are explicit
``host:port`` pairs (a ``tcp/`` prefix is accepted); nothing is discovered, and the
default is loopback (``127.0.0.1:7600``).

Receipt stamps. The harness enables ``SO_TIMESTAMPNS`` and reads with ``recvmsg``,
so each read carries the kernel's receive time (``CLOCK_REALTIME``); it is mapped to
the link's clock with a paired read of both clocks at the same instant. ``t0'`` is
then when the kernel took the bytes, not when the reader thread woke up. A read
without the stamp falls back to the clock reading after it (counted).

Liveness: end of stream or a socket error marks the target gone at once. For a peer
that vanishes without closing (a powered-off board), both sides set
``TCP_USER_TIMEOUT`` = 1 s and 1 s keepalives, and the harness sends a HEARTBEAT
whenever it has sent nothing for 250 ms, so unacknowledged data times out within
about a second.

Both halves live here: ``TcpLink`` (harness) and ``serve_endpoint`` (the target, used
by ``hil.adapters.sdk.serve``). Standard library only.
"""

from __future__ import annotations

import queue
import socket
import struct
import threading
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING

from hil.adapters import protocol
from hil.adapters.link import Link, Received
from hil.adapters.messages import Heartbeat, Hello
from hil.adapters.sdk import serve_stream
from hil.common.errors import TargetError, TransportError
from hil.timing.clock import Clock

if TYPE_CHECKING:
    from hil.adapters.sdk import Endpoint

DEFAULT_PORT = 7600
DEFAULT_ADDRESS = f"127.0.0.1:{DEFAULT_PORT}"
HEARTBEAT_IDLE_S = 0.25  # the harness sends a HEARTBEAT after this long without sending
USER_TIMEOUT_MS = 1000  # unacknowledged data for this long: the connection is dead
_SO_TIMESTAMPNS = getattr(socket, "SO_TIMESTAMPNS", 35)  # Linux; SCM_TIMESTAMPNS is the same value
_TIMESPEC = struct.Struct("@qq")  # struct timespec on 64-bit Linux
_CMSG_SIZE = socket.CMSG_SPACE(_TIMESPEC.size)
_RECV_BYTES = 1 << 20
_SOCK_BUF = 4 * 1024 * 1024
_CONNECT_RETRY_S = 0.05


def parse_address(text: str, *, field: str = "address") -> tuple[str, int]:
    """``"host:port"``, ``"tcp/host:port"`` or ``"[v6]:port"`` -> (host, port).

    Raises:
        TransportError: not of that form, or the port is outside 1..65535 (the
            message names ``field`` and the text).
    """
    raw = text.strip()
    if raw.startswith("tcp/"):
        raw = raw[4:]
    host, sep, port_text = raw.rpartition(":")
    if host.startswith("[") and host.endswith("]"):
        host = host[1:-1]
    if not sep or not host or not port_text.isdigit() or not 1 <= int(port_text) <= 65535:
        raise TransportError(f"{field}={text!r}: expected host:port with a port in 1..65535, "
                             f"e.g. {DEFAULT_ADDRESS}")
    return host, int(port_text)


def _tune(sock: socket.socket) -> None:
    """No Nagle delay, big buffers, and a dead peer noticed within about a second."""
    sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, _SOCK_BUF)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, _SOCK_BUF)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_KEEPALIVE, 1)
    for opt, value in (("TCP_KEEPIDLE", 1), ("TCP_KEEPINTVL", 1), ("TCP_KEEPCNT", 2),
                       ("TCP_USER_TIMEOUT", USER_TIMEOUT_MS)):
        if hasattr(socket, opt):
            sock.setsockopt(socket.IPPROTO_TCP, getattr(socket, opt), value)


@dataclass
class TcpStats:
    """Counters only this transport has (the shared ones are in ``LinkStats``)."""

    kernel_stamps: int = 0  # reads stamped with the kernel's receive time
    fallback_stamps: int = 0  # reads without it, stamped when the reader woke (the kernel turns
    # stamping on a moment after the first socket asks, so a first read may lack it)
    wake_delay_max_ns: int = 0  # longest time from the kernel's receipt to the reader waking
    heartbeats_sent: int = 0


class RealtimeMapper:
    """Maps ``CLOCK_REALTIME`` readings (kernel receive stamps) onto ``clock``.

    Each mapping reads ``clock``, the realtime clock and ``clock`` again, and takes
    the realtime reading to sit midway (µs-level error); a realtime step between two
    reads is therefore picked up at the next read.
    """

    def __init__(self, clock: Clock) -> None:
        self.clock = clock

    def now_pair(self) -> tuple[int, int]:
        """(``clock`` now, ``clock`` minus realtime), both ns."""
        a = self.clock.now_ns()
        r = time.time_ns()
        b = self.clock.now_ns()
        return b, (a + b) // 2 - r

    def map(self, realtime_ns: int) -> tuple[int, int]:
        """(``realtime_ns`` on ``clock``, ``clock`` now); the mapped time is never
        later than now."""
        now, offset = self.now_pair()
        return min(realtime_ns + offset, now), now


def recv_stamped(sock: socket.socket, view: memoryview) -> tuple[int, int | None]:
    """One ``recvmsg_into``: (bytes read, kernel receive time in ns of
    ``CLOCK_REALTIME`` or None when the kernel gave none).

    Raises:
        OSError: the socket failed.
    """
    n, ancdata, _flags, _addr = sock.recvmsg_into([view], _CMSG_SIZE)
    for level, kind, data in ancdata:
        if level == socket.SOL_SOCKET and kind == _SO_TIMESTAMPNS and len(data) >= _TIMESPEC.size:
            sec, nsec = _TIMESPEC.unpack_from(data)
            return n, sec * 1_000_000_000 + nsec
    return n, None


class TcpLink(Link):
    """Harness side of one TCP connection to one target.

    Args:
        connect: ``host:port`` of a target that listens (the harness dials).
        listen: ``host:port`` the harness listens on for a target that dials in
            (give exactly one of the two; neither: connect to ``127.0.0.1:7600``).
        kernel_stamps: stamp receipt with ``SO_TIMESTAMPNS`` (default on).
        heartbeat_idle_s: send a HEARTBEAT after this long without sending (0: never).

    Raises:
        TransportError: both or a malformed address.
    """

    transport_name = "tcp"

    def __init__(self, *, vehicle_id: int, clock: Clock, connect: str | None = None, listen: str | None = None,
                 kernel_stamps: bool = True, heartbeat_idle_s: float = HEARTBEAT_IDLE_S,
                 rx_queue_size: int = 1024, rx_queue: queue.Queue[Received] | None = None) -> None:
        super().__init__(vehicle_id=vehicle_id, clock=clock, rx_queue_size=rx_queue_size, rx_queue=rx_queue)
        self._sock: socket.socket | None = None
        self._listener: socket.socket | None = None
        self._reader: threading.Thread | None = None
        self._beater: threading.Thread | None = None
        if connect and listen:
            raise TransportError(f"tcp: give connect or listen, not both (connect={connect!r}, listen={listen!r})")
        self.listening = bool(listen)
        self.address = parse_address(listen or connect or DEFAULT_ADDRESS, field="listen" if listen else "connect")
        self.kernel_stamps = kernel_stamps
        self.heartbeat_idle_s = heartbeat_idle_s
        self.tcp_stats = TcpStats()
        self._mapper = RealtimeMapper(clock)
        self._send_lock = threading.Lock()
        self._state_lock = threading.Lock()
        self._connected = threading.Event()
        self._stop = threading.Event()
        self._deadline = 0.0
        self._last_send = 0.0
        self._connect_error = ""

    @property
    def bound_address(self) -> tuple[str, int] | None:
        """(host, port) the harness listens on (after ``open``; port 0 resolved)."""
        return self._listener.getsockname()[:2] if self._listener is not None else None

    def open(self, *, hello_timeout_s: float) -> Hello:
        """Connect (or wait for the target to connect) and wait for its HELLO; both
        within ``hello_timeout_s``.

        Raises:
            TransportError: no connection within the timeout, or cannot listen.
            TargetError: connected, but no HELLO in time.
        """
        self._deadline = time.monotonic() + hello_timeout_s
        try:
            return super().open(hello_timeout_s=hello_timeout_s)
        except TargetError as err:
            if not self._connected.is_set():
                raise TransportError(self._no_connection_reason(hello_timeout_s)) from err
            raise

    def start_listening(self) -> tuple[str, int]:
        """Bind and listen now (before ``open``), so that a target started next finds
        the port open; returns the bound (host, port).

        Raises:
            TransportError: cannot listen on the address.
        """
        if self._listener is None:
            family = socket.AF_INET6 if ":" in self.address[0] else socket.AF_INET
            ls = socket.socket(family, socket.SOCK_STREAM)
            try:
                ls.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
                ls.bind(self.address)
                ls.listen(1)
            except OSError as err:
                ls.close()
                raise TransportError(f"tcp: cannot listen on {self.address[0]}:{self.address[1]}: {err}") from err
            if self.kernel_stamps:  # inherited by the accepted connection
                ls.setsockopt(socket.SOL_SOCKET, _SO_TIMESTAMPNS, 1)
            ls.settimeout(0.05)
            self._listener = ls
        return self.bound_address  # type: ignore[return-value]

    def _no_connection_reason(self, timeout_s: float) -> str:
        host, port = self.bound_address or self.address
        if self.listening:
            return f"tcp: no target connected to {host}:{port} within {timeout_s:g} s"
        detail = f" (last error: {self._connect_error})" if self._connect_error else ""
        return f"tcp: cannot connect to the target at {host}:{port} within {timeout_s:g} s{detail}"

    def _open(self) -> None:
        if self.listening:
            self.start_listening()
        reader = threading.Thread(target=self._read_loop, name=f"tcp-rx-{self.vehicle_id}", daemon=True)
        reader.start()
        self._reader = reader  # only a started thread: close() may join it from another thread

    def _establish(self) -> socket.socket | None:
        """The connection, retried until the open deadline; None when closed or late."""
        listener = self._listener  # close() may clear the attribute meanwhile
        while not self._stop.is_set() and time.monotonic() < self._deadline:
            try:
                if listener is not None:
                    try:
                        sock, _peer = listener.accept()
                    except TimeoutError:
                        continue
                    sock.settimeout(None)
                else:
                    sock = self._dial_once()
            except OSError as err:
                self._connect_error = str(err)
                if self._stop.wait(_CONNECT_RETRY_S):
                    return None
                continue
            _tune(sock)
            return sock
        return None

    def _dial_once(self) -> socket.socket:
        """One connection attempt. Stamping is on before the first byte can arrive,
        so that the HELLO is stamped by the kernel too."""
        left = max(0.05, self._deadline - time.monotonic())
        info = socket.getaddrinfo(*self.address, type=socket.SOCK_STREAM)[0]
        sock = socket.socket(info[0], info[1], info[2])
        try:
            if self.kernel_stamps:
                sock.setsockopt(socket.SOL_SOCKET, _SO_TIMESTAMPNS, 1)
            sock.settimeout(min(left, 2.0))
            sock.connect(info[4])
            sock.settimeout(None)
        except OSError:
            sock.close()
            raise
        return sock

    def _read_loop(self) -> None:
        sock = self._establish()
        listener = self._listener
        if listener is not None:  # one target per link: stop listening
            listener.close()
        if sock is None:
            self._mark_gone(self._connect_error or "no connection")
            return
        with self._state_lock:
            if self._stop.is_set():  # closed while connecting
                sock.close()
                return
            self._sock = sock
        self._last_send = time.monotonic()
        self._connected.set()
        if self.heartbeat_idle_s > 0:
            beater = threading.Thread(target=self._beat, name=f"tcp-hb-{self.vehicle_id}", daemon=True)
            beater.start()
            self._beater = beater
        buf = bytearray(_RECV_BYTES)
        view = memoryview(buf)
        st = self.tcp_stats
        while True:
            try:
                if self.kernel_stamps:
                    n, kernel_ns = recv_stamped(sock, view)
                else:
                    n, kernel_ns = sock.recv_into(view), None
            except OSError as err:
                if not self._closed:
                    self._mark_gone(f"tcp: connection failed: {err}")
                break
            if n == 0:
                self._mark_gone("tcp: the target closed the connection")
                break
            if kernel_ns is not None:
                t_rx, now = self._mapper.map(kernel_ns)
                st.kernel_stamps += 1
                st.wake_delay_max_ns = max(st.wake_delay_max_ns, now - t_rx)
            else:
                t_rx = self.clock.now_ns()
                st.fallback_stamps += 1
            self._on_bytes(view[:n], t_rx)

    def _beat(self) -> None:
        while not self._stop.wait(self.heartbeat_idle_s / 2):
            if self._closed or not self.alive:
                return
            if time.monotonic() - self._last_send >= self.heartbeat_idle_s:
                try:
                    self._send_bytes(protocol.encode(Heartbeat(self.vehicle_id, self.clock.now_ns())))
                except TransportError:
                    return
                self.tcp_stats.heartbeats_sent += 1

    def _send_bytes(self, data: bytes) -> None:
        sock = self._sock
        if sock is None:
            raise TransportError("tcp link is not connected")
        try:
            with self._send_lock:  # the heartbeat thread sends too: whole messages only
                sock.sendall(data)
                self._last_send = time.monotonic()
        except OSError as err:
            self._mark_gone(f"tcp: send failed: {err}")
            raise TransportError(f"cannot send to the tcp target: {err}") from err

    def _close_transport(self) -> None:
        with self._state_lock:  # not the send lock: a blocked send must not hold up close
            self._stop.set()
            sock, self._sock = self._sock, None
        if sock is not None:
            try:
                sock.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
            sock.close()
        listener, self._listener = self._listener, None
        if listener is not None:
            listener.close()
        for t in (self._reader, self._beater):
            if t is not None and t is not threading.current_thread():
                t.join(timeout=2.0)


def serve_endpoint(ep: Endpoint, *, listen: str | None = None, connect: str | None = None,
                   connect_timeout_s: float = 30.0) -> None:
    """Target side: serve ``ep`` on one TCP connection until BYE or end of stream
    (SIGTERM: BYE, then leave; ``hil.adapters.sdk.serve_stream``).

    Listens on ``listen`` (default ``127.0.0.1:7600``) for one harness, or dials the
    harness at ``connect`` (retrying for ``connect_timeout_s``).

    Raises:
        TransportError: both addresses given, a malformed one, cannot listen, or
            cannot connect in time.
    """
    if listen and connect:
        raise TransportError(f"tcp: give --listen or --connect, not both ({listen!r}, {connect!r})")
    if connect:
        sock = _dial(parse_address(connect, field="connect"), connect_timeout_s)
    else:
        sock = _accept_one(parse_address(listen or DEFAULT_ADDRESS, field="listen"))
    _tune(sock)
    buf = bytearray(_RECV_BYTES)
    view = memoryview(buf)
    try:
        serve_stream(ep, sock, send=sock.sendall, read=lambda: view[:sock.recv_into(view)], deliver=ep.on_bytes)
    finally:
        sock.close()


def _accept_one(address: tuple[str, int]) -> socket.socket:
    family = socket.AF_INET6 if ":" in address[0] else socket.AF_INET
    with socket.socket(family, socket.SOCK_STREAM) as ls:
        try:
            ls.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            ls.bind(address)
            ls.listen(1)
        except OSError as err:
            raise TransportError(f"tcp: cannot listen on {address[0]}:{address[1]}: {err}") from err
        sock, _peer = ls.accept()
    return sock


def _dial(address: tuple[str, int], timeout_s: float) -> socket.socket:
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            sock = socket.create_connection(address, timeout=2.0)
            sock.settimeout(None)
            return sock
        except OSError as err:
            if time.monotonic() >= deadline:
                raise TransportError(f"tcp: cannot connect to the harness at {address[0]}:{address[1]} "
                                     f"within {timeout_s:g} s: {err}") from err
            time.sleep(_CONNECT_RETRY_S)


__all__ = ["DEFAULT_ADDRESS", "DEFAULT_PORT", "RealtimeMapper", "TcpLink", "TcpStats", "parse_address",
           "recv_stamped", "serve_endpoint"]
