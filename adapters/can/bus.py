"""Opening a vehicle's CAN FD bus, for both halves of the can transport: only buses on
this machine (``hil.adapters.can.options.LOCAL_INTERFACES``), CAN FD, bitrates and the
vehicle id checked first, and a receive filter on the vehicle's ids.

Raises: :class:`hil.common.errors.ConfigError` for a refused option,
:class:`hil.common.errors.TransportError` when the bus cannot be opened.
"""

from __future__ import annotations

from typing import Any

try:
    import can
except ImportError as err:  # pragma: no cover - depends on the install
    raise ImportError("the CAN transport needs python-can: pip install 'python-can>=4.6,<5'") from err

from hil.adapters.can.dbc import MAX_VEHICLE_ID, VEHICLE_MASK
from hil.adapters.can.options import LOCAL_INTERFACES, CanOptions
from hil.common.errors import ConfigError, TransportError


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


def check_options(options: CanOptions, *, vehicle_id: int) -> None:
    """Raise ``ConfigError`` naming the first of ``options`` (or ``vehicle_id``) that is refused."""
    interface, bitrate, data_bitrate, fd = options.interface, options.bitrate, options.data_bitrate, options.fd
    check_interface(interface)
    if not 0 <= vehicle_id <= MAX_VEHICLE_ID:
        raise ConfigError(f"vehicle_id={vehicle_id}: the CAN id carries vehicle ids 0..{MAX_VEHICLE_ID}")
    if not fd:
        raise ConfigError("fd=False: the CAN transport needs CAN FD (its DBC frames are up to 64 bytes); "
                          "use an FD-capable adapter, or send over zenoh")
    if bitrate <= 0 or data_bitrate < bitrate:
        raise ConfigError(f"bitrate={bitrate}, data_bitrate={data_bitrate}: expected 0 < bitrate <= "
                          f"data_bitrate (bit/s), e.g. 500000 and 2000000")


def open_bus(options: CanOptions, *, vehicle_id: int) -> can.BusABC:
    """Open a CAN FD bus receiving only ``vehicle_id``'s frames.

    socketcan takes its bitrates from the interface (``ip link set can0 type can
    bitrate 500000 dbitrate 2000000 fd on``); other interfaces get them here.
    Configuration files of python-can are ignored: the options are explicit.

    Raises:
        ConfigError: refused or unknown interface.
        TransportError: the bus cannot be opened (with a hint).
    """
    interface, channel = options.interface, options.channel
    check_interface(interface)
    kwargs: dict[str, Any] = {"fd": True}  # python-can's Bus takes per-interface options
    if interface not in ("socketcan", "virtual"):
        kwargs.update(bitrate=options.bitrate, data_bitrate=options.data_bitrate)
    filters = [{"can_id": vehicle_id, "can_mask": VEHICLE_MASK, "extended": True}]
    try:
        return can.Bus(interface=interface, channel=channel, can_filters=filters, ignore_config=True, **kwargs)
    except (can.CanError, OSError, ValueError, ImportError) as err:
        hint = ""
        if interface == "socketcan":
            hint = (f"; does {channel} exist and is it up? A virtual one: sudo modprobe vcan && sudo ip link "
                    f"add dev {channel} type vcan && sudo ip link set {channel} mtu 72 up")
        raise TransportError(f"cannot open CAN interface {interface!r} channel {channel!r}: {err}{hint}") from err


__all__ = ["check_interface", "check_options", "interface_of", "open_bus"]
