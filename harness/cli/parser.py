"""The parser of the ``hil`` command line (``hil.harness.cli.main`` runs what it parses).

Exit codes: 0 success; 1 the run ended early or part of its outputs could not be
written; 2 a user mistake, in one line (see ``hil.harness.cli.main``).
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from pathlib import Path
from typing import NoReturn

from hil.common.errors import ConfigError
from hil.harness import __version__

EXIT_OK, EXIT_EARLY, EXIT_USAGE = 0, 1, 2
# Example targets by name: module with a main(argv) -> int.
TARGETS = {"cnn": "hil.targets.cnn.cli", "cv": "hil.targets.cv_baseline", "echo": "hil.targets.echo"}


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> NoReturn:  # one line, exit 2, like every user mistake
        self.exit(EXIT_USAGE, f"hil: error: {message} (see {self.prog} --help)\n")

    def parse_args(self, args: Sequence[str] | None = None,  # type: ignore[override]
                   namespace: object = None) -> argparse.Namespace:
        """As argparse's, but an unknown option is reported with the help of the
        command it was given to (``hil run --bogus``: see ``hil run --help``)."""
        ns, extra = self.parse_known_args(args, namespace if isinstance(namespace, argparse.Namespace) else None)
        if extra:
            command = getattr(ns, "command", None)
            prog = f"{self.prog} {command}" if command else self.prog
            self.exit(EXIT_USAGE, f"hil: error: unrecognized arguments: {' '.join(extra)} (see {prog} --help)\n")
        return ns


def _live_address(text: str) -> str:
    """``--live``'s value: HOST:PORT (checked here, so a mistake is argparse's one line)."""
    if text:
        from hil.harness.record.live_front import split_address

        try:
            split_address(text)
        except ConfigError as err:
            raise argparse.ArgumentTypeError(str(err)) from None
    return text


def live_before_config(argv: list[str]) -> list[str]:
    """``hil run --live CONFIG``: ``--live`` takes an optional HOST:PORT, so argparse
    would take the config for the address; a word after ``--live`` that names a
    config (an existing file, or ``*.yaml``/``*.yml``), where none came before, is
    left for the positional."""
    if argv[:1] != ["run"]:
        return argv

    def config_like(word: str) -> bool:
        return word.endswith((".yaml", ".yml")) or Path(word).is_file()

    out = list(argv)
    for k, word in enumerate(out[:-1]):
        if word == "--live" and config_like(out[k + 1]) and not any(config_like(w) for w in out[1:k]):
            out[k] = "--live="
    return out


# The commands in the order ``hil --help`` lists them, each with the module whose
# ``add_parser(sub)`` adds it (None: added here); ``cases`` and ``replay`` share one module,
# which adds both.
_PARSERS: dict[str, str | None] = {
    "run": None, "scenarios": None, "clock": "hil.harness.cli.clock", "cases": "hil.harness.cli.cases",
    "replay": "hil.harness.cli.cases", "target": None, "report": "hil.harness.report.run_report",
    "compare": "hil.harness.check.gate", "train": "hil.training.train", "calibrate": "hil.harness.check.calibrate",
    "target-check": "hil.harness.check.target_check", "search": "hil.harness.search.cli",
    "study": "hil.harness.study.study", "trace": "hil.harness.report.trace", "rosbag": "hil.harness.report.rosbag2"}


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The parser of ``hil``; with ``command`` (the first word of ``hil COMMAND ...``)
    only that command's, as importing every command's module cost ~0.35 s of each
    start (``python -X importtime``); ``--version``: none (it prints and exits before any
    command is read); None or another unknown word: all of them."""
    import importlib

    p = _Parser(prog="hil", description="Hardware-in-the-loop timing harness for autonomous-driving AI.")
    p.add_argument("--version", action="version", version=f"hil {__version__}")
    sub: argparse._SubParsersAction[argparse.ArgumentParser] = p.add_subparsers(dest="command", required=True,
                                                                                parser_class=_Parser)
    added: set[str] = set()
    for name, module in _PARSERS.items() if command != "--version" else ():
        if (command in _PARSERS and name != command) or module in added:
            continue
        if module is None:
            _add_builtin_parser(sub, name)
            continue
        added.add(module)
        importlib.import_module(module).add_parser(sub)
    return p


def _add_builtin_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser], name: str) -> None:
    if name == "run":
        r = sub.add_parser("run", help="run a configuration and write a run folder")
        r.add_argument("config", help="a hil_configs/*.yaml file")
        r.add_argument("--set", dest="overrides", action="append", default=[], metavar="PATH=VALUE",
                       help="override a config field, e.g. --set camera.fps=10 (repeatable)")
        r.add_argument("--out", type=Path, default=None,
                       help="run folder (default runs/<name>-<timestamp>/)")
        r.add_argument("--no-progress", action="store_true", help="no live display")
        r.add_argument("--fail-on", dest="fail_on", default="", metavar="CHECK,...",
                       help="exit 3 when one of these verdicts fails: realtime, deadline, drop, collision, mismatch, "
                            "anomaly (adds to the config's verdict.fail_on)")
        r.add_argument("--live", nargs="?", const="", default=None, metavar="HOST:PORT", type=_live_address,
                       help="serve the run live to Foxglove (foxglove.sdk.v1 and foxglove.websocket.v1) on "
                            "HOST:PORT (default 127.0.0.1 and a free port, printed; recording.live, "
                            "recording.live_address)")
        from hil.harness.report.ci_outputs import add_ci_args

        add_ci_args(r)
    elif name == "scenarios":
        sc = sub.add_parser("scenarios", help="list the scenarios with their parameters, ranges and defaults")
        sc.add_argument("name", nargs="?", default=None, help="show only this scenario")
        sc.add_argument("--json", action="store_true", help="machine-readable output")
    else:
        t = sub.add_parser("target", help="serve an example AI target (on this host or a device)",
                           description="Serve an example AI target over a transport, e.g. on a remote host: "
                                       "hil target cv --transport zenoh --listen tcp/0.0.0.0:7447. Options after "
                                       "the name go to the target (see hil target cv --help).",
                           add_help=False)
        t.add_argument("name", choices=sorted(TARGETS), help="which example target")
        t.add_argument("target_args", nargs=argparse.REMAINDER, help="options for the target")
