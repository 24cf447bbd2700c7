"""Events as people read them: the one-line text of Foxglove's ``/log``, the
report's event table, its tooltips and the corner cases' evidence.

An ``/events`` message (``hil.harness.vocab.events.Event.to_json``) is made for
programs: a driving state is a number (``measured 2``, ``threshold 1``, unit
``state``), times are integer nanoseconds on the monotonic clock, ``None`` and empty
lists stand for "not known". Here a state is its name (``AI STOP, truth SLOW``), a
time field (``*_ns`` named for a time: ``t0_ns``, ``sim_time_apply_ns``) is in
seconds, a duration (``latency_ns``) in milliseconds, and what is not known is left
out. Nested values (a mismatch's ``evidence``) are written whole, never cut inside
a key or a number: a text that must stay short drops whole items and says how many.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

from hil.adapters.wire.messages import DrivingState

#: Fields every event carries; :func:`event_line` writes them in its own words.
_CORE = ("kind", "vehicle", "frame_ids", "sim_time_ns", "harness_time_ns", "measured", "threshold", "unit",
         "severity", "cause", "links", "detail", "stage", "entity")
_LIST_ITEMS = 6  # numbers of a list shown before "(+N more)"


def _finite(v: object) -> float | None:
    """``v`` as a float when it is a finite number (a bool is not one), else None."""
    return float(v) if isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) else None


def _num(v: object) -> bool:
    return _finite(v) is not None


def number(v: float) -> str:
    """At most 4 significant digits, no exponent for everyday sizes (``61.23``, ``0.0042``)."""
    if isinstance(v, int) or float(v).is_integer() and abs(v) < 1e15:
        return str(int(v))
    return f"{v:.4g}"


def state_name(v: Any) -> str:
    """A driving state's name from its wire value (``2`` → ``STOP``); the value itself
    when it is none of them."""
    try:
        return DrivingState(int(v)).name
    except (TypeError, ValueError):
        return str(v)


_COUNTED = frozenset({"frames", "estimates", "records", "steps", "cameras", "messages"})  # plural count units


def value_vs_threshold(data: Mapping[str, Any]) -> str:
    """``measured`` against ``threshold`` with their unit (``61.2 ms > 50 ms``); a
    state mismatch as the two states (``AI STOP, truth SLOW``); ``–`` without a value."""
    m, th, unit = data.get("measured"), data.get("threshold"), data.get("unit")
    mf, tf = _finite(m), _finite(th)
    if mf is None:
        return "–"
    if unit == "state":
        return f"AI {state_name(m)}" + (f", truth {state_name(th)}" if tf is not None else "")
    u = f" {unit}" if isinstance(unit, str) and unit else ""
    one = u[:-1] if mf == 1 and unit in _COUNTED else u  # "1 frame", not "1 frames"
    if tf is None:
        return f"{number(mf)}{one}"
    return f"{number(mf)}{one} {'>' if mf > tf else '≤'} {number(tf)}{u}"


def frames(data: Mapping[str, Any]) -> str:
    """The event's frame ids (``46, 47, 48``; a long list as its first three and a count)."""
    ids = data.get("frame_ids")
    if isinstance(ids, list) and ids:
        return ", ".join(str(i) for i in ids[:3]) + (f" (+{len(ids) - 3})" if len(ids) > 3 else "")
    fid = data.get("frame_id")
    return str(fid) if isinstance(fid, int) else "–"


def cause(data: Mapping[str, Any]) -> str:
    """Cause, stage, entity and detail, as given (``–`` when none)."""
    parts = [str(data[k]) for k in ("cause", "stage", "entity") if isinstance(data.get(k), str) and data[k]]
    detail = data.get("detail")
    if isinstance(detail, str) and detail:
        parts.append(detail)
    return "; ".join(parts) or "–"


def _is_time(key: str) -> bool:
    """A ``*_ns`` field that is an instant (seconds), not a duration (ms)."""
    stem = key[:-3]
    return "time" in stem or stem.startswith("t_") or stem in ("t0", "t0p", "ref")


def field(key: str, v: Any) -> tuple[str, str] | None:
    """One field as ``(name, value)`` in words and units; ``None`` for "not known"."""
    if v is None or v == [] or v == {} or v == "":
        return None
    name = key
    if key.endswith("_ns") and _num(v):
        name = key[:-3]
        text = f"{v / 1e9:.3f} s" if _is_time(key) else f"{number(round(v / 1e6, 3))} ms"
    elif key == "state" or key.endswith("_state"):
        text = state_name(v) if _num(v) else str(v)
    elif isinstance(v, Mapping):
        inner = value(v)
        if not inner:
            return None
        text = f"({inner})"
    else:
        text = value(v)
    return name.replace("_", " "), text


def value(v: Any) -> str:
    """Any JSON value in words: a mapping as ``key value, key value``, a list as
    its items, a number with at most 4 significant digits, ``yes``/``no``."""
    if isinstance(v, bool):
        return "yes" if v else "no"
    if _num(v):
        return number(v)
    if isinstance(v, Mapping):
        return ", ".join(f"{n} {t}" for n, t in (f for f in (field(str(k), x) for k, x in v.items()) if f))
    if isinstance(v, Sequence) and not isinstance(v, str):
        items = [value(x) for x in v]
        more = len(items) - _LIST_ITEMS
        return "[" + ", ".join(items[:_LIST_ITEMS]) + (f", +{more} more" if more > 0 else "") + "]"
    return str(v)


def fit(parts: Sequence[str], limit: int, sep: str = "; ") -> str:
    """``parts`` joined, dropping whole parts from the end (and saying how many) to
    stay within ``limit`` characters: never a cut inside one."""
    out: list[str] = []
    for i, p in enumerate(parts):
        rest = len(parts) - i - 1
        tail = f"{sep}(+{rest} more)" if rest else ""
        if len(sep.join([*out, p])) + len(tail) > limit and out:
            return sep.join(out) + f"{sep}(+{len(parts) - i} more)"
        out.append(p)
    return sep.join(out)


def extra_fields(data: Mapping[str, Any]) -> list[str]:
    """The event's own fields beyond the promised ones, in words (``evidence (...)``)."""
    out = []
    for k, v in data.items():
        if k in _CORE:
            continue
        f = field(str(k), v)
        if f is not None:
            out.append(f"{f[0]} {f[1]}")
    return out


def event_line(data: Mapping[str, Any], *, limit: int = 1000) -> str:
    """One line for an ``/events`` message (Foxglove's ``/log``), e.g.
    ``mismatch.state_mismatch ego0, frames 46, 47, 48, sim 4.800 s: AI STOP, truth
    SLOW; perception; AI said STOP where truth says SLOW; evidence (frame id 48, ...)``.
    Whole parts only: at most ``limit`` characters after the head."""
    head = [str(data.get("kind", "event"))]
    if isinstance(data.get("vehicle"), str):
        head.append(str(data["vehicle"]))
    who = " ".join(head)
    where = []
    if frames(data) != "–":
        where.append(f"frame{'s' if len(data.get('frame_ids') or ()) > 1 else ''} {frames(data)}")
    if _num(data.get("sim_time_ns")):
        where.append(f"sim {data['sim_time_ns'] / 1e9:.3f} s")
    parts = [p for p in (value_vs_threshold(data), cause(data)) if p != "–"]
    links = data.get("links")
    if isinstance(links, list) and links:
        parts.append("linked: " + ", ".join(str(x) for x in links))
    parts += extra_fields(data)
    return (who + (", " + ", ".join(where) if where else "") + (": " + fit(parts, limit) if parts else ""))


__all__ = ["cause", "event_line", "extra_fields", "field", "fit", "frames", "number", "state_name", "value",
           "value_vs_threshold"]
