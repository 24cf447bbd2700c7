"""The scenario library as text or data: what ``hil scenarios`` prints."""

from __future__ import annotations

import textwrap
from typing import Any

from hil.scenarios.registry import ScenarioDef, get, names


def as_dict(name: str | None = None) -> dict[str, Any]:
    """Every scenario (or the one called ``name``) with its parameters.

    Raises:
        ConfigError: ``name`` is not a registered scenario (listing the valid ones).
    """
    defs = [get(name)] if name else [get(n) for n in names()]
    return {d.name: {"summary": d.summary, "params": [
        {"name": p.name, "type": p.kind, "min": p.lo, "max": p.hi, "default": p.default, "unit": p.unit,
         "help": p.help} for p in d.params]} for d in defs}


def describe(name: str | None = None, *, width: int = 100) -> str:
    """A readable listing: each scenario, its summary and a table of its parameters
    (name, range, default, unit, meaning). Raises ConfigError as ``as_dict``."""
    defs = [get(name)] if name else [get(n) for n in names()]
    blocks = [_block(d, width) for d in defs]
    # Not `--set scenario.name=NAME`: the config's params belong to its own scenario, and are refused by another.
    foot = ("Tune the configured scenario with: hil run CONFIG --set scenario.params.PARAM=VALUE; pick another with its"
            " parameters: --set 'scenario={name: NAME, params: {PARAM: VALUE}}'; the seed (--set seed=N) jitters"
            " what each summary says.")
    return "\n\n".join(blocks) + "\n\n" + "\n".join(textwrap.wrap(foot, width)) + "\n"


def _block(d: ScenarioDef, width: int) -> str:
    lines = [d.name]
    lines += textwrap.wrap(d.summary, width, initial_indent="  ", subsequent_indent="  ")
    rows = [("parameter", "range", "default", "unit", "meaning")]
    for p in d.params:
        kind = " (integer)" if p.integer else ""
        rows.append((p.name, f"[{p.lo:g}, {p.hi:g}]{kind}", f"{p.default:g}", p.unit, p.help))
    widths = [max(len(r[i]) for r in rows) for i in range(4)]
    for r in rows:
        lines.append("    " + "  ".join(c.ljust(w) for c, w in zip(r[:4], widths)) + "  " + r[4])
    return "\n".join(line.rstrip() for line in lines)
