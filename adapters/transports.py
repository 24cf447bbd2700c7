"""The transports, registered as data: one table from transport kind to its halves.

Each transport is a package, ``hil.adapters.<name>``, and its :class:`Backend` row
names, as ``"module:attribute"`` strings, its harness-side link class (a
:class:`hil.adapters.link.Link`, in ``<name>.link``), its target-side serve function
(``serve_endpoint(ep, **options)``, driving an :class:`hil.adapters.sdk.Endpoint`, in
``<name>.target``), its options model (a frozen dataclass in ``<name>.options``: the
one home of the transport's defaults, which the link, the serve function, the
harness's config and the SDK's command line read) and, where it has one, the serve
function of a shared target (one process serving many vehicles,
``serve_shared(scheduler, make_endpoint, **options)``). They are imported by
:mod:`importlib` only when a run asks for that transport, so zenoh and python-can
stay optional and this module imports no transport: ``open_link``, ``sdk.serve`` and
``batching.serve_batched`` look their transport up here instead of importing every
transport, and the transports import ``link`` and ``sdk`` without a circle.

Adding a transport is one package and one row in :data:`BACKENDS` (and one member of
:class:`Transport`); config, the SDK command line and ``open_link`` take it from here.

Raises: :class:`hil.common.errors.TransportError` for an unknown transport name (listing the
valid ones) or a transport without the half asked for.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from dataclasses import dataclass
from enum import Enum
from typing import TYPE_CHECKING, Protocol, cast

from hil.common.errors import TransportError

if TYPE_CHECKING:
    from hil.adapters.link import Link


class Transport(str, Enum):
    """How the harness reaches the AI target (the names config and ``--transport`` take)."""

    LOCAL = "local"  # a child process of the harness: a socketpair (+ shared-memory frames)
    ZENOH = "zenoh"  # Zenoh pub/sub over the network
    CAN = "can"  # a CAN FD bus (DBC frames, ISO-TP for the rest)
    MIXED = "mixed"  # frames over zenoh, everything else over CAN
    TCP = "tcp"  # the local transport's stream framing over one TCP connection
    ROS2 = "ros2"  # ROS 2 topics over Cyclone DDS: an unmodified ROS 2 node is the target


class TransportOptions(Protocol):
    """What every transport's options model has besides its fields."""

    def child_env(self) -> dict[str, str]:
        """The environment a target the harness starts is given (its run's keys,
        token, domain...): ``{}`` where the transport tells it nothing."""
        ...


@dataclass(frozen=True)
class Backend:
    """Where a transport's halves live, as ``"module:attribute"``.

    Attributes:
        link: the harness-side :class:`hil.adapters.link.Link` subclass.
        serve: the target side, ``serve_endpoint(ep, **options) -> None``.
        options: its options model (a frozen dataclass, a :class:`TransportOptions`).
        shared: a shared target's ``serve_shared(scheduler, make_endpoint, **options)``,
            or None where the transport cannot serve many vehicles from one process.
    """

    link: str
    serve: str
    options: str
    shared: str | None = None

    @classmethod
    def of(cls, package: str, link: str, options: str, *, shared: bool = False) -> Backend:
        """The row of the transport in ``hil.adapters.<package>``: ``link.<link>``,
        ``target.serve_endpoint``, ``options.<options>`` and, if ``shared``,
        ``shared_target.serve_shared``."""
        base = f"hil.adapters.{package}"
        return cls(f"{base}.link:{link}", f"{base}.target:serve_endpoint", f"{base}.options:{options}",
                   f"{base}.shared_target:serve_shared" if shared else None)


BACKENDS: dict[Transport, Backend] = {
    Transport.LOCAL: Backend.of("local", "LocalLink", "LocalOptions", shared=True),
    Transport.ZENOH: Backend.of("zenoh", "ZenohLink", "ZenohOptions", shared=True),
    Transport.CAN: Backend.of("can", "CanLink", "CanOptions"),
    Transport.MIXED: Backend.of("mixed", "MixedLink", "MixedOptions"),
    Transport.TCP: Backend.of("tcp", "TcpLink", "TcpOptions"),
    Transport.ROS2: Backend.of("ros2", "Ros2Link", "Ros2Options"),
}

NAMES: tuple[str, ...] = tuple(t.value for t in Transport)  # in table order: local, zenoh, can, mixed, tcp, ros2


def transport_of(name: str | Transport) -> Transport:
    """The :class:`Transport` called ``name``.

    Raises:
        TransportError: no transport has that name (the message lists the valid ones).
    """
    try:
        return Transport(name)
    except ValueError:
        raise TransportError(f"unknown transport {name!r}; valid: {', '.join(NAMES)}") from None


def _resolve(path: str) -> object:
    module, _, attribute = path.partition(":")
    return getattr(importlib.import_module(module), attribute)


def link_class(name: str | Transport) -> type[Link]:
    """The harness-side link class of transport ``name`` (its module imported now).

    Raises:
        TransportError: unknown transport. ImportError: its library is not installed.
    """
    return cast("type[Link]", _resolve(BACKENDS[transport_of(name)].link))


def serve_function(name: str | Transport) -> Callable[..., None]:
    """The target-side ``serve_endpoint(ep, **options)`` of transport ``name``.

    Raises:
        TransportError: unknown transport. ImportError: its library is not installed.
    """
    return cast(Callable[..., None], _resolve(BACKENDS[transport_of(name)].serve))


def options_class(name: str | Transport) -> type[TransportOptions]:
    """The options model of transport ``name`` (its ``options`` module imported now: no
    transport library is).

    Raises:
        TransportError: unknown transport.
    """
    return cast("type[TransportOptions]", _resolve(BACKENDS[transport_of(name)].options))


def shared_serve_function(name: str | Transport) -> Callable[..., None]:
    """A shared target's ``serve_shared(scheduler, make_endpoint, **options)`` over ``name``.

    Raises:
        TransportError: unknown transport, or one that cannot serve a shared target.
    """
    transport = transport_of(name)
    path = BACKENDS[transport].shared
    if path is None:
        shared = ", ".join(t.value for t, b in BACKENDS.items() if b.shared is not None)
        raise TransportError(f"a shared target serves over {shared.replace(', ', ' or ')}, not {transport.value!r}")
    return cast(Callable[..., None], _resolve(path))


__all__ = ["BACKENDS", "NAMES", "Backend", "Transport", "TransportOptions", "link_class", "options_class",
           "serve_function", "shared_serve_function", "transport_of"]
