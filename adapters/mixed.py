"""The mixed transport: a device that answers on CAN and takes its camera frames over Zenoh.

A CAN bus carries estimates, control and clock sync well but a camera poorly (a
12 KB JPEG holds a 500k/2M bus for 87 ms, PROTOCOL.md section 10.3). A mixed target
takes FRAMEs over Zenoh and does everything else on CAN:

==========================  =====  ===================================================
message                     over   how
==========================  =====  ===================================================
FRAME                       Zenoh  one message per sample on ``{prefix}/v{vehicle}/h2t``
                                   (``hil.adapters.zenoh_transport.Keys``), put with
                                   congestion control BLOCK
HELLO, ESTIMATE, SYNC_*,    CAN    as the CAN transport (``hil.adapters.can_transport``,
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
import signal
import threading
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

from hil.adapters import protocol
from hil.adapters.can_peer import HEARTBEAT_TIMEOUT_S
from hil.adapters.can_transport import CanLink, check_interface
from hil.adapters.can_transport import serve_endpoint as serve_can
from hil.adapters.link import Received
from hil.adapters.messages import Bye, Hello, MsgType
from hil.adapters.zenoh_transport import CONGESTION, DEFAULT_LEASE_MS, Keys, make_config
from hil.common.errors import ConfigError, TargetError, TransportError
from hil.timing.clock import Clock

try:
    import zenoh
except ImportError as _err:  # pragma: no cover - depends on the install
    raise ImportError("the mixed transport needs eclipse-zenoh: pip install eclipse-zenoh==1.10.2") from _err

if TYPE_CHECKING:
    import can

    from hil.adapters.sdk import Endpoint


@dataclass
class MixedStats:
    """Counters of the Zenoh half (the CAN half's are in ``can_stats``)."""

    frames_zenoh: int = 0
    put_failures: int = 0


def _open_session(cfg: zenoh.Config, where: str) -> zenoh.Session:
    try:
        return zenoh.open(cfg)
    except zenoh.ZError as err:
        raise TransportError(f"cannot open a zenoh session ({where}): {err}") from err


class MixedLink(CanLink):
    """Harness side of a mixed target: ``CanLink`` with ``camera_over="none"`` for
    everything but frames, and a Zenoh publisher for frames (module docstring).

    Args:
        vehicle_id: 0..65535 (the CAN id carries it).
        clock: the harness clock.
        interface, channel, bitrate, data_bitrate, fd, heartbeat_timeout_s: the CAN
            half, as ``CanLink`` (a local bus only).
        connect, listen, mode, key_prefix, multicast_scouting, tls,
            congestion_control, lease_ms, shared_memory: the Zenoh half, as
            ``ZenohLink`` (multicast scouting off unless asked for).

    Raises:
        ConfigError: an option of either half is invalid (names it).
    """

    transport_name = "mixed"

    def __init__(self, *, vehicle_id: int, clock: Clock, interface: str = "socketcan", channel: str = "vcan0",
                 bitrate: int = 500_000, data_bitrate: int = 2_000_000, fd: bool = True,
                 heartbeat_timeout_s: float = HEARTBEAT_TIMEOUT_S,
                 connect: Sequence[str] = ("tcp/127.0.0.1:7447",), listen: Sequence[str] = (), mode: str = "peer",
                 key_prefix: str = "hil", multicast_scouting: bool = False, tls: Mapping[str, object] | None = None,
                 congestion_control: str = "block", lease_ms: int = DEFAULT_LEASE_MS,
                 shared_memory: bool | None = None, rx_queue_size: int = 1024,
                 rx_queue: queue.Queue[Received] | None = None) -> None:
        self._session: zenoh.Session | None = None
        self._publisher: zenoh.Publisher | None = None
        self._entities: list[object] = []
        super().__init__(vehicle_id=vehicle_id, clock=clock, interface=interface, channel=channel, bitrate=bitrate,
                         data_bitrate=data_bitrate, fd=fd, camera_over="none",
                         heartbeat_timeout_s=heartbeat_timeout_s, rx_queue_size=rx_queue_size, rx_queue=rx_queue)
        if congestion_control not in CONGESTION:
            raise ConfigError(f"zenoh congestion_control={congestion_control!r}: expected 'block' or 'drop'")
        if not connect and not listen:
            raise ConfigError("the mixed link's zenoh half needs at least one connect or listen endpoint")
        self.keys = Keys.of(key_prefix, vehicle_id)
        self.congestion_control = congestion_control
        self.connect, self.listen = list(connect), list(listen)
        self.zenoh_config = make_config(mode=mode, connect=connect, listen=listen, tls=tls,
                                        multicast_scouting=multicast_scouting, lease_ms=lease_ms,
                                        shared_memory=shared_memory)
        self.mixed_stats = MixedStats()
        self._frame_route = threading.Event()  # the target's zenoh token is up
        self._bye_on_can = False

    def open(self, *, hello_timeout_s: float) -> Hello:
        """Wait for HELLO on CAN, then for the target's Zenoh token (module docstring).

        Raises:
            TargetError: no HELLO, or no Zenoh token, within ``hello_timeout_s``.
        """
        start_ns = self.clock.now_ns()
        hello = super().open(hello_timeout_s=hello_timeout_s)
        left_s = hello_timeout_s - (self.clock.now_ns() - start_ns) / 1e9
        if not self._frame_route.wait(max(left_s, 0.0)) or not self.alive:
            raise TargetError(self.peer_gone_reason or
                              f"the target said hello on CAN, but its zenoh token {self.keys.alive!r} did not "
                              f"appear within {hello_timeout_s:g} s: frames would go nowhere. Check that the "
                              f"device's zenoh side runs (--listen/--connect) with the same --key-prefix and "
                              f"--vehicle, and this link's connect={self.connect} listen={self.listen}")
        return hello

    def _open(self) -> None:
        self._session = s = _open_session(self.zenoh_config, f"connect={self.connect} listen={self.listen}")
        try:
            self._publisher = s.declare_publisher(self.keys.h2t,
                                                  congestion_control=CONGESTION[self.congestion_control])
            # Zenoh undeclares an entity when its Python object is dropped: keep them all.
            self._entities = [
                s.liveliness().declare_token(self.keys.harness),
                s.liveliness().declare_subscriber(self.keys.alive, self._on_liveliness, history=True),
            ]
        except zenoh.ZError as err:
            raise TransportError(f"zenoh declarations on {self.keys.h2t!r} failed: {err}") from err
        super()._open()  # the CAN half

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
            pub = self._publisher
            if pub is None:
                raise TransportError("mixed link is not open")
            try:
                pub.put(data)
            except zenoh.ZError as err:
                self.mixed_stats.put_failures += 1
                self.stats.last_error = f"zenoh put failed: {err}"
                raise TransportError(f"zenoh put on {self.keys.h2t!r} failed: {err}") from err
            self.mixed_stats.frames_zenoh += 1
            return
        super()._send_bytes(data)

    def _close_transport(self) -> None:
        if getattr(self, "_bye_on_can", False):
            self._bye_on_can = False
            try:
                super()._send_bytes(protocol.encode(Bye(self.vehicle_id, "harness closing: zenoh frame path lost")))
            except (TransportError, OSError):
                pass
        try:
            super()._close_transport()
        finally:
            session, self._session = getattr(self, "_session", None), None
            self._publisher, self._entities = None, []
            if session is not None and not session.is_closed():
                session.close()  # undeclares everything and flushes; without it exit can hang


def serve_endpoint(ep: Endpoint, *, interface: str = "socketcan", channel: str = "vcan0", bitrate: int = 500_000,
                   data_bitrate: int = 2_000_000, vehicle_id: int = 0, bus: can.BusABC | None = None,
                   heartbeat_timeout_s: float = HEARTBEAT_TIMEOUT_S, listen: Sequence[str] = (),
                   connect: Sequence[str] = (), mode: str = "peer", key_prefix: str = "hil",
                   multicast_scouting: bool = False, tls: Mapping[str, object] | None = None,
                   lease_ms: int = DEFAULT_LEASE_MS, shared_memory: bool | None = None) -> None:
    """Target side: frames from Zenoh (``listen``/``connect``), everything else on the
    CAN bus, until the harness says BYE, ``ep.stop()``, or SIGTERM (then BYE on CAN).

    Args:
        bus: an open python-can bus to use (tests pass a ``virtual`` one); the caller
            keeps ownership. Other CAN options as ``hil.adapters.can_transport.serve_endpoint``,
            Zenoh options as ``hil.adapters.zenoh_transport.serve_endpoint``.

    Raises:
        ConfigError: an option is invalid, or neither ``listen`` nor ``connect`` is given.
        TransportError: the Zenoh session or the CAN bus cannot be opened, or the bus failed.
    """
    if not listen and not connect:
        raise ConfigError("a mixed target takes its frames over zenoh: give --listen ENDPOINT "
                          "(e.g. tcp/0.0.0.0:7447) or --connect ENDPOINT")
    check_interface(interface)
    keys = Keys.of(key_prefix, vehicle_id)
    cfg = make_config(mode=mode, connect=connect, listen=listen, tls=tls, multicast_scouting=multicast_scouting,
                      lease_ms=lease_ms, shared_memory=shared_memory)
    session = _open_session(cfg, f"listen={list(listen)} connect={list(connect)}")

    def on_frame(sample: zenoh.Sample) -> None:
        t_rx = ep.clock.now_ns()
        try:
            ep.on_message_bytes(sample.payload.to_bytes(), t_rx)
        except TransportError:
            pass  # not started yet, or closing: an ERROR reply cannot go out

    old_term = None
    entities: list[object] = []
    try:
        try:
            # Subscriber, then token, then HELLO (in serve_can): a harness that has seen
            # both knows a route for its first frame.
            entities.append(session.declare_subscriber(keys.h2t, on_frame))
            entities.append(session.liveliness().declare_token(keys.alive))
        except zenoh.ZError as err:
            raise TransportError(f"zenoh declarations on {keys.h2t!r} failed: {err}") from err
        if threading.current_thread() is threading.main_thread():
            old_term = signal.signal(signal.SIGTERM, lambda *_: ep.stop())
        serve_can(ep, interface=interface, channel=channel, bitrate=bitrate, data_bitrate=data_bitrate,
                  vehicle_id=vehicle_id, bus=bus, heartbeat_timeout_s=heartbeat_timeout_s)
    finally:
        if old_term is not None:
            signal.signal(signal.SIGTERM, old_term)
        entities.clear()
        session.close()


__all__ = ["MixedLink", "MixedStats", "serve_endpoint"]
