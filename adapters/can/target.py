"""Target side of the can transport: serve an ``Endpoint`` on a CAN FD bus to one
harness, or to harness after harness (``keep_serving``), until stopped. The wire is
described in ``hil.adapters.can.link``; the bus is opened by ``hil.adapters.can.bus``.
"""

from __future__ import annotations

import itertools
import sys
import threading
from collections.abc import Callable
from typing import TYPE_CHECKING

from hil.adapters.can.bus import check_interface, check_options, interface_of, open_bus
from hil.adapters.can.dbc import Role
from hil.adapters.can.options import CanOptions
from hil.adapters.can.peer import CanPeer
from hil.adapters.sdk import add_stats, announce_line, fresh_endpoint, said_bye, serving, session_line, stop_on_sigterm
from hil.common.errors import TransportError

if TYPE_CHECKING:
    import can

    from hil.adapters.sdk import Endpoint


def serve_endpoint(ep: Endpoint, *, options: CanOptions | None = None, vehicle_id: int = 0,
                   bus: can.BusABC | None = None, keep_serving: bool = False,
                   announce: Callable[[str], None] | None = None, transport: str = "can", frames_from: str = "",
                   on_session: Callable[[Endpoint], None] | None = None) -> None:
    """Target side: serve ``ep`` on the CAN bus until the harness says BYE (with
    ``keep_serving``: then the next harness, on the same bus), ``ep.stop()`` or
    SIGTERM/Ctrl-C. Sends HELLO (repeated until the harness is heard), then heartbeats
    every 250 ms; sends BYE on leaving unless the harness said it first. A harness that
    goes silent is waited for (a new one gets HELLO). Prints one start-up line and one
    line per session to ``announce`` (default stderr).

    Args:
        options: the bus (``CanOptions``: interface, channel, bitrates, heartbeat
            timeout; ``camera_over`` is the harness's).
        bus: an open python-can bus to use instead of opening one (tests pass a
            ``virtual`` bus); the caller keeps ownership and closes it.
        transport, frames_from, on_session: for a mixed target (``hil.adapters.mixed.link``):
            the name and where frames come from in the start-up line, and a call with
            each session's endpoint before it starts.

    Raises:
        ConfigError: an option is invalid.
        TransportError: the bus cannot be opened, or failed while serving.
    """
    o = options or CanOptions()
    interface, channel = o.interface, o.channel
    check_options(o, vehicle_id=vehicle_id)
    if bus is not None and (name := interface_of(bus)) is not None:
        check_interface(name)
    owns = bus is None
    if bus is None:
        bus = open_bus(o, vehicle_id=vehicle_id)
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
                ended = _serve_session(current, bus, vehicle_id=vehicle_id, heartbeat_timeout_s=o.heartbeat_timeout_s,
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


__all__ = ["serve_endpoint"]
