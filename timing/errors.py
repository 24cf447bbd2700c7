"""Re-export of the project's exception tree, which lives in :mod:`hil_errors`.

Kept so that ``from timing.errors import ConfigError`` (and the like) keeps working;
new code imports from ``hil_errors`` directly. The tree is drawn in
``hil_errors``'s docstring.
"""

from __future__ import annotations

from hil_errors import (
    ConfigError,
    HilError,
    ProtocolError,
    RecordingError,
    SimulationError,
    TargetError,
    TransportError,
)

__all__ = [
    "ConfigError",
    "HilError",
    "ProtocolError",
    "RecordingError",
    "SimulationError",
    "TargetError",
    "TransportError",
]
