"""What CI systems read: ``--junit FILE`` (JUnit XML, one testcase per check, its
figures as properties, as CARLA ScenarioRunner's ``--junit`` gives one per criterion)
and ``--json FILE`` (the same checks as a machine-readable verdict), for ``hil run``,
``compare``, ``search``, ``study``, ``calibrate`` and ``target-check``.

The file always agrees with the command's exit code: a testcase fails exactly when
its check makes the command exit non-zero. A check that failed but does not fail the
command (``hil run`` without it in ``--fail-on``: a warning) is a passed testcase
whose properties say ``ok=false`` and ``fails_command=false``, with the headline in
its ``system-out``: a CI that turns red on any JUnit failure then agrees with the
exit code that the user chose with ``--fail-on``.

JUnit XML is written with ``junitparser`` (a maintained library): a ``<testsuites>``
root with one ``<testsuite>`` named after the command (suite properties: what was
checked), each ``<testcase classname="hil.COMMAND.GROUP" name="CHECK">`` with
``<properties>`` (pytest's ``record_property`` layout, which Jenkins, GitLab and
GitHub test reporters read), ``<failure message type>`` when it failed, and
``<system-out>`` for a warning. JSON (schema version 1): ``command``, ``name``,
``passed`` (exit code 0), ``exit_code``, ``properties``, ``checks`` (each ``name``,
``group``, ``ok``, ``fails_command``, ``message``, ``properties``, ``output``), and
the command's own ``details``.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from hil.common.errors import ConfigError

SCHEMA_VERSION = 1


@dataclass(frozen=True)
class CiCase:
    """One check. ``ok``: it passed; ``fails_command``: it failed and makes the
    command exit non-zero (a JUnit failure); a failed check that does not is a
    warning (``output``). ``message``: one line a person reads; ``properties``: its
    figures (scalars; anything else is written as JSON text)."""

    name: str
    ok: bool
    message: str = ""
    properties: Mapping[str, Any] = field(default_factory=dict)
    group: str = ""
    fails_command: bool | None = None  # None: exactly when not ok
    output: str = ""

    @property
    def failure(self) -> bool:
        return (not self.ok) if self.fails_command is None else self.fails_command


@dataclass(frozen=True)
class CiReport:
    """A command's checks and its exit code, as CI outputs (see the module docstring)."""

    command: str
    name: str
    cases: Sequence[CiCase]
    exit_code: int
    properties: Mapping[str, Any] = field(default_factory=dict)
    details: Mapping[str, Any] = field(default_factory=dict)
    time_s: float | None = None

    def to_json(self) -> dict[str, Any]:
        return {"schema_version": SCHEMA_VERSION, "command": self.command, "name": self.name,
                "passed": self.exit_code == 0, "exit_code": self.exit_code, "properties": _plain(self.properties),
                "checks": [{"name": c.name, "group": c.group, "ok": c.ok, "fails_command": c.failure,
                            "message": c.message, "properties": _plain(c.properties), "output": c.output}
                           for c in self.cases],
                "details": _plain(self.details)}


def add_ci_args(p: argparse.ArgumentParser) -> None:
    """``--junit FILE`` and ``--json FILE`` on a command's parser."""
    p.add_argument("--junit", type=Path, default=None, metavar="FILE",
                   help="write a JUnit XML file: one testcase per check, its figures as properties, failed "
                        "exactly when the check makes the command fail")
    p.add_argument("--json", dest="json_out", type=Path, default=None, metavar="FILE",
                   help="write the checks and the exit code as JSON (machine-readable verdict)")


def check_ci_args(args: argparse.Namespace) -> None:
    """Refuse, before any work, an output file whose folder is missing or not writable.

    Raises:
        ConfigError: names the flag and the file.
    """
    for flag, path in (("--junit", getattr(args, "junit", None)), ("--json", getattr(args, "json_out", None))):
        if path is None:
            continue
        folder = Path(path).parent if str(Path(path).parent) else Path(".")
        if Path(path).is_dir():
            raise ConfigError(f"{flag} {path}: is a folder; expected a file name")
        if not folder.is_dir():
            raise ConfigError(f"{flag} {path}: folder {folder} does not exist")
        if not os.access(folder, os.W_OK):
            raise ConfigError(f"{flag} {path}: folder {folder} is not writable")


def write_ci_outputs(report: CiReport, args: argparse.Namespace) -> None:
    """Write the files asked for by ``--junit`` / ``--json`` (none: nothing).

    Raises:
        ConfigError: a file cannot be written (names it and why).
    """
    junit, js = getattr(args, "junit", None), getattr(args, "json_out", None)
    try:
        if junit is not None:
            write_junit(report, Path(junit))
        if js is not None:
            _atomic_write(Path(js), json.dumps(report.to_json(), indent=2, allow_nan=False, ensure_ascii=False) + "\n")
    except OSError as err:
        raise ConfigError(f"cannot write {err.filename or junit or js}: {err.strerror or err}") from err


def write_junit(report: CiReport, path: Path) -> None:
    """``report`` as a JUnit XML file (layout in the module docstring)."""
    try:
        import junitparser as jp
    except ImportError as err:  # pragma: no cover - depends on the install
        raise ConfigError("--junit needs junitparser: pip install 'junitparser>=4,<6'") from err

    suite = jp.TestSuite(f"hil {report.command}: {report.name}")
    suite.timestamp = time.strftime("%Y-%m-%dT%H:%M:%S")
    suite.hostname = os.uname().nodename
    for k, v in {"exit_code": report.exit_code, **report.properties}.items():
        suite.add_property(str(k), _text(v))
    for c in report.cases:
        case = jp.TestCase(c.name, f"hil.{report.command}" + (f".{c.group}" if c.group else ""))
        props = jp.Properties()
        for k, v in {"ok": c.ok, "fails_command": c.failure, **c.properties}.items():
            props.add_property(jp.Property(str(k), _text(v)))
        case.append(props)
        if c.failure:
            failure = jp.Failure(c.message or f"{c.name} failed", c.name)
            failure.text = c.message
            case.result = [failure]
        out = c.output or ("" if c.ok or c.failure else f"warning: {c.message}")
        if out:
            case.system_out = out
        suite.add_testcase(case)
    if report.time_s is not None:
        suite.time = round(report.time_s, 3)
    xml = jp.JUnitXml()
    xml.add_testsuite(suite)
    tmp = path.with_name(f".{path.name}.tmp")
    xml.write(str(tmp))
    os.replace(tmp, path)


def _atomic_write(path: Path, text: str) -> None:
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(text, encoding="utf-8")
    os.replace(tmp, path)


def _plain(v: Any) -> Any:
    """JSON-safe: NaN and infinities become None; tuples lists; unknown objects text."""
    if isinstance(v, float):
        return v if math.isfinite(v) else None
    if isinstance(v, Mapping):
        return {str(k): _plain(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_plain(x) for x in v]
    if v is None or isinstance(v, (bool, int, str)):
        return v
    return str(v)


def _text(v: Any) -> str:
    """A property value: booleans ``true``/``false``, numbers as Python writes them,
    missing as empty, anything structured as JSON."""
    if v is None:
        return ""
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, float, str)):
        return str(v)
    return json.dumps(_plain(v), sort_keys=True)


def flat(prefix: str, values: Mapping[str, Any]) -> dict[str, Any]:
    """``{"a": {"b": 1}}`` as ``{"prefix.a.b": 1}`` (scalars and lists kept)."""
    out: dict[str, Any] = {}
    for k, v in values.items():
        key = f"{prefix}.{k}" if prefix else str(k)
        if isinstance(v, Mapping):
            out.update(flat(key, v))
        else:
            out[key] = v
    return out


__all__ = ["CiCase", "CiReport", "SCHEMA_VERSION", "add_ci_args", "check_ci_args", "flat", "write_ci_outputs",
           "write_junit"]
