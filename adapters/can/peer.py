"""One side of a vehicle's CAN link on an open bus, shared by the harness's ``CanLink``
and the target's ``serve_endpoint`` (``hil.adapters.can.link`` documents the wire).

A reader thread owns ``bus.recv``: it stamps each frame on the side's ``Clock`` when
``recv`` returns, reassembles ISO-TP (can-isotp's state machine driven frame by frame,
so a message is stamped with its last frame), decodes DBC frames (``hil.adapters.can.dbc``),
sends this side's heartbeat every 250 ms and watches the other side's. A sender thread
runs ISO-TP transmissions (waiting for flow control), so a camera frame in flight never
delays receive stamps. DBC frames are sent at once from the caller's thread.

A ``tap`` sees every CAN frame this side sends or receives, with the side's own stamp
(``tap(msg, t_ns, is_rx)``: a received frame's ``t_ns`` is its receive stamp, a sent
one's the clock right after ``bus.send`` returned), for a bus log (the harness writes
``run.blf``). It runs on the reader and sender threads: it must not block.
"""

from __future__ import annotations

import collections
import errno
import queue
import threading
from collections.abc import Callable
from dataclasses import dataclass

try:
    import can
except ImportError as err:  # pragma: no cover - depends on the install
    raise ImportError("the CAN transport needs python-can: pip install 'python-can>=4.6,<5'") from err
try:
    import isotp
except ImportError as err:  # pragma: no cover - depends on the install
    raise ImportError("the CAN transport needs can-isotp: pip install 'can-isotp>=2.0'") from err

from hil.adapters.can.dbc import MESSAGE_MASK, VEHICLE_MASK, HilCan, Role
from hil.adapters.wire import protocol
from hil.adapters.wire.messages import Bye, Heartbeat, Hello, Message, MsgType
from hil.adapters.wire.receipt import RealtimeMapper
from hil.common.errors import ProtocolError, TransportError
from hil.timing.clock import Clock

#: Sees each frame sent or received: (the frame, its stamp on the side's clock in ns, received).
CanTap = Callable[[can.Message, int, bool], None]

HEARTBEAT_PERIOD_S = 0.25
ISOTP_MAX_MESSAGE = protocol.HEADER_SIZE + protocol.MAX_PAYLOAD
TX_QUEUE_LIMIT = 64  # ISO-TP messages waiting to be sent
SEND_TIMEOUT_S = 0.5
_POLL_MAX_S = 0.1  # longest reader sleep (bounds how long close() waits for it)
_POLL_ACTIVE_S = 0.02  # while an ISO-TP reception runs (its timeouts are checked on wake-up)
_FC_POLL_S = 0.02
_ENOBUFS_WAIT_S = 0.0005
_ENOBUFS_RETRIES = int(SEND_TIMEOUT_S / _ENOBUFS_WAIT_S)
_ISOTP_PARAMS = {"can_fd": True, "tx_data_length": 64, "bitrate_switch": True, "blocksize": 0, "stmin": 0,
                 "max_frame_size": ISOTP_MAX_MESSAGE, "rx_flowcontrol_timeout": 1000,
                 "rx_consecutive_frame_timeout": 1000}


@dataclass
class CanStats:
    """Counters of one side of a CAN link (frames are CAN frames)."""

    frames_sent: int = 0
    frames_received: int = 0
    frames_ignored: int = 0  # not ours: another direction or an unknown id
    isotp_sent: int = 0
    isotp_received: int = 0
    isotp_errors: int = 0
    frames_superseded: int = 0  # camera frames replaced by a newer one before sending
    interface_stamps: int = 0  # frames stamped with the interface's receive time (socketcan's kernel, virtual's send)
    late_stamp_fallbacks: int = 0  # an interface time that could not be the arrival (> 1 s old, or ahead): read time


class CanPeer:
    """One side (``role``) of one vehicle's CAN link on an open bus: a reader thread
    (stamps, ISO-TP reassembly, DBC decoding, heartbeats, watchdog) and an ISO-TP
    sender thread. Messages go to ``deliver(item, t_rx_ns, nbytes)``, ISO-TP payloads
    to ``deliver_bytes(data, t_rx_ns)``."""

    def __init__(self, *, role: Role, bus: can.BusABC, owns_bus: bool, vehicle_id: int, clock: Clock,
                 deliver: Callable[[Message | ProtocolError, int, int], None],
                 deliver_bytes: Callable[[bytes, int], None], on_error: Callable[[str], None],
                 on_silent: Callable[[str], None], on_fatal: Callable[[str], None],
                 heartbeat_timeout_s: float, camera_over: str = "isotp", tap: CanTap | None = None) -> None:
        self.role, self.bus, self._owns_bus, self.clock = role, bus, owns_bus, clock
        self._tap = tap
        self.vehicle_id = vehicle_id
        self.codec = HilCan(role=role, vehicle_id=vehicle_id)
        self.stats = CanStats()
        self._deliver, self._deliver_bytes = deliver, deliver_bytes
        self._on_error, self._on_silent, self._on_fatal = on_error, on_silent, on_fatal
        self._timeout_ns = int(heartbeat_timeout_s * 1e9)
        self._camera_over = camera_over
        # The harness stamps with socketcan's Message.timestamp (the kernel's receive
        # time) and virtual's (the send), both on the host's realtime clock: mapped, they
        # are the arrival however late the reader runs. Other adapters' clocks are not
        # the host's, and a target's clock need not run with it: read time there.
        module = type(bus).__module__
        host_clock = module.endswith((".socketcan.socketcan", ".virtual"))
        self._mapper = RealtimeMapper(clock) if host_clock and role is Role.HARNESS else None
        self._stop = threading.Event()
        self._send_lock = threading.Lock()
        self._heard_ns: int | None = None
        self._hello: list[tuple[int, bytes]] | None = None  # a target's HELLO frames, repeated
        self.peer_said_bye = False
        self.failure: str | None = None  # why the bus failed under this side
        self._iso_in: collections.deque[isotp.CanMessage] = collections.deque()
        self._fc_in: queue.Queue[isotp.CanMessage] = queue.Queue(maxsize=64)
        self._tx_cv = threading.Condition()
        self._tx_box: collections.deque[tuple[bytes, bool]] = collections.deque()
        self._tx_busy = False
        c = self.codec
        self._rx_stack = isotp.TransportLayerLogic(
            rxfn=self._iso_rx, txfn=self._iso_tx,
            address=isotp.Address(isotp.AddressingMode.Normal_29bits, txid=c.isotp_rx_fc, rxid=c.isotp_rx_data),
            error_handler=self._iso_error, params=_ISOTP_PARAMS)
        self._tx_stack = isotp.TransportLayerLogic(
            rxfn=self._fc_rx, txfn=self._iso_tx,
            address=isotp.Address(isotp.AddressingMode.Normal_29bits, txid=c.isotp_tx_data, rxid=c.isotp_tx_fc),
            error_handler=self._iso_error, params=_ISOTP_PARAMS)
        name = f"can-{role.value}-{vehicle_id}"
        self._reader = threading.Thread(target=self._read_loop, name=f"{name}-rx", daemon=True)
        self._sender = threading.Thread(target=self._send_loop, name=f"{name}-isotp-tx", daemon=True)

    def start(self) -> None:
        self._reader.start()
        self._sender.start()

    # -- sending -------------------------------------------------------------

    def send_bytes(self, buf: bytes) -> None:
        """Send one PROTOCOL.md message (or raw bytes): as DBC frames when they carry it,
        else over ISO-TP (queued for the sender thread).

        Raises:
            TransportError: the bus failed, the ISO-TP queue is full, or a camera frame
                with ``camera_over="none"``.
        """
        if self._stop.is_set():
            raise TransportError("CAN link is closed")
        is_frame = len(buf) >= 6 and buf[:4] == protocol.MAGIC and buf[5] == MsgType.FRAME
        msg = None if is_frame else _decode_small(buf)
        frames = self.codec.encode(msg) if msg is not None else None
        if frames is not None:
            for f in frames:
                self._send_can(f.arbitration_id, f.data)
            if isinstance(msg, Hello):
                self._hello = [(f.arbitration_id, f.data) for f in frames]
            return
        if is_frame and self._camera_over == "none":
            raise TransportError("camera_over='none': camera frames travel over another transport (a mixed "
                                 "target), not this CAN link")
        with self._tx_cv:
            if is_frame:
                for i, (_, waiting_is_frame) in enumerate(self._tx_box):
                    if waiting_is_frame:  # newest wins: replace the frame still waiting
                        self._tx_box[i] = (buf, True)
                        self.stats.frames_superseded += 1
                        return
            if len(self._tx_box) >= TX_QUEUE_LIMIT:
                raise TransportError(f"ISO-TP send queue full ({TX_QUEUE_LIMIT} messages waiting): the CAN bus "
                                     f"does not carry what is sent; see hil.adapters.can.capacity.bus_capacity")
            self._tx_box.append((buf, is_frame))
            self._tx_cv.notify()

    def wait_sent(self, timeout_s: float) -> bool:
        """Wait until no ISO-TP message is waiting or in transmission; False on timeout."""
        with self._tx_cv:
            return self._tx_cv.wait_for(lambda: not self._tx_box and not self._tx_busy, timeout_s)

    def _send_can(self, arbitration_id: int, data: bytes) -> None:
        msg = can.Message(arbitration_id=arbitration_id, data=data, is_extended_id=True, is_fd=True,
                          bitrate_switch=True)
        with self._send_lock:
            for attempt in range(_ENOBUFS_RETRIES + 1):
                try:
                    self.bus.send(msg, timeout=SEND_TIMEOUT_S)
                    break
                except can.CanOperationError as err:
                    # socketcan: ENOBUFS while the adapter's transmit queue is full.
                    if err.error_code != errno.ENOBUFS or attempt == _ENOBUFS_RETRIES:
                        raise TransportError(f"CAN send failed: {err}") from err
                    self._stop.wait(_ENOBUFS_WAIT_S)
                except (can.CanError, OSError) as err:
                    raise TransportError(f"CAN send failed: {err}") from err
            if self._tap is not None:  # under the send lock: frames are tapped in the order they left
                self._tap(msg, self.clock.now_ns(), False)
        self.stats.frames_sent += 1

    def _send_loop(self) -> None:
        stack = self._tx_stack
        while True:
            with self._tx_cv:
                self._tx_busy = False
                self._tx_cv.notify_all()
                while not self._tx_box and not self._stop.is_set():
                    self._tx_cv.wait()
                if self._stop.is_set():
                    return
                buf, _ = self._tx_box.popleft()
                self._tx_busy = True
            while not self._fc_in.empty():  # stale flow control of an earlier transfer
                self._fc_in.get_nowait()
            errors = self.stats.isotp_errors
            try:
                stack.send(buf)
                while stack.transmitting() and not self._stop.is_set():
                    delay = stack.next_cf_delay()
                    if delay is None:
                        stack.process(rx_timeout=_FC_POLL_S)  # waits in _fc_rx for flow control
                    else:
                        if delay > 0:
                            self._stop.wait(delay)
                        stack.process(do_rx=False)
            except (TransportError, ValueError, RuntimeError) as err:
                self._iso_error(err)
                stack.reset()
            if self.stats.isotp_errors == errors:
                self.stats.isotp_sent += 1

    # -- ISO-TP plumbing -----------------------------------------------------

    def _iso_rx(self, timeout: float) -> isotp.CanMessage | None:
        del timeout  # frames are pushed by the reader before each process()
        return self._iso_in.popleft() if self._iso_in else None

    def _fc_rx(self, timeout: float) -> isotp.CanMessage | None:
        try:
            return self._fc_in.get(timeout=timeout)
        except queue.Empty:
            return None

    def _iso_tx(self, m: isotp.CanMessage) -> None:
        self._send_can(m.arbitration_id, bytes(m.data))

    def _iso_error(self, err: Exception) -> None:
        self.stats.isotp_errors += 1
        self._on_error(f"ISO-TP: {type(err).__name__}: {err}")

    # -- receiving -----------------------------------------------------------

    def _read_loop(self) -> None:
        now = next_beat = self.clock.now_ns()
        period = int(HEARTBEAT_PERIOD_S * 1e9)
        while not self._stop.is_set():
            # Sleep in recv until the next heartbeat or watchdog deadline: few wake-ups,
            # so an in-process peer's threads are rarely made to hand over the GIL.
            due = next_beat if self._heard_ns is None else min(next_beat, self._heard_ns + self._timeout_ns + 1)
            wait_s = min(_POLL_ACTIVE_S if self._rx_stack.is_rx_active() else _POLL_MAX_S, max(0, due - now) / 1e9)
            try:
                msg = self.bus.recv(timeout=wait_s)
            except (can.CanError, OSError, ValueError) as err:
                self._fail(f"CAN receive failed: {err}")
                return
            now = self.clock.now_ns()
            try:
                if msg is not None:
                    arrival = self._arrival(msg, now)
                    if self._tap is not None:
                        self._tap(msg, arrival, True)
                    self._on_frame(msg, arrival)
                if self._heard_ns is not None and now - self._heard_ns > self._timeout_ns:
                    self._heard_ns = None
                    self._on_silent(f"no CAN frame from the {'target' if self.role is Role.HARNESS else 'harness'} "
                                    f"(vehicle {self.vehicle_id}) for {self._timeout_ns / 1e9:g} s: it stopped "
                                    f"sending heartbeats (crashed, powered off or unplugged)")
                if now >= next_beat:
                    next_beat = now + period
                    self._beat(now)
                if self._rx_stack.is_rx_active():
                    self._rx_stack.process()  # consecutive-frame timeout
            except TransportError as err:
                self._fail(str(err))
                return

    def _arrival(self, msg: can.Message, read_ns: int) -> int:
        """When ``msg`` arrived, on our clock: the interface's receive time where it is
        on the host's realtime clock (a message of several frames: its last frame's),
        else when ``recv`` returned (``read_ns``)."""
        if self._mapper is None or not msg.timestamp:
            return read_ns
        t, now = self._mapper.map(round(msg.timestamp * 1e9))
        if not now - 1_000_000_000 <= t <= now:
            self.stats.late_stamp_fallbacks += 1
            return read_ns
        self.stats.interface_stamps += 1
        return t

    @property
    def failed(self) -> bool:
        return self.failure is not None

    def _fail(self, reason: str) -> None:
        if not self._stop.is_set():
            self.failure = reason
            self._on_fatal(reason)

    def _beat(self, now: int) -> None:
        if self.role is Role.TARGET and self._heard_ns is None and self._hello is not None:
            for aid, data in self._hello:
                self._send_can(aid, data)
            return
        (f,) = self.codec.encode(Heartbeat(self.vehicle_id, now)) or []
        self._send_can(f.arbitration_id, f.data)

    def _on_frame(self, msg: can.Message, t_rx: int) -> None:
        aid = msg.arbitration_id
        if msg.is_error_frame or msg.is_remote_frame or not msg.is_extended_id or aid & VEHICLE_MASK != self.vehicle_id:
            self.stats.frames_ignored += 1
            return
        base, c = aid & MESSAGE_MASK, self.codec
        if base == c.isotp_rx_data & MESSAGE_MASK:
            # isotp takes any bytes-like data; python-can's is a bytearray.
            self._iso_in.append(isotp.CanMessage(arbitration_id=aid, data=msg.data,  # type: ignore[arg-type]
                                                 extended_id=True, is_fd=msg.is_fd,
                                                 bitrate_switch=msg.bitrate_switch))
            self._rx_stack.process()
            while self._rx_stack.available():
                data = self._rx_stack.recv()
                assert data is not None
                self.stats.isotp_received += 1
                self._deliver_bytes(bytes(data), t_rx)
        elif base == c.isotp_tx_fc & MESSAGE_MASK:
            try:
                self._fc_in.put_nowait(isotp.CanMessage(arbitration_id=aid, data=msg.data,  # type: ignore[arg-type]
                                                        extended_id=True, is_fd=msg.is_fd,
                                                        bitrate_switch=msg.bitrate_switch))
            except queue.Full:
                pass
        elif c.is_inbound(aid):
            for item in c.decode(aid, bytes(msg.data)):
                if isinstance(item, Bye):
                    self.peer_said_bye = True
                self._deliver(item, t_rx, len(msg.data))
        else:
            self.stats.frames_ignored += 1
            return
        self.stats.frames_received += 1
        first = self._heard_ns is None
        self._heard_ns = t_rx
        if first and self.role is Role.TARGET and self._hello is not None:
            for aid_, hello in self._hello:  # answer a (re)appearing harness at once
                self._send_can(aid_, hello)

    def close(self) -> None:
        """Stop both threads and, when this peer opened it, shut the bus down. Idempotent."""
        self._stop.set()
        with self._tx_cv:
            self._tx_cv.notify_all()
        for t in (self._reader, self._sender):
            if t.is_alive() and t is not threading.current_thread():
                t.join(timeout=2.0)
        if self._owns_bus:
            self.bus.shutdown()


def _decode_small(buf: bytes) -> Message | None:
    try:
        return protocol.decode(buf)
    except ProtocolError:
        return None


__all__ = ["CanPeer", "CanStats", "CanTap", "HEARTBEAT_PERIOD_S", "ISOTP_MAX_MESSAGE"]
