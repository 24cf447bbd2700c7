"""A small harness written for tests that speaks the wire itself over TCP: it connects
to a target that listens, reads what the target sends with the stream decoder, and
sends whatever message it is given, a camera rig's frame sets among them (the harness
does not send rigs yet)."""

from __future__ import annotations

import select
import socket
import time
from collections import deque
from dataclasses import replace

from hil.adapters.wire import protocol
from hil.adapters.wire.messages import CameraInfo, Frame, ImageEncoding, Message
from hil.adapters.wire.stream import StreamDecoder
from hil.common.errors import ProtocolError

CAM = CameraInfo(277.0, 277.0, 160.0, 120.0, 1.3)
TINY = Frame(0, 0, 0, 1, 2, 4, 2, ImageEncoding.RGB8, CAM, 0.0, bytes(24))  # a 4x2 image


def rig_frame(frame_id: int, camera_index: int, camera_count: int, sim_time_ns: int) -> Frame:
    """Camera ``camera_index`` of a set of ``camera_count`` (0: a single camera)."""
    return replace(TINY, frame_id=frame_id, camera_index=camera_index, camera_count=camera_count,
                   sim_time_ns=sim_time_ns)


class WirePeer:
    """One TCP connection to a listening target; ``close`` ends it."""

    def __init__(self, address: str, *, timeout_s: float = 20.0) -> None:
        host, port = address.rsplit(":", 1)
        deadline = time.monotonic() + timeout_s
        while True:  # the target process may not listen yet
            try:
                self.sock = socket.create_connection((host, int(port)), timeout=1.0)
                break
            except OSError:
                if time.monotonic() > deadline:
                    raise
                select.select([], [], [], 0.05)  # no target yet: dial again shortly
        self.sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self._decoder: StreamDecoder[object] = StreamDecoder()
        self._got: deque[Message | ProtocolError | object] = deque()

    def send(self, *msgs: Message) -> None:
        self.sock.sendall(b"".join(protocol.encode(m) for m in msgs))

    def recv(self, timeout_s: float = 5.0) -> Message | ProtocolError | object | None:
        """The next thing the target sent, or None after ``timeout_s``."""
        deadline = time.monotonic() + timeout_s
        while not self._got:
            left = deadline - time.monotonic()
            if left <= 0 or not select.select([self.sock], [], [], left)[0]:
                return None
            data = self.sock.recv(1 << 16)
            if not data:
                return None
            self._got.extend(self._decoder.feed(data))
        return self._got.popleft()

    def recv_a(self, kind: type, timeout_s: float = 5.0) -> object:
        """The next message of ``kind`` (others the target sends meanwhile are skipped)."""
        deadline = time.monotonic() + timeout_s
        while (left := deadline - time.monotonic()) > 0:
            m = self.recv(left)
            if m is None:
                break
            if isinstance(m, kind):
                return m
        raise AssertionError(f"no {kind.__name__} within {timeout_s} s")

    def close(self) -> None:
        self.sock.close()
