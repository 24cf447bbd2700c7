"""The target SDK: serve an AI's ``infer(frame) -> Inference`` over a transport.

An AI developer writes one function and calls ``serve``::

    from adapters.sdk import serve
    from adapters.messages import Inference, Control, DrivingState

    def infer(frame):
        return Inference(DrivingState.SAFE, Control(throttle=0.2))

    serve(infer, target_name="my-ai")

The SDK says HELLO, stamps ``t_rx``, ``t_infer_start``, ``t_infer_end`` and
``t_reply`` on the target's own clock, answers clock-sync requests at once (from
the reader, never queued behind inference) and sends one ESTIMATE per processed
frame. When frames arrive faster than ``infer`` runs, only the newest waiting frame
is processed; the skipped ones are counted (``SdkStats.frames_skipped``) and the
harness sees them as dropped.

Needs only numpy and the chosen transport: no simulator, torch or harness code.
"""

from __future__ import annotations

import os
import socket
import threading
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from adapters import protocol
from adapters.messages import (Bye, ClockId, ErrorMsg, Estimate, Frame, Hello, ImageEncoding,
                               Inference, Message, SyncRequest, SyncResponse)
from timing.clock import Clock, MonotonicClock
from timing.errors import ProtocolError, TransportError

InferFn = Callable[[Frame], Inference]


@dataclass
class SdkStats:
    frames_received: int = 0
    frames_skipped: int = 0
    estimates_sent: int = 0
    sync_answered: int = 0
    protocol_errors: int = 0
    infer_errors: int = 0


def decode_image(frame: Frame) -> np.ndarray:
    """The frame's pixels as an HxWx3 uint8 array in BGR order (OpenCV's).

    Raw RGB8/BGR8 need only numpy; JPEG needs OpenCV (``opencv-python-headless``).

    Raises:
        ProtocolError: the image bytes cannot be decoded (offset 0 of the image).
    """
    if frame.encoding in (ImageEncoding.RGB8, ImageEncoding.BGR8):
        img = np.frombuffer(frame.data, np.uint8).reshape(frame.height, frame.width, 3)
        return img[:, :, ::-1] if frame.encoding == ImageEncoding.RGB8 else img
    try:
        import cv2
    except ImportError as err:  # pragma: no cover - depends on the device's install
        raise ImportError("JPEG frames need OpenCV: pip install opencv-python-headless") from err
    img = cv2.imdecode(np.frombuffer(frame.data, np.uint8), cv2.IMREAD_COLOR)
    if img is None or img.shape[:2] != (frame.height, frame.width):
        raise ProtocolError("JPEG image does not decode to the frame's size", offset=0)
    return img


class _Endpoint:
    """Target side of one connection: reader thread + inference worker."""

    def __init__(self, infer: InferFn, *, send: Callable[[bytes], None], target_name: str,
                 clock: Clock, clock_id: ClockId, clock_resolution_ns: int) -> None:
        self.infer = infer
        self._send_raw = send
        self.clock = clock
        self.stats = SdkStats()
        self.target_name = target_name
        self.clock_id = clock_id
        self.clock_resolution_ns = clock_resolution_ns
        self._send_lock = threading.Lock()
        self._cv = threading.Condition()
        self._pending: tuple[Frame, int] | None = None
        self._stop = False
        self._vehicle_id = 0

    def send(self, msg: Message) -> None:
        buf = protocol.encode(msg)
        with self._send_lock:
            self._send_raw(buf)

    def say_hello(self) -> None:
        self.send(Hello(self.target_name, protocol.VERSION, self.clock_id, self.clock_resolution_ns, 0))

    def on_message(self, item: Message | ProtocolError, t_rx: int) -> None:
        """Reader-thread handler; returns quickly."""
        if isinstance(item, ProtocolError):
            self.stats.protocol_errors += 1
            self.send(ErrorMsg(self._vehicle_id, protocol.ErrorCode.MALFORMED, str(item)[:1000]))
            return
        if isinstance(item, SyncRequest):
            t3 = self.clock.now_ns()
            self.send(SyncResponse(item.vehicle_id, item.seq, item.t1_ns, t_rx, t3))
            self.stats.sync_answered += 1
        elif isinstance(item, Frame):
            self._vehicle_id = item.vehicle_id
            self.stats.frames_received += 1
            with self._cv:
                if self._pending is not None:
                    self.stats.frames_skipped += 1
                self._pending = (item, t_rx)
                self._cv.notify()
        elif isinstance(item, Bye):
            self.stop()

    def stop(self) -> None:
        with self._cv:
            self._stop = True
            self._cv.notify()

    def work(self) -> None:
        """Inference worker: process the newest pending frame, one at a time."""
        while True:
            with self._cv:
                while self._pending is None and not self._stop:
                    self._cv.wait()
                if self._stop:
                    return
                assert self._pending is not None
                frame, t_rx = self._pending
                self._pending = None
            t_start = self.clock.now_ns()
            try:
                result = self.infer(frame)
            except Exception as err:  # the AI's bug must not kill the session
                self.stats.infer_errors += 1
                self.send(ErrorMsg(frame.vehicle_id, protocol.ErrorCode.TARGET_FAILURE, f"infer failed: {type(err).__name__}: {err}"[:1000]))
                continue
            t_end = self.clock.now_ns()
            est = Estimate(frame.vehicle_id, frame.frame_id, result.state, result.control,
                           tuple(result.objects), t_rx, t_start, t_end, self.clock.now_ns())
            try:
                self.send(est)
            except (OSError, TransportError):
                return
            self.stats.estimates_sent += 1


def serve(infer: InferFn, *, target_name: str, transport: str = "local", clock: Clock | None = None,
          clock_id: ClockId = ClockId.MONOTONIC, clock_resolution_ns: int = 1) -> SdkStats:
    """Serve ``infer`` until the harness says BYE or closes the connection.

    Args:
        infer: the AI; called with each frame, returns an ``Inference``.
        target_name: reported in HELLO (at most 64 bytes of UTF-8).
        transport: ``"local"`` (a child of the harness; more transports later).
        clock: the clock to stamp with (default: this host's monotonic clock).

    Returns:
        Counters of what was served.

    Raises:
        TransportError: the transport cannot be used (for example ``HIL_LOCAL_FD``
            is not set because the program was not started by the harness).
    """
    if transport != "local":
        raise TransportError(f"unknown transport {transport!r}; valid: local")
    fd_text = os.environ.get("HIL_LOCAL_FD")
    if not fd_text or not fd_text.isdigit():
        raise TransportError("HIL_LOCAL_FD is not set: a local target is started by the harness "
                             "(hil run), not by hand")
    sock = socket.socket(fileno=int(fd_text))
    ep = _Endpoint(infer, send=sock.sendall, target_name=target_name, clock=clock or MonotonicClock(),
                   clock_id=clock_id, clock_resolution_ns=clock_resolution_ns)
    worker = threading.Thread(target=ep.work, name="infer", daemon=True)
    worker.start()
    decoder = protocol.StreamDecoder()
    try:
        ep.say_hello()
        while not ep._stop:
            try:
                data = sock.recv(1 << 20)
            except OSError:
                break
            t_rx = ep.clock.now_ns()
            if not data:
                break
            for item in decoder.feed(data):
                ep.on_message(item, t_rx)
    finally:
        ep.stop()
        worker.join(timeout=5.0)
        sock.close()
    return ep.stats
