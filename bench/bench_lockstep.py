"""Lockstep throughput against the bare rendering floor of the same cameras, and the
harness's own CPU per frame (issue 24, goal on the 2-core machine: frames/s at N=16,
10 fps, echo targets >= 0.8 x the floor; run-side CPU <= 300 µs per frame).

Per round, one after another (never two at once):

* floor: plain ``mujoco.Renderer`` over the N cameras of ``multi_vehicle`` (320x240,
  no shadows or reflections, scale.yaml's ``camera.antialias``, one process;
  ``bench_sim.bare``), ``--floor-images`` images;
* run: ``hil run hil_configs/scale.yaml`` with N vehicles in lockstep, echo targets,
  ``truth.visible_boxes=false``, ``--duration`` simulated seconds, for each
  ``--workers`` (render workers) and ``--shards`` (engine.shards) setting: frames/s
  over the loop's wall time (``summary.wall_time_s``), its ratio to the round's
  floor, and ``harness_cost.run_us_per_frame`` (every harness process but the
  physics and the render workers, targets excluded); ``start_s`` (command to first
  step: targets, workers, shards), ``finish_s`` (last step to summary) and the whole
  command's wall time (report included).

    .venv/bin/python bench/bench_lockstep.py [--vehicles 16] [--rounds 3] [--workers 1 2]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def _load() -> str:
    return open("/proc/loadavg").read().split()[0]


def floor(n: int, images: int) -> float:
    """Images per second of bare rendering of the N cameras (a child process, so the
    GL context is gone before the run), anti-aliased as scale.yaml's runs are."""
    from hil.harness.config.loading import load_config

    antialias = load_config(ROOT / "hil_configs" / "scale.yaml").camera.antialias
    code = (f"import sys; sys.path.insert(0, {str(ROOT / 'bench')!r}); import bench_sim; "
            f"print(bench_sim.bare({n}, {max(2, images // n)}, seg=False, antialias={antialias}))")
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, check=True)
    return float(out.stdout.strip().splitlines()[-1])


def run(n: int, *, workers: int, shards: int | None, duration_s: float) -> dict[str, float]:
    with tempfile.TemporaryDirectory() as d:
        out = Path(d) / "run"
        sets = [f"scenario.params.n_vehicles={n}", "mode=lockstep", f"duration_s={duration_s}",
                'target.command=["{python}", "-m", "hil.targets.echo"]', f"engine.render_workers={workers}",
                "truth.visible_boxes=false", "target.startup_timeout_s=120"]
        if shards is not None:
            sets.append(f"engine.shards={shards}")
        args = [str(ROOT / ".venv/bin/hil"), "run", "hil_configs/scale.yaml", "--no-progress", "--out", str(out)]
        for s in sets:
            args += ["--set", s]
        t = time.monotonic()
        p = subprocess.run(args, cwd=ROOT, capture_output=True, text=True, check=False)
        total = time.monotonic() - t
        if p.returncode not in (0, 1, 3) or not (out / "summary.json").exists():
            raise SystemExit(f"run failed ({p.returncode}): {p.stderr[-2000:]}")
        s = json.loads((out / "summary.json").read_text())
    frames = sum(v["frames_sent"] for v in s["vehicles"].values())
    cost = s.get("harness_cost", {})
    return {"frames": frames, "wall_s": s["wall_time_s"], "fps": frames / s["wall_time_s"],
            "run_us": float(cost.get("run_us_per_frame", float("nan"))), "total_s": total,
            "start_s": float(cost.get("start_s", float("nan"))), "finish_s": float(cost.get("finish_s", float("nan"))),
            "dropped": sum(v["dropped"] for v in s["vehicles"].values())}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--vehicles", type=int, default=16)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--shards", type=int, nargs="+", default=None, help="engine.shards settings (default: auto)")
    ap.add_argument("--duration", type=float, default=6.0)
    ap.add_argument("--floor-images", type=int, default=320)
    a = ap.parse_args()
    n = a.vehicles
    print(f"machine: {os.cpu_count()} cores; N={n} at 10 fps, lockstep, echo targets; load before {_load()}\n")
    print("| round | render workers | shards | frames | loop wall s | frames/s | floor img/s | ratio | "
          "run µs/frame | dropped | start s | finish s | command s | load |")
    print("|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    ratios: dict[tuple[int, int | None], list[float]] = {}
    costs: dict[tuple[int, int | None], list[float]] = {}
    for i in range(a.rounds):
        for w in a.workers:
            for sh in (a.shards or [None]):
                fl = floor(n, a.floor_images)
                load = _load()
                r = run(n, workers=w, shards=sh, duration_s=a.duration)
                ratio = r["fps"] / fl
                ratios.setdefault((w, sh), []).append(ratio)
                costs.setdefault((w, sh), []).append(r["run_us"])
                print(f"| {i + 1} | {w} | {'auto' if sh is None else sh} | {r['frames']} | {r['wall_s']:.2f} | "
                      f"{r['fps']:.0f} | {fl:.0f} | {ratio:.2f} | {r['run_us']:.0f} | {r['dropped']} | "
                      f"{r['start_s']:.1f} | {r['finish_s']:.1f} | {r['total_s']:.1f} | {load} |", flush=True)
    print("\n| render workers | shards | ratio to floor (median) | goal >= 0.8 | run µs/frame (median) | "
          "goal <= 300 |")
    print("|---:|---:|---:|---|---:|---|")
    for (w, sh), rs in ratios.items():
        med, cost = statistics.median(rs), statistics.median(costs[(w, sh)])
        print(f"| {w} | {'auto' if sh is None else sh} | {med:.2f} | {'met' if med >= 0.8 else 'NOT met'} | "
              f"{cost:.0f} | {'met' if cost <= 300 else 'NOT met'} |")
    print(f"\nload after: {_load()}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
