"""Target side of the mixed transport: a device that takes its camera frames over Zenoh
and does everything else on CAN (the wire and the session start are described in
``hil.adapters.mixed.link``).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING

from hil.adapters.can.bus import check_interface
from hil.adapters.can.target import serve_endpoint as serve_can
from hil.adapters.mixed.options import MixedOptions
from hil.adapters.zenoh.session import CLOSE_TIMEOUT_S, Keys, close_session, open_with
from hil.adapters.zenoh.target import where
from hil.common.errors import ConfigError, TransportError

try:
    import zenoh
except ImportError as _err:  # pragma: no cover - depends on the install
    raise ImportError("the mixed transport needs eclipse-zenoh: pip install eclipse-zenoh==1.10.2") from _err

if TYPE_CHECKING:
    import can

    from hil.adapters.sdk import Endpoint


def serve_endpoint(ep: Endpoint, *, options: MixedOptions | None = None, vehicle_id: int = 0,
                   bus: can.BusABC | None = None, keep_serving: bool = False,
                   announce: Callable[[str], None] | None = None) -> None:
    """Target side: frames from Zenoh (``options.zenoh``: ``listen``/``connect``),
    everything else on the CAN bus (``options.can``), until the harness says BYE (with
    ``keep_serving``: then the next harness), ``ep.stop()``, or SIGTERM (then BYE on
    CAN, ``hil.adapters.sdk.serving``).

    Args:
        bus: an open python-can bus to use (tests pass a ``virtual`` one); the caller
            keeps ownership. The CAN half as ``hil.adapters.can.target.serve_endpoint``,
            the Zenoh half as ``hil.adapters.zenoh.target.serve_endpoint``.

    Raises:
        ConfigError: an option is invalid, or neither ``listen`` nor ``connect`` is given.
        TransportError: the Zenoh session or the CAN bus cannot be opened, or the bus failed.
    """
    o = options or MixedOptions()
    if not o.zenoh.listen and not o.zenoh.connect:
        raise ConfigError("a mixed target takes its frames over zenoh: give --listen ENDPOINT "
                          "(e.g. tcp/0.0.0.0:7447) or --connect ENDPOINT")
    check_interface(o.can.interface)
    keys = Keys.of(o.zenoh.key_prefix, vehicle_id)
    session = open_with(o.zenoh)

    current = [ep]  # the endpoint of the session being served

    def on_frame(sample: zenoh.Sample) -> None:
        now = current[0]
        t_rx = now.clock.now_ns()
        try:
            now.on_message_bytes(sample.payload.to_bytes(), t_rx)
        except TransportError:
            pass  # not started yet, or closing: an ERROR reply cannot go out

    entities: list[object] = []
    try:
        try:
            # Subscriber, then token, then HELLO (in serve_can): a harness that has seen
            # both knows a route for its first frame.
            entities.append(session.declare_subscriber(keys.h2t, on_frame))
            entities.append(session.liveliness().declare_token(keys.alive))
        except zenoh.ZError as err:
            raise TransportError(f"zenoh declarations on {keys.h2t!r} failed: {err}") from err
        serve_can(ep, options=o.can, vehicle_id=vehicle_id, bus=bus, keep_serving=keep_serving, announce=announce,
                  transport="mixed", frames_from=f"over zenoh {where(o.zenoh)} on {keys.h2t}",
                  on_session=lambda e: current.__setitem__(0, e))
    finally:
        entities.clear()
        close_session(session, timeout_s=CLOSE_TIMEOUT_S)  # bounded: the harness may be frozen


__all__ = ["serve_endpoint"]
