"""``hil search``: corner-case search campaigns.

::

    hil search SPEC [--episodes N] [--seed S] [--strategy random|cem|mutate] [--shard i/N]
                    [--workers W] [--engine process|dask] [--scheduler ADDRESS]
                    [--out DIR] [--resume] [--set PATH=VALUE ...] [--no-progress]
    hil search merge OUT SHARD_DIR...
    hil search cases CAMPAIGN
    hil search report CAMPAIGN

Exit codes: 0 every episode (of the shard) ran to its duration, or the merge/report
was written; 1 the campaign was stopped or some episodes failed (what ran is kept;
``--resume`` continues); 2 a user mistake (bad spec, shard, folder), one line.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, NoReturn

from hil.common.errors import HilError

if TYPE_CHECKING:
    from rich.console import Console

EXIT_OK, EXIT_INCOMPLETE, EXIT_USAGE = 0, 1, 2
SUBCOMMANDS = ("merge", "cases", "report")


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> NoReturn:  # one line, exit 2, like every user mistake
        self.exit(EXIT_USAGE, f"hil: error: {message} (see {self.prog} --help)\n")


def add_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """List ``hil search`` in ``hil --help`` (``main`` parses its arguments)."""
    sub.add_parser("search", help="search for corner cases: many episodes with drawn parameters "
                                  "(hil search --help)", add_help=False)


def run_parser() -> argparse.ArgumentParser:
    p = _Parser(prog="hil search", description="Run a corner-case search campaign: episodes of a scenario with "
                "parameters (and link latency) drawn from its space, in parallel, keeping every corner case. "
                "Also: hil search merge OUT SHARD_DIR... | hil search cases CAMPAIGN | hil search report CAMPAIGN.")
    p.add_argument("spec", help="a campaign spec (YAML), e.g. hil_configs/search.yaml")
    p.add_argument("--episodes", type=int, default=None, help="episodes in the campaign (overrides the spec)")
    p.add_argument("--seed", type=int, default=None, help="campaign seed (overrides the spec)")
    p.add_argument("--strategy", choices=("random", "cem", "mutate"), default=None,
                   help="how parameters are drawn (overrides the spec's strategy.kind)")
    p.add_argument("--shard", default=None, metavar="i/N",
                   help="run slice i of N (episodes with index %% N == i); e.g. the Kubernetes completion index")
    p.add_argument("--workers", type=int, default=None,
                   help=f"episodes at once, each in its own process (default: the cores, {os.cpu_count()})")
    p.add_argument("--engine", choices=("process", "dask"), default=None,
                   help="where episodes run: a process pool here (default), or a Dask cluster (a local one of "
                        "--workers processes, or --scheduler's)")
    p.add_argument("--scheduler", default=None, metavar="ADDRESS",
                   help="a running Dask scheduler, e.g. tcp://10.0.0.5:8786 (implies --engine dask; its workers "
                        "set the parallelism)")
    p.add_argument("--out", type=Path, default=None, help="campaign folder (default campaigns/<name>-<time>)")
    p.add_argument("--resume", action="store_true", help="continue the campaign in --out (same spec and shard)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="PATH=VALUE",
                   help="override a field of the episodes' run config, e.g. --set duration_s=3 (repeatable)")
    p.add_argument("--no-progress", action="store_true", help="a line per episode instead of the live bar")
    from hil.harness.report.ci_outputs import add_ci_args

    add_ci_args(p)
    return p


def merge_parser() -> argparse.ArgumentParser:
    p = _Parser(prog="hil search merge", description="Combine the shard folders of one campaign (databases, "
                "episode folders with their MCAP files) into a new campaign folder OUT.")
    p.add_argument("out", type=Path, help="the merged campaign folder (must not exist)")
    p.add_argument("shards", type=Path, nargs="+", help="campaign folders written by hil search --shard i/N")
    return p


def folder_parser(name: str, what: str) -> argparse.ArgumentParser:
    p = _Parser(prog=f"hil search {name}", description=what)
    p.add_argument("campaign", type=Path, help="a campaign folder")
    return p


def main(argv: Sequence[str]) -> int:
    """``hil search ...`` (argv without ``search``)."""
    argv = list(argv)
    try:
        if argv and argv[0] == "merge":
            return _cmd_merge(merge_parser().parse_args(argv[1:]))
        if argv and argv[0] == "cases":
            return _cmd_cases(folder_parser("cases", "List a campaign's corner cases and how to replay each.")
                              .parse_args(argv[1:]))
        if argv and argv[0] == "report":
            return _cmd_report(folder_parser("report", "Rewrite a campaign's summary.json and report.html.")
                               .parse_args(argv[1:]))
        return _cmd_run(run_parser().parse_args(argv))
    except HilError as err:
        print(f"hil: error: {err}", file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt:
        print("hil: interrupted", file=sys.stderr)
        return EXIT_INCOMPLETE


def _cmd_run(args: argparse.Namespace) -> int:
    from hil.common.errors import ConfigError
    from hil.harness.search.campaign import check_campaign_dir, run_campaign
    from hil.harness.search.executor import DaskEngine, EngineKind
    from hil.harness.search.progress import CampaignProgress
    from hil.harness.search.shard import Shard, parse_shard
    from hil.harness.search.spec import load_spec
    from hil.harness.report.ci_outputs import check_ci_args
    from hil.scenarios.gl import select_backend

    check_ci_args(args)
    shard = parse_shard(args.shard) if args.shard is not None else Shard()
    workers = args.workers if args.workers is not None else (os.cpu_count() or 1)
    if workers < 1:
        raise ConfigError(f"--workers {workers}: expected at least 1")
    kind = EngineKind(args.engine) if args.engine else (EngineKind.DASK if args.scheduler else EngineKind.PROCESS)
    if args.scheduler is not None and kind is not EngineKind.DASK:
        raise ConfigError(f"--scheduler {args.scheduler}: needs --engine dask (a process pool has no scheduler)")
    if args.scheduler is not None and not args.scheduler.strip():
        raise ConfigError("--scheduler '': expected a Dask scheduler address, e.g. tcp://10.0.0.5:8786")
    c = load_spec(args.spec, overrides=args.overrides, episodes=args.episodes, seed=args.seed,
                  strategy=args.strategy)
    out = args.out
    if out is None:
        suffix = "" if shard.count == 1 else f"-shard{shard.index}of{shard.count}"
        out = Path("campaigns") / f"{c.name}-{time.strftime('%Y%m%d-%H%M%S')}{suffix}"
    check_campaign_dir(out, resume=args.resume)  # refused before the campaign's line
    console = _console()
    backend = select_backend()
    console.print(f"campaign {c.name} [dim]{c.campaign_id}[/dim]: {c.scenario}, {c.strategy.kind.value}, "
                  f"searching {', '.join(d.name for d in c.dims)}; renderer {backend.upper()}; folder {out}")
    reporter = CampaignProgress(console, live=not args.no_progress)
    if kind is EngineKind.DASK:
        with DaskEngine(gl_backend=backend, scheduler=args.scheduler, workers=workers) as engine:
            console.print(f"engine: {engine.describe()} (up in {engine.start_s:.1f} s)", highlight=False)
            oc = run_campaign(c, out=out, gl_backend=backend, shard=shard, resume=args.resume, reporter=reporter,
                              engine=engine)
    else:
        oc = run_campaign(c, out=out, gl_backend=backend, shard=shard, workers=workers, resume=args.resume,
                          reporter=reporter)
    _print_summary(console, oc.summary, out)
    code = EXIT_OK
    if oc.stopped:
        console.print(f"[red]stopped[/red]: {len(oc.ran)} episodes ran this time; continue with --resume --out {out}")
        code = EXIT_INCOMPLETE
    elif not oc.complete:
        console.print("[yellow]some episodes did not finish (see summary.json errors); --resume runs them again"
                      "[/yellow]")
        code = EXIT_INCOMPLETE
    from hil.harness.search.ci_cases import of_search
    from hil.harness.report.ci_outputs import write_ci_outputs

    write_ci_outputs(of_search(oc, exit_code=code), args)
    return code


def _console() -> Console:
    from hil.harness.report.progress import make_console

    return make_console()


def _print_summary(console: Console, s: dict[str, Any], folder: Path) -> None:
    from rich.table import Table

    e, k = s["episodes"], s["cases"]
    t = Table(title=f"campaign {s['campaign']['name']} ({s['campaign']['id']})", title_justify="left")
    for col in ("episodes", "virtual km", "wall s", "episodes/min", "km/h", "cases", "perception", "latency",
                "timing"):
        t.add_column(col, justify="right")
    rate = s["episodes_per_min"]
    kmh = s["km_per_h"]
    t.add_row(f"{e['ran']}/{e['planned']}", f"{s['virtual_km']:.3f}", f"{s['wall_s']:.1f}",
              "-" if rate is None else f"{rate:.1f}", "-" if kmh is None else f"{kmh:.2f}", str(k["total"]),
              *(str(k["by_cause"][c]) for c in ("perception", "latency", "timing")))
    console.print(t)
    for b in s["most_anomalous"][:3]:
        console.print(f"  worst: {b['dir']} score {b['score']:g}, {b['cases']} cases, min gap "
                      f"{'-' if b['min_gap_m'] is None else format(b['min_gap_m'], '.2f')} m: "
                      + ", ".join(f"{n}={v:.4g}" for n, v in b["params"].items()), highlight=False)
    console.print(f"summary.json: {folder / 'summary.json'}")
    console.print(f"report.html:  {folder / 'report.html'}")
    if k["total"]:
        console.print(f"cases: hil search cases {folder}   replay one: hil replay {folder}/EPISODE_DIR CASE_ID")


def _cmd_merge(args: argparse.Namespace) -> int:
    from hil.harness.search.merge import merge

    r = merge(args.out, args.shards)
    console = _console()
    how = "hard-linked" if r.linked else "copied"
    console.print(f"merged {len(args.shards)} shards: {r.episodes} episodes ({how}), {r.cases} corner cases "
                  f"into {r.out}")
    _print_summary(console, r.summary, r.out)
    if not r.summary["episodes"]["complete"]:
        e = r.summary["episodes"]
        console.print(f"[yellow]incomplete: {e['missing']} of {e['planned']} episodes missing (first: "
                      f"{', '.join(map(str, e['missing_first']))}); statuses {e['by_status']}[/yellow]")
    return EXIT_OK


def _cmd_report(args: argparse.Namespace) -> int:
    from hil.harness.search.db import open_campaign_db
    from hil.harness.search.campaign_page import write_outputs

    open_campaign_db(args.campaign).close()
    s = write_outputs(args.campaign)
    _print_summary(_console(), s, args.campaign)
    return EXIT_OK


def _cmd_cases(args: argparse.Namespace) -> int:
    from rich.table import Table

    from hil.harness.cases.replayable import Reproducibility, reproducibility
    from hil.harness.search.db import open_campaign_db
    from hil.harness.search.summary import case_cause

    with open_campaign_db(args.campaign) as db:
        cases = db.cases()
    console = _console()
    t = Table(title=f"{len(cases)} corner cases in {args.campaign}", title_justify="left")
    for col in ("episode", "case", "vehicle", "sim s", "kind", "cause", "severity", "replay"):
        t.add_column(col, no_wrap=col != "replay", overflow="fold")
    for k in cases:
        sim = k["sim_time_ns"]
        t.add_row(str(k["episode"]), str(k["case_id"]), str(k["vehicle"]),
                  "-" if sim is None or sim < 0 else f"{sim / 1e9:.2f}", str(k["kind"]).removeprefix("mismatch."),
                  case_cause(k), str(k["severity"] or "-"),
                  f"hil replay {args.campaign / k['episode_dir']} {k['case_id']}"
                  if reproducibility(str(k["kind"])) is Reproducibility.REPLAY
                  else "real time only (a wall-clock timing anomaly: no lockstep replay)")
    console.print(t)
    return EXIT_OK


__all__ = ["add_parser", "main"]
