"""Whether ``hil replay`` may start the target a run folder's ``config.json`` names.

A run folder received from someone else is code: replay starts its
``target.command`` (with ``target.args``). A command is trusted without asking when
it starts nothing (the target runs elsewhere), runs one of this package's example
targets (``{python} -m hil.targets.<name>``: their options are options of code in this
package), or is exactly the command of one of the current configs (``hil_configs/``
of the working directory and of this package). Anything else is run only after the
user says yes at a terminal, or with ``--trust-config``.
"""

from __future__ import annotations

import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import yaml

from hil.common.errors import ConfigError

__all__ = ["check_replay_command", "current_config_commands", "is_trusted"]

_PACKAGE_ROOT = Path(__file__).resolve().parents[2]
_PYTHONS = ("{python}",)


def _example_target(command: Sequence[str]) -> bool:
    if len(command) < 3 or command[1] != "-m" or command[0] not in (*_PYTHONS, sys.executable):
        return False
    module = command[2]
    if not module.startswith("hil.targets.") or not all(p.isidentifier() for p in module.split(".")):
        return False
    rel = Path(*module.split(".")[1:])  # hil.targets.x is targets/x.py
    return (_PACKAGE_ROOT / rel).with_suffix(".py").is_file() or (_PACKAGE_ROOT / rel / "__main__.py").is_file()


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
                args = target.get("args") if isinstance(target.get("args"), list) else []
                out.add((tuple(map(str, target["command"])), tuple(map(str, args))))
    return out


def is_trusted(command: Sequence[str], args: Sequence[str] = (), *, places: Sequence[Path] = ()) -> bool:
    """True when ``command`` + ``args`` may run without asking (module docstring)."""
    if not command or _example_target(command):
        return True
    return (tuple(command), tuple(args)) in current_config_commands(places)


def check_replay_command(cfg_data: dict[str, Any], *, source: str, trust: bool,
                         ask: Callable[[str], str] | None = None) -> None:
    """Refuse to replay a run whose target command is not trusted, unless ``trust``
    or the user answers yes to ``ask`` (None: not a terminal, nobody to ask).

    Raises:
        ConfigError: one line naming the command and ``--trust-config``.
    """
    target = cfg_data.get("target") if isinstance(cfg_data.get("target"), dict) else {}
    command = [str(w) for w in target.get("command") or []] if isinstance(target.get("command"), list) else []
    args = [str(w) for w in target.get("args") or []] if isinstance(target.get("args"), list) else []
    if trust or is_trusted(command, args):
        return
    shown = " ".join([*command, *args])
    if ask is not None:
        answer = ask(f"{source} starts the target `{shown}`, which is not one of the current configs; "
                     f"a run folder from elsewhere can run any program. Run it? [y/N] ")
        if answer.strip().lower() in ("y", "yes"):
            return
    raise ConfigError(f"{source}: target.command `{shown}` is not one of the current configs or example targets "
                      f"and a run folder can run any program: read it, then pass --trust-config to replay it")
