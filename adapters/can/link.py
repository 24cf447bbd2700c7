"""The CAN transport: a device on a CAN FD bus (python-can, cantools, can-isotp).

Two ways over the wire (PROTOCOL.md section 10.3 has the full specification, ``hil.dbc``
the frames, ``hil.adapters.can.dbc`` the id layout ``P << 26 | M << 16 | vehicle``):

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
``hil.adapters.can.dbc``) and bytes that are not a valid message (``Link.send_raw``).
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
link's ``Clock`` (``hil.adapters.wire.receipt.RealtimeMapper``); otherwise, and on the
target side, the moment ``bus.recv`` returns.

Camera frames are newest-wins: while one is in transmission, a newer frame replaces
the one waiting (``CanLink.frames_superseded`` counts them; the harness sees them as
dropped). ``camera_over="none"`` is a mixed target: frames travel over Zenoh
(``hil.adapters.mixed.link``) and sending one here raises.

python-can's ``virtual`` interface works within one process and has no bit timing
(``hil.adapters.can.capacity`` gives a real bus's limits). Only buses on this machine are
accepted (``hil.adapters.can.options``): network interfaces would send frames off it.
"""

from __future__ import annotations

import queue
from collections.abc import Callable

from hil.adapters.can.bus import check_options, open_bus
from hil.adapters.can.capacity import CapacityReport, bus_capacity
from hil.adapters.can.dbc import Role
from hil.adapters.can.options import CanOptions
from hil.adapters.can.peer import CanPeer, CanStats, CanTap
from hil.adapters.link import Link, LinkStats, Received
from hil.adapters.wire.messages import Hello, Message
from hil.common.errors import ConfigError, ProtocolError, TransportError
from hil.timing.clock import Clock

class CanHalf:
    """The harness's side of one vehicle on a CAN bus, not itself a ``Link``: the bus
    options (checked when built), the bus and its ``CanPeer``. ``CanLink`` is this half
    and nothing else; ``hil.adapters.mixed.link.MixedLink`` composes it with a Zenoh
    frame path. Repeated HELLOs (a target's heartbeat until it hears us) are dropped here.

    Args:
        as ``CanLink``.

    Raises:
        ConfigError: an option is invalid (names it).
    """

    def __init__(self, *, vehicle_id: int, clock: Clock, options: CanOptions, tap: CanTap | None = None) -> None:
        check_options(options, vehicle_id=vehicle_id)
        if options.camera_over not in ("isotp", "none"):
            raise ConfigError(f"camera_over={options.camera_over!r}; expected 'isotp' (frames on this bus) or 'none' "
                              f"(a mixed target takes frames over another transport)")
        self.vehicle_id, self.clock, self.options = vehicle_id, clock, options
        self.interface, self.channel = options.interface, options.channel
        self.bitrate, self.data_bitrate, self.camera_over = options.bitrate, options.data_bitrate, options.camera_over
        self.heartbeat_timeout_s = options.heartbeat_timeout_s
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

        bus = open_bus(self.options, vehicle_id=self.vehicle_id)
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
        options: the bus (``CanOptions``: a local interface and channel, bitrates, CAN
            FD, ``camera_over``, the heartbeat timeout).
        tap: sees every frame sent and received with its stamp on ``clock``
            (``hil.adapters.can.peer.CanTap``; the harness's bus log).

    Raises:
        ConfigError: an option is invalid (names it).
    """

    transport_name = "can"

    def __init__(self, *, vehicle_id: int, clock: Clock, options: CanOptions | None = None,
                 rx_queue_size: int = 1024, rx_queue: queue.Queue[Received] | None = None,
                 tap: CanTap | None = None) -> None:
        self.options = options or CanOptions()
        self.can = CanHalf(vehicle_id=vehicle_id, clock=clock, options=self.options, tap=tap)
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


__all__ = ["CanHalf", "CanLink"]
