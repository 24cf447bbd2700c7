"""The mixed transport: a device that answers on CAN and takes its camera frames over Zenoh.

A CAN bus carries estimates, control and clock sync well but a camera poorly (a
12 KB JPEG holds a 500k/2M bus for 87 ms, PROTOCOL.md section 10.3). A mixed target
takes FRAMEs over Zenoh and does everything else on CAN:

==========================  =====  ===================================================
message                     over   how
==========================  =====  ===================================================
FRAME                       Zenoh  one message per sample on ``{prefix}/v{vehicle}/h2t``
                                   (``hil.adapters.zenoh.session.Keys``), put with
                                   congestion control BLOCK
HELLO, ESTIMATE, SYNC_*,    CAN    as the CAN transport (``hil.adapters.can.link``,
HEARTBEAT, ERROR, BYE              ``camera_over="none"``): DBC frames or ISO-TP
==========================  =====  ===================================================

Clock sync runs over CAN, so the mapped uplink ``t_tx -> t_rx`` is the Zenoh path
measured against the CAN clock exchange.

Session start. The target declares its Zenoh subscriber on ``h2t`` and then its
liveliness token ``{prefix}/v{vehicle}/alive`` *before* it says HELLO on CAN. The
harness (``MixedLink.open``) waits for HELLO on CAN and then for that token, so its
first frame has a route (a frame put before the subscriber is known would vanish).

Liveness. CAN heartbeats as in the CAN transport: the target is gone after 0.75 s
without a CAN frame from it. The DELETE of its Zenoh token (its session closed, its
process died, its lease ran out) marks it gone too: without the frame path the
target would only answer sync (the harness still says BYE on CAN when it closes). The harness declares its own token
(``{prefix}/v{vehicle}/harness``) for tools; the target follows the harness by CAN.
"""

from __future__ import annotations

import queue
import threading
from dataclasses import dataclass, replace

from hil.adapters.can.link import CanHalf
from hil.adapters.can.peer import CanStats, CanTap
from hil.adapters.link import Link, Received
from hil.adapters.mixed.options import MixedOptions
from hil.adapters.wire import protocol
from hil.adapters.wire.messages import Bye, Hello, MsgType
from hil.adapters.zenoh.link import ZenohHalf, ZenohStats
from hil.common.errors import TargetError, TransportError
from hil.timing.clock import Clock

try:
    import zenoh
except ImportError as _err:  # pragma: no cover - depends on the install
    raise ImportError("the mixed transport needs eclipse-zenoh: pip install eclipse-zenoh==1.10.2") from _err


@dataclass
class MixedStats:
    """Counters of the mixed link itself (its halves': ``can_stats``, ``zenoh_stats``)."""

    frames_zenoh: int = 0


class MixedLink(Link):
    """Harness side of a mixed target: a ``Link`` composed of a CAN half
    (``CanHalf``, ``camera_over="none"``) for everything but frames and a Zenoh half
    (``ZenohHalf``) that publishes frames (module docstring).

    Args:
        vehicle_id: 0..65535 (the CAN id carries it).
        clock: the harness clock.
        options: ``MixedOptions``: ``can`` the CAN half's, as ``CanLink`` takes them (a
            local bus only; ``camera_over`` is ``none`` here), ``zenoh`` the Zenoh
            half's, as ``ZenohLink`` takes them (at least one endpoint).
        tap: sees every CAN frame, as ``CanLink``'s.

    Raises:
        ConfigError: an option of either half is invalid (names it).
    """

    transport_name = "mixed"

    def __init__(self, *, vehicle_id: int, clock: Clock, options: MixedOptions | None = None,
                 rx_queue_size: int = 1024, rx_queue: queue.Queue[Received] | None = None,
                 tap: CanTap | None = None) -> None:
        o = self.options = options or MixedOptions()
        self.can = CanHalf(vehicle_id=vehicle_id, clock=clock, options=replace(o.can, camera_over="none"), tap=tap)
        self.zenoh = ZenohHalf(vehicle_id=vehicle_id, options=o.zenoh, what="the mixed link's zenoh half")
        super().__init__(vehicle_id=vehicle_id, clock=clock, rx_queue_size=rx_queue_size, rx_queue=rx_queue)
        self.keys = self.zenoh.keys
        self.mixed_stats = MixedStats()
        self._frame_route = threading.Event()  # the target's zenoh token is up
        self._bye_on_can = False

    @property
    def can_stats(self) -> CanStats | None:
        """The CAN half's counters (None before ``open``)."""
        return self.can.stats

    @property
    def zenoh_stats(self) -> ZenohStats:
        """The Zenoh half's counters."""
        return self.zenoh.stats

    def open(self, *, hello_timeout_s: float) -> Hello:
        """Wait for HELLO on CAN, then for the target's Zenoh token (module docstring).

        Raises:
            TargetError: no HELLO, or no Zenoh token, within ``hello_timeout_s``.
        """
        start_ns = self.clock.now_ns()
        hello = super().open(hello_timeout_s=hello_timeout_s)
        left_s = hello_timeout_s - (self.clock.now_ns() - start_ns) / 1e9
        if not self._frame_route.wait(max(left_s, 0.0)) or not self.alive:
            no_session = self.zenoh.no_session_reason(hello_timeout_s)
            raise TargetError(self.peer_gone_reason or
                              f"the target said hello on CAN, but its zenoh token {self.keys.alive!r} did not "
                              f"appear within {hello_timeout_s:g} s: frames would go nowhere"
                              + (f" ({no_session})" if no_session else "") +
                              f". Check that the device's zenoh side runs (--listen/--connect) with the same "
                              f"--key-prefix and --vehicle, and this link's connect={self.zenoh.connect} "
                              f"listen={self.zenoh.listen}")
        return hello

    def _open(self) -> None:
        self.zenoh.open(on_target_token=self._on_liveliness)
        self.can.open(self.stats, dispatch=self._dispatch, deliver_bytes=self._on_message_bytes,
                      on_gone=self._mark_gone)

    def _on_liveliness(self, sample: zenoh.Sample) -> None:
        if sample.kind == zenoh.SampleKind.PUT:
            self._frame_route.set()
        elif sample.kind == zenoh.SampleKind.DELETE:
            if self.alive:
                self._bye_on_can = True  # the CAN half still hears the device: tell it on close
            self._mark_gone(f"zenoh liveliness lost: the mixed target's frame subscriber {self.keys.alive!r} "
                            f"went away (its process exited, closed its session or its lease expired)")
            self._frame_route.set()  # wakes open(); alive is False now

    def _send_bytes(self, data: bytes) -> None:
        if len(data) >= protocol.HEADER_SIZE and data[5] == MsgType.FRAME and data[:4] == protocol.MAGIC:
            self.zenoh.put(data, self.stats)
            self.mixed_stats.frames_zenoh += 1
            return
        self.can.send_bytes(data)

    def _close_transport(self) -> None:
        if getattr(self, "_bye_on_can", False):
            self._bye_on_can = False
            try:
                self.can.send_bytes(protocol.encode(Bye(self.vehicle_id, "harness closing: zenoh frame path lost")))
            except (TransportError, OSError):
                pass
        try:
            can_half = getattr(self, "can", None)
            if can_half is not None:
                can_half.close()
        finally:
            zenoh_half = getattr(self, "zenoh", None)
            if zenoh_half is not None:
                zenoh_half.close(self.stats)


__all__ = ["MixedLink", "MixedStats"]
