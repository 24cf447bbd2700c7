"""Target side of the tcp transport: serve an ``Endpoint`` to one harness, or to
harness after harness (a target on a bench device), until stopped.

Serving starts with one line on stderr: where the target listens or dials, its
clock, capabilities and how a harness knows it is the right target (the token, if
any); each session ends with one line: who connected, what was served, how it ended.
Listening, the target keeps its port between runs (a second target on that port
cannot bind and says so); dialling, it dials again after each run. SIGTERM or
Ctrl-C ends it (saying BYE to a harness that is connected).

The token that proves this is the run's target (PROTOCOL.md 4.8) is read from the
environment variable ``token_env`` (default ``HIL_SESSION_TOKEN``, which a harness
that starts the target sets); without one the target announces no ``CAP_AUTH`` and
a harness that requires a token refuses it.
"""

from __future__ import annotations

import itertools
import socket
import sys
import threading
import time
from collections.abc import Callable
from typing import TYPE_CHECKING

from hil.adapters.sdk import add_stats, announce_line, fresh_endpoint, session_line, stop_on_sigterm
from hil.adapters.tcp.handshake import listening_socket, parse_address, peer_text, tune
from hil.adapters.tcp.options import DEFAULT_ADDRESS, TcpOptions
from hil.adapters.wire.auth import token_from_env
from hil.adapters.wire.receipt import StreamReader
from hil.common.errors import TransportError

if TYPE_CHECKING:
    from hil.adapters.sdk import Endpoint

RETRY_S = 0.05
__all__ = ["serve_endpoint"]


def serve_endpoint(ep: Endpoint, *, options: TcpOptions | None = None, keep_serving: bool = False,
                   announce: Callable[[str], None] | None = None) -> None:
    """Serve ``ep`` on TCP until the harness says BYE or the connection ends (with
    ``keep_serving``: then serve the next harness), or SIGTERM/Ctrl-C.

    ``options`` (``TcpOptions``): listens on ``listen`` (default ``127.0.0.1:7600``)
    for a harness, or dials the harness at ``connect`` (retrying for
    ``connect_timeout_s``; with ``keep_serving``, until stopped); proves the token in
    ``token_env``. ``announce`` gets the start-up and session lines (default: stderr).

    Raises:
        TransportError: both addresses given, a malformed one, cannot listen (the
            port is in use), or cannot connect in time.
        ConfigError: the token in ``token_env`` is too short.
    """
    o = options or TcpOptions()
    listen, connect, token_env = o.listen, o.connect, o.token_env
    if listen and connect:
        raise TransportError(f"tcp: give --listen or --connect, not both ({listen!r}, {connect!r})")
    say = announce or (lambda text: print(text, file=sys.stderr, flush=True))
    token = token_from_env(token_env, field=f"the token in ${token_env}", required=False)
    if token is not None and ep.token is None:
        ep.token = token
    quit_ = threading.Event()  # SIGTERM or Ctrl-C: no further runs
    access = (f"proves the token in ${token_env} to the harness (AUTH, PROTOCOL.md 4.8)" if ep.token else
              f"no token (${token_env} unset): a harness that requires one refuses this target")
    current = ep
    if connect:
        address = parse_address(connect, field="connect")
        listener = None
        where = f"dialling the harness at {connect}"
    else:
        address = parse_address(listen or DEFAULT_ADDRESS, field="listen")
        listener = listening_socket(address, backlog=4)  # raises at once when the port is taken
        listener.settimeout(0.25)  # accept wakes to see a SIGTERM between runs
        where = f"listening on {address[0]}:{listener.getsockname()[1]}"
    try:
        with stop_on_sigterm(quit_.set):
            say(announce_line(ep, transport="tcp", where=where, access=access, keep_serving=keep_serving))
            for n in itertools.count(1):
                got = _accept(listener, quit_) if listener is not None else _dial(address, quit_, o.connect_timeout_s,
                                                                                 keep_serving=keep_serving)
                if got is None:
                    return
                sock, peer = got
                if quit_.is_set():  # a SIGTERM that came while the harness connected
                    sock.close()
                    return
                ended = _serve_one(current, sock, quit_)
                say(session_line(current, n, peer, ended))
                if quit_.is_set() or not keep_serving:
                    return
                current = fresh_endpoint(ep, current)
    except KeyboardInterrupt:
        quit_.set()
    finally:
        add_stats(ep, current)
        if listener is not None:
            listener.close()


def _serve_one(ep: Endpoint, sock: socket.socket, quit_: threading.Event) -> str:
    from hil.adapters.sdk import serve_stream

    tune(sock)
    # Stamped on the target's own clock as each message's read returns (a target clock
    # need not run with the host's realtime clock, which kernel stamps are on).
    reader: StreamReader[object] = StreamReader(sock, ep.clock, uncertainty=False)
    try:
        return serve_stream(ep, reader, send=sock.sendall, quit_=quit_)
    finally:
        sock.close()


def _accept(listener: socket.socket, quit_: threading.Event) -> tuple[socket.socket, str] | None:
    while not quit_.is_set():
        try:
            sock, addr = listener.accept()
        except TimeoutError:
            continue
        except OSError as err:
            raise TransportError(f"tcp: cannot accept a harness: {err}") from err
        sock.settimeout(None)
        return sock, peer_text(addr)
    return None


def _dial(address: tuple[str, int], quit_: threading.Event, timeout_s: float, *,
          keep_serving: bool) -> tuple[socket.socket, str] | None:
    deadline = time.monotonic() + timeout_s
    while not quit_.is_set():
        try:
            sock = socket.create_connection(address, timeout=2.0)
        except OSError as err:
            if not keep_serving and time.monotonic() >= deadline:
                raise TransportError(f"tcp: cannot connect to the harness at {address[0]}:{address[1]} "
                                     f"within {timeout_s:g} s: {err.strerror or err}") from err
            quit_.wait(RETRY_S)
            continue
        sock.settimeout(None)
        return sock, peer_text(address)
    return None
