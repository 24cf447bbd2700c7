"""What OpenCV's thread pool costs the OpenCV target when a host runs a target per
vehicle: K target processes at once, each with OpenCV's default pool (a thread per
core), one thread, or 16 threads (a 16-core host's pool), each inferring one
rendered frame over and over (``stopped_car``, 320x240 JPEG).

    python bench/bench_cv_threads.py [--procs 1 2 4] [--frames 300]

Per row: the CPU each process spends per frame, the wall time per frame, and the
frames/s of all K together. The target (``python -m hil.targets.cv_baseline``) and the
render workers run with one OpenCV thread (bench/README, "OpenCV threads").
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import os
import sys
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))


def _frame() -> tuple[bytes, Any, int, int]:
    """One JPEG frame of a car 30 m ahead, and its camera."""
    from hil.scenarios.gl import select_backend

    select_backend()  # before the first import of mujoco
    import cv2

    from hil.adapters.wire.messages import CameraInfo
    from hil.scenarios import get
    from hil.scenarios.sim import Simulation
    from hil.scenarios.world import CameraSpec

    world = get("stopped_car").build(params={"gap_m": 30.0}, seed=0, camera=CameraSpec(), physics_step_s=0.002)
    with Simulation(world) as sim:
        rgb = sim.render("ego0").copy()
        k, spec = sim.intrinsics(), sim.world.camera
        cam = CameraInfo(k.fx, k.fy, k.cx, k.cy, spec.mount_height_m, spec.pitch_rad)
    ok, buf = cv2.imencode(".jpg", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    assert ok
    return buf.tobytes(), cam, rgb.shape[1], rgb.shape[0]


def _worker(args: tuple[bytes, Any, int, int, int | None, int]) -> tuple[float, float, int]:
    data, cam, w, h, threads, n = args
    import cv2

    if threads is not None:
        cv2.setNumThreads(threads)
    from hil.adapters.wire.messages import Frame, ImageEncoding
    from hil.targets.cv_baseline import CvBaseline

    b = CvBaseline()
    f = Frame(vehicle_id=0, frame_id=0, sim_time_ns=0, t0_ns=0, t_tx_ns=0, width=w, height=h,
              encoding=ImageEncoding.JPEG, camera=cam, ego_speed_mps=8.0, data=data)
    for _ in range(20):
        b.infer(f)
    c0, t0 = time.process_time(), time.perf_counter()
    for _ in range(n):
        b.infer(f)
    return (time.process_time() - c0) / n * 1e3, (time.perf_counter() - t0) / n * 1e3, cv2.getNumThreads()


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--procs", type=int, nargs="+", default=[1, 2, 4])
    ap.add_argument("--frames", type=int, default=300)
    a = ap.parse_args()
    import bench_realtime

    frame = _frame()
    ctx = mp.get_context("spawn")
    print(f"{os.cpu_count()} cores, load before {bench_realtime._load()}\n")
    print("| processes | OpenCV threads each | CPU ms per frame | wall ms per frame | frames/s, all |")
    print("|---:|---|---:|---:|---:|")
    for k in a.procs:
        for threads in (None, 1, 16):
            with ctx.Pool(k) as pool:
                got = pool.map(_worker, [(*frame, threads, a.frames)] * k)
            cpu, wall = sum(g[0] for g in got) / k, sum(g[1] for g in got) / k
            label = f"default ({got[0][2]})" if threads is None else str(got[0][2])
            print(f"| {k} | {label} | {cpu:.2f} | {wall:.2f} | {k * 1e3 / wall:.0f} |", flush=True)
    print(f"\nload after {bench_realtime._load()}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
