"""``hil cases RUN`` lists a run's corner cases (``--window ID`` cuts a case's window
out of run.mcap into ``corner_cases/case-NNNN.mcap``); ``hil replay RUN CASE_ID`` re-runs
one in lockstep with the same scenario, seed and parameters and the run's recorded
per-frame latencies, and says whether the mismatch comes back.

Exit codes: ``cases`` 0; ``replay`` 0 reproduced, 1 not reproduced; 2 for a missing
or foreign run folder, a truncated database, an unknown case id, or a target command
that is not trusted (``hil.harness.cases.replay_trust``: a run folder from elsewhere is code;
``--trust-config`` runs it anyway).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

from rich.table import Table

from hil.common.errors import ConfigError
from hil.harness.cases.casebook import DB_NAME, read_cases
from hil.harness.cases.replayable import Reproducibility, reproducibility, why_not_replayable
from hil.harness.report.progress import make_console

CONFIG_NAME = "config.json"
REPRODUCE_WINDOW_S = 1.0


def add_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    c = sub.add_parser("cases", help="list a run's corner cases")
    c.add_argument("run", type=Path, help="a run folder")
    c.add_argument("--window", type=int, action="append", default=None, metavar="ID",
                   help="write case ID's window (its sim-time range of run.mcap, its vehicle's channels) to "
                        "corner_cases/case-ID.mcap; repeatable")
    r = sub.add_parser("replay", help="re-run a corner case in lockstep and say whether it reproduces")
    r.add_argument("run", type=Path, help="a run folder")
    r.add_argument("case_id", type=int, help="the case id (see hil cases RUN)")
    r.add_argument("--out", type=Path, default=None, help="replay folder (default RUN/replays/case-N-<time>)")
    r.add_argument("--trust-config", action="store_true",
                   help="run the target command of RUN/config.json even when it is not one of the current "
                        "configs or example targets (a run folder from elsewhere can run any program)")


def _run_dir(path: Path) -> Path:
    if not path.exists():
        raise ConfigError(f"{path}: no such run folder")
    if not path.is_dir() or not (path / "run.mcap").exists():
        raise ConfigError(f"{path}: not a run folder (no run.mcap)")
    return path


def _window(r: dict[str, Any]) -> str:
    """Where a case's data is: its own file, or run.mcap and the sim-time range."""
    path = Path(str(r["mcap_path"])).name
    lo, hi = r.get("window_start_ns"), r.get("window_end_ns")
    if path == "run.mcap" and isinstance(lo, int) and isinstance(hi, int):
        return f"run.mcap @ {lo / 1e9:.2f}-{hi / 1e9:.2f} s"
    return path


def cmd_cases(args: argparse.Namespace) -> int:
    from hil.harness.cases.windows import write_case_windows

    run = _run_dir(args.run)
    console = make_console()
    if not args.window and not (run / DB_NAME).exists():  # a run without a case writes no database
        console.print(f"0 corner cases in {run} (the run recorded none)")
        return 0
    if args.window:
        errors = write_case_windows(run, case_ids=sorted(set(args.window)), limit=len(set(args.window)))
        for line in errors:
            console.print(f"[yellow]warning: {line}[/yellow]")
    rows, bad = read_cases(run)
    t = Table(title=f"{len(rows)} corner cases in {run}", title_justify="left")
    for col in ("id", "vehicle", "sim s", "kind", "cause", "severity", "replay", "summary", "window"):
        t.add_column(col, no_wrap=col in ("kind", "window"))
    t.caption = ("replay: whether hil replay (lockstep) brings the case back; no: a wall-clock timing anomaly, "
                 "real time only")
    for r in rows:  # replay: hil.harness.cases.replayable
        t.add_row(str(r["id"]), r["vehicle"], f"{r['sim_time_ns'] / 1e9:.2f}" if r["sim_time_ns"] >= 0 else "-",
                  r["kind"].removeprefix("mismatch."), r.get("cause") or "-", r.get("severity") or "-",
                  "yes" if reproducibility(r["kind"]) is Reproducibility.REPLAY else "no", r["summary"], _window(r))
    console.print(t)
    for line in bad:
        console.print(f"[yellow]warning: {line}[/yellow]")
    return 0


def cmd_replay(args: argparse.Namespace) -> int:
    from hil.harness.config.loading import parse_config
    from hil.harness.run.driver import execute, prepare_out_dir
    from hil.scenarios.gl import select_backend

    run = _run_dir(args.run)
    rows, _bad = read_cases(run)
    case = next((r for r in rows if int(r["id"]) == args.case_id), None)
    if case is None:
        raise ConfigError(f"{run}: no corner case {args.case_id} (cases: "
                          f"{', '.join(str(r['id']) for r in rows) or 'none'})")
    if reproducibility(case["kind"]) is not Reproducibility.REPLAY:
        raise ConfigError(f"{run}: case {args.case_id}: {why_not_replayable(case['kind'])}")
    cfg_path = run / CONFIG_NAME
    try:
        cfg_data = json.loads(cfg_path.read_text())
    except (OSError, ValueError) as err:
        raise ConfigError(f"{cfg_path}: cannot read the run's config ({err})") from err
    from hil.harness.cases.replay_trust import check_replay_command

    check_replay_command(cfg_data, source=str(cfg_path), trust=args.trust_config,
                         ask=input if sys.stdin.isatty() else None)
    sim_s = max(case["sim_time_ns"], 0) / 1e9
    cfg_data.update(mode="lockstep", progress=False, name=f"{cfg_data.get('name', 'run')}-replay-{args.case_id}",
                    duration_s=min(cfg_data.get("duration_s", sim_s + 3), sim_s + 3.0))
    cfg_data.setdefault("lockstep", {})["latency"] = {"kind": "recorded", "path": str(run)}
    cfg = parse_config(cfg_data, source=str(cfg_path))
    out = prepare_out_dir(args.out or run / "replays" / f"case-{args.case_id}-{time.strftime('%Y%m%d-%H%M%S')}")
    console = make_console()
    console.print(f"replaying case {args.case_id} ({case['kind']}, {case['vehicle']}, sim {sim_s:.2f} s) "
                  f"in lockstep with the recorded latencies")
    result = execute(cfg, out_dir=out, gl_backend=select_backend(), notify=console.print)
    again: list[dict[str, Any]] = []
    try:
        again, _ = read_cases(out)
    except ConfigError:
        pass
    hits = [r for r in again if r["vehicle"] == case["vehicle"] and r["kind"] == case["kind"]
            and abs(r["sim_time_ns"] - case["sim_time_ns"]) <= REPRODUCE_WINDOW_S * 1e9]
    console.print(f"replay: {result.out_dir}")
    if hits:
        h = hits[0]
        console.print(f"[bold]reproduced[/bold]: {h['kind']} at sim {h['sim_time_ns'] / 1e9:.2f} s "
                      f"(original {sim_s:.2f} s): {h['summary']}")
        return 0
    console.print(f"[bold]not reproduced[/bold]: no {case['kind']} for {case['vehicle']} within "
                  f"{REPRODUCE_WINDOW_S:g} s of sim {sim_s:.2f} s ({len(again)} other cases in the replay)")
    return 1
