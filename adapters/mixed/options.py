"""Options of the mixed transport: the zenoh transport's for the frames and the can
transport's for everything else (no library imports)."""

from __future__ import annotations

from dataclasses import dataclass, field

from hil.adapters.can.options import CanOptions
from hil.adapters.zenoh.options import ZenohOptions


@dataclass(frozen=True)
class MixedOptions:
    """Both halves' options, each its own transport's model: ``zenoh`` (the frame path;
    its run's keys and credentials as a zenoh target's) and ``can`` (everything else;
    its ``camera_over`` is ignored: a mixed link sends no frame on the bus)."""

    zenoh: ZenohOptions = field(default_factory=ZenohOptions)
    can: CanOptions = field(default_factory=CanOptions)

    def child_env(self) -> dict[str, str]:
        """What a target the harness starts is told: its zenoh half's keys and credentials."""
        return self.zenoh.child_env()


__all__ = ["MixedOptions"]
