"""``hil clock CONFIG``: connect to the configured targets and show their clocks
live, like ``chronyc tracking``: offset (target − harness), skew (ppm), best round
trip and the uncertainty of a mapped timestamp, after every burst of exchanges."""

from __future__ import annotations

import argparse
import queue
import threading
from pathlib import Path
from tempfile import TemporaryDirectory

from rich.live import Live
from rich.table import Table

from hil.harness.report.progress import make_console
from hil.timing.clock import MonotonicClock
from hil.timing.sync import ClockSync, SyncState


def add_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser("clock", help="show the targets' clock offset, skew, delay and uncertainty live")
    p.add_argument("config", help="a hil_configs/*.yaml file (its targets are started or connected)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="PATH=VALUE",
                   help="override a config field (repeatable)")
    p.add_argument("--bursts", type=_bursts, default=0, help="stop after this many bursts (default: until Ctrl-C)")


def _bursts(text: str) -> int:
    """``--bursts N``, N >= 1 (0, the default, means until Ctrl-C, which a negative N also did)."""
    try:
        n = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"invalid int value: {text!r}") from None
    if n < 1:
        raise argparse.ArgumentTypeError(f"expected a number of bursts >= 1 (got {n}); leave it out to run until Ctrl-C")
    return n


def _us(ns: float | None) -> str:
    return "-" if ns is None else f"{ns / 1e3:+.1f} µs" if abs(ns) < 1e6 else f"{ns / 1e6:+.3f} ms"


def _table(rows: dict[str, tuple[SyncState, int, int]]) -> Table:
    t = Table(title="clock sync (target − harness)", title_justify="left")
    for col in ("vehicle", "samples", "offset", "skew ppm", "best delay", "uncertainty", "rejected", "state"):
        t.add_column(col, justify="right")
    for name, (st, n, rejected) in rows.items():
        t.add_row(name, str(n), _us(st.offset_ns if st.samples_used else None), f"{st.skew_ppm:+.3f}",
                  _us(st.delay_ns).lstrip("+"), _us(st.uncertainty_ns if st.samples_used else None).lstrip("+"),
                  str(rejected), "synced" if st.synced else "unsynced")
    return t


def cmd(args: argparse.Namespace) -> int:
    from hil.adapters.link import Received
    from hil.harness.config.loading import load_config
    from hil.harness.run.target_launch import TargetProcess, make_link
    from hil import scenarios
    from hil.scenarios.world import CameraSpec

    cfg = load_config(args.config, overrides=args.overrides)
    sdef = scenarios.get(cfg.scenario.name)
    world = sdef.build(params=sdef.resolve(cfg.scenario.params), seed=cfg.seed, camera=CameraSpec(),
                       physics_step_s=cfg.physics_step_s)
    egos = [v.name for v in world.vehicles if v.ego]
    clock = MonotonicClock()
    console = make_console()
    sync_cfg = cfg.timing.sync
    syncs = {name: ClockSync(sync_cfg.to_sync_config()) for name in egos}
    counts = {name: 0 for name in egos}
    rx: queue.Queue[Received] = queue.Queue(maxsize=1024)
    links = []
    procs: list[TargetProcess] = []
    stop = threading.Event()
    with TemporaryDirectory(prefix="hil-clock-") as tmp:
        try:
            for i, name in enumerate(egos):
                link, proc = make_link(cfg, vehicle_id=i, vehicle=name, clock=clock, out_dir=Path(tmp), rx=rx)
                if proc is not None:
                    procs.append(proc)
                links.append((name, link))
                link.open(hello_timeout_s=cfg.target.startup_timeout_s)
            live = Live(console=console, auto_refresh=False) if console.is_terminal else None
            if live is not None:
                live.__enter__()
            try:
                bursts = 0
                while not stop.is_set() and (args.bursts <= 0 or bursts < args.bursts):
                    for name, link in links:
                        for _ in range(sync_cfg.burst):
                            s = link.sync_exchange(timeout_s=1.0)
                            if s is not None:
                                syncs[name].add(s)
                                counts[name] += 1
                        syncs[name].check(clock.now_ns())
                    bursts += 1
                    rows = {n: (syncs[n].state(), counts[n], sum(getattr(syncs[n], "rejected", {}).values()))
                            for n in egos}
                    if live is not None:
                        live.update(_table(rows), refresh=True)
                    else:
                        console.print(_table(rows))
                    stop.wait(sync_cfg.interval_s)
            except KeyboardInterrupt:
                pass
            finally:
                if live is not None:
                    live.__exit__(None, None, None)
                    console.print(_table({n: (syncs[n].state(), counts[n], 0) for n in egos}))
        finally:
            for _, link in links:
                link.close()
            for p in procs:
                p.close()
    return 0
