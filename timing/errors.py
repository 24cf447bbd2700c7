"""The one exception tree of the harness.

::

    HilError                      base: anything the harness raises on purpose
    ├── ConfigError               a configuration value is wrong (names the YAML path)
    ├── TransportError            a link or endpoint failed (connect, send, peer gone)
    │   └── TimeoutError_         nothing arrived within a deadline
    ├── ProtocolError             bytes on the wire are malformed (names the byte offset)
    ├── SimulationError           the simulator cannot build or step the scenario
    └── TargetError               the AI target process failed (missing, exited)

It lives in ``timing`` because ``timing`` is the leaf package every other one may
import (numpy only), so the whole project shares one root error. A library's error
is wrapped ``from err``; user mistakes are printed as one line by the CLI.
"""

from __future__ import annotations


class HilError(Exception):
    """Base of every error the harness raises on purpose."""


class ConfigError(HilError):
    """A configuration value is missing, malformed or out of range."""


class TransportError(HilError):
    """A transport could not connect, send or receive, or its peer went away."""


class TimeoutError_(TransportError):
    """Nothing arrived within the deadline (named with a trailing underscore so it
    never shadows the builtin ``TimeoutError``)."""


class ProtocolError(HilError):
    """Malformed bytes on the wire.

    Attributes:
        offset: byte offset into the message where decoding failed.
    """

    def __init__(self, message: str, *, offset: int) -> None:
        super().__init__(f"{message} (at byte offset {offset})")
        self.offset = offset


class SimulationError(HilError):
    """The simulator cannot build or step the scenario."""


class TargetError(HilError):
    """The AI target process could not be started or exited unexpectedly."""
