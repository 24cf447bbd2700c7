"""The transport table (hil.adapters.transports); the import graph it keeps acyclic is
checked in tests/test_imports.py."""

from __future__ import annotations

import pytest

from hil.adapters import transports
from hil.adapters.link import TRANSPORTS, Link, open_link
from hil.adapters.transports import BACKENDS, NAMES, Transport
from hil.common.errors import TransportError


def test_every_transport_has_a_row_and_its_halves_resolve() -> None:
    assert set(BACKENDS) == set(Transport) and NAMES == TRANSPORTS == ("local", "zenoh", "can", "mixed", "tcp", "ros2")
    for kind in Transport:
        cls = transports.link_class(kind)
        assert issubclass(cls, Link) and cls.transport_name == kind.value
        assert callable(transports.serve_function(kind.value))
    assert {t for t, b in BACKENDS.items() if b.shared is not None} == {Transport.LOCAL, Transport.ZENOH}
    assert callable(transports.shared_serve_function("zenoh"))
    with pytest.raises(TransportError, match="a shared target serves over local or zenoh, not 'can'"):
        transports.shared_serve_function(Transport.CAN)


def test_the_config_takes_the_same_enum() -> None:
    from hil.harness.config.model import Transport as ConfigTransport
    from hil.harness.config.model import parse_config

    assert ConfigTransport is Transport
    assert parse_config({"target": {"transport": "tcp", "command": ["x"]}}).target.transport is Transport.TCP


def test_unknown_transport_is_one_error_listing_the_valid_ones() -> None:
    with pytest.raises(TransportError, match=r"unknown transport 'pigeon'; valid: local, zenoh, can, mixed, tcp, ros2"):
        open_link("pigeon")
    from hil.adapters.sdk import serve

    with pytest.raises(TransportError, match="unknown transport 'pigeon'"):
        serve(lambda frame: None, target_name="t", transport="pigeon")  # type: ignore[arg-type,return-value]
