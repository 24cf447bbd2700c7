"""Reading one JSON object of ``summary.json`` field by field, for the typed records of
:mod:`hil.harness.vocab.figures`.

A missing key (or ``null`` where the field may be absent) gives the field's default;
a value of the wrong type raises :class:`hil.common.errors.ConfigError` with one line
naming the field by its dotted path (``vehicles.ego0.frames_sent: expected an
integer, got 'many'``). JSON numbers keep their type (an ``int`` stays an ``int``), so
a figure prints as ``summary.json`` holds it.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any

from hil.common.errors import ConfigError


def bad(path: str, expected: str, value: Any) -> ConfigError:
    """The one-line error for ``path`` holding ``value`` where ``expected`` was due."""
    shown = repr(value)
    return ConfigError(f"{path}: expected {expected}, got {shown if len(shown) <= 40 else shown[:37] + '...'}")


class Fields:
    """The JSON object ``d`` found at ``path`` (``""``: the top level).

    Raises:
        ConfigError: ``d`` is not an object.
    """

    def __init__(self, d: Any, path: str = "") -> None:
        if not isinstance(d, Mapping):
            raise bad(path or "summary", "an object", d)
        self.d: Mapping[str, Any] = d
        self.path = path

    def at(self, key: str) -> str:
        """The dotted path of ``key``."""
        return f"{self.path}.{key}" if self.path else key

    def integer(self, key: str, default: int = 0) -> int:
        if key not in self.d:
            return default
        v = self.d[key]
        if not isinstance(v, int) or isinstance(v, bool):
            raise bad(self.at(key), "an integer", v)
        return v

    def opt_integer(self, key: str) -> int | None:
        v = self.d.get(key)
        if v is None:
            return None
        if not isinstance(v, int) or isinstance(v, bool):
            raise bad(self.at(key), "an integer or null", v)
        return v

    def number(self, key: str, default: float = 0.0) -> float:
        if key not in self.d:
            return default
        v = self.d[key]
        if not isinstance(v, (int, float)) or isinstance(v, bool):
            raise bad(self.at(key), "a number", v)
        return v  # int or float, as written

    def opt_number(self, key: str) -> float | None:
        v = self.d.get(key)
        if v is None:
            return None
        if not isinstance(v, (int, float)) or isinstance(v, bool):
            raise bad(self.at(key), "a number or null", v)
        return v

    def flag(self, key: str, default: bool) -> bool:
        v = self.d.get(key, default)
        if not isinstance(v, bool):
            raise bad(self.at(key), "true or false", v)
        return v

    def opt_text(self, key: str) -> str | None:
        v = self.d.get(key)
        if v is not None and not isinstance(v, str):
            raise bad(self.at(key), "a string or null", v)
        return v

    def text(self, key: str, default: str = "") -> str:
        v = self.opt_text(key)
        return default if v is None else v

    def texts(self, key: str) -> tuple[str, ...]:
        v = self.d.get(key)
        if v is None:
            return ()
        if not isinstance(v, list) or not all(isinstance(x, str) for x in v):
            raise bad(self.at(key), "a list of strings", v)
        return tuple(v)

    def obj(self, key: str) -> Fields | None:
        """The object at ``key``; ``None`` when it is missing or null."""
        v = self.d.get(key)
        return None if v is None else Fields(v, self.at(key))

    def raw_obj(self, key: str) -> Mapping[str, Any] | None:
        """The object at ``key`` as written; ``None`` when missing or null."""
        f = self.obj(key)
        return None if f is None else f.d

    def objs(self, key: str) -> dict[str, Fields]:
        """An object of objects (``vehicles``, ``latency_ms`` ...), by name; ``{}`` when missing."""
        f = self.obj(key)
        return {} if f is None else {name: Fields(v, f.at(name)) for name, v in f.d.items()}

    def counts(self, key: str) -> dict[str, int]:
        """An object of integers (counts by kind); ``{}`` when missing."""
        f = self.obj(key)
        return {} if f is None else {k: f.integer(k) for k in f.d}

    def nums(self, key: str) -> dict[str, float | None]:
        """An object of numbers (or nulls); ``{}`` when missing."""
        f = self.obj(key)
        return {} if f is None else {k: f.opt_number(k) for k in f.d}

    def items(self, key: str) -> tuple[Any, ...]:
        v = self.d.get(key)
        if v is None:
            return ()
        if not isinstance(v, list):
            raise bad(self.at(key), "a list", v)
        return tuple(v)

    def rest(self, typed: Mapping[str, Any] | tuple[str, ...]) -> dict[str, Any]:
        """The keys not in ``typed``, as written."""
        return {k: v for k, v in self.d.items() if k not in typed}


def field_names(cls: Any) -> tuple[str, ...]:
    """The field names of the dataclass ``cls`` (what its ``extra`` leaves out)."""
    return tuple(x.name for x in dataclasses.fields(cls))


def optional(cls: Any, f: Fields | None) -> Any:
    """``cls.from_json(f)``; ``None`` for a missing (or null) object."""
    return None if f is None else cls.from_json(f)


__all__ = ["Fields", "bad", "field_names", "optional"]
