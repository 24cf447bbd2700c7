"""Putting a run's loop together: its shards, their tasks and the world's, wired to
the engine's pumps and the links' readers."""

from __future__ import annotations

from typing import Any

from hil.harness.config.model import RunConfig
from hil.harness.engine.analysis_thread import AnalysisThread
from hil.harness.run.loop import SimLoop
from hil.harness.run.rig_frames import rig_cams
from hil.harness.run.shard import VehicleShard
from hil.harness.run.tasks import TruthCache, VehicleTasks, WorldTasks


def local_loop(cfg: RunConfig, sim: Any, vehicles: list[Any], *, engine: Any, physics: Any, rec: Any, bus: Any,
                clock: Any, latency: Any) -> SimLoop:
    """The loop of a run whose vehicles all live in this process: one shard, whose
    handlers the engine's pumps and the links' readers call directly."""
    analysis = AnalysisThread()
    cache = TruthCache()  # the world's truth of an instant serves the detector's at t_apply (lockstep)
    tasks = VehicleTasks(sim, rec, clock, cache=cache, render_worker=engine.assign)
    box: list[Any] = []  # the loop, once built (the shard's callbacks reach it)
    shard = VehicleShard(cfg, vehicles, egos=sim.egos, step_ns=sim.step_ns, cams=rig_cams(sim), tasks=tasks,
                         analysis=analysis, events=bus, clock=clock, frame_bytes=engine.frame_bytes,
                         send_control=engine.control, on_stop=lambda why: box[0].request_stop(why),
                         wake=lambda: box[0].wake(), latency=latency)
    world = WorldTasks(sim, rec, bus, clock, egos={v.name for v in vehicles}, observers=tasks.observers, cache=cache,
                       view_every_ns=cfg.camera_period_steps * sim.step_ns)
    loop = SimLoop(cfg, sim, [shard], engine=engine, physics=physics, world=world, analysis=analysis, events=bus,
                   clock=clock, recorder=rec)
    box.append(loop)
    engine.connect(on_physics=loop.on_physics, on_render=loop.on_render)
    for v in vehicles:
        v.link.deliver_to(shard.on_received)
    return loop
