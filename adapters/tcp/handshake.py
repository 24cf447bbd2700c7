"""Setting up a TCP session: addresses, socket options, listening, and the start of
a session before the connection is the run's: HELLO, then the proof of the run's
token (PROTOCOL.md sections 4.8 and 10.5).

Every connection the harness accepts or makes is a :class:`Candidate` until its
peer has said HELLO with the expected name (``target.expect_name``) and, where the
run has a token, answered a fresh AUTH challenge with the right proof. A candidate
that fails is told why (BYE), closed and counted by the link; the harness goes on
waiting for its own target. Reads stop at the end of each message
(``StreamDecoder.wanted``), so the bytes after the proof stay in the socket for the
session's reader, with their own receipt stamps.
"""

from __future__ import annotations

import select
import socket
from dataclasses import dataclass
from typing import Any, NoReturn

from hil.adapters.tcp.options import DEFAULT_ADDRESS
from hil.adapters.wire import auth, protocol
from hil.adapters.wire.messages import Auth, AuthStep, Bye, ErrorMsg, Heartbeat, Hello, Message
from hil.adapters.wire.stream import StreamDecoder
from hil.common.errors import ProtocolError, TransportError
from hil.timing.clock import Clock

HANDSHAKE_S = 3.0  # a dialled peer has this long to say HELLO and prove the token before the next dial
USER_TIMEOUT_MS = 1000  # unacknowledged data for this long: the connection is dead
_SOCK_BUF = 4 * 1024 * 1024


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


def tune(sock: socket.socket) -> None:
    """No Nagle delay, big buffers, and a dead peer noticed within about a second."""
    sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, _SOCK_BUF)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, _SOCK_BUF)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_KEEPALIVE, 1)
    for opt, value in (("TCP_KEEPIDLE", 1), ("TCP_KEEPINTVL", 1), ("TCP_KEEPCNT", 2),
                       ("TCP_USER_TIMEOUT", USER_TIMEOUT_MS)):
        if hasattr(socket, opt):
            sock.setsockopt(socket.IPPROTO_TCP, getattr(socket, opt), value)


def listening_socket(address: tuple[str, int], *, backlog: int) -> socket.socket:
    """A socket bound and listening on ``address``.

    Raises:
        TransportError: cannot bind or listen (for example the port is in use).
    """
    family = socket.AF_INET6 if ":" in address[0] else socket.AF_INET
    ls = socket.socket(family, socket.SOCK_STREAM)
    try:
        ls.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        ls.bind(address)
        ls.listen(backlog)
    except OSError as err:
        ls.close()
        why = "the port is in use (another target, or another run?)" if err.errno == 98 else err.strerror or str(err)
        raise TransportError(f"tcp: cannot listen on {address[0]}:{address[1]}: {why}") from err
    return ls


def peer_text(addr: Any) -> str:
    host, port = addr[0], addr[1]
    return f"[{host}]:{port}" if ":" in str(host) else f"{host}:{port}"




@dataclass(frozen=True)
class Requirements:
    """What a peer must show: ``token`` (bytes of the shared secret, or None: no
    proof asked) and ``expect_name`` (the HELLO name's prefix, or None)."""

    vehicle_id: int
    token: bytes | None = None
    expect_name: str | None = None

    @property
    def any(self) -> bool:
        return self.token is not None or self.expect_name is not None


class Candidate:
    """One connection whose peer has not yet shown it is the run's target.

    ``advance()`` reads what has arrived (without blocking) and returns None while
    the handshake goes on, ``""`` once the peer is accepted, or why it is refused.
    """

    def __init__(self, sock: socket.socket, peer: str, need: Requirements, *, clock: Clock, deadline: float,
                 opened_ns: int) -> None:
        """``opened_ns``: on ``clock``, an instant before any byte of the connection
        arrived (the dial began, or the harness began listening)."""
        sock.setblocking(False)
        self.opened_ns = opened_ns
        self.sock = sock
        self.peer = peer
        self.need = need
        self.clock = clock
        self.deadline = deadline  # time.monotonic()
        self.decoder: StreamDecoder[NoReturn] = StreamDecoder()
        self.hello: Hello | None = None
        self.hello_rx_ns = 0
        self.after: list[Message] = []  # messages after the HELLO that the session keeps (heartbeats)
        self._challenge: bytes | None = None
        self._buf = memoryview(bytearray(protocol.HEADER_SIZE + 4096))

    def fileno(self) -> int:
        return self.sock.fileno()

    def expired(self, now: float) -> bool:
        return now >= self.deadline

    def late_reason(self) -> str:
        if self.hello is None:
            return "said no HELLO in time"
        return f"{self.hello.target_name!r} did not answer the AUTH challenge in time"

    def advance(self) -> str | None:
        while True:
            want = min(self.decoder.wanted(), len(self._buf))
            try:
                n = self.sock.recv_into(self._buf[:want], want)
            except BlockingIOError:
                return None
            except OSError as err:
                return f"connection failed during the handshake: {err}"
            if n == 0:
                return "closed the connection during the handshake" if self.hello else "closed without a HELLO"
            t_rx = self.clock.now_ns()
            for item in self.decoder.feed(self._buf[:n]):
                verdict = self._on(item, t_rx)
                if verdict is not None:
                    return verdict

    def _on(self, item: Message | ProtocolError, t_rx: int) -> str | None:
        if isinstance(item, ProtocolError):
            return f"sent bytes that are not a message: {item}"
        if self.hello is None:
            if not isinstance(item, Hello):
                return f"its first message is {type(item).__name__}, not HELLO"
            self.hello, self.hello_rx_ns = item, t_rx
            return self._on_hello(item)
        if self._challenge is None or isinstance(item, Heartbeat):
            self.after.append(item)
            return None
        if isinstance(item, Auth) and item.step == AuthStep.PROOF:
            assert self.need.token is not None
            if auth.verify(self.need.token, self._challenge, self.need.vehicle_id, item.data):
                return ""
            return f"{self.hello.target_name!r} answered the AUTH challenge with a wrong proof (another token)"
        if isinstance(item, ErrorMsg):
            return f"{self.hello.target_name!r} answered the AUTH challenge with ERROR {item.code}: {item.message}"
        return f"{self.hello.target_name!r} answered the AUTH challenge with {type(item).__name__}"

    def _on_hello(self, hello: Hello) -> str | None:
        need = self.need
        if need.any and hello.protocol_version != protocol.VERSION:
            return f"{hello.target_name!r} speaks protocol version {hello.protocol_version}, not {protocol.VERSION}"
        if need.expect_name is not None and not hello.target_name.startswith(need.expect_name):
            return f"says it is {hello.target_name!r}, not {need.expect_name!r} (target.expect_name)"
        if need.token is None:
            return ""
        if not hello.capabilities & protocol.CAP_AUTH:
            return (f"{hello.target_name!r} does not announce CAP_AUTH, so it cannot prove the run's token "
                    "(a target left over on the port, another run's, or one that predates PROTOCOL.md 4.8)")
        self._challenge = auth.new_challenge()
        return self._send(Auth(need.vehicle_id, AuthStep.CHALLENGE, self._challenge))

    def _send(self, msg: Message) -> str | None:
        view = memoryview(protocol.encode(msg))
        while view:  # 100 bytes into a fresh socket: one send, unless the peer reads nothing at all
            try:
                view = view[self.sock.send(view):]
            except BlockingIOError:
                if not select.select([], [self.sock], [], 1.0)[1]:
                    return "does not read what it is sent"
            except OSError as err:
                return f"connection failed during the handshake: {err}"
        return None

    def refuse(self, why: str) -> None:
        """Say why (BYE, best effort) and close."""
        try:
            self.sock.send(protocol.encode(Bye(self.need.vehicle_id, f"not this run's target: {why}"[:200])))
        except OSError:
            pass
        self.close()

    def close(self) -> None:
        try:
            self.sock.close()
        except OSError:
            pass

    def accepted_socket(self) -> socket.socket:
        """The connection, blocking again, for the session's reader."""
        self.sock.setblocking(True)
        return self.sock


__all__ = ["HANDSHAKE_S", "USER_TIMEOUT_MS", "Candidate", "Requirements",
           "listening_socket", "parse_address", "peer_text", "tune"]
