"""The transport table (hil.adapters.transports); the import graph it keeps acyclic is
checked in tests/test_imports.py."""

from __future__ import annotations

import ast
from pathlib import Path

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
    from hil.harness.config.loading import parse_config
    from hil.harness.config.model import Transport as ConfigTransport

    assert ConfigTransport is Transport
    assert parse_config({"target": {"transport": "tcp", "command": ["x"]}}).target.transport is Transport.TCP


def test_unknown_transport_is_one_error_listing_the_valid_ones() -> None:
    with pytest.raises(TransportError, match=r"unknown transport 'pigeon'; valid: local, zenoh, can, mixed, tcp, ros2"):
        open_link("pigeon")
    from hil.adapters.sdk import serve

    with pytest.raises(TransportError, match="unknown transport 'pigeon'"):
        serve(lambda frame: None, target_name="t", transport="pigeon")  # type: ignore[arg-type,return-value]


def test_options_of_another_transport_are_refused_by_name() -> None:
    from hil.adapters.tcp.options import TcpOptions
    from hil.timing.clock import MonotonicClock

    with pytest.raises(TransportError, match="zenoh link: options must be a ZenohOptions, not TcpOptions"):
        open_link("zenoh", vehicle_id=0, clock=MonotonicClock(), options=TcpOptions())


ADAPTERS = Path(__file__).resolve().parents[2] / "adapters"


def test_each_transport_is_a_package_of_its_halves_and_options() -> None:
    for kind, row in BACKENDS.items():
        package = ADAPTERS / kind.value
        assert {"__init__.py", "link.py", "target.py", "options.py"} <= {p.name for p in package.glob("*.py")}, kind
        for path in (row.link, row.serve, row.options, *((row.shared,) if row.shared else ())):
            assert path.startswith(f"hil.adapters.{kind.value}."), path
    assert {p.parent.name for p in ADAPTERS.glob("*/__init__.py")} == {*NAMES, "wire"}


def _imports_at_load(module: str) -> set[str]:
    """The modules of ours ``module`` imports while it loads, transitively (imports in
    functions and under ``if TYPE_CHECKING:`` are not run at load)."""
    seen: set[str] = set()
    todo = [module]
    while todo:
        name = todo.pop()
        if name in seen:
            continue
        seen.add(name)
        rel = name.removeprefix("hil.adapters").strip(".").replace(".", "/")
        path = ADAPTERS / f"{rel}.py" if (ADAPTERS / f"{rel}.py").exists() else ADAPTERS / rel / "__init__.py"
        if not path.exists():
            continue
        for node in ast.parse(path.read_text(encoding="utf-8")).body:  # module level only
            if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("hil.adapters"):
                todo.append(node.module)
                todo += [f"{node.module}.{a.name}" for a in node.names]
            elif isinstance(node, ast.Import):
                todo += [a.name for a in node.names if a.name.startswith("hil.adapters")]
    return seen


def test_a_device_half_never_loads_a_harness_half() -> None:
    """What a device runs (the SDK, every target.py and shared_target.py) loads no link:
    neither the base (hil.adapters.link) nor a transport's link.py."""
    devices = ["hil.adapters.sdk", "hil.adapters.batching",
               *(f"hil.adapters.{p.parent.name}.{p.stem}" for p in ADAPTERS.glob("*/*target.py"))]
    assert len(devices) == 2 + 6 + 2
    for device in devices:
        links = sorted(m for m in _imports_at_load(device) if m == "hil.adapters.link" or m.endswith(".link"))
        assert links == [], (device, links)
