"""Whether ``hil replay`` may start the target a run folder's ``config.json`` names.

A run folder received from someone else is code: replay starts its
``target.command`` (with ``target.args``). A command is trusted without asking when
it starts nothing (the target runs elsewhere), is exactly the command of one of the
current configs (``hil_configs/`` of the working directory and of this package), or
runs one of this package's example targets (``{python} -m hil.targets.<name>``) with
only options whose values this module knows to be harmless (``_OPTIONS``: numbers,
fixed choices, names, loopback endpoints). An option that names a file (``--truth``
and ``--batch-log`` write one; ``--weights``, ``--tls``, ``--auth-dictionary`` read
one), an unknown or abbreviated option, or a value outside its kind makes the
command untrusted. Anything untrusted is run only after the user says yes at a
terminal, or with ``--trust-config``.
"""

from __future__ import annotations

import math
import re
import sys
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import yaml

from hil.common.errors import ConfigError

__all__ = ["check_replay_command", "current_config_commands", "is_trusted", "untrusted_reason"]

_PYTHONS = ("{python}",)
_PACKAGE_ROOT = Path(__file__).resolve().parents[2]
# Placeholders the harness fills in a command word (harness/config/target.substitute).
_PLACEHOLDERS = {"{python}": "python", "{vehicle_id}": "0", "{port}": "7447"}


def _number(value: str) -> bool:
    try:
        return math.isfinite(float(value))
    except ValueError:
        return False


def _integer(value: str) -> bool:
    return re.fullmatch(r"-?[0-9]{1,19}", value) is not None


def _matches(pattern: str) -> Callable[[str], bool]:
    compiled = re.compile(pattern)
    return lambda value: compiled.fullmatch(value) is not None


def _choice(*names: str) -> Callable[[str], bool]:
    return lambda value: value in names


def _frames(value: str) -> bool:
    return re.fullmatch(r"[0-9]{1,12}(,[0-9]{1,12})*,?", value) is not None


_NAME = _matches(r"[A-Za-z0-9][A-Za-z0-9_.@:+-]{0,127}")
_LOOPBACK = _matches(r"(tcp/|udp/)?(127\.0\.0\.1|localhost|\[::1\]):[0-9]{1,5}")

# Option → check of its value (None: a flag, no value). Options absent here (files,
# anything new) are untrusted until they are classified.
_Check = Callable[[str], bool] | None
_TRANSPORT: Mapping[str, _Check] = {
    "--transport": _choice("local", "zenoh", "can", "mixed", "tcp", "ros2"),
    "--listen": _LOOPBACK, "--connect": _LOOPBACK,  # never a network interface
    "--mode": _choice("peer", "client"), "--key-prefix": _matches(r"[A-Za-z0-9][A-Za-z0-9_/-]{0,127}"),
    "--vehicle": _integer,
    "--interface": _choice("socketcan", "pcan", "kvaser", "vector", "slcan", "virtual"),
    "--channel": _NAME, "--bitrate": _integer, "--data-bitrate": _integer,
    "--keep-serving": None, "--once": None,
}
_CLOCK: Mapping[str, _Check] = {"--name": _NAME, "--clock-offset-s": _number, "--clock-skew-ppm": _number,
                                "--infer-ms": _number}
_OPTIONS: Mapping[str, Mapping[str, _Check]] = {
    "hil.targets.echo": {**_TRANSPORT, **_CLOCK, "--throttle": _number, "--brake": _number,
                         "--exit-after-frames": _integer,
                         "--bad-stamps": _choice("zero", "future", "backwards")},
    "hil.targets.reference": {**_TRANSPORT, **_CLOCK, "--spike-ms": _number, "--spike-frames": _frames,
                              "--drop-frames": _frames, "--reorder-frames": _frames,
                              "--bad-crc-frames": _frames, "--bad-length-frames": _frames,
                              "--step-frame": _integer, "--step-ms": _number},
    "hil.targets.cv_baseline": {**_TRANSPORT, "--name": _NAME, "--cruise-speed": _number},
    "hil.targets.cnn": {**_TRANSPORT, "--name": _NAME, "--cruise-speed": _number,
                        "--detector": _choice("cnn", "cv"), "--steering": _choice("cnn", "cv"),
                        "--det-confidence": _number, "--det-uncertain": _number, "--steer-error-max": _number,
                        "--threads": _integer, "--device": _matches(r"cpu|auto|cuda(:[0-9]{1,2})?"),
                        "--shared": None, "--vehicles": _frames, "--batch-window-ms": _number,
                        "--max-batch": _integer},
}


def _fill(word: str) -> str:
    for key, value in _PLACEHOLDERS.items():
        word = word.replace(key, value)
    return word


def _option_problem(module: str, words: Sequence[str]) -> str | None:
    """Why the options ``words`` of example target ``module`` are not known harmless (None: they are)."""
    table = _OPTIONS[module]
    i = 0
    while i < len(words):
        word = words[i]
        name, eq, inline = word.partition("=")
        if name not in table:
            return f"option `{word}` of {module} is not one this package knows to be harmless"
        check = table[name]
        if check is None:
            if eq:
                return f"flag `{name}` takes no value"
            i += 1
            continue
        if eq:
            value, i = inline, i + 1
        elif i + 1 < len(words):
            value, i = words[i + 1], i + 2
        else:
            return f"option `{name}` has no value"
        if not check(_fill(value)):
            return f"`{name} {value}` is not a value this package knows to be harmless"
    return None


def current_config_commands(places: Sequence[Path] = ()) -> set[tuple[tuple[str, ...], tuple[str, ...]]]:
    """``(command, args)`` of every YAML config in ``hil_configs/`` of each place
    (default: the working directory and this package's checkout)."""
    out: set[tuple[tuple[str, ...], tuple[str, ...]]] = set()
    for base in places or (Path.cwd(), _PACKAGE_ROOT):
        for path in sorted((base / "hil_configs").glob("*.yaml")):
            try:
                data = yaml.safe_load(path.read_text(encoding="utf-8"))
            except (OSError, UnicodeDecodeError, yaml.YAMLError):
                continue
            target = data.get("target") if isinstance(data, dict) else None
            if isinstance(target, dict) and isinstance(target.get("command"), list):
                given = target.get("args")
                args = given if isinstance(given, list) else []
                out.add((tuple(map(str, target["command"])), tuple(map(str, args))))
    return out


def untrusted_reason(command: Sequence[str], args: Sequence[str] = (), *,
                     places: Sequence[Path] = ()) -> str | None:
    """Why ``command`` + ``args`` may not run without asking (module docstring); None: it may."""
    if not command or (tuple(command), tuple(args)) in current_config_commands(places):
        return None
    if len(command) < 3 or command[1] != "-m" or command[0] not in (*_PYTHONS, sys.executable):
        return "it is not one of the current configs or example targets"
    if command[2] not in _OPTIONS:
        return f"module {command[2]} is not one of this package's example targets"
    return _option_problem(command[2], [*command[3:], *args])


def is_trusted(command: Sequence[str], args: Sequence[str] = (), *, places: Sequence[Path] = ()) -> bool:
    """True when ``command`` + ``args`` may run without asking (module docstring)."""
    return untrusted_reason(command, args, places=places) is None


def check_replay_command(cfg_data: dict[str, Any], *, source: str, trust: bool,
                         ask: Callable[[str], str] | None = None) -> None:
    """Refuse to replay a run whose target command is not trusted, unless ``trust``
    or the user answers yes to ``ask`` (None: not a terminal, nobody to ask).

    Raises:
        ConfigError: one line naming the command, why it is not trusted, and ``--trust-config``.
    """
    given = cfg_data.get("target")
    target: dict[str, Any] = given if isinstance(given, dict) else {}
    command = [str(w) for w in target.get("command") or []] if isinstance(target.get("command"), list) else []
    args = [str(w) for w in target.get("args") or []] if isinstance(target.get("args"), list) else []
    reason = None if trust else untrusted_reason(command, args)
    if reason is None:
        return
    shown = " ".join([*command, *args])
    if ask is not None:
        answer = ask(f"{source} starts the target `{shown}` ({reason}); "
                     f"a run folder from elsewhere can run any program or write any file. Run it? [y/N] ")
        if answer.strip().lower() in ("y", "yes"):
            return
    raise ConfigError(f"{source}: target.command `{shown}`: {reason}, and a run folder can run any program "
                      f"or write any file: read it, then pass --trust-config to replay it")
