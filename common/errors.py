"""The one exception tree of the project, in a leaf package every other one may import.

::

    HilError                      base: anything the project raises on purpose
    ├── ConfigError               a configuration value is wrong (names the YAML path)
    ├── TransportError            a link or endpoint failed (connect, send, peer gone)
    ├── ProtocolError             bytes on the wire are malformed (names the byte offset)
    ├── SimulationError           the simulator cannot build or step the scenario
    ├── TargetError               the AI target process failed (missing, exited)
    └── RecordingError            the recording could not be written (disk full, I/O error)

This package imports nothing (not even of ours), so ``timing``, ``scenarios``,
``adapters``, ``harness`` and ``targets`` all share one root error without any of
them importing another only for its errors. ``hil.common.errors`` re-exports these
names for existing imports. A library's error is wrapped ``from err``; user
mistakes are printed as one line by the CLI (exit 2).

A timeout is not an error here: a receive that times out returns ``None`` and the
caller decides what it means.
"""

from __future__ import annotations


class HilError(Exception):
    """Base of every error the harness raises on purpose."""


class ConfigError(HilError):
    """A configuration value is missing, malformed or out of range."""


class TransportError(HilError):
    """A transport could not connect, send or receive, or its peer went away."""


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


class RecordingError(HilError):
    """The recording (MCAP) could not be written: disk full, permissions lost, I/O error.

    Not a :class:`ConfigError`: the configuration was fine, the file system failed
    during the run. The underlying :class:`OSError` is the ``__cause__``.
    """


__all__ = [
    "ConfigError",
    "HilError",
    "ProtocolError",
    "RecordingError",
    "SimulationError",
    "TargetError",
    "TransportError",
]
