"""Target side of a shared local target (``hil.adapters.local.shared_link`` is the
harness's side and documents the control socket): one process takes every vehicle's
socket (and frame ring) from ``HIL_LOCAL_CTL`` and serves each with an endpoint of
one ``BatchScheduler``."""

from __future__ import annotations

import os
import socket
import struct
import threading
from collections.abc import Callable

from hil.adapters.batching import ENV_CTL, BatchedEndpoint, BatchScheduler
from hil.adapters.local.shm import ShmReader
from hil.adapters.local.target import serve_socket
from hil.common.errors import TransportError

ATTACH = struct.Struct("<II")  # one control packet per vehicle: vehicle id, flags
HAS_RING = 1  # flag bit 0: a ring descriptor follows the socket's


def _serve_socket(ep: BatchedEndpoint, sock: socket.socket, ring: ShmReader | None) -> None:
    """One vehicle's socket, as ``hil.adapters.local.target.serve_endpoint`` serves its one."""
    serve_socket(ep, sock, ring)


def serve_shared(scheduler: BatchScheduler, make_endpoint: Callable[[], BatchedEndpoint],
                 *, on_vehicle: Callable[[int], None] | None = None) -> int:
    """Target side: take vehicles' sockets from ``HIL_LOCAL_CTL`` and serve each with
    an endpoint from ``make_endpoint``, all on ``scheduler``, until the harness
    closes the control socket and every session has ended. Returns the number of
    vehicles served.

    Raises:
        TransportError: ``HIL_LOCAL_CTL`` is not set (not started by the harness).
    """
    fd_text = os.environ.get(ENV_CTL, "")
    if not fd_text.isdigit():
        raise TransportError(f"{ENV_CTL} is not set: a shared local target is started by the harness "
                             "(hil run with target.shared: true), not by hand")
    ctl = socket.socket(fileno=int(fd_text))
    threads: list[threading.Thread] = []
    scheduler.start()
    try:
        while True:
            try:
                msg, fds, _flags, _addr = socket.recv_fds(ctl, ATTACH.size, 2)
            except OSError:
                break
            if not msg:
                for fd in fds:
                    os.close(fd)
                break
            if len(msg) != ATTACH.size or not fds:
                for fd in fds:
                    os.close(fd)
                continue  # not an attach packet: nothing to serve
            vehicle_id, flags = ATTACH.unpack(msg)
            sock = socket.socket(fileno=fds[0])
            ring = None
            if flags & HAS_RING and len(fds) > 1:
                try:
                    ring = ShmReader(fds[1])  # closes the descriptor; the mapping stays
                except TransportError:
                    ring = None  # frames then come inline: the HELLO does not offer the ring
            if on_vehicle is not None:
                on_vehicle(vehicle_id)
            t = threading.Thread(target=_serve_socket, args=(make_endpoint(), sock, ring),
                                 name=f"vehicle-{vehicle_id}", daemon=True)
            t.start()
            threads.append(t)
        for t in threads:
            t.join()
    finally:
        ctl.close()
        scheduler.stop()
    return len(threads)


__all__ = ["ATTACH", "HAS_RING", "serve_shared"]
