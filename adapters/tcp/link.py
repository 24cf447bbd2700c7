"""The tcp transport: the local transport's stream framing over one TCP connection.

Messages travel back to back on the stream, exactly as on the local transport's
socket (PROTOCOL.md sections 8 and 10.5). Either side may listen: the harness
connects to a target that listens (``connect="10.0.0.5:7600"``), or listens for a
target that dials in (``listen="0.0.0.0:7600"``). Addresses are explicit
``host:port`` pairs (a ``tcp/`` prefix is accepted); nothing is discovered, and the
default is loopback (``127.0.0.1:7600``).

Only the run's own target is measured. A connection is the run's once its peer has
said HELLO with the expected name and, where the run has a token, proved it
(``hil.adapters.tcp.handshake``, PROTOCOL.md 4.8); any other connection is told why,
closed and counted (``LinkStats.connections_refused``), and the harness keeps
waiting for its own target: a program already listening on the port, or one that
dials a listening harness first, never takes the vehicle's place.

Receipt stamps. The harness enables ``SO_TIMESTAMPNS`` and reads one message at a
time (``hil.adapters.wire.receipt``): each message is stamped with the kernel's arrival of
its own last byte, mapped to the link's clock, and carries how much earlier the
arrival may have been when the kernel merged it with later bytes.

Liveness: end of stream or a socket error marks the target gone at once. For a peer
that vanishes without closing (a powered-off board), both sides set
``TCP_USER_TIMEOUT`` = 1 s and 1 s keepalives, and the harness sends a HEARTBEAT
whenever it has sent nothing for 250 ms, so unacknowledged data times out within
about a second.

The harness half is ``TcpLink``; the target half, ``serve_endpoint``, lives in
``hil.adapters.tcp.target`` (used by ``hil.adapters.sdk.serve``). Standard library only.
"""

from __future__ import annotations

import queue
import selectors
import socket
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

from hil.adapters.link import Link, Received
from hil.adapters.tcp.handshake import (HANDSHAKE_S, Candidate, Requirements, listening_socket, parse_address,
                                        peer_text, tune)
from hil.adapters.tcp.options import DEFAULT_ADDRESS, TcpOptions
from hil.adapters.wire import protocol
from hil.adapters.wire.messages import Heartbeat, Hello
from hil.adapters.wire.receipt import ReaderStats, StreamReader, enable_kernel_stamps
from hil.common.errors import TargetError, TransportError
from hil.timing.clock import Clock

MAX_CANDIDATES = 16  # connections a listening harness checks at once; more: the oldest is refused
CONNECT_RETRY_S = 0.05
REDIAL_S = 0.25  # after a refused peer, before dialling again


@dataclass
class TcpStats(ReaderStats):
    """Counters only this transport has (the shared ones are in ``LinkStats``): the
    receipt stamps' (``ReaderStats``; the kernel turns stamping on a moment after the
    first socket asks, so a first read may lack it) and the heartbeats sent."""

    heartbeats_sent: int = 0


class TcpLink(Link):
    """Harness side of one TCP connection to one target.

    Args:
        options: ``TcpOptions``: the address to dial (``connect``, a target that
            listens) or to listen on (``listen``, a target that dials in), receipt
            stamps, heartbeats, the token the target must prove and the name it must
            say (default: dial ``127.0.0.1:7600``, no token).
        abandon: called while waiting for the target; a text (why, e.g. "the target
            process exited") stops the wait at once.

    Raises:
        TransportError: both or a malformed address.
    """

    transport_name = "tcp"

    def __init__(self, *, vehicle_id: int, clock: Clock, options: TcpOptions | None = None,
                 abandon: Callable[[], str | None] | None = None,
                 rx_queue_size: int = 1024, rx_queue: queue.Queue[Received] | None = None) -> None:
        super().__init__(vehicle_id=vehicle_id, clock=clock, rx_queue_size=rx_queue_size, rx_queue=rx_queue)
        self._sock: socket.socket | None = None
        self._listener: socket.socket | None = None
        self._reader: threading.Thread | None = None
        self._beater: threading.Thread | None = None
        o = self.options = options or TcpOptions()
        if o.connect and o.listen:
            raise TransportError(f"tcp: give connect or listen, not both (connect={o.connect!r}, listen={o.listen!r})")
        self.listening = bool(o.listen)
        self.address = parse_address(o.listen or o.connect or DEFAULT_ADDRESS,
                                     field="listen" if o.listen else "connect")
        self.kernel_stamps = o.kernel_stamps
        self.heartbeat_idle_s = o.heartbeat_idle_s
        self.need = Requirements(vehicle_id, o.token.encode("utf-8") if o.token else None, o.expect_name)
        self._abandon = abandon
        self.tcp_stats = TcpStats()
        self.peer: str | None = None  # host:port of the accepted peer
        self._send_lock = threading.Lock()
        self._state_lock = threading.Lock()
        self._connected = threading.Event()
        self._stop = threading.Event()
        self._deadline = 0.0
        self._last_send = 0.0
        self._connect_error = ""
        self._abandoned = ""
        self._next_dial = 0.0
        self._listening_ns = 0

    @property
    def bound_address(self) -> tuple[str, int] | None:
        """(host, port) the harness listens on (after ``open``; port 0 resolved)."""
        return self._listener.getsockname()[:2] if self._listener is not None else None

    def open(self, *, hello_timeout_s: float) -> Hello:
        """Connect (or wait for the target to connect) and wait for its HELLO (and
        proof of the token); all within ``hello_timeout_s``.

        Raises:
            TransportError: no connection was the run's target within the timeout
                (the message counts and names the refused ones), or cannot listen.
            TargetError: the accepted target's HELLO is unusable (version).
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
            self._listening_ns = self.clock.now_ns()
            ls = listening_socket(self.address, backlog=MAX_CANDIDATES)
            if self.kernel_stamps:  # inherited by the accepted connections
                enable_kernel_stamps(ls)
            self._listener = ls
        return self.bound_address  # type: ignore[return-value]

    def _no_connection_reason(self, timeout_s: float) -> str:
        host, port = self.bound_address or self.address
        st = self.stats
        if self.listening:
            text = f"tcp: no target connected to {host}:{port} within {timeout_s:g} s"
        else:
            detail = f" (last error: {self._connect_error})" if self._connect_error else ""
            text = f"tcp: cannot connect to the target at {host}:{port} within {timeout_s:g} s{detail}"
        if st.connections_refused:
            what = "no connection proved to be this run's target" if self.need.token else "no target answered"
            text = f"tcp: {what} {'on' if self.listening else 'at'} {host}:{port} within {timeout_s:g} s"
        if self._abandoned:
            text = f"tcp: stopped waiting for the target at {host}:{port}: {self._abandoned}"
        if st.connections_refused:
            n = st.connections_refused
            text += f"; {n} connection{'s' * (n > 1)} refused ({'; '.join(dict.fromkeys(st.refused))})"
        return text

    def _open(self) -> None:
        if self.listening:
            self.start_listening()
        reader = threading.Thread(target=self._read_loop, name=f"tcp-rx-{self.vehicle_id}", daemon=True)
        reader.start()
        self._reader = reader  # only a started thread: close() may join it from another thread

    # -- reaching the run's own target --------------------------------------------

    def _establish(self) -> Candidate | None:
        """The connection whose peer is the run's target (HELLO, name, proof), every
        other one refused; None when closed, abandoned or late."""
        listener = self._listener  # close() may clear the attribute meanwhile
        sel = selectors.DefaultSelector()
        pending: list[Candidate] = []
        self._next_dial = 0.0
        try:
            if listener is not None:
                listener.setblocking(False)
                sel.register(listener, selectors.EVENT_READ)
            while not self._stop.is_set() and (now := time.monotonic()) < self._deadline:
                if self._abandon is not None and (why := self._abandon()):
                    self._abandoned = why
                    return None
                if listener is None and not pending and now >= self._next_dial:
                    self._next_dial = now + CONNECT_RETRY_S
                    self._add(pending, sel, self._dial_once())
                for key, _ in sel.select(timeout=CONNECT_RETRY_S):
                    if key.fileobj is listener:
                        self._add(pending, sel, self._accept(listener))
                        continue
                    cand: Candidate = key.data
                    verdict = cand.advance()
                    if verdict == "":
                        sel.unregister(cand.sock)
                        pending.remove(cand)
                        return cand
                    if verdict is not None:
                        self._drop(pending, sel, cand, verdict)
                now = time.monotonic()
                for cand in [c for c in pending if c.expired(now)]:
                    self._drop(pending, sel, cand, cand.late_reason())
            return None
        except OSError:
            if self._stop.is_set():  # close() closed the listener under us (EBADF): the wait just ends
                return None
            raise
        finally:
            for cand in pending:  # the run's target came (or the wait ended): the rest go
                cand.close()
            sel.close()

    def _add(self, pending: list[Candidate], sel: selectors.BaseSelector,
             conn: tuple[socket.socket, str, int] | None) -> None:
        if conn is None:
            return
        sock, peer, opened_ns = conn
        tune(sock)
        # A dialled peer that stalls is left for the next dial; a listening harness
        # checks every caller at once, so a slow one holds no one up.
        late = time.monotonic() + HANDSHAKE_S if self.need.any and not self.listening else self._deadline
        cand = Candidate(sock, peer, self.need, clock=self.clock, deadline=min(late, self._deadline),
                         opened_ns=opened_ns)
        if len(pending) >= MAX_CANDIDATES:
            self._drop(pending, sel, pending[0], "too many connections waiting at once")
        pending.append(cand)
        sel.register(sock, selectors.EVENT_READ, cand)

    def _drop(self, pending: list[Candidate], sel: selectors.BaseSelector, cand: Candidate, why: str) -> None:
        self._next_dial = time.monotonic() + REDIAL_S  # a dialled port that answered wrongly: not at once again
        pending.remove(cand)
        sel.unregister(cand.sock)
        cand.refuse(why)
        self._refuse(cand.peer, why)

    def _accept(self, listener: socket.socket) -> tuple[socket.socket, str, int] | None:
        try:
            sock, addr = listener.accept()
        except (BlockingIOError, InterruptedError):
            return None
        except OSError as err:
            self._connect_error = str(err)
            return None
        return sock, peer_text(addr), self._listening_ns  # no byte came before we listened

    def _dial_once(self) -> tuple[socket.socket, str, int] | None:
        """One connection attempt (None: failed, the error kept). Stamping is on
        before the first byte can arrive, so that the HELLO is stamped by the kernel too."""
        left = max(0.05, self._deadline - time.monotonic())
        opened_ns = self.clock.now_ns()
        try:
            info = socket.getaddrinfo(*self.address, type=socket.SOCK_STREAM)[0]
            sock = socket.socket(info[0], info[1], info[2])
        except OSError as err:
            self._connect_error = str(err)
            return None
        try:
            if self.kernel_stamps:
                enable_kernel_stamps(sock)
            sock.settimeout(min(left, 2.0))
            sock.connect(info[4])
            sock.settimeout(None)
        except OSError as err:
            sock.close()
            self._connect_error = str(err)
            return None
        return sock, peer_text(info[4]), opened_ns

    # -- the session ------------------------------------------------------------------

    def _read_loop(self) -> None:
        cand = self._establish()
        listener = self._listener
        if listener is not None:  # one target per link: stop listening
            listener.close()
        if cand is None:
            self._mark_gone(self._abandoned or self._connect_error or "no connection")
            return
        sock = cand.accepted_socket()
        with self._state_lock:
            if self._stop.is_set():  # closed while connecting
                sock.close()
                return
            self._sock = sock
        self.peer = cand.peer
        self._last_send = time.monotonic()
        self._connected.set()
        assert cand.hello is not None
        for msg in (cand.hello, *cand.after):
            self._dispatch(msg, cand.hello_rx_ns)
        if self.heartbeat_idle_s > 0:
            beater = threading.Thread(target=self._beat, name=f"tcp-hb-{self.vehicle_id}", daemon=True)
            beater.start()
            self._beater = beater
        reader = StreamReader(sock, self.clock, decoder=cand.decoder, kernel_stamps=self.kernel_stamps,
                              stats=self.tcp_stats, not_before_ns=cand.opened_ns)
        self._read_stream(reader, failed=lambda err: f"tcp: connection failed: {err}",
                          ended=lambda: "tcp: the target closed the connection")

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


__all__ = ["TcpLink", "TcpStats"]
