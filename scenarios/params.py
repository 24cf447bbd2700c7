"""Typed scenario parameter spaces: each parameter has a name, a range and a default."""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

from hil.common.errors import ConfigError


@dataclass(frozen=True)
class Param:
    """One scenario parameter: a float (or, with ``integer``, a whole number) in
    ``[lo, hi]`` with a default and a unit."""

    name: str
    lo: float
    hi: float
    default: float
    unit: str = ""
    help: str = ""
    integer: bool = False

    def __post_init__(self) -> None:
        if not (self.lo <= self.default <= self.hi):
            raise ValueError(f"param {self.name}: default {self.default} outside [{self.lo}, {self.hi}]")
        if self.integer and not float(self.default).is_integer():
            raise ValueError(f"param {self.name}: integer parameter with default {self.default}")

    @property
    def kind(self) -> str:
        return "integer" if self.integer else "number"

    def describe(self) -> str:
        kind = " integer" if self.integer else ""
        return f"{self.name}{kind} in [{self.lo:g}, {self.hi:g}] {self.unit} (default {self.default:g})".replace("  ", " ")


def resolve_params(scenario: str, space: tuple[Param, ...], given: Mapping[str, float]) -> dict[str, float]:
    """Fill defaults and check ``given`` against ``space``.

    Raises:
        ConfigError: an unknown name (listing the valid ones) or a value out of range.
    """
    by_name = {p.name: p for p in space}
    for key in given:
        if key not in by_name:
            valid = "; ".join(p.describe() for p in space) or "none"
            raise ConfigError(
                f"scenario.params.{key}: unknown parameter of scenario {scenario!r}; valid: {valid}"
            )
    out: dict[str, float] = {}
    for p in space:
        value = float(given.get(p.name, p.default))
        kind = "an integer" if p.integer else "a value"
        if not math.isfinite(value) or not (p.lo <= value <= p.hi) or (p.integer and not value.is_integer()):
            valid = "; ".join(q.describe() for q in space)
            raise ConfigError(
                f"scenario.params.{p.name}: got {value:g}; expected {kind} in [{p.lo:g}, {p.hi:g}] {p.unit}".rstrip()
                + f" (parameters of {scenario!r}: {valid})"
            )
        out[p.name] = value
    return out
