"""Loading a run configuration: ``load_config`` reads YAML, applies
``dotted.path=value`` overrides and validates against the schema
(``hil.harness.config.model``); ``parse_config`` validates a mapping. Whatever is wrong
comes back as one ``ConfigError`` line that names the file, the YAML path, the bad
value and what was expected, e.g.::

    run.yaml: config error at camera.fps: got 0; expected greater than 0

``dump_config`` and ``config_hash`` give a config's canonical form.
"""

from __future__ import annotations

import copy
import difflib
import os
import re
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, get_origin

import yaml
from pydantic import BaseModel, ValidationError

from hil.common.errors import ConfigError
from hil.harness.config.digest import digest
from hil.harness.config.model import _GOT_MAX_CHARS, _PERIOD_ERROR, _RULE_ERROR, RunConfig

__all__ = ["config_hash", "dump_config", "load_config", "parse_config"]


# --- loading ----------------------------------------------------------------------


def load_config(path: str | os.PathLike[str], *, overrides: Sequence[str] = ()) -> RunConfig:
    """Read a YAML run config, apply ``dotted.path=value`` overrides, validate.

    Override values are parsed as YAML (``10``, ``true``, ``[a, b]``); a missing key
    on the path is created (``scenario.params.gap_m=40``). An empty file is the
    empty config.

    Raises:
        ConfigError: one line: file missing or unreadable, YAML syntax (with line and
            column), top level not a mapping, malformed override, or a value that
            fails validation (with its YAML path, the value and what was expected).
    """
    source = os.fspath(path)
    data = _read_yaml(Path(source))
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise ConfigError(
            f"{source}: config error at <root>: got {_short_repr(data)}; "
            "expected a mapping of keys to values"
        )
    return parse_config(data, source=source, overrides=overrides)


def parse_config(
    data: Mapping[str, Any], *, source: str = "<config>", overrides: Sequence[str] = ()
) -> RunConfig:
    """Validate an already-parsed mapping (after applying ``overrides``).

    ``source`` starts every error message. Raises ``ConfigError`` as ``load_config``.
    """
    merged = copy.deepcopy(dict(data))
    applied: list[tuple[tuple[str, ...], str]] = []
    for override in overrides:
        keys, value = _parse_override(override, source)
        _apply_override(merged, keys, value, override, source)
        applied.append((keys, override))
    try:
        return RunConfig.model_validate(merged)
    except ValidationError as err:
        raise ConfigError(_format_validation_error(err, source, applied)) from err


def _read_yaml(path: Path) -> Any:
    if not path.exists():
        raise ConfigError(f"config file not found: {path}")
    if path.is_dir():
        raise ConfigError(f"config path is a directory, not a file: {path}")
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as err:
        reason = err.strerror if isinstance(err, OSError) and err.strerror else str(err)
        raise ConfigError(f"cannot read config file {path}: {reason}") from err
    try:
        return yaml.safe_load(text)
    except yaml.MarkedYAMLError as err:
        raise ConfigError(_one_line(f"{path}: {_describe_yaml_error(err)}")) from err
    except yaml.YAMLError as err:
        raise ConfigError(_one_line(f"{path}: YAML error: {err}")) from err


def _describe_yaml_error(err: yaml.MarkedYAMLError) -> str:
    mark = err.problem_mark or err.context_mark
    where = f"line {mark.line + 1}, column {mark.column + 1}" if mark else "unknown place"
    problem = err.problem or "invalid YAML"
    context = f" ({err.context})" if err.context else ""
    return f"YAML syntax error at {where}: {problem}{context}"


def _parse_override(override: str, source: str) -> tuple[tuple[str, ...], Any]:
    dotted, sep, text = override.partition("=")
    keys = tuple(part.strip() for part in dotted.split("."))
    if not sep or not all(keys):
        raise ConfigError(
            f"{source}: malformed override {_short_repr(override)}: expected dotted.path=value, "
            "e.g. camera.fps=10"
        )
    try:
        value = yaml.safe_load(text)
    except yaml.YAMLError as err:
        problem = err.problem if isinstance(err, yaml.MarkedYAMLError) else str(err)
        raise ConfigError(
            _one_line(f"{source}: override {_short_repr(override)}: value is not valid YAML: {problem}")
        ) from err
    return keys, value


def _apply_override(
    data: dict[str, Any], keys: tuple[str, ...], value: Any, override: str, source: str
) -> None:
    node, model = data, _model_at(())
    for depth, key in enumerate(keys[:-1]):
        field = model.model_fields.get(key) if model else None
        model = _model_at(keys[: depth + 1])
        if key not in node and field and not model and get_origin(field.annotation) is not dict:
            # Absent scalar field: the path runs through its default, not a new mapping.
            child = field.get_default(call_default_factory=True)
        else:
            child = node.setdefault(key, {})
        if not isinstance(child, dict):
            raise ConfigError(
                f"{source}: override {_short_repr(override)}: cannot set {'.'.join(keys)} "
                f"because {'.'.join(keys[: depth + 1])} is {_short_repr(child)}, "
                "not a mapping"
            )
        node = child
    node[keys[-1]] = value


# --- error messages ---------------------------------------------------------------

_MESSAGE_REWRITES = (
    (re.compile(r"^Value error, "), ""),
    (re.compile(r"^Input should be a valid dictionary or instance of \w+"), "a mapping"),
    (re.compile(r"^Input should be "), ""),
    (re.compile(r"^(String|List|Dictionary) should have "), lambda m: f"a {m[1].lower()} with "),
    (re.compile(r"^String should match "), "a string matching "),
)


def _format_validation_error(
    err: ValidationError, source: str, applied: Sequence[tuple[tuple[str, ...], str]]
) -> str:
    errors = _untag_rig(err.errors(include_url=False))
    first = errors[0]
    loc = tuple(first["loc"])
    if first["type"] == "extra_forbidden":
        key, parent = loc[-1], loc[:-1]
        message = f"{source}: unknown key {_short_repr(key)} at {_loc_text(parent)}"
        model = _model_at(parent)
        if model is not None:
            valid = list(model.model_fields)
            close = difflib.get_close_matches(str(key), valid, n=1)
            if close:
                message += f" (did you mean {close[0]!r}?)"
            message += f" (valid keys: {', '.join(valid)})"
    else:
        got = first["input"]
        if first["type"] == _PERIOD_ERROR:
            loc, got = ("camera", "fps"), first["ctx"]["fps"]
        elif first["type"] == _RULE_ERROR:
            loc, got = tuple(first["ctx"]["loc"]), first["ctx"]["got"]
        message = (
            f"{source}: config error at {_loc_text(loc)}: got {_short_repr(got)}; "
            f"expected {_expected(first['msg'])}"
        )
    for keys, override in applied:
        if loc and (loc[: len(keys)] == keys or keys[: len(loc)] == loc):
            message += f" (set by override {_short_repr(override)})"
            break
    if len(errors) > 1:
        others = ", ".join(_loc_text(tuple(e["loc"])) for e in errors[1:6])
        more = ", ..." if len(errors) > 6 else ""
        message += f" (+{len(errors) - 1} more: {others}{more})"
    return _one_line(message)


_RIG_TAGS = ("str", "list[RigCamera]")


def _untag_rig(errors: list[Any]) -> list[Any]:
    """``camera.rig`` is a preset's name or a list: pydantic tries both and names each
    try in the location; keep the errors of the kind that was given, untagged."""
    def tag(e: Any) -> str | None:
        loc = tuple(e["loc"])
        return loc[2] if loc[:2] == ("camera", "rig") and len(loc) > 2 and loc[2] in _RIG_TAGS else None

    if not any(tag(e) for e in errors):
        return errors
    given = next((e["input"] for e in errors if tag(e) == "str"), None)
    keep = "str" if isinstance(given, str) else "list[RigCamera]"
    out = [{**e, "loc": (*tuple(e["loc"])[:2], *tuple(e["loc"])[3:])} for e in errors if tag(e) in (None, keep)]
    return out or errors


def _expected(msg: str) -> str:
    for pattern, replacement in _MESSAGE_REWRITES:
        new = pattern.sub(replacement, msg, count=1)
        if new != msg:
            return new
    return msg[:1].lower() + msg[1:]


def _model_at(loc: tuple[Any, ...]) -> type[BaseModel] | None:
    model: type[BaseModel] = RunConfig
    for part in loc:
        field = model.model_fields.get(part) if isinstance(part, str) else None
        annotation = field.annotation if field else None
        if not (isinstance(annotation, type) and issubclass(annotation, BaseModel)):
            return None
        model = annotation
    return model


def _loc_text(loc: tuple[Any, ...]) -> str:
    text = ""
    if loc and loc[-1] == "[key]":  # pydantic's marker for a bad mapping key: the key is named already
        loc = loc[:-1]
    for part in loc:
        text += f"[{part}]" if isinstance(part, int) else (f".{part}" if text else str(part))
    return text or "<root>"


class _Enough(Exception):
    """Raised inside ``_short_repr`` once the text is long enough."""


def _short_repr(value: Any, *, limit: int = _GOT_MAX_CHARS) -> str:
    """``repr(value)`` cut to ``limit`` characters, in work bounded by ``limit``.

    A YAML alias bomb (each level a list of aliases of the level below) is a few
    hundred bytes whose full ``repr`` would take minutes and gigabytes, so
    containers are walked only until ``limit`` characters are out.
    """
    parts: list[str] = []
    room = [limit + 1]

    def emit(text: str) -> None:
        parts.append(text[: room[0]])
        room[0] -= len(text)
        if room[0] <= 0:
            raise _Enough

    def walk(v: Any) -> None:
        if isinstance(v, dict):
            emit("{")
            for i, (k, x) in enumerate(v.items()):
                emit(", " if i else "")
                walk(k)
                emit(": ")
                walk(x)
            emit("}")
        elif isinstance(v, (list, tuple)):
            emit("[" if isinstance(v, list) else "(")
            for i, x in enumerate(v):
                emit(", " if i else "")
                walk(x)
            emit("]" if isinstance(v, list) else ")")
        elif isinstance(v, str):
            emit(repr(v[: limit + 2]) if len(v) > limit + 2 else repr(v))
        elif isinstance(v, int) and not isinstance(v, bool) and v.bit_length() > 4 * limit:
            emit(f"<integer of {v.bit_length()} bits>")  # repr of a huge int is slow, or refused
        else:
            emit(repr(v))

    try:
        walk(value)
    except _Enough:
        pass
    text = "".join(parts)
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _one_line(text: str) -> str:
    return " ".join(text.split())


# --- canonical form ---------------------------------------------------------------


def dump_config(cfg: RunConfig) -> dict[str, Any]:
    """The config as a JSON-able dict (enums as their string values)."""
    return cfg.model_dump(mode="json")


def config_hash(cfg: RunConfig) -> str:
    """sha256 hex digest of the canonical JSON (``hil.harness.config.digest``): stable
    across runs."""
    return digest(dump_config(cfg))
