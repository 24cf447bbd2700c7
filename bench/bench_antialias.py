"""What ``camera.antialias`` costs: one camera's render, its segmentation and its
camera truth (``truth.visible_boxes``), CPU and wall ms each, per sample count.

    .venv/bin/python bench/bench_antialias.py [--vehicles 8] [--samples 4 0] [--images 80] [--rounds 3]

The ``multi_vehicle`` world with N egos (320x240 cameras, as ``hil_configs/scale.yaml``),
one simulation per sample count, its egos' cameras in turn; rounds interleave the sample
counts so the machine's load hits each alike; medians of the rounds. CPU is the
process's (software GL renders on threads of its own: CPU can exceed wall). Prints a
markdown table.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from hil.scenarios.gl import select_backend

select_backend()

from hil import scenarios
from hil.scenarios.sim import Simulation
from hil.scenarios.world import CameraSpec


def _timed(fn: Callable[[str], Any], egos: tuple[str, ...], images: int) -> tuple[float, float]:
    """(CPU ms, wall ms) per call of ``fn`` over the egos in turn."""
    for e in egos[:2]:
        fn(e)  # warm: shaders, buffers
    cpu, wall = time.process_time(), time.perf_counter()
    for i in range(images):
        fn(egos[i % len(egos)])
    return (time.process_time() - cpu) / images * 1e3, (time.perf_counter() - wall) / images * 1e3


def measure(n: int, samples: int, images: int) -> dict[str, tuple[float, float]]:
    world = scenarios.get("multi_vehicle").build(params={"n_vehicles": n}, seed=0,
                                                 camera=CameraSpec(antialias=samples), physics_step_s=0.002)
    with Simulation(world) as sim:
        sim.open_renderer()
        egos = tuple(sim.egos)
        return {"render": _timed(sim.render, egos, images), "segmentation": _timed(sim.segmentation, egos, images),
                "camera truth": _timed(sim.camera_truth, egos, images)}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--vehicles", type=int, default=8)
    ap.add_argument("--samples", type=int, nargs="+", default=[4, 0])
    ap.add_argument("--images", type=int, default=80, help="calls of each kind per measurement")
    ap.add_argument("--rounds", type=int, default=3)
    a = ap.parse_args()
    load = os.getloadavg()[0]
    runs: dict[int, list[dict[str, tuple[float, float]]]] = {s: [] for s in a.samples}
    for _ in range(a.rounds):
        for s in a.samples:
            runs[s].append(measure(a.vehicles, s, a.images))
    print(f"{a.vehicles} vehicles, 320x240, {a.images} calls each, medians of {a.rounds} rounds, "
          f"load {load:.2f} -> {os.getloadavg()[0]:.2f}\n")
    print("| antialias (samples) | render CPU / wall ms | segmentation CPU / wall ms | camera truth CPU / wall ms "
          "| render + truth CPU ms |")
    print("| ---: | ---: | ---: | ---: | ---: |")
    for s in a.samples:
        med = {k: (statistics.median(r[k][0] for r in runs[s]), statistics.median(r[k][1] for r in runs[s]))
               for k in runs[s][0]}
        cells = " | ".join(f"{med[k][0]:.2f} / {med[k][1]:.2f}" for k in ("render", "segmentation", "camera truth"))
        print(f"| {s} | {cells} | {med['render'][0] + med['camera truth'][0]:.2f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
