"""Campaign engines side by side: the process pool and a Dask cluster, 1/2/4 workers.

For each worker count it starts both engines (the pool; a Dask ``LocalCluster`` of
that many worker processes, one thread each, on 127.0.0.1), warms each with one
episode per worker (spawned interpreters import MuJoCo), then times the same random
campaign of ``--episodes`` episodes on each, interleaved so load hits both alike.

Reported per point: episodes/min, the mean episode's own wall time (measured inside
the worker), and the engine's overhead per episode: the worker time not spent in an
episode, ``(workers x campaign wall - sum of episode walls) / episodes`` — dispatch,
(de)serialisation, shipping the episode folder back (Dask), the campaign database,
and any idle tail when the last episodes do not fill every worker — as a share of
the mean episode. For Dask, ``ship ms`` is the part spent packing the episode folder
on the worker and unpacking it here. Cluster start-up is reported apart.

    .venv/bin/python bench/bench_engine.py                          # 1, 2, 4 workers, 4 episodes
    .venv/bin/python bench/bench_engine.py --workers 1 2 --episodes 8 --set duration_s=4
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from hil.scenarios.gl import select_backend

BACKEND = select_backend()  # before anything imports mujoco

from hil.harness.search.campaign import run_campaign
from hil.harness.search.executor import DaskEngine, ProcessEngine
from hil.harness.search.spec import Campaign, StrategySpec, load_spec


def timed(c: Campaign, engine: Any, out: Path) -> dict[str, float]:
    shipped_before = len(getattr(engine, "overhead_ns", []))
    oc = run_campaign(c, out=out, gl_backend=BACKEND, engine=engine, install_signal_handlers=False)
    assert oc.complete, [r.error for r in oc.ran if r.status != "ok"]
    ep = [r.wall_s for r in oc.ran]
    n = len(ep)
    ship = getattr(engine, "overhead_ns", [])[shipped_before:]
    return {"wall": oc.wall_s, "rate": n / oc.wall_s * 60, "episode": statistics.mean(ep),
            "overhead": (engine.workers * oc.wall_s - sum(ep)) / n,
            "ship_ms": statistics.mean(ship) / 1e6 if ship else float("nan")}


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--spec", default=str(ROOT / "hil_configs" / "search.yaml"))
    p.add_argument("--workers", type=int, nargs="+", default=[1, 2, 4])
    p.add_argument("--episodes", type=int, default=4)
    p.add_argument("--set", dest="overrides", action="append", default=["duration_s=2"], metavar="PATH=VALUE")
    a = p.parse_args()
    base = load_spec(a.spec, episodes=a.episodes, strategy="random", overrides=a.overrides)
    c = Campaign(**{**base.__dict__, "strategy": StrategySpec(kind="random", generation=base.strategy.generation)})
    rows: list[tuple[int, str, dict[str, float], float]] = []
    with tempfile.TemporaryDirectory(prefix="bench-engine-") as tmp:
        for w in a.workers:
            warm = load_spec(a.spec, episodes=w, seed=c.seed + 1, strategy="random", overrides=a.overrides)
            t0 = time.perf_counter()
            pool = ProcessEngine(workers=w, gl_backend=BACKEND)
            pool_start = time.perf_counter() - t0
            dask = DaskEngine(gl_backend=BACKEND, workers=w)
            try:
                for name, eng in (("pool", pool), ("dask", dask)):
                    run_campaign(warm, out=Path(tmp) / f"warm-{name}-{w}", gl_backend=BACKEND, engine=eng,
                                 install_signal_handlers=False)
                rows.append((w, "process pool", timed(c, pool, Path(tmp) / f"pool-{w}"), pool_start))
                rows.append((w, "Dask LocalCluster", timed(c, dask, Path(tmp) / f"dask-{w}"), dask.start_s))
            finally:
                pool.close()
                dask.close()
            print(f"{w} workers done; load {os.getloadavg()[0]:.2f}", file=sys.stderr)
    print(f"\n{a.episodes} episodes per point of {c.scenario}, {c.run['duration_s']:g} s simulated each, lockstep "
          f"({' '.join(a.overrides)}), {os.cpu_count()} cores, GL {BACKEND}; warm engines\n")
    print("| workers | engine | start s | wall s | episodes/min | vs pool | mean episode s | overhead s/episode | "
          "overhead % | ship ms |")
    print("| ---: | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |")
    pool_rate: dict[int, float] = {}
    for w, name, r, start in rows:
        if name == "process pool":
            pool_rate[w] = r["rate"]
        vs = r["rate"] / pool_rate[w]
        ship = "–" if r["ship_ms"] != r["ship_ms"] else f"{r['ship_ms']:.1f}"
        print(f"| {w} | {name} | {start:.2f} | {r['wall']:.1f} | {r['rate']:.1f} | {vs:.2f} | {r['episode']:.2f} | "
              f"{r['overhead']:.3f} | {r['overhead'] / r['episode']:.1%} | {ship} |")
    print(f"\nload average after: {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
