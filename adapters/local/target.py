"""Target side of the local transport: serve an ``Endpoint`` on the socket the harness
handed over (``HIL_LOCAL_FD``), frames inline or through the shared-memory ring of
``HIL_LOCAL_SHM`` (``hil.adapters.local.shm``; HELLO capability bit 0 says the target
reads it). The harness half is ``hil.adapters.local.link``.
"""

from __future__ import annotations

import dataclasses
import os
import socket
from collections.abc import Callable
from typing import TYPE_CHECKING

from hil.adapters.local.options import ENV_FD
from hil.adapters.local.shm import NOTICES, SHM_FRAMES, Notice, ShmReader
from hil.adapters.sdk import serve_stream
from hil.adapters.wire import protocol
from hil.adapters.wire.messages import Hello, Message, MsgType
from hil.adapters.wire.receipt import StreamReader
from hil.adapters.wire.stream import StreamDecoder
from hil.common.errors import ProtocolError, TransportError

if TYPE_CHECKING:
    from hil.adapters.sdk import Endpoint


def _advertising(send: Callable[[bytes], None], capabilities: int) -> Callable[[bytes], None]:
    """``send`` that adds ``capabilities`` to the HELLO the endpoint sends first."""
    first = [True]

    def wrapped(buf: bytes) -> None:
        if first and len(buf) > 5 and buf[5] == MsgType.HELLO:
            first.clear()
            hello = protocol.decode(buf)
            assert isinstance(hello, Hello)
            buf = protocol.encode(dataclasses.replace(hello, capabilities=hello.capabilities | capabilities))
        send(buf)

    return wrapped


def serve_endpoint(ep: Endpoint) -> None:
    """Target side: serve ``ep`` on the socket the harness handed over in
    ``HIL_LOCAL_FD`` until BYE or end of stream, reading frames from the
    shared-memory ring when ``HIL_LOCAL_SHM`` offers one (and saying so in HELLO).

    Raises:
        TransportError: ``HIL_LOCAL_FD`` is not set (not started by the harness).
    """
    fd_text = os.environ.get(ENV_FD)
    if not fd_text or not fd_text.isdigit():
        raise TransportError("HIL_LOCAL_FD is not set: a local target is started by the harness (hil run); "
                             "to serve by hand, give --transport tcp, zenoh, can or mixed (see --help)")
    serve_socket(ep, socket.socket(fileno=int(fd_text)), ShmReader.from_env())


def serve_socket(ep: Endpoint, sock: socket.socket, ring: ShmReader | None) -> None:
    """Serve one harness's stream on ``sock`` (frames inline or through ``ring``) until
    it ends (SIGTERM: BYE, then leave; ``hil.adapters.sdk.serve_stream``); closes both. The
    shared target serves each vehicle's socket with this."""
    reader = StreamReader(sock, ep.clock, decoder=StreamDecoder(NOTICES), uncertainty=False)
    send: Callable[[bytes], None] = sock.sendall
    if ring is not None:
        send = _advertising(send, SHM_FRAMES)

    def deliver(item: Message | ProtocolError | Notice, t_rx: int) -> None:
        if isinstance(item, Notice):
            if ring is None:
                item = ProtocolError("shared-memory notice, but no frame ring was negotiated", offset=0)
            else:
                got = ring.read(item)
                if got is None:
                    return  # overwritten before it was read: the harness counted it
                item = got
        ep.on_message(item, t_rx)

    try:
        serve_stream(ep, reader, send=send, deliver=deliver)
    finally:
        sock.close()
        if ring is not None:
            ring.close()


__all__ = ["serve_endpoint", "serve_socket"]
