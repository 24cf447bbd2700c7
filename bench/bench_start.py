"""What a run's start costs with the engine's children (physics, render workers)
spawned, as before, or forked from the fork server (``hil.harness.engine.procs``):
``execute`` of short runs in this process, as a test session, ``hil study``,
``hil calibrate`` and a search's episodes run them.

    .venv/bin/python bench/bench_start.py [--rounds 4] [--duration 1] [--configs demo scale4]

Ways, one run each per round in turn (the machine's load hits each alike): ``spawned``
(an interpreter per child, each importing MuJoCo, numpy and the engine; the floor of
the old way), ``fork server, cold`` (the server started with the run: what ``hil run``
pays where it cannot start it early) and ``fork server, warm`` (started by an earlier
run of the process). Per way: the medians of ``execute``'s wall time, the summary's
``start_s`` (from the config to the first step) and ``finish_s``, and the late steps.
Prints a markdown table. ``scale4``: ``hil_configs/scale.yaml`` with 4 echo targets.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import statistics
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from hil.scenarios.gl import select_backend

GL = select_backend()

from hil.harness.config.loading import load_config
from hil.harness.engine import pool, procs
from hil.harness.run.driver import execute, prepare_out_dir

CONFIGS = {
    "demo": ("hil_configs/demo.yaml", []),
    "scale4": ("hil_configs/scale.yaml", ["scenario.params.n_vehicles=4",
                                          'target.command=["{python}", "-m", "hil.targets.echo"]']),
}


def _cold() -> Any:
    procs.stop_child_server()
    return procs.child_context()  # started anew


WAYS: dict[str, Callable[[], Any]] = {
    "spawned": lambda: mp.get_context("spawn"),
    "fork server, cold": _cold,
    "fork server, warm": procs.child_context,
}


def run_once(config: str, way: str, duration: float, root: Path) -> dict[str, float]:
    path, overrides = CONFIGS[config]
    cfg = load_config(ROOT / path, overrides=[*overrides, f"duration_s={duration}", "progress=false"])
    out = prepare_out_dir(Path(tempfile.mkdtemp(dir=root)) / "run")
    t = time.perf_counter()
    ctx = WAYS[way]()
    pool.child_context = lambda: ctx  # type: ignore[assignment]  # what Engine starts its children from
    execute(cfg, out_dir=out, gl_backend=GL, install_signal_handlers=False)
    wall = time.perf_counter() - t
    s = json.loads((out / "summary.json").read_text())
    cost = s["harness_cost"]
    return {"wall": wall, "start": cost["start_s"], "finish": cost["finish_s"],
            "late": s["realtime"]["late_steps"]}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rounds", type=int, default=4)
    ap.add_argument("--duration", type=float, default=1.0)
    ap.add_argument("--configs", nargs="+", default=list(CONFIGS), choices=list(CONFIGS))
    args = ap.parse_args()
    root = Path(tempfile.mkdtemp(prefix="bench-start-"))
    load0 = os.getloadavg()[0]
    got: dict[tuple[str, str], list[dict[str, float]]] = {}
    procs.child_context()  # the warm way's server: started by a first run, as in a session
    run_once(args.configs[0], "fork server, warm", args.duration, root)
    for _ in range(args.rounds):
        for config in args.configs:
            for way in WAYS:
                got.setdefault((config, way), []).append(run_once(config, way, args.duration, root))
    print(f"{args.rounds} rounds, runs of {args.duration:g} s, load {load0:.2f} -> {os.getloadavg()[0]:.2f}\n")
    print("| config | children | execute s | start_s | finish_s | late steps | start_s / spawned |")
    print("| --- | --- | ---: | ---: | ---: | ---: | ---: |")
    for config in args.configs:
        floor = statistics.median(r["start"] for r in got[(config, "spawned")])
        for way in WAYS:
            rs = got[(config, way)]
            med = {k: statistics.median(r[k] for r in rs) for k in ("wall", "start", "finish")}
            print(f"| {config} | {way} | {med['wall']:.3f} | {med['start']:.3f} | {med['finish']:.3f} | "
                  f"{sum(int(r['late']) for r in rs)} | {med['start'] / floor:.2f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
