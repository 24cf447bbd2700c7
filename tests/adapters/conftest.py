"""Transport pairs for the conformance suite.

A pair factory opens a harness-side ``Link`` (HELLO received) to a real target
running the SDK's echo target, and closes everything it started. Each transport
contributes its factory in its own module ``tests/adapters/<name>/pair.py`` exposing
``PAIR_FACTORY`` (a context-manager function ``(tmp_path, echo_args) -> Link``) and
optionally ``SKIP_REASON`` (a string when the transport cannot run here).
"""

from __future__ import annotations

import contextlib
import importlib
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

from hil.adapters.link import Link, open_link
from hil.timing.clock import MonotonicClock

TRANSPORT_NAMES = ("local", "zenoh", "can", "tcp")


@contextlib.contextmanager
def local_pair(tmp_path: Path, echo_args: list[str]) -> Iterator[Link]:
    link = open_link("local", command=[sys.executable, "-m", "hil.targets.echo", *echo_args], vehicle_id=0,
                     clock=MonotonicClock(), log_path=tmp_path / "target.log")
    try:
        link.open(hello_timeout_s=20)
        yield link
    finally:
        link.close()


def _factory(name: str):
    if name == "local":
        return local_pair, None
    try:
        mod = importlib.import_module(f"tests.adapters.{name}.pair")
    except ModuleNotFoundError as err:
        if err.name == f"tests.adapters.{name}.pair":
            return None, f"no {name} pair factory yet"
        raise
    return mod.PAIR_FACTORY, getattr(mod, "SKIP_REASON", None)


@pytest.fixture(params=TRANSPORT_NAMES)
def pair(request: pytest.FixtureRequest, tmp_path: Path):
    """A factory ``pair(echo_args) -> context manager yielding an open Link``."""
    factory, skip = _factory(request.param)
    if factory is None or skip:
        pytest.skip(skip or f"{request.param}: unavailable")
    return lambda echo_args=(): factory(tmp_path, list(echo_args))
