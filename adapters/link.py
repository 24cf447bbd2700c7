"""The harness side of a transport: one small interface, shared work in the base.

A ``Link`` sends frames and clock-sync probes to one target and receives what it
answers. The base class stamps (``t_tx`` before the hand-off, ``t0'`` on receipt by
the transport's reader), decodes, counts protocol errors and drops, and keeps
received messages in bounded queues. A transport fills four private hooks:

* ``_open()``            connect / spawn; start delivering bytes or messages
* ``_send_bytes(data)``  hand one encoded message to the wire
* ``_close_transport()`` release everything (idempotent)
* and calls ``self._on_bytes(data, t_rx_ns)`` (stream transports) or
  ``self._on_message_bytes(data, t_rx_ns)`` (message transports) from its reader.

Transports are chosen by name (``open_link``); an unknown name lists valid ones.
"""

from __future__ import annotations

import queue
import threading
from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import NoReturn

from hil.adapters import transports
from hil.adapters.impair import LinkImpairment
from hil.adapters.wire import protocol
from hil.adapters.wire.messages import (Bye, CameraInfo, Command, ErrorMsg, Estimate, Frame, Hello, ImageEncoding,
                                        Message, SyncRequest, SyncResponse)
from hil.adapters.wire.receipt import Receipt, StreamReader
from hil.adapters.wire.stream import StreamDecoder
from hil.common.errors import ProtocolError, TargetError, TransportError
from hil.timing.clock import Clock
from hil.timing.sync import SyncSample


@dataclass(frozen=True)
class Received:
    """A message, the harness-clock instant (ns) its last byte arrived, the vehicle id
    of the link it came through, and how much earlier the arrival may have been: the
    truth lies in ``[t_rx_ns - rx_uncertainty_ns, t_rx_ns]`` (``hil.adapters.wire.receipt``)."""

    msg: Message
    t_rx_ns: int
    link_vehicle_id: int = 0
    rx_uncertainty_ns: int = 0


@dataclass(frozen=True)
class ProtocolFault:
    """A message from the target that could not be decoded: delivered in order with
    the messages (as ``Received.msg``) so the run records it as an event and replies
    ERROR (PROTOCOL.md section 8)."""

    detail: str
    offset: int


@dataclass
class LinkStats:
    frames_sent: int = 0
    bytes_sent: int = 0
    messages_received: int = 0
    bytes_received: int = 0
    protocol_errors: int = 0
    rx_dropped: int = 0
    target_errors: int = 0
    last_error: str | None = None
    impairment: dict[str, dict[str, int]] | None = None  # adapters/impair.py counts per direction, if set
    transport: dict[str, object] | None = None  # counters only one transport has (ros2: Ros2Link.ros2_stats)
    # Connections closed before the session because the peer was not this run's target
    # (tcp: no proof of the run's token, or another name than target.expect_name), and
    # the first few different ones, each "peer address: why".
    connections_refused: int = 0
    refused: list[str] = field(default_factory=list)


class Link(ABC):
    """Harness side of one transport to one target (vehicle).

    Use as a context manager; ``close()`` is idempotent and safe on a half-built
    object. Not thread-safe for sending: the sim loop is the only sender.
    """

    transport_name = "abstract"

    def __init__(self, *, vehicle_id: int, clock: Clock, rx_queue_size: int = 1024,
                 rx_queue: queue.Queue[Received] | None = None) -> None:
        """``rx_queue``: deliver received messages into this (shared, bounded) queue
        instead of a private one, so one loop can wait on many links."""
        self.vehicle_id = vehicle_id
        self.clock = clock
        self.stats = LinkStats()
        self.hello: Hello | None = None
        self._rx: queue.Queue[Received] = rx_queue if rx_queue is not None else queue.Queue(maxsize=rx_queue_size)
        self._sync_rx: queue.Queue[Received] = queue.Queue(maxsize=64)
        self._decoder: StreamDecoder[NoReturn] = StreamDecoder()
        self._lock = threading.Lock()
        self._closed = False
        self._peer_gone = threading.Event()
        self.peer_gone_reason: str | None = None
        self._sync_seq = 0
        self._command_seq = 0
        self._impair: LinkImpairment | None = None
        self._deliver: Callable[[Received], None] | None = None
        self._started = False
        self._give_up: Callable[[], str | None] | None = None

    def give_up_when(self, why: Callable[[], str | None] | None) -> None:
        """While ``open`` waits for HELLO, stop as soon as ``why()`` gives a reason
        (e.g. the target process the run started has exited), not at the timeout."""
        self._give_up = why

    def set_impairment(self, stage: LinkImpairment) -> None:
        """Put a link-fault stage (adapters/impair.py) on the send and receive paths;
        call before ``open()``. The link closes it."""
        self._impair = stage
        self.stats.impairment = stage.counts
        stage.bind(send=self._send_bytes, put=self._enqueue, name=f"impair-v{self.vehicle_id}")

    @property
    def impairment(self) -> LinkImpairment | None:
        """The link-fault stage, if one was set."""
        return self._impair

    # -- lifecycle -----------------------------------------------------------

    def start(self) -> None:
        """Start the transport now (a local target: its process is spawned, from the
        calling thread) without waiting for the HELLO; :meth:`open` then only waits.
        So a run starts many targets at once and waits for them together.

        Raises:
            TargetError: the target could not start.
        """
        if not self._started:
            self._started = True
            self._open()

    def open(self, *, hello_timeout_s: float) -> Hello:
        """Connect (or start, unless :meth:`start` did) the target and wait for its
        HELLO.

        Raises:
            TargetError: the target could not start or did not say hello in time.
            TransportError: the transport could not connect.
        """
        self.start()
        deadline = self.clock.now_ns() + int(hello_timeout_s * 1e9)
        while True:
            remaining = (deadline - self.clock.now_ns()) / 1e9
            if remaining <= 0:
                raise TargetError(self._no_hello_reason(hello_timeout_s))
            try:
                r = self._rx.get(timeout=min(remaining, 0.05))
            except queue.Empty:
                if self._peer_gone.is_set():
                    raise TargetError(self._no_hello_reason(hello_timeout_s)) from None
                if self._closed:  # closed from another thread (the run is being ended)
                    raise TargetError("the link was closed while waiting for the target's hello") from None
                if self._give_up is not None and (why := self._give_up()):
                    raise TargetError(f"stopped waiting for the target's hello: {why}") from None
                continue
            if r.link_vehicle_id != self.vehicle_id:
                self._rx.put(r)  # another link's message: give it back
                continue
            if isinstance(r.msg, Hello):
                if r.msg.protocol_version != protocol.VERSION:
                    try:
                        self._send_bytes(protocol.encode(ErrorMsg(self.vehicle_id, protocol.ErrorCode.UNSUPPORTED_VERSION,
                                                                  f"harness speaks protocol version {protocol.VERSION}")))
                    except (TransportError, OSError):
                        pass
                    raise TargetError(f"target speaks protocol version {r.msg.protocol_version}; "
                                      f"this harness speaks {protocol.VERSION}")
                self.hello = r.msg
                return r.msg

    def _no_hello_reason(self, timeout_s: float) -> str:
        if self.peer_gone_reason:
            return f"target went away before saying hello: {self.peer_gone_reason}"
        return f"target did not say hello within {timeout_s:g} s"

    @property
    def alive(self) -> bool:
        """False once the peer has gone (EOF, process exit, liveliness lost)."""
        return not self._peer_gone.is_set()

    def close(self) -> None:
        if getattr(self, "_closed", True):
            return
        self._closed = True
        if getattr(self, "_impair", None) is not None:
            self._impair.close()  # type: ignore[union-attr]  # in-flight messages go down with the link
        try:
            if self.alive:
                try:
                    self._send_bytes(protocol.encode(Bye(self.vehicle_id, "harness closing")))
                except (TransportError, OSError):
                    pass
        finally:
            self._close_transport()

    def __enter__(self) -> Link:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- sending -------------------------------------------------------------

    def send_frame(self, *, frame_id: int, sim_time_ns: int, t0_ns: int, width: int, height: int,
                   encoding: ImageEncoding, camera: CameraInfo,
                   ego_speed_mps: float, data: bytes, camera_index: int = 0, camera_count: int = 0) -> int:
        """Stamp ``t_tx`` (harness clock, ns), encode and send one frame; returns t_tx.
        ``camera_index``/``camera_count``: its camera and frame set (PROTOCOL.md
        4.2.1; 0, 0: a single camera).

        Raises:
            TransportError: the peer is gone or the write failed.
        """
        t_tx = self.clock.now_ns()
        frame = Frame(self.vehicle_id, frame_id, sim_time_ns, t0_ns, t_tx, width, height,
                      encoding, camera, ego_speed_mps, data, camera_index=camera_index, camera_count=camera_count)
        buf = protocol.encode(frame)
        self._send_checked(buf)
        self.stats.frames_sent += 1
        return t_tx

    def send_sync_request(self) -> SyncRequest:
        """Send one clock-sync probe stamped with t1 (harness clock)."""
        self._sync_seq += 1
        req = SyncRequest(self.vehicle_id, self._sync_seq, self.clock.now_ns())
        self._send_checked(protocol.encode(req))
        return req

    def send_error(self, code: int, text: str) -> None:
        """Tell the target that something it sent was bad (ERROR, PROTOCOL.md section 8).

        Raises:
            TransportError: the peer is gone.
        """
        self._send_checked(protocol.encode(ErrorMsg(self.vehicle_id, int(code), text[:1000])))

    def send_command(self, text: str) -> Command:
        """Send one COMMAND (a line of text for the target's control software, e.g.
        ``"swap detector cv"``) stamped with the harness clock; returns it. The
        target's reply, a ``Command`` with the same ``seq``, arrives through ``recv``.

        Raises:
            TransportError: the target's HELLO did not announce ``CAP_COMMANDS``, or
                the peer is gone.
            ProtocolError: ``text`` is over ``MAX_COMMAND_LEN`` bytes of UTF-8.
        """
        if self.hello is None or not self.hello.capabilities & protocol.CAP_COMMANDS:
            name = self.hello.target_name if self.hello else "the target"
            raise TransportError(f"{name} accepts no commands (its HELLO does not announce CAP_COMMANDS)")
        self._command_seq += 1
        cmd = Command(self.vehicle_id, self._command_seq, text, self.clock.now_ns())
        self._send_checked(protocol.encode(cmd))
        return cmd

    def sync_exchange(self, *, timeout_s: float = 0.5) -> SyncSample | None:
        """One blocking 4-timestamp exchange; None if no answer in ``timeout_s``."""
        req = self.send_sync_request()
        deadline = self.clock.now_ns() + int(timeout_s * 1e9)
        while (remaining := (deadline - self.clock.now_ns()) / 1e9) > 0:
            try:
                r = self._sync_rx.get(timeout=remaining)
            except queue.Empty:
                break
            m = r.msg
            if isinstance(m, SyncResponse) and m.seq == req.seq:
                return SyncSample(m.t1_ns, m.t2_target_ns, m.t3_target_ns, r.t_rx_ns, seq=m.seq)
        return None

    def send_raw(self, data: bytes) -> None:
        """Send bytes as they are, unchecked: for conformance tests and diagnostics
        (for example, to see how a target handles a corrupt message)."""
        self._send_checked(data)

    def _send_checked(self, buf: bytes) -> None:
        if self._closed:
            raise TransportError("link is closed")
        if not self.alive:
            raise TransportError(f"target is gone: {self.peer_gone_reason}")
        if self._impair is not None:
            self._impair.send(buf)  # now, or at its due time from the stage's thread
        else:
            self._send_bytes(buf)
        self.stats.bytes_sent += len(buf)

    # -- receiving -----------------------------------------------------------

    def sync_samples(self) -> list[SyncSample]:
        """Answers to earlier ``send_sync_request`` calls, without waiting."""
        out: list[SyncSample] = []
        while True:
            try:
                r = self._sync_rx.get_nowait()
            except queue.Empty:
                return out
            m = r.msg
            if isinstance(m, SyncResponse):
                out.append(SyncSample(m.t1_ns, m.t2_target_ns, m.t3_target_ns, r.t_rx_ns, seq=m.seq))

    def recv(self, *, timeout_s: float) -> Received | None:
        """Next received estimate/heartbeat/error, or None after ``timeout_s``.

        A timeout is not an error: it returns None (callers decide what it means).
        """
        try:
            if timeout_s <= 0:
                return self._rx.get_nowait()
            return self._rx.get(timeout=timeout_s)
        except queue.Empty:
            return None

    def deliver_to(self, fn: Callable[[Received], None] | None) -> None:
        """Hand every received message but clock-sync answers (estimates, errors,
        command replies, protocol faults) to ``fn`` on the thread that stamped and
        decoded it, the moment it is decoded, instead of queueing it for ``recv``: the
        harness handles an estimate where it arrived, with no hand-off to another
        thread. What was queued before is handed over first; ``None`` queues again.
        ``fn`` must not block for long: it holds up this link's reading."""
        pending: list[Received] = []
        while True:
            try:
                pending.append(self._rx.get_nowait())
            except queue.Empty:
                break
        for r in pending:
            if fn is not None:
                fn(r)
        self._deliver = fn

    def _on_bytes(self, data: bytes | bytearray | memoryview, t_rx_ns: int) -> None:
        """Reader-thread entry for stream transports: decode and dispatch."""
        self.stats.bytes_received += len(data)
        for item in self._decoder.feed(data):
            self._dispatch(item, t_rx_ns)

    def _on_receipt(self, r: Receipt[NoReturn]) -> None:
        """Reader-thread entry for stream transports read one message at a time
        (``hil.adapters.wire.receipt.StreamReader``): each item with the read's own stamp."""
        self.stats.bytes_received += r.nbytes
        for item in r.items:
            self._dispatch(item, r.t_rx_ns, r.uncertainty_ns)

    def _read_stream(self, reader: StreamReader[NoReturn], *, failed: Callable[[OSError], str],
                     ended: Callable[[], str]) -> None:
        """A stream transport's reader loop: every message as it is read, until the
        peer ends the stream (``ended()``: why) or the read fails (``failed(err)``:
        why, unless the link was closed)."""
        while True:
            try:
                r = reader.next()
            except OSError as err:
                if not self._closed:
                    self._mark_gone(failed(err))
                break
            if r is None:
                self._mark_gone(ended())
                break
            self._on_receipt(r)

    def _on_message_bytes(self, data: bytes, t_rx_ns: int) -> None:
        """Reader-thread entry for message transports (one message per call)."""
        self.stats.bytes_received += len(data)
        try:
            item: Message | ProtocolError = protocol.decode(data)
        except ProtocolError as err:
            item = err
        self._dispatch(item, t_rx_ns)

    def _dispatch(self, item: Message | ProtocolError, t_rx_ns: int, uncertainty_ns: int = 0) -> None:
        if isinstance(item, ProtocolError):
            self.stats.protocol_errors += 1
            self.stats.last_error = str(item)
            fault = ProtocolFault(str(item), item.offset)
            self._enqueue(self._rx, Received(fault, t_rx_ns, self.vehicle_id, uncertainty_ns))  # type: ignore[arg-type]
            return
        self.stats.messages_received += 1
        if isinstance(item, ErrorMsg):
            self.stats.target_errors += 1
            self.stats.last_error = f"target error {item.code}: {item.message}"
        if isinstance(item, Bye):
            self._mark_gone(f"target said bye ({item.reason or 'no reason given'})")
            return
        target = self._sync_rx if isinstance(item, SyncResponse) else self._rx
        r = Received(item, t_rx_ns, self.vehicle_id, uncertainty_ns)
        if self._impair is not None and self._impair.receive(r, target):
            return  # queued at its due time, stamped with the release instant
        self._enqueue(target, r)

    def _enqueue(self, target: queue.Queue[Received], r: Received) -> None:
        deliver = self._deliver
        if deliver is not None and target is self._rx:
            deliver(r)
            return
        try:
            target.put_nowait(r)
        except queue.Full:
            # Counted, never silent; the consumer is far behind, so the oldest
            # message is the least useful one.
            self.stats.rx_dropped += 1
            try:
                target.get_nowait()
                target.put_nowait(r)
            except (queue.Empty, queue.Full):
                pass

    def _refuse(self, peer: str, why: str) -> None:
        """Count (and name the first few) connections refused before the session."""
        self.stats.connections_refused += 1
        if len(self.stats.refused) < 8 and not any(r.endswith(f": {why}") for r in self.stats.refused):
            self.stats.refused.append(f"{peer}: {why}")

    def _mark_gone(self, reason: str) -> None:
        if not self._peer_gone.is_set():
            self.peer_gone_reason = reason
            self._peer_gone.set()

    # -- transport hooks -----------------------------------------------------

    @abstractmethod
    def _open(self) -> None: ...

    @abstractmethod
    def _send_bytes(self, data: bytes) -> None: ...

    @abstractmethod
    def _close_transport(self) -> None: ...


TRANSPORTS = transports.NAMES  # the transport names, from the table in hil.adapters.transports


def open_link(transport: str | transports.Transport, *, options: object = None, **kwargs: object) -> Link:
    """Build the link for ``transport`` by name (not yet opened). The link class is
    looked up in :data:`hil.adapters.transports.BACKENDS` and its module imported only
    now, so zenoh and python-can stay optional and this module imports no transport.

    Args:
        options: the transport's options model (``transports.options_class``, e.g. a
            ``ZenohOptions``); None: its defaults.
        kwargs: what the link takes besides: ``vehicle_id``, ``clock``, ``rx_queue``
            and the run's hooks of that transport (a local link's ``command``, a CAN
            bus's ``tap``, a tcp link's ``abandon``).

    Raises:
        TransportError: unknown transport name (listing the valid ones), or options
            of another model.
    """
    cls: Callable[..., Link] = transports.link_class(transport)
    if options is not None:
        model = transports.options_class(transport)
        if not isinstance(options, model):
            raise TransportError(f"{transports.transport_of(transport).value} link: options must be a "
                                 f"{model.__name__}, not {type(options).__name__}")
        kwargs["options"] = options
    return cls(**kwargs)


__all__ = ["Estimate", "Link", "LinkStats", "Received", "SyncSample", "open_link"]
