"""The live view's front door: the address viewers connect to, relaying each
WebSocket to foxglove-sdk's server on a private loopback port.

Why a relay: foxglove-sdk 0.30's server accepts only the subprotocol
``foxglove.sdk.v1`` (HTTP 400 to anything else), while viewers speaking the
original ``foxglove.websocket.v1`` (the ``@foxglove/ws-protocol`` client) send the
same messages under that name. The front rewrites the handshake (the request's
``Sec-WebSocket-Protocol`` to ``foxglove.sdk.v1``, the answer's back to what the
viewer asked for) and then copies bytes both ways unchanged. It also owns every
viewer's connection, so closing never waits for a viewer that stopped reading: the
front aborts its sockets (no close handshake), after which the SDK's server has no
client left to wait for.

Bounds: at most ``MAX_VIEWERS`` viewers at once (more are closed at once), a
handshake within ``HANDSHAKE_TIMEOUT_S`` and ``HEAD_LIMIT`` bytes, and at most the
transport's write buffer (64 KiB) held per viewer: a viewer that stops reading
stops the relay reading from the server, whose own per-client backlog then drops
the oldest messages.

Raises: :class:`hil.common.errors.ConfigError` when the address cannot be bound.
"""

from __future__ import annotations

import asyncio
import socket
import threading
from concurrent.futures import TimeoutError as FutureTimeout

from hil.common.errors import ConfigError

SDK_SUBPROTOCOL = "foxglove.sdk.v1"
RELAYED = ("foxglove.websocket.v1",)  # served by renaming them to SDK_SUBPROTOCOL
MAX_VIEWERS = 8
HANDSHAKE_TIMEOUT_S = 5.0
HEAD_LIMIT = 16 * 1024
_CHUNK = 64 * 1024


def _offered(head: bytes) -> list[str]:
    """Subprotocols a WebSocket upgrade request offers, in order."""
    out: list[str] = []
    for line in head.split(b"\r\n")[1:]:
        name, _, value = line.partition(b":")
        if name.strip().lower() == b"sec-websocket-protocol":
            out += [p.strip() for p in value.decode("latin-1").split(",") if p.strip()]
    return out


def _set_protocol(head: bytes, protocol: str) -> bytes:
    """``head`` with every ``Sec-WebSocket-Protocol`` header replaced by one naming ``protocol``."""
    lines = [ln for ln in head.split(b"\r\n") if ln.partition(b":")[0].strip().lower() != b"sec-websocket-protocol"]
    while lines and not lines[-1]:
        lines.pop()
    return b"\r\n".join([*lines, b"Sec-WebSocket-Protocol: " + protocol.encode()]) + b"\r\n\r\n"


def split_address(text: str) -> tuple[str, int]:
    """``HOST:PORT`` (``[v6]:PORT`` for IPv6) as (host, port).

    Raises:
        ConfigError: not HOST:PORT, or the port is not 0-65535.
    """
    host, sep, port = text.rpartition(":")
    host = host[1:-1] if host.startswith("[") and host.endswith("]") else host
    if not sep or not host or not port.isdigit() or int(port) > 65535:
        raise ConfigError(f"live view address {text!r}: expected HOST:PORT, e.g. 127.0.0.1:8765 "
                          "(port 0-65535; [::1]:8765 for IPv6)")
    return host, int(port)


def bind(host: str, port: int) -> socket.socket:
    """A listening TCP socket on ``host:port`` (0: any free port).

    Raises:
        ConfigError: the address cannot be resolved or bound (in use, not this host's).
    """
    try:
        family, kind, proto, _, addr = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM,
                                                          flags=socket.AI_PASSIVE)[0]
        sock = socket.socket(family, kind, proto)
    except OSError as err:
        raise ConfigError(f"live view cannot listen on {host}:{port}: {err.strerror or err}") from err
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.bind(addr)
        sock.listen(MAX_VIEWERS)
    except OSError as err:
        sock.close()
        raise ConfigError(f"live view cannot listen on {host}:{port}: {err.strerror or err} "
                          "(choose another port with --live HOST:PORT)") from err
    return sock


class LiveFront:
    """Listens on ``host:port`` and relays each viewer to ``127.0.0.1:upstream_port``
    on a thread of its own (``live-front``). Idempotent :meth:`close`.

    Raises:
        ConfigError: ``host:port`` cannot be bound.
    """

    def __init__(self, *, host: str, port: int, upstream_port: int) -> None:
        self._sock = bind(host, port)
        self.port = int(self._sock.getsockname()[1])
        self._upstream = upstream_port
        self._writers: set[asyncio.StreamWriter] = set()
        self._pumps: set[asyncio.Future[None]] = set()
        self._lock = threading.Lock()
        self.viewers = self.refused = 0
        self.protocols: dict[str, int] = {}
        self._closed = False
        self._loop = asyncio.new_event_loop()
        self._started = threading.Event()
        self._thread = threading.Thread(target=self._run, name="live-front", daemon=True)
        self._thread.start()
        self._started.wait(5.0)

    def _run(self) -> None:
        asyncio.set_event_loop(self._loop)

        async def start() -> asyncio.AbstractServer:
            return await asyncio.start_server(self._serve, sock=self._sock, limit=HEAD_LIMIT)

        self._server = self._loop.run_until_complete(start())
        self._started.set()
        self._loop.run_forever()

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        if len(self._writers) >= 2 * MAX_VIEWERS or self._closed:  # two sockets per viewer
            self.refused += 1
            writer.transport.abort()
            return
        self._writers.add(writer)
        up_w: asyncio.StreamWriter | None = None
        try:
            head = await asyncio.wait_for(reader.readuntil(b"\r\n\r\n"), HANDSHAKE_TIMEOUT_S)
            offered = _offered(head)
            asked = next((p for p in offered if p == SDK_SUBPROTOCOL), None) or next(
                (p for p in offered if p in RELAYED), None)
            if asked is not None and asked != SDK_SUBPROTOCOL:
                head = _set_protocol(head, SDK_SUBPROTOCOL)
            up_r, up_w = await asyncio.open_connection("127.0.0.1", self._upstream, limit=HEAD_LIMIT)
            self._writers.add(up_w)
            up_w.write(head)
            answer = await asyncio.wait_for(up_r.readuntil(b"\r\n\r\n"), HANDSHAKE_TIMEOUT_S)
            if asked is not None and answer.startswith(b"HTTP/1.1 101"):
                answer = _set_protocol(answer, asked)
                with self._lock:
                    self.viewers += 1
                    self.protocols[asked] = self.protocols.get(asked, 0) + 1
            writer.write(answer)
            pumps = [asyncio.ensure_future(_pump(up_r, writer)), asyncio.ensure_future(_pump(reader, up_w))]
            self._pumps.update(pumps)
            await asyncio.wait(pumps, return_when=asyncio.FIRST_COMPLETED)
            for p in pumps:
                p.cancel()
                self._pumps.discard(p)
        except (OSError, asyncio.IncompleteReadError, asyncio.LimitOverrunError, asyncio.TimeoutError):
            pass  # a viewer that left or never spoke: its sockets are closed below
        finally:
            writer.transport.abort()  # the viewer: no waiting on one that does not read
            self._writers.discard(writer)
            if up_w is not None:  # the SDK's side reads: a plain close
                up_w.close()
                self._writers.discard(up_w)

    def close(self, *, timeout_s: float = 0.3) -> None:
        """Stop listening and drop every viewer at once (no close handshake, no
        waiting on a viewer that does not read); within about ``timeout_s``."""
        if self._closed:
            return
        self._closed = True

        async def shutdown() -> None:
            self._server.close()
            for w in list(self._writers):
                w.transport.abort()  # a viewer's socket (or the SDK's) at once
            for p in list(self._pumps):
                p.cancel()
            # Not cancelled: asyncio 3.11's stream callback raises on a cancelled task.
            tasks = [t for t in asyncio.all_tasks() if t is not asyncio.current_task()]
            if tasks:
                await asyncio.wait(tasks, timeout=timeout_s / 2)

        try:
            asyncio.run_coroutine_threadsafe(shutdown(), self._loop).result(timeout_s)
        except (FutureTimeout, RuntimeError):
            pass
        self._loop.call_soon_threadsafe(self._loop.stop)
        self._thread.join(timeout_s)
        if not self._thread.is_alive():
            self._loop.close()
        self._sock.close()


async def _pump(src: asyncio.StreamReader, dst: asyncio.StreamWriter) -> None:
    """Copy ``src`` to ``dst`` until end of stream; waits while ``dst`` is full."""
    while data := await src.read(_CHUNK):
        dst.write(data)
        await dst.drain()
