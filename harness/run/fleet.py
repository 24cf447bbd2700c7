"""Where a run's vehicles live: all in the run process (one shard), or in shard
processes of their own (``engine.shards``; issue 24, per-vehicle work spreads over
processes). Either way the driver sees one :class:`Fleet`: start its targets, attach
it to the run's recording and bus (which builds the loop), sum it up, close it.

The run process keeps, whatever the fleet: the physics and render pool, the world's
truth (``/ground_truth``, collisions), the one MCAP writer, the event bus (``/events``,
corner cases), the summary and the report.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from hil.common.errors import ConfigError
from hil.harness.vocab.events import EventBus
from hil.harness.config.model import RunConfig, Transport
from hil.harness.engine.pool import Engine
from hil.harness.run.assemble import local_loop
from hil.harness.run.loop import SimLoop
from hil.harness.run.vehicle_state import ProgressRow, VehicleRun
from hil.timing.clock import Clock

VEHICLES_PER_SHARD = 16   # "auto": a shard process per this many vehicles or part of it ...
CORES_PER_SHARD = 4       # ... at most one per this many cores


def shard_count(cfg: RunConfig, n_vehicles: int, *, cores: int | None = None) -> int:
    """The shard processes of a run (``engine.shards``); 1: the run process itself.

    Raises:
        ConfigError: more than one asked for where the vehicles cannot leave the run
            process (CAN or mixed transports: the bus is the process's; a shared target).
    """
    kept = cfg.target.transport in (Transport.CAN, Transport.MIXED) or cfg.target.shared
    setting = cfg.engine.shards
    if setting == "auto":
        if kept:
            return 1
        cores = cores or os.cpu_count() or 1
        # 17-32 vehicles: 2 shards. One shard of 24 (cv targets, GPU host) saturated its
        # process: frames queued 4.7 ms behind each other, 13.2 frames/s of 20 (bench/README).
        return max(1, min(-(-n_vehicles // VEHICLES_PER_SHARD), cores // CORES_PER_SHARD))
    n = min(int(setting), max(1, n_vehicles))
    if n > 1 and kept:
        why = "a shared target" if cfg.target.shared else f"transport {cfg.target.transport.value}"
        raise ConfigError(f"engine.shards: {setting} needs vehicles that can leave the run process, but {why} "
                          "keeps them all in it; use engine.shards: auto (or 1)")
    return n


def assign(n_vehicles: int, shards: int) -> tuple[int, ...]:
    """The shard of each ego: in turn, so each shard's cameras spread over the period."""
    return tuple(i % shards for i in range(n_vehicles)) if shards > 1 else ()


class LocalFleet:
    """Every vehicle in the run process: one shard, its targets started here."""

    def __init__(self, cfg: RunConfig, *, egos: tuple[str, ...], clock: Clock, out_dir: Path, session: str) -> None:
        self.cfg, self.egos, self.clock, self.out_dir, self.session = cfg, egos, clock, out_dir, session
        self.vehicles: list[VehicleRun] = []
        self.procs: list[Any] = []  # TargetProcess, or a shared target's handle (anything with close())
        self.warmup: dict[str, list[Any]] = {}
        self.timing: Any = None
        self.detector: Any = None
        self.can_tap: Any = None  # the run's CAN bus log (CAN and mixed keep every vehicle here)

    def start(self, engine: Engine) -> None:
        """Start every target at once and wait for their HELLOs; warm up clock sync.

        Raises:
            TargetError: a target could not start, did not answer or is not the one
                expected; TransportError: a transport could not connect.
        """
        from hil.harness.run.target_launch import SYNC_WARMUP_SAMPLES, check_identity, make_link, open_links

        opening = []
        for i, name in enumerate(self.egos):
            link, proc = make_link(self.cfg, vehicle_id=i, vehicle=name, clock=self.clock, out_dir=self.out_dir,
                                   session=self.session, can_tap=self.can_tap)
            if proc is not None:
                self.procs.append(proc)
            self.vehicles.append(VehicleRun(name, i, link))
            opening.append((name, link, proc))
        open_links(opening, timeout_s=self.cfg.target.startup_timeout_s)
        # The engine's children started beside the targets; the clock sync's warm-up
        # waits for them, so that their start-up does not load its round trips.
        engine.wait_ready()
        self.warmup = {v.name: [s for _ in range(SYNC_WARMUP_SAMPLES)
                                if (s := v.link.sync_exchange(timeout_s=0.5)) is not None] for v in self.vehicles}
        check_identity(self.cfg, self.vehicles, self.procs)

    def attach(self, *, sim: Any, engine: Engine, physics: Any, rec: Any, main_rec: Any, bus: EventBus,
               latency: Any) -> SimLoop:
        """The run's loop, with this fleet's observers on the run's recording and bus."""
        from hil.adapters.impair import record_on
        from hil.harness.cases.detector_observer import DetectorObserver
        from hil.harness.analysis.timing_observer import TimingObserver
        from hil.harness.record.channels import sync_sample_json

        cfg, names = self.cfg, [v.name for v in self.vehicles]
        for v in self.vehicles:  # link faults in real time: each impaired message on /<vehicle>/impairment
            record_on(v.link.impairment, rec, f"/{v.name}/impairment")
        self.timing = TimingObserver.for_run(cfg, names, recorder=rec, events=bus)
        self.detector = (DetectorObserver(cfg.detector, names, camera=cfg.camera, recorder=rec,
                                          timing=self.timing, events=bus) if cfg.detector.enabled else None)
        for name, samples in self.warmup.items():
            for s in samples:
                rec.write_json(f"/{name}/clock_sync", sync_sample_json(s, warmup=True), log_time_ns=s.t4_ns,
                               publish_time_ns=s.t1_ns)
                self.timing.on_sync(name, s)
        loop = local_loop(cfg, sim, self.vehicles, engine=engine, physics=physics, rec=rec, bus=bus,
                          clock=self.clock, latency=latency)
        loop.shards[0].tasks.observers.append(self.timing)
        if self.detector is not None:
            loop.shards[0].tasks.observers.append(self.detector)
        return loop

    def progress_rows(self, now_ns: int) -> list[ProgressRow]:
        return [v.progress_row(now_ns, self.timing.anomaly_count(v.name)) for v in self.vehicles]

    def finish(self, loop: SimLoop, *, wall_s: float) -> tuple[dict[str, Any], dict[str, Any], int, dict[str, Any]]:
        """After the loop: every vehicle summed up (``vehicle_summary``, camera
        figures), the CPU time spent outside this process (none here), and the
        per-frame columns' spill (``summary.json``'s ``spill``)."""
        from hil.harness.run.spill import spill_summary
        from hil.harness.run.summary import CameraFigures, vehicle_summary
        from hil.harness.run.target_launch import close_links

        close_links([v.link for v in self.vehicles])
        loop.collect_sync()  # answers that arrived while closing
        self.timing.finish()
        if self.detector is not None:
            self.detector.finish()
        vehicles = {v.name: vehicle_summary(v, wall_s=wall_s, timing=self.timing, detector=self.detector)
                    for v in self.vehicles}
        return (vehicles, {v.name: CameraFigures.of(v) for v in self.vehicles}, 0,
                spill_summary(self.vehicles, self.timing))

    def close(self) -> None:
        from hil.harness.run.target_launch import close_links

        close_links([v.link for v in self.vehicles])
        for p in self.procs:
            p.close()


class ShardedFleet:
    """The vehicles in shard processes (``hil.harness.run.shard_proc``), each starting
    its own targets at once; their recording comes to the run's writer as bytes."""

    def __init__(self, cfg: RunConfig, *, world: Any, rules: Any, egos: tuple[str, ...], shard_of: tuple[int, ...],
                 clock: Clock, out_dir: Path, session: str, latency: Any) -> None:
        self.cfg, self.world, self.rules, self.egos, self.shard_of = cfg, world, rules, egos, shard_of
        self.clock, self.out_dir, self.session, self.latency = clock, out_dir, session, latency
        self.shards: list[Any] = []

    def start(self, engine: Engine) -> None:
        """Start the shard processes (each starts its targets) and wait for them all.

        Raises:
            TargetError, SimulationError: a shard's target or the shard itself failed.
        """
        from hil.harness.run.shard_handle import RemoteShard
        from hil.harness.run.shard_proc import ShardSpec

        for k in range(max(self.shard_of) + 1):
            mine = tuple((i, n) for i, n in enumerate(self.egos) if self.shard_of[i] == k)
            self.shards.append(RemoteShard(ShardSpec(k, self.cfg, self.world, self.rules, mine, str(self.out_dir),
                                                     self.session, self.latency, engine.shard_io(k),
                                                     {n: engine.assign[n] for _i, n in mine})))
        engine.release_shard_io()
        engine.wait_ready()  # its children started beside the shards
        timeout = self.cfg.target.startup_timeout_s + 60.0  # its own start-up (imports, MuJoCo) on top
        for sh in self.shards:
            sh.wait_ready(timeout)

    def attach(self, *, sim: Any, engine: Engine, physics: Any, rec: Any, main_rec: Any, bus: EventBus,
               latency: Any) -> SimLoop:
        from hil.adapters.impair import IMPAIRMENT_SCHEMA
        from hil.harness.engine.analysis_thread import AnalysisThread
        from hil.harness.record import foxglove_schemas as fx
        from hil.harness.record.rig_views import camera_topic
        from hil.harness.run.tasks import WorldTasks

        cfg = self.cfg
        image = fx.COMPRESSED_IMAGE if cfg.camera.encoding.value == "jpeg" else fx.RAW_IMAGE
        cams = [c.name for c in cfg.camera.cameras()]
        for name in self.egos:  # what the shards write, registered with the one writer
            for k, cam in enumerate(cams):  # camera 0 on /camera, a rig's others on /camera/<name>
                main_rec.register_json_channel(camera_topic(name, cam if k else None), image, fx.schema_for(image))
            if cfg.target.impair.active:
                main_rec.register_json_channel(f"/{name}/impairment", "hil.Impairment", IMPAIRMENT_SCHEMA)
        analysis = AnalysisThread()
        world = WorldTasks(sim, rec, bus, self.clock, egos=set(self.egos), observers=[],
                           view_every_ns=cfg.camera_period_steps * sim.step_ns)
        loop = SimLoop(cfg, sim, self.shards, engine=engine, physics=physics, world=world, analysis=analysis,
                       events=bus, clock=self.clock, recorder=rec)
        engine.connect(on_physics=loop.on_physics, on_render=loop.on_render)
        for sh in self.shards:
            sh.start(wall_start_ns=0, log_time_offset_ns=main_rec.log_time_offset_ns, recorder=main_rec, bus=bus,
                     analysis=analysis, on_stop=loop.request_stop, wake=loop.wake)
        return loop

    def progress_rows(self, now_ns: int) -> list[ProgressRow]:
        return [r for sh in self.shards for r in sh.rows]

    def finish(self, loop: SimLoop, *, wall_s: float) -> tuple[dict[str, Any], dict[str, Any], int, dict[str, Any]]:
        from hil.harness.run.summary import CameraFigures

        vehicles: dict[str, Any] = {}
        camera: dict[str, Any] = {}
        spill: dict[str, Any] = {"failures": 0}
        cpu = 0
        for sh in self.shards:  # all at once: each sums its vehicles up in its own process
            sh.ask_finish(wall_s)
        for sh in self.shards:
            done = sh.finish()
            if done is None:
                continue
            vehicles.update(done.vehicles)
            camera.update({n: CameraFigures(*c) for n, c in done.camera.items()})
            cpu += done.cpu_ns
            for role, ns in done.threads_cpu_ns.items():  # the shards' threads, summed over shards
                key = f"shard:{role}"
                loop.stats.threads_cpu_ns[key] = loop.stats.threads_cpu_ns.get(key, 0) + ns
            loop.stats.analysis_dropped += done.analysis_dropped
            spill = _merge_spill(spill, done.spill)
        order = {n: i for i, n in enumerate(self.egos)}
        return (dict(sorted(vehicles.items(), key=lambda kv: order[kv[0]])),
                dict(sorted(camera.items(), key=lambda kv: order[kv[0]])), cpu, spill)

    def close(self) -> None:
        for sh in self.shards:
            sh.close()


def _merge_spill(a: dict[str, Any], b: dict[str, Any]) -> dict[str, Any]:
    """Two shards' ``spill`` as one (``hil.harness.run.spill``)."""
    out = {**b, **a, "failures": a.get("failures", 0) + b.get("failures", 0)}
    if "columns" in a or "columns" in b:
        out["columns"] = {**a.get("columns", {}), **b.get("columns", {})}
    return out


__all__ = ["LocalFleet", "ShardedFleet", "assign", "shard_count"]
