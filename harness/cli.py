"""The ``hil`` command line.

Exit codes: 0 success; 1 the run ended early (target died, interrupted); 2 a user
mistake (bad config, missing file, target that cannot start) with a one-line
message and no traceback.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path

from harness import __version__
from timing.errors import HilError

EXIT_OK, EXIT_EARLY, EXIT_USAGE = 0, 1, 2


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> None:  # one line, exit 2, like every user mistake
        self.exit(EXIT_USAGE, f"hil: error: {message} (see hil {self.prog.split()[-1]} --help)\n")


def build_parser() -> argparse.ArgumentParser:
    p = _Parser(prog="hil", description="Hardware-in-the-loop timing harness for autonomous-driving AI.")
    p.add_argument("--version", action="version", version=f"hil {__version__}")
    sub = p.add_subparsers(dest="command", required=True, parser_class=_Parser)
    r = sub.add_parser("run", help="run a configuration and write a run folder")
    r.add_argument("config", help="a hil_configs/*.yaml file")
    r.add_argument("--set", dest="overrides", action="append", default=[], metavar="PATH=VALUE",
                   help="override a config field, e.g. --set camera.fps=10 (repeatable)")
    r.add_argument("--out", type=Path, default=None,
                   help="run folder (default runs/<name>-<timestamp>/)")
    r.add_argument("--no-progress", action="store_true", help="no live display")
    sc = sub.add_parser("scenarios", help="list the scenarios with their parameters, ranges and defaults")
    sc.add_argument("name", nargs="?", default=None, help="show only this scenario")
    sc.add_argument("--json", action="store_true", help="machine-readable output")
    from harness import cases_cmd, clock_cmd

    clock_cmd.add_parser(sub)
    cases_cmd.add_parsers(sub)
    t = sub.add_parser("target", help="serve an example AI target (on this host or a device)",
                       description="Serve an example AI target over a transport, e.g. on a remote host: "
                                   "hil target cv --transport zenoh --listen tcp/0.0.0.0:7447. Options after "
                                   "the name go to the target (see hil target cv --help).",
                       add_help=False)
    t.add_argument("name", choices=sorted(TARGETS), help="which example target")
    t.add_argument("target_args", nargs=argparse.REMAINDER, help="options for the target")
    # Each command lives in its own module: add_parser(sub) and cmd(args).
    from harness import compare, report, train

    report.add_parser(sub)
    compare.add_parser(sub)
    train.add_parser(sub)
    from harness.search import cli as search_cli

    search_cli.add_parser(sub)
    return p


# Example targets by name: module with a main(argv) -> int.
TARGETS = {"cnn": "targets.cnn.target", "cv": "targets.cv_baseline", "echo": "targets.echo"}


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if len(argv) >= 2 and argv[0] == "target" and argv[1] in TARGETS:
        # Everything after the name belongs to the target (including --help).
        import importlib

        return int(importlib.import_module(TARGETS[argv[1]]).main(argv[2:]) or 0)
    if argv and argv[0] == "search":
        # hil search SPEC ... / hil search merge|cases|report ...: parsed by harness.search.cli.
        from harness.search import cli as search_cli

        return search_cli.main(argv[1:])
    args = build_parser().parse_args(argv)
    try:
        if args.command == "run":
            return _cmd_run(args)
        if args.command in ("cases", "replay"):
            from harness import cases_cmd

            return cases_cmd.cmd_cases(args) if args.command == "cases" else cases_cmd.cmd_replay(args)
        if args.command == "clock":
            from harness import clock_cmd

            return clock_cmd.cmd(args)
        if args.command == "scenarios":
            return _cmd_scenarios(args)
        if args.command in ("report", "compare", "train"):
            import importlib

            return int(importlib.import_module(f"harness.{args.command}").cmd(args))
    except HilError as err:
        print(f"hil: error: {err}", file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt:
        print("hil: interrupted before the run started; nothing recorded", file=sys.stderr)
        return EXIT_EARLY
    return EXIT_USAGE  # pragma: no cover - argparse requires a command


def _cmd_scenarios(args: argparse.Namespace) -> int:
    import json

    from scenarios import catalog

    if args.json:
        print(json.dumps(catalog.as_dict(args.name), indent=2))
    else:
        print(catalog.describe(args.name), end="")
    return EXIT_OK


def _cmd_run(args: argparse.Namespace) -> int:
    from harness.config import load_config
    from harness.progress import Progress, final_table, make_console
    from harness.run import default_out_dir, execute, prepare_out_dir
    from scenarios.gl import select_backend

    cfg = load_config(args.config, overrides=args.overrides)
    import scenarios  # validate scenario and parameters before starting anything

    scenarios.get(cfg.scenario.name).resolve(cfg.scenario.params)
    out = prepare_out_dir(args.out or default_out_dir(cfg))
    console = make_console()
    backend = select_backend()
    console.print(f"renderer: MuJoCo offscreen via [bold]{backend.upper()}[/bold]"
                  + (" (software fallback: slower)" if backend == "osmesa" else ""))
    with Progress(console=console, enabled=cfg.progress and not args.no_progress) as progress:
        result = execute(cfg, out_dir=out, gl_backend=backend, on_progress=progress.update,
                         notify=console.print)
    s = result.summary
    console.print(final_table(s))
    if not s["realtime"]["kept_realtime"]:
        console.print(f"[yellow]warning: real time was not kept: achieved factor "
                      f"{s['realtime']['achieved_factor']:.2f} of {s['realtime']['requested_factor']:g}, "
                      f"{s['realtime']['late_steps']} late physics steps[/yellow]")
    console.print(f"run.mcap:     {result.mcap_path}")
    console.print(f"summary.json: {result.summary_path}")
    console.print(f"report.html:  {result.out_dir / 'report.html'}")
    if s["ended_by"] != "duration":
        console.print(f"[red]run ended early: {s['ended_by']}[/red] (what was recorded is kept)")
        return EXIT_EARLY
    return EXIT_OK


if __name__ == "__main__":
    raise SystemExit(main())
