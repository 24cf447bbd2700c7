"""Campaign throughput: episodes per minute and virtual km per hour, 1 vs 2 workers.

For each worker count it runs a fresh random campaign of ``--episodes`` episodes of
a spec (default ``hil_configs/search.yaml``: the stopped-car scene, 4 simulated
seconds, the OpenCV baseline target, 320x240 JPEG at 20 fps, a drawn link latency)
through ``hil.harness.search.campaign.run_campaign`` — the process pool, spawn start-up
included — and reports wall time, episodes/min, virtual km/h, simulated seconds per
wall second, and the scaling ratio against 1 worker (efficiency = ratio / workers).

The floor, measured in the same run: the same first episodes run one after another
in this process (no pool), the rate one worker could reach without the pool's
start-up. Worker counts are interleaved round by round so load on the machine hits
all columns alike; the table shows the median of ``--rounds``.

    .venv/bin/python bench/bench_search.py                       # 1 and 2 workers, 8 episodes
    .venv/bin/python bench/bench_search.py --workers 1 2 4 --episodes 16 --rounds 3

Every campaign of a round draws the same episodes (same seed), so the columns run
identical work.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from hil.scenarios.gl import select_backend

BACKEND = select_backend()  # before anything imports mujoco

from hil.harness.search.campaign import run_campaign
from hil.harness.search.episode import run_episode
from hil.harness.search.sampling import draw_generation
from hil.harness.search.spec import Campaign, StrategySpec, load_spec


def floor(c: Campaign, n: int, tmp: Path) -> tuple[float, float, float]:
    """(wall s, km, sim s) of the first ``n`` episodes run in this process, in turn."""
    draws = [d for g in range(n // c.strategy.generation + 1) for d in draw_generation(c, g)][:n]
    t0 = time.perf_counter()
    km = sim = 0.0
    for d in draws:
        r = run_episode(c, d, campaign_dir=tmp, shard="floor", gl_backend=BACKEND, install_signal_handlers=False)
        assert r.status == "ok", r.error
        km += r.virtual_km
        sim += r.sim_s
    return time.perf_counter() - t0, km, sim


def campaign(c: Campaign, workers: int, out: Path) -> tuple[float, float, float]:
    oc = run_campaign(c, out=out, gl_backend=BACKEND, workers=workers, install_signal_handlers=False)
    assert oc.complete, [r.error for r in oc.ran if r.status != "ok"]
    return oc.wall_s, sum(r.virtual_km for r in oc.ran), sum(r.sim_s for r in oc.ran)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--spec", default=str(ROOT / "hil_configs" / "search.yaml"))
    p.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    p.add_argument("--episodes", type=int, default=8)
    p.add_argument("--rounds", type=int, default=1)
    a = p.parse_args()
    base = load_spec(a.spec, episodes=a.episodes, strategy="random")
    # A random campaign: every column runs the very same episodes.
    c = Campaign(**{**base.__dict__, "strategy": StrategySpec(kind="random", generation=base.strategy.generation)})
    cols: dict[str, list[tuple[float, float, float]]] = {"floor": []} | {f"w{w}": [] for w in a.workers}
    with tempfile.TemporaryDirectory(prefix="bench-search-") as tmp:
        for rnd in range(a.rounds):
            cols["floor"].append(floor(c, a.episodes, Path(tmp) / f"floor-{rnd}"))
            for w in a.workers:
                cols[f"w{w}"].append(campaign(c, w, Path(tmp) / f"w{w}-{rnd}"))
            print(f"round {rnd + 1}/{a.rounds} done", file=sys.stderr)

    def med(key: str) -> tuple[float, float, float]:
        rows = cols[key]
        return (statistics.median(r[0] for r in rows), statistics.median(r[1] for r in rows),
                statistics.median(r[2] for r in rows))

    f_wall, f_km, f_sim = med("floor")
    f_rate = a.episodes / f_wall * 60
    print(f"\n{a.episodes} episodes of {c.scenario}, {c.run['duration_s']:g} s simulated each "
          f"({c.run['camera']['width']}x{c.run['camera']['height']} {c.run['camera']['encoding']} at "
          f"{c.run['camera']['fps']:g} fps, target {' '.join(c.run['target']['command'][1:])}), "
          f"{os.cpu_count()} cores, GL {BACKEND}, median of {a.rounds} round(s)\n")
    print("| run | wall s | episodes/min | virtual km/h | sim s / wall s | vs 1 worker | efficiency | vs floor |")
    print("| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: |")
    print(f"| floor: in-process, one after another | {f_wall:.1f} | {f_rate:.1f} | {f_km / f_wall * 3600:.2f} | "
          f"{f_sim / f_wall:.2f} | – | – | 1.00 |")
    one = None
    for w in a.workers:
        wall, km, sim = med(f"w{w}")
        rate = a.episodes / wall * 60
        one = rate if w == 1 else one
        ratio = "–" if one is None else f"{rate / one:.2f}"
        eff = "–" if one is None else f"{rate / one / w:.0%}"
        print(f"| {w} worker{'s' if w > 1 else ''} (pool) | {wall:.1f} | {rate:.1f} | {km / wall * 3600:.2f} | "
              f"{sim / wall:.2f} | {ratio} | {eff} | {rate / f_rate:.2f} |")
    print("\nvirtual km/h counts every ego's distance (from /ground_truth); wall time includes the pool's "
          "start-up (spawned interpreters import MuJoCo) and the campaign summary.")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
