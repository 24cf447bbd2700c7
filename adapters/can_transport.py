"""The CAN transport: a device on a CAN FD bus (python-can, cantools, can-isotp).

Two ways over the wire (PROTOCOL.md section 10.3 has the full specification, ``hil.dbc``
the frames, ``hil.adapters.can_dbc`` the id layout ``P << 26 | M << 16 | vehicle``):

================  =========  ===========================================  =========
message           direction  on CAN                                       priority
================  =========  ===========================================  =========
ESTIMATE          T -> H     HIL_ESTIMATE (16 B), HIL_ESTIMATE_OBJECT     0, 2
                             (48 B) per object, HIL_TARGET_TIMESTAMPS
                             (48 B) last; more than 8 objects: ISO-TP
SYNC_REQUEST      H -> T     HIL_SYNC_REQUEST (12 B)                      1
SYNC_RESPONSE     T -> H     HIL_SYNC_RESPONSE (32 B)                     1
HEARTBEAT         both       HIL_HEARTBEAT_HARNESS / _TARGET (8 B),       3
                             every 250 ms from each side
HELLO             T -> H     HIL_HELLO (64 B), name <= 52 B               4
ERROR, BYE        both       HIL_ERROR_* / HIL_BYE_* (64 B), text <= 60 B 4
FRAME (camera)    H -> T     ISO-TP, PROTOCOL.md bytes                    6 (FC 5)
anything else     both       ISO-TP, PROTOCOL.md bytes                    6 (FC 5)
================  =========  ===========================================  =========

"Anything else": a message the DBC frames cannot carry exactly (see
``hil.adapters.can_dbc``) and bytes that are not a valid message (``Link.send_raw``).
ISO-TP (ISO 15765-2) runs on CAN FD 64-byte frames, block size 0, STmin 0, with one
address pair per vehicle per direction: HIL_ISOTP_UP_DATA/UP_FC (harness -> target)
and HIL_ISOTP_DOWN_DATA/DOWN_FC (target -> harness); ``max_frame_size`` is
``HEADER_SIZE + MAX_PAYLOAD``. The link needs CAN FD: ``fd=False`` is refused.

Liveness: each side sends a heartbeat every 250 ms. A target sends HELLO instead until
it hears the harness, and answers the first frame it hears with HELLO at once, so a
harness that starts later still gets one. The harness marks the target gone after
``heartbeat_timeout_s`` (0.75 s, three periods) without a frame from it, so a vanished
device is noticed within 1 s.

Receive stamps: a message is stamped with its (last) frame's arrival. On the harness
side that is python-can's ``Message.timestamp`` where it is on the host's realtime
clock (socketcan: the kernel's receive time; virtual: the send), mapped onto the
link's ``Clock`` (``hil.adapters.receipt.RealtimeMapper``); otherwise, and on the
target side, the moment ``bus.recv`` returns.

Camera frames are newest-wins: while one is in transmission, a newer frame replaces
the one waiting (``CanLink.frames_superseded`` counts them; the harness sees them as
dropped). ``camera_over="none"`` is a mixed target: frames travel over Zenoh
(``hil.adapters.mixed``) and sending one here raises.

python-can's ``virtual`` interface works within one process and has no bit timing
(``hil.adapters.can_capacity`` gives a real bus's limits). Only buses on this machine are
accepted (``hil.adapters.can_interfaces``): network interfaces would send frames off it.
"""

from __future__ import annotations

import itertools
import queue
import sys
import threading
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

try:
    import can
except ImportError as err:  # pragma: no cover - depends on the install
    raise ImportError("the CAN transport needs python-can: pip install 'python-can>=4.6,<5'") from err

from hil.adapters import protocol
from hil.adapters.can_capacity import CapacityReport, bus_capacity
from hil.adapters.can_dbc import MAX_VEHICLE_ID, VEHICLE_MASK, Role
from hil.adapters.can_interfaces import LOCAL_INTERFACES
from hil.adapters.can_peer import HEARTBEAT_TIMEOUT_S, CanPeer, CanStats, CanTap
from hil.adapters.link import Link, LinkStats, Received
from hil.adapters.messages import Hello, Message
from hil.adapters.sdk import (add_stats, announce_line, fresh_endpoint, said_bye, serving, session_line,
                              stop_on_sigterm)
from hil.common.errors import ConfigError, ProtocolError, TransportError
from hil.timing.clock import Clock

if TYPE_CHECKING:
    from hil.adapters.sdk import Endpoint

def check_interface(interface: str) -> None:
    """Raise ``ConfigError`` unless ``interface`` is a local bus (``LOCAL_INTERFACES``)."""
    if interface in LOCAL_INTERFACES:
        return
    valid = ", ".join(LOCAL_INTERFACES)
    if interface not in can.VALID_INTERFACES:
        raise ConfigError(f"unknown CAN interface {interface!r}; valid: {valid}")
    raise ConfigError(f"CAN interface {interface!r} is refused: it is not a bus on this machine, and a network "
                      f"interface would send CAN frames off this machine. Use 'virtual' (in-process tests), "
                      f"'socketcan' (vcan0, can0) or an adapter's interface ({valid})")


def interface_of(bus: can.BusABC) -> str | None:
    """The python-can interface name of an open bus object, when python-can has one."""
    from can.interfaces import BACKENDS

    mod, cls = type(bus).__module__, type(bus).__name__
    return next((name for name, (m, c) in BACKENDS.items() if mod.startswith(m) and c == cls), None)


def _check_options(*, interface: str, vehicle_id: int, bitrate: int, data_bitrate: int, fd: bool) -> None:
    check_interface(interface)
    if not 0 <= vehicle_id <= MAX_VEHICLE_ID:
        raise ConfigError(f"vehicle_id={vehicle_id}: the CAN id carries vehicle ids 0..{MAX_VEHICLE_ID}")
    if not fd:
        raise ConfigError("fd=False: the CAN transport needs CAN FD (its DBC frames are up to 64 bytes); "
                          "use an FD-capable adapter, or send over zenoh")
    if bitrate <= 0 or data_bitrate < bitrate:
        raise ConfigError(f"bitrate={bitrate}, data_bitrate={data_bitrate}: expected 0 < bitrate <= "
                          f"data_bitrate (bit/s), e.g. 500000 and 2000000")


def open_bus(*, interface: str, channel: str, bitrate: int, data_bitrate: int, vehicle_id: int) -> can.BusABC:
    """Open a CAN FD bus receiving only ``vehicle_id``'s frames.

    socketcan takes its bitrates from the interface (``ip link set can0 type can
    bitrate 500000 dbitrate 2000000 fd on``); other interfaces get them here.
    Configuration files of python-can are ignored: the options are explicit.

    Raises:
        ConfigError: refused or unknown interface.
        TransportError: the bus cannot be opened (with a hint).
    """
    check_interface(interface)
    kwargs: dict[str, Any] = {"fd": True}  # python-can's Bus takes per-interface options
    if interface not in ("socketcan", "virtual"):
        kwargs.update(bitrate=bitrate, data_bitrate=data_bitrate)
    filters = [{"can_id": vehicle_id, "can_mask": VEHICLE_MASK, "extended": True}]
    try:
        return can.Bus(interface=interface, channel=channel, can_filters=filters, ignore_config=True, **kwargs)
    except (can.CanError, OSError, ValueError, ImportError) as err:
        hint = ""
        if interface == "socketcan":
            hint = (f"; does {channel} exist and is it up? A virtual one: sudo modprobe vcan && sudo ip link "
                    f"add dev {channel} type vcan && sudo ip link set {channel} mtu 72 up")
        raise TransportError(f"cannot open CAN interface {interface!r} channel {channel!r}: {err}{hint}") from err


class CanHalf:
    """The harness's side of one vehicle on a CAN bus, not itself a ``Link``: the bus
    options (checked when built), the bus and its ``CanPeer``. ``CanLink`` is this half
    and nothing else; ``hil.adapters.mixed.MixedLink`` composes it with a Zenoh frame
    path. Repeated HELLOs (a target's heartbeat until it hears us) are dropped here.

    Args:
        as ``CanLink``.

    Raises:
        ConfigError: an option is invalid (names it).
    """

    def __init__(self, *, vehicle_id: int, clock: Clock, interface: str, channel: str, bitrate: int,
                 data_bitrate: int, fd: bool, camera_over: str, heartbeat_timeout_s: float,
                 tap: CanTap | None = None) -> None:
        _check_options(interface=interface, vehicle_id=vehicle_id, bitrate=bitrate, data_bitrate=data_bitrate, fd=fd)
        if camera_over not in ("isotp", "none"):
            raise ConfigError(f"camera_over={camera_over!r}; expected 'isotp' (frames on this bus) or 'none' "
                              f"(a mixed target takes frames over another transport)")
        self.vehicle_id, self.clock = vehicle_id, clock
        self.interface, self.channel = interface, channel
        self.bitrate, self.data_bitrate, self.camera_over = bitrate, data_bitrate, camera_over
        self.heartbeat_timeout_s = heartbeat_timeout_s
        self.tap = tap
        self._peer: CanPeer | None = None
        self._hello_seen = False

    @property
    def stats(self) -> CanStats | None:
        """CAN-level counters (None before ``open``)."""
        return self._peer.stats if self._peer is not None else None

    def open(self, link_stats: LinkStats, *, dispatch: Callable[[Message | ProtocolError, int], None],
             deliver_bytes: Callable[[bytes, int], None], on_gone: Callable[[str], None]) -> None:
        """Open the bus and start the peer: decoded messages go to ``dispatch``, ISO-TP
        bytes to ``deliver_bytes``, silence or a failed bus to ``on_gone``; byte and
        error counts into ``link_stats``.

        Raises:
            TransportError: the bus cannot be opened.
        """
        def deliver(item: Message | ProtocolError, t_rx_ns: int, nbytes: int) -> None:
            if isinstance(item, Hello):
                if self._hello_seen:
                    return
                self._hello_seen = True
            link_stats.bytes_received += nbytes
            dispatch(item, t_rx_ns)

        def count_error(text: str) -> None:
            link_stats.protocol_errors += 1
            link_stats.last_error = text

        bus = open_bus(interface=self.interface, channel=self.channel, bitrate=self.bitrate,
                       data_bitrate=self.data_bitrate, vehicle_id=self.vehicle_id)
        try:
            self._peer = CanPeer(role=Role.HARNESS, bus=bus, owns_bus=True, vehicle_id=self.vehicle_id,
                                 clock=self.clock, deliver=deliver, deliver_bytes=deliver_bytes,
                                 on_error=count_error, on_silent=on_gone, on_fatal=on_gone,
                                 heartbeat_timeout_s=self.heartbeat_timeout_s, camera_over=self.camera_over,
                                 tap=self.tap)
        except BaseException:
            bus.shutdown()
            raise
        self._peer.start()

    def send_bytes(self, data: bytes) -> None:
        if self._peer is None:
            raise TransportError("CAN link is not open")
        self._peer.send_bytes(data)

    def wait_sent(self, timeout_s: float) -> bool:
        return self._peer.wait_sent(timeout_s) if self._peer is not None else True

    def close(self) -> None:
        peer, self._peer = self._peer, None
        if peer is not None:
            peer.close()


class CanLink(Link):
    """Harness side of the CAN transport for one vehicle (see the module docstring):
    a ``Link`` over one ``CanHalf``.

    Args:
        vehicle_id: 0..65535, carried in every CAN id.
        clock: stamps sends and receipts (the harness clock).
        interface, channel: python-can's, a local bus (``LOCAL_INTERFACES``).
        bitrate, data_bitrate: nominal and CAN FD data bitrates, bit/s (socketcan
            takes them from ``ip link`` instead).
        fd: must be True (the transport's frames are CAN FD).
        camera_over: ``"isotp"`` (camera frames on this bus) or ``"none"`` (a mixed
            target takes frames over another transport).
        heartbeat_timeout_s: silence after which the target is gone.
        tap: sees every frame sent and received with its stamp on ``clock``
            (``hil.adapters.can_peer.CanTap``; the harness's bus log).

    Raises:
        ConfigError: an option is invalid (names it).
    """

    transport_name = "can"

    def __init__(self, *, vehicle_id: int, clock: Clock, interface: str = "socketcan", channel: str = "vcan0",
                 bitrate: int = 500_000, data_bitrate: int = 2_000_000, fd: bool = True,
                 camera_over: str = "isotp", heartbeat_timeout_s: float = HEARTBEAT_TIMEOUT_S,
                 rx_queue_size: int = 1024, rx_queue: queue.Queue[Received] | None = None,
                 tap: CanTap | None = None) -> None:
        self.can = CanHalf(vehicle_id=vehicle_id, clock=clock, interface=interface, channel=channel,
                           bitrate=bitrate, data_bitrate=data_bitrate, fd=fd, camera_over=camera_over,
                           heartbeat_timeout_s=heartbeat_timeout_s, tap=tap)
        super().__init__(vehicle_id=vehicle_id, clock=clock, rx_queue_size=rx_queue_size, rx_queue=rx_queue)

    @property
    def can_stats(self) -> CanStats | None:
        """CAN-level counters (None before ``open``)."""
        return self.can.stats

    @property
    def frames_superseded(self) -> int:
        """Camera frames replaced by a newer one before they were sent."""
        stats = self.can.stats
        return stats.frames_superseded if stats is not None else 0

    def capacity(self, *, frame_bytes: int, fps: float, **options: object) -> CapacityReport:
        """``bus_capacity`` at this link's bitrates (options as there)."""
        return bus_capacity(bitrate=self.can.bitrate, data_bitrate=self.can.data_bitrate, fd=True,
                            frame_bytes=frame_bytes, fps=fps, camera_over=self.can.camera_over,
                            **options)  # type: ignore[arg-type]

    def wait_sent(self, timeout_s: float) -> bool:
        """Wait until every ISO-TP message handed over has left; False on timeout."""
        return self.can.wait_sent(timeout_s)

    def _open(self) -> None:
        self.can.open(self.stats, dispatch=self._dispatch, deliver_bytes=self._on_message_bytes,
                      on_gone=self._mark_gone)

    def _send_bytes(self, data: bytes) -> None:
        self.can.send_bytes(data)

    def _close_transport(self) -> None:
        half = getattr(self, "can", None)
        if half is not None:
            half.close()


def serve_endpoint(ep: Endpoint, *, interface: str = "socketcan", channel: str = "vcan0", bitrate: int = 500_000,
                   data_bitrate: int = 2_000_000, vehicle_id: int = 0, bus: can.BusABC | None = None,
                   heartbeat_timeout_s: float = HEARTBEAT_TIMEOUT_S, keep_serving: bool = False,
                   announce: Callable[[str], None] | None = None, transport: str = "can", frames_from: str = "",
                   on_session: Callable[[Endpoint], None] | None = None) -> None:
    """Target side: serve ``ep`` on the CAN bus until the harness says BYE (with
    ``keep_serving``: then the next harness, on the same bus), ``ep.stop()`` or
    SIGTERM/Ctrl-C. Sends HELLO (repeated until the harness is heard), then heartbeats
    every 250 ms; sends BYE on leaving unless the harness said it first. A harness that
    goes silent is waited for (a new one gets HELLO). Prints one start-up line and one
    line per session to ``announce`` (default stderr).

    Args:
        bus: an open python-can bus to use instead of opening one (tests pass a
            ``virtual`` bus); the caller keeps ownership and closes it.
        transport, frames_from, on_session: for a mixed target (``hil.adapters.mixed``):
            the name and where frames come from in the start-up line, and a call with
            each session's endpoint before it starts.

    Raises:
        ConfigError: an option is invalid.
        TransportError: the bus cannot be opened, or failed while serving.
    """
    _check_options(interface=interface, vehicle_id=vehicle_id, bitrate=bitrate, data_bitrate=data_bitrate, fd=True)
    if bus is not None and (name := interface_of(bus)) is not None:
        check_interface(name)
    owns = bus is None
    if bus is None:
        bus = open_bus(interface=interface, channel=channel, bitrate=bitrate, data_bitrate=data_bitrate,
                       vehicle_id=vehicle_id)
    say = announce or (lambda text: print(text, file=sys.stderr, flush=True))
    quit_ = threading.Event()  # SIGTERM or Ctrl-C: no further runs
    current = ep
    try:
        with stop_on_sigterm(quit_.set):
            where = f"on {interface} channel {channel}, vehicle {vehicle_id}" + (f", frames {frames_from}"
                                                                                  if frames_from else "")
            say(announce_line(ep, transport=transport, where=where,
                              access="open (any node on the bus can act as the harness; see README, threat model)",
                              keep_serving=keep_serving))
            for n in itertools.count(1):
                if on_session is not None:
                    on_session(current)
                ended = _serve_session(current, bus, vehicle_id=vehicle_id, heartbeat_timeout_s=heartbeat_timeout_s,
                                       quit_=quit_)
                st = current.stats
                if st.frames_received or st.sync_answered or current.harness_said_bye:  # a harness came
                    say(session_line(current, n, f"the harness on {channel}", ended))
                if quit_.is_set() or not keep_serving:
                    return
                current = fresh_endpoint(ep, current)
    except KeyboardInterrupt:
        quit_.set()
    finally:
        add_stats(ep, current)
        if owns:
            bus.shutdown()


def _serve_session(ep: Endpoint, bus: can.BusABC, *, vehicle_id: int, heartbeat_timeout_s: float,
                   quit_: threading.Event) -> str:
    """One harness: HELLO until heard, serve until its BYE or we stop; how it ended.

    Raises:
        TransportError: the bus failed.
    """
    def count_error(text: str) -> None:
        ep.stats.protocol_errors += 1

    bus_failed = threading.Event()  # no BYE can go out any more

    def on_fatal(why: str) -> None:
        bus_failed.set()
        ep.stop()

    peer = CanPeer(role=Role.TARGET, bus=bus, owns_bus=False, vehicle_id=vehicle_id, clock=ep.clock,
                   deliver=lambda item, t_rx, n: ep.on_message(item, t_rx), deliver_bytes=ep.on_message_bytes,
                   on_error=count_error, on_silent=lambda why: None, on_fatal=on_fatal,
                   heartbeat_timeout_s=heartbeat_timeout_s)
    try:
        with serving(ep, vehicle_id=vehicle_id, harness_gone=bus_failed, on_term=quit_.set):
            ep.start(peer.send_bytes)  # HELLO first, so the reader can repeat it
            peer.start()
            while not ep.wait_stopped(0.25):
                if quit_.is_set():  # a SIGTERM that came between two sessions
                    ep.stop()
    finally:
        peer.close()
    if peer.failed:
        raise TransportError(f"the target left the CAN bus: {peer.failure}")
    return said_bye(ep) or "stopped (SIGTERM)"


__all__ = ["CanHalf", "CanLink", "CanStats", "CapacityReport", "bus_capacity", "check_interface", "open_bus",
           "serve_endpoint"]
