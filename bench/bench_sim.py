"""Sim-loop throughput against bare MuJoCo rendering of the same cameras.

    .venv/bin/python bench/bench_sim.py [--vehicles 1 2 4 8 16] [--images 400] [--rounds 3]

For each vehicle count N it builds the ``multi_vehicle`` scenario with N egos
(320x240, 10 fps, physics step 2 ms: 50 physics steps per camera frame) and
measures, interleaved round by round so machine noise hits both alike:

* bare render: ``mujoco.Renderer.update_scene`` + ``render(out=...)`` for each of the
  N cameras, nothing else (the floor);
* bare render + seg: the same plus one segmentation render per camera (what
  ``truth.visible_boxes`` costs at the very least);
* the sim loop (``hil.harness.run.loop.SimLoop``, lockstep) on the real engine — the physics
  process, the render pool (one worker per spare core) and the run process — with
  in-process echo links (no transport, no target process: the harness's own cost):
  physics, scripted motion, JPEG encoding, ground truth, MCAP recording with images,
  applying controls; once with ``truth.visible_boxes`` off and once on. With more
  than one core the loop can beat the single-process bare floor (render workers run
  in parallel).

Printed as a markdown table of images per second (frames of all vehicles); the
overhead is the loop's time per frame over the bare floor's. A vehicle count fits
10 fps when the loop's frames/s reaches 10 * N. Each measurement renders about
``--images`` images (at least 10 frames); medians of ``--rounds``. About 3 minutes.
"""

from __future__ import annotations

import argparse
import os
import queue
import statistics
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from hil.scenarios.gl import select_backend

select_backend()

import mujoco
import numpy as np

from hil.adapters.link import LinkStats, Received
from hil.adapters.wire.messages import Control, DrivingState, Estimate
from hil.harness.config.loading import parse_config
from hil.harness.engine.pool import Engine, auto_workers
from hil.harness.record.channels import register_all
from hil.harness.record.recorder import Recorder
from hil.harness.vocab.events import EventBus
from hil.harness.run.assemble import local_loop
from hil.harness.run.loop import engine_specs
from hil.harness.run.vehicle_state import VehicleRun
from hil import scenarios
from hil.scenarios.ground_truth import RefStateRules
from hil.scenarios.road import ROAD_GROUP
from hil.scenarios.sim import Simulation
from hil.scenarios.world import CameraSpec, camera_name
from hil.timing.clock import MonotonicClock

FPS = 10.0
STEP_S = 0.002


class EchoLink:
    """An in-process stand-in for a link: every frame is answered at once (a gentle
    throttle) from a reader thread of its own, as a real link's reader delivers. No
    transport, no process."""

    def __init__(self, vehicle_id: int, clock: MonotonicClock) -> None:
        self.vehicle_id, self.clock = vehicle_id, clock
        self.alive = True
        self.peer_gone_reason: str | None = None
        self.hello = None
        self.impairment = None
        self.stats = LinkStats()
        self._out: queue.Queue[Received | None] = queue.Queue()
        self._deliver: Any = None
        threading.Thread(target=self._reader, daemon=True).start()

    def deliver_to(self, fn: Any) -> None:
        self._deliver = fn

    def _reader(self) -> None:
        while (r := self._out.get()) is not None:
            self._deliver(r)

    def send_frame(self, *, frame_id: int, **_: Any) -> int:
        t = self.clock.now_ns()
        est = Estimate(self.vehicle_id, frame_id, DrivingState.SAFE, Control(0.0, 0.1, 0.0), (), t, t, t, t)
        self._out.put(Received(est, self.clock.now_ns(), self.vehicle_id))
        self.stats.frames_sent += 1
        return t

    def send_sync_request(self) -> None:
        pass

    def sync_samples(self) -> list[Any]:
        return []

    def close(self) -> None:
        self._out.put(None)


def _world(n: int, antialias: int = 4) -> Any:
    return scenarios.get("multi_vehicle").build(params={"n_vehicles": n}, seed=0,
                                                camera=CameraSpec(antialias=antialias), physics_step_s=STEP_S)


def bare(n: int, frames: int, *, seg: bool, antialias: int = 4) -> float:
    """Images per second of plain mujoco.Renderer over the N cameras (``antialias``:
    samples per pixel, as ``camera.antialias``; the run compared must use the same)."""
    with Simulation(_world(n, antialias)) as sim:
        m, d = sim.model, sim.data
        r = mujoco.Renderer(m, 240, 320)
        r.scene.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = False
        r.scene.flags[mujoco.mjtRndFlag.mjRND_REFLECTION] = False
        seg_opt = mujoco.MjvOption()
        seg_opt.geomgroup[ROAD_GROUP] = 0
        cams = [m.camera(camera_name(e)).id for e in sim.egos]
        rgb = np.empty((240, 320, 3), np.uint8)
        ids = np.empty((240, 320, 2), np.int32)
        for c in cams:  # warm up (shader compilation)
            r.update_scene(d, camera=c)
            r.render(out=rgb)
        t0 = time.perf_counter()
        for _ in range(frames):
            for c in cams:
                r.update_scene(d, camera=c)
                r.render(out=rgb)
                if seg:
                    r.enable_segmentation_rendering()
                    r.update_scene(d, camera=c, scene_option=seg_opt)
                    r.render(out=ids)
                    r.disable_segmentation_rendering()
        dt = time.perf_counter() - t0
        r.close()
    return frames * n / dt


def loop(n: int, frames: int, *, boxes: bool, out: Path) -> float:
    """Images per second of the sim loop in lockstep with in-process echo links."""
    cfg = parse_config({
        "name": "bench", "mode": "lockstep", "duration_s": frames / FPS, "physics_step_s": STEP_S,
        "progress": False, "camera": {"fps": FPS}, "truth": {"visible_boxes": boxes},
        "scenario": {"name": "multi_vehicle", "params": {"n_vehicles": n}},
    })
    clock = MonotonicClock()
    world = _world(n)
    phys, rend = engine_specs(cfg, world, RefStateRules())
    with Simulation(world) as sim, Engine(physics=phys, render=rend, workers=auto_workers(n)) as eng:
        vehicles = [VehicleRun(e, i, EchoLink(i, clock)) for i, e in enumerate(sim.egos)]  # type: ignore[arg-type]
        with Recorder(out, queue_size=65536, compression="zstd") as rec:
            register_all(rec, sim.egos)
            lp = local_loop(cfg, sim, vehicles, engine=eng, physics=phys, rec=rec, bus=EventBus.recording_to(rec),
                            clock=clock, latency=None)
            t0 = time.perf_counter()
            stats = lp.run()
            dt = time.perf_counter() - t0
            rec.flush()
            for v in vehicles:
                v.link.close()
        sent = sum(v.next_frame_id for v in vehicles)
        assert stats.ended_by == "duration", stats.ended_by
    return sent / dt


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--vehicles", type=int, nargs="+", default=[1, 2, 4, 8, 16])
    p.add_argument("--images", type=int, default=400, help="images per measurement (about)")
    p.add_argument("--rounds", type=int, default=3)
    a = p.parse_args(argv)
    print(f"MUJOCO_GL={os.environ.get('MUJOCO_GL')}, {os.cpu_count()} CPUs, 320x240, {FPS:g} fps, "
          f"physics step {STEP_S * 1e3:g} ms ({round(1 / (FPS * STEP_S))} steps per frame), "
          f"~{a.images} images per measurement, median of {a.rounds} rounds\n")
    print("| vehicles | bare render img/s | loop img/s | overhead | bare render+seg img/s | loop+boxes img/s "
          "| overhead | 10 fps each fits (loop / loop+boxes) |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- |")
    with tempfile.TemporaryDirectory() as tmp:
        for n in a.vehicles:
            frames = max(10, -(-a.images // n))
            res: dict[str, list[float]] = {"bare": [], "loop": [], "bare_seg": [], "loop_seg": []}
            for r in range(a.rounds):
                res["bare"].append(bare(n, frames, seg=False))
                res["loop"].append(loop(n, frames, boxes=False, out=Path(tmp) / f"a{n}-{r}.mcap"))
                res["bare_seg"].append(bare(n, frames, seg=True))
                res["loop_seg"].append(loop(n, frames, boxes=True, out=Path(tmp) / f"b{n}-{r}.mcap"))
            med = {k: statistics.median(v) for k, v in res.items()}
            ov = med["bare"] / med["loop"] - 1
            ov_seg = med["bare_seg"] / med["loop_seg"] - 1
            fits = f"{'yes' if med['loop'] >= FPS * n else 'no'} / {'yes' if med['loop_seg'] >= FPS * n else 'no'}"
            print(f"| {n} | {med['bare']:.0f} | {med['loop']:.0f} | {ov * 100:+.0f} % | {med['bare_seg']:.0f} | "
                  f"{med['loop_seg']:.0f} | {ov_seg * 100:+.0f} % | {fits} |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
