"""Options of the tcp transport (standard library only): the addresses either side
listens on or dials."""

from __future__ import annotations

DEFAULT_PORT = 7600
DEFAULT_ADDRESS = f"127.0.0.1:{DEFAULT_PORT}"  # loopback: nothing is reachable from elsewhere unless asked

__all__ = ["DEFAULT_ADDRESS", "DEFAULT_PORT"]
