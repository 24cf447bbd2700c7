"""The run driver: validate, start targets, run the loop, write the run folder.

A run folder holds ``run.mcap`` (everything, Foxglove-readable), ``summary.json``
and ``target-<vehicle>.log`` (the targets' own output). Whatever happens after the
recorder opens (a target dying, Ctrl-C, SIGTERM) the MCAP is finalized and the
summary written with what was recorded.
"""

from __future__ import annotations

import json
import math
import os
import platform
import secrets
import signal
import time
from collections.abc import Callable
from dataclasses import dataclass
from importlib import metadata
from pathlib import Path
from typing import Any

from hil.adapters.impair import impairment_seed
from hil.common.errors import ConfigError, HilError, RecordingError, TargetError, TransportError
from hil.harness import __version__
from hil.harness.config.loading import config_hash, dump_config
from hil.harness.config.model import RunConfig, Transport
from hil.harness.engine.heap import fix_mmap_threshold
from hil.harness.run.vehicle_state import PROGRESS_NS
from hil.timing.clock import MonotonicClock



@dataclass(frozen=True)
class RunResult:
    out_dir: Path
    mcap_path: Path
    summary_path: Path
    summary: dict[str, Any]


def default_out_dir(cfg: RunConfig, *, root: Path = Path("runs")) -> Path:
    return root / f"{cfg.name}-{time.strftime('%Y%m%d-%H%M%S')}"


def prepare_out_dir(out: Path) -> Path:
    """Create the run folder and claim it for this process (an exclusive lock file,
    held until the process exits or ``hil.harness.record.out_dir.release_out_dir``); refuse to
    overwrite an earlier run or to share the folder with a concurrent one. The disk
    is probed with real bytes (an empty file fits on a full disk).

    Raises:
        ConfigError: one line: the folder holds a run already, another run holds
            it, or it cannot be created or written (read-only, full).
    """
    from hil.harness.record.out_dir import claim_out_dir

    return claim_out_dir(out)


def versions() -> dict[str, str]:
    out = {"hil-harness": __version__, "python": platform.python_version()}
    for pkg in ("mujoco", "numpy", "opencv-python-headless", "mcap", "eclipse-zenoh", "python-can"):
        try:
            out[pkg] = metadata.version(pkg)
        except metadata.PackageNotFoundError:
            out[pkg] = "not installed"
    return out


def execute(cfg: RunConfig, *, out_dir: Path, gl_backend: str,
            on_progress: Callable[..., None] | None = None, notify: Callable[[str], None] = lambda _m: None,
            install_signal_handlers: bool = True) -> RunResult:
    """Run ``cfg`` and write its folder. The MuJoCo GL backend must already be chosen.

    SIGTERM before the loop starts ends the start-up as Ctrl-C does (KeyboardInterrupt:
    targets and workers are ended, nothing is left running); during the loop it ends
    the run cleanly.

    Raises:
        ConfigError: bad scenario name/parameters or overlapping vehicles (before
            anything starts).
        TargetError: a target could not start (before the loop; nothing recorded).
        SimulationError: the world cannot be built or rendered.
    """
    restore = _sigterm_interrupts() if install_signal_handlers else None
    fix_mmap_threshold()  # a long run's heap stays flat (hil.harness.engine.heap)
    try:
        return _execute(cfg, out_dir=out_dir, gl_backend=gl_backend, on_progress=on_progress, notify=notify,
                        install_signal_handlers=install_signal_handlers)
    finally:
        if restore is not None:
            restore()


def build_world(cfg: RunConfig) -> tuple[Any, Any]:
    """(``WorldSpec``, ``RefStateRules``) of a config: the scenario built with its
    seed and camera. Import mujoco-free; the GL backend need not be chosen.

    Raises:
        ConfigError: unknown scenario or bad parameters.
    """
    from hil import scenarios
    from hil.scenarios.ground_truth import RefStateRules
    from hil.scenarios.world import CameraSpec, RigMount

    sdef = scenarios.get(cfg.scenario.name)
    params = sdef.resolve(cfg.scenario.params)
    cam = cfg.camera
    # The "front" preset is the one camera of before rigs: no rig, the same world.
    rig = () if cam.rig == "front" else tuple(
        RigMount(c.name, c.forward_m, c.lateral_m, c.height_m, math.radians(c.yaw_deg), math.radians(c.pitch_deg),
                 math.radians(c.roll_deg), float(c.fovy_deg or cam.fovy_deg), int(c.width or cam.width),
                 int(c.height or cam.height)) for c in cam.cameras())
    world = sdef.build(params=params, seed=cfg.seed, physics_step_s=cfg.physics_step_s,
                       camera=CameraSpec(width=cam.width, height=cam.height, fovy_deg=cam.fovy_deg,
                                         mount_forward_m=cam.mount_forward_m,
                                         mount_height_m=cam.mount_height_m, mount_lateral_m=cam.mount_lateral_m,
                                         pitch_rad=math.radians(cam.pitch_deg), yaw_rad=math.radians(cam.yaw_deg),
                                         rig=rig, antialias=cam.antialias),
                       shadows=cam.shadows, reflections=cam.reflections)
    egos = [v.name for v in world.egos]
    for name in cfg.timing.vehicles:  # a typo'd vehicle's thresholds would judge nothing
        if name not in egos:
            raise ConfigError(f"timing.vehicles.{name}: no such vehicle in this run (its vehicles: {', '.join(egos)})")
    t = cfg.truth
    rules = RefStateRules(comfort_decel_mps2=t.comfort_decel_mps2, stop_margin_m=t.stop_margin_m,
                          slow_headway_s=t.slow_headway_s, slow_ttc_s=t.slow_ttc_s)
    return world, rules


def _target_batches(out_dir: Path) -> dict[str, Any] | None:
    """A shared target's batches (its ``target-shared-batches.csv``): how many of each
    size, and the mean size; None without a shared target."""
    import csv

    from hil.harness.run.shared_target import BATCH_LOG_NAME

    path = out_dir / BATCH_LOG_NAME
    if not path.is_file():
        return None
    sizes: dict[int, int] = {}
    try:
        with open(path, newline="") as f:
            seen = set()
            for row in csv.DictReader(f):
                if row.get("batch") in seen:
                    continue
                seen.add(row.get("batch"))
                n = int(row.get("batch_size") or 0)
                sizes[n] = sizes.get(n, 0) + 1
    except (OSError, ValueError) as err:
        return {"error": f"{path.name}: {err}"}
    total = sum(sizes.values())
    return {"batches": total, "by_size": {str(k): v for k, v in sorted(sizes.items())},
            "mean_size": round(sum(k * v for k, v in sizes.items()) / total, 3) if total else 0.0}


def _progress_every(every_ns: int, clock: Any, show: Callable[[int], None]) -> Callable[[], None]:
    """The loop's tick (every 20 ms) calling ``show(now)`` at most every ``every_ns``: the
    rows cost a percentile per vehicle, computed 50 times a second before (lockstep, 16
    vehicles: a quarter of the loop thread's CPU)."""
    due = [0]

    def tick() -> None:
        now = clock.now_ns()
        if now >= due[0]:
            due[0] = now + every_ns
            show(now)

    return tick


RESERVE_BYTES = 2 << 20  # kept free on the run's disk until the summary and report are written


def _reserve_disk(out_dir: Path) -> Path:
    """Hold ``RESERVE_BYTES`` of real bytes in the run folder, released before the
    summary and report are written, so a disk that fills during the run cannot cost
    them. Best effort: a disk already too full for it just has no reserve."""
    path = out_dir / ".hil-reserve"
    try:
        with open(path, "wb") as f:
            f.write(b"\0" * RESERVE_BYTES)
            f.flush()
            os.fsync(f.fileno())
    except OSError:
        path.unlink(missing_ok=True)
    return path


class _RecordingGuard:
    """Lets a recording failure raised when the recorder closes (disk full) through
    as a note once the summary exists: what was recorded is kept, the summary says
    why the run ended."""

    def __init__(self) -> None:
        self.summary_ready = False
        self.error: str | None = None

    def __enter__(self) -> _RecordingGuard:
        return self

    def __exit__(self, et: type[BaseException] | None, ev: BaseException | None, _tb: object) -> bool:
        if et is not None and issubclass(et, RecordingError) and self.summary_ready:
            self.error = str(ev)
            return True
        return False


def _sigterm_interrupts() -> Callable[[], None] | None:
    """Until restored, SIGTERM raises KeyboardInterrupt (main thread only)."""
    import threading

    if threading.current_thread() is not threading.main_thread():
        return None

    def on_term(_signum: int, _frame: object) -> None:
        raise KeyboardInterrupt

    prev = signal.signal(signal.SIGTERM, on_term)

    def restore() -> None:
        signal.signal(signal.SIGTERM, prev)

    return restore


def _execute(cfg: RunConfig, *, out_dir: Path, gl_backend: str, on_progress: Callable[..., None] | None,
             notify: Callable[[str], None], install_signal_handlers: bool) -> RunResult:
    # Imported here: these pull in mujoco, whose GL backend the caller chose first.
    from hil.harness.vocab.events import EventBus
    from hil.harness.run.summary import build_summary, rate_seconds
    from hil.harness.vocab.verdict import parse_fail_on, verdict_json
    from hil.harness.cases.casebook import CaseRecorder
    from hil.harness.engine.pool import Engine, auto_workers
    from hil.harness.engine.procs import keep_off_core, restore_affinity
    from hil.harness.record.can_log import open_can_log
    from hil.harness.record.channels import register_all
    from hil.harness.record.recorder import Recorder, TimeAnchor
    from hil.harness.report.run_report import write_report
    from hil.harness.run.latency import LatencyProfile
    from hil.harness.run import capacity
    from hil.harness.run.fleet import LocalFleet, ShardedFleet, assign, shard_count
    from hil.harness.run.loop import encode_image, engine_specs
    from hil.harness.run.run_specs import stall_of
    from hil.harness.run.target_launch import can_preflight
    from hil import scenarios
    from hil.scenarios.sim import Simulation

    world, rules = build_world(cfg)
    params = scenarios.get(cfg.scenario.name).resolve(cfg.scenario.params)
    lat_cfg = cfg.lockstep.latency
    latency = (LatencyProfile(lat_cfg, seed=cfg.seed, vehicles=[v.name for v in world.egos],
                              cameras=[c.name for c in cfg.camera.cameras()]) if lat_cfg.active else None)
    clock = MonotonicClock()
    began_ns = clock.now_ns()
    mcap_path = out_dir / "run.mcap"
    (out_dir / "config.json").write_text(json.dumps(dump_config(cfg), indent=2, sort_keys=True) + "\n")
    summary_path = out_dir / "summary.json"
    meta = {
        "name": cfg.name, "scenario": cfg.scenario.name, "scenario_params": params, "seed": cfg.seed,
        "config_hash": config_hash(cfg), "gl_backend": gl_backend, "versions": versions(),
        "scenario_realized": world.realized,
        "latency_profile": None if latency is None else latency.describe(),
        "session": secrets.token_hex(6),  # this run's nonce: a started Zenoh target's keys carry it
        # The settings the run used, with the seed its stage draws from.
        "impairment": {**cfg.target.impair.model_dump(mode="json"),
                       "seed": impairment_seed(cfg.target.impair, run_seed=cfg.seed)}
        if cfg.target.impair.active else None,
    }
    # ``sim`` mirrors the physics process's world here (truth, summary); it renders
    # only for the CAN preflight.
    with Simulation(world, rules=rules) as sim:
        if cfg.target.transport == Transport.CAN:
            # The bus must carry the frames: check with a real frame of this run
            # (+25 % for scenes busier than the first one) before anything starts.
            size = len(encode_image(sim.render(sim.egos[0]), cfg.camera)[0])
            sim.close()
            notify(can_preflight(cfg, frame_bytes=int(size * 1.25)))
        workers = cfg.engine.render_workers or auto_workers(len(sim.egos))
        # Beyond 16 vehicles in real time: refuse what this machine cannot render in time.
        note = capacity.check(cfg, sim, workers=workers, cores=os.cpu_count() or 1)
        if note:
            notify(note)
        n_shards = shard_count(cfg, len(sim.egos))
        shard_of = assign(len(sim.egos), n_shards)
        fleet: LocalFleet | ShardedFleet = (
            LocalFleet(cfg, egos=sim.egos, clock=clock, out_dir=out_dir, session=meta["session"]) if n_shards == 1
            else ShardedFleet(cfg, world=world, rules=rules, egos=sim.egos, shard_of=shard_of, clock=clock,
                              out_dir=out_dir, session=meta["session"], latency=latency))
        engine: Engine | None = None
        reserve: Path | None = None
        affinity: set[int] | None = None
        # One wall-clock anchor for run.mcap's log_time and the CAN log's timestamps.
        anchor = TimeAnchor.capture()
        can_log = open_can_log(cfg, out_dir, offset_ns=anchor.offset_ns, now_ns=clock.now_ns())
        if isinstance(fleet, LocalFleet) and can_log is not None:
            fleet.can_tap = can_log.tap  # CAN keeps every vehicle in this process
        try:
            # Physics and render processes start first: their start-up (MuJoCo, EGL,
            # shaders) overlaps the targets'.
            phys_spec, render_spec = engine_specs(cfg, world, rules)
            # The physics's own core (engine.physics_cpu): this process, and so the
            # render workers and targets it starts, keep off it until the run ends.
            affinity = keep_off_core(phys_spec.cpu)
            engine = Engine(physics=phys_spec, render=render_spec, ring_bytes=cfg.engine.ring_kib * 1024,
                            workers=workers, stall_run=stall_of(cfg),
                            shard_of=shard_of, render_warm=cfg.engine.render_warm_ms)
            fleet.start(engine)
            guard = _RecordingGuard()
            reserve = _reserve_disk(out_dir)
            with guard, Recorder(mcap_path, queue_size=cfg.recording.queue_size, compression="zstd", metadata={
                "run": {k: json.dumps(val) if not isinstance(val, str) else val for k, val in meta.items()},
                "config": {"yaml_json": json.dumps(dump_config(cfg), sort_keys=True)},
            }) as main_rec:
                cc = cfg.corner_cases
                rec = CaseRecorder(main_rec, out_dir, run_meta=meta, history_s=cc.history_s, after_s=cc.after_s,
                                   trigger_kinds=set(cc.on_anomalies)) if cc.enabled else main_rec
                register_all(rec, list(sim.egos), anchor=anchor)
                # The run's one event bus: recorded on /events first, then the corner cases.
                bus = EventBus.recording_to(rec)
                if isinstance(rec, CaseRecorder):
                    bus.subscribe(rec.on_event)
                loop = fleet.attach(sim=sim, engine=engine, physics=phys_spec, rec=rec, main_rec=main_rec, bus=bus,
                                    latency=latency)
                if on_progress is not None:
                    loop.on_tick = _progress_every(PROGRESS_NS, clock, lambda now: on_progress(
                        now_ns=now, sim_time_s=sim.sim_time_ns / 1e9, duration_s=cfg.duration_s,
                        rows=fleet.progress_rows(now)))
                restore = _install_stop_handlers(loop) if install_signal_handlers else None
                cpu0 = time.process_time_ns()
                try:
                    stats = loop.run()
                finally:
                    if restore is not None:
                        restore()
                if main_rec.failure is not None:  # the disk filled: the reserve is for the case rows,
                    reserve.unlink(missing_ok=True)  # the summary and the report, from now on
                vehicles, camera, shard_cpu, spill = fleet.finish(loop, wall_s=rate_seconds(stats))
                if can_log is not None:
                    can_log.close()
                if isinstance(rec, CaseRecorder):
                    rec.close()  # writes the cases still open with what was recorded
                main_rec.flush()
                stats.run_cpu_ns = time.process_time_ns() - cpu0 + shard_cpu
                rec_stats = main_rec.stats
                summary = build_summary(loop=loop, stats=stats, recorder_stats={
                    "written": rec_stats.written, "dropped": rec_stats.dropped, "enqueued": rec_stats.enqueued},
                    meta=meta, vehicles=vehicles, camera=camera)
                summary["spill"] = spill  # per-frame columns that stayed in memory
                summary["realtime"]["shards"] = n_shards
                # Start-up (targets, workers, shards) and the end-of-run work up to this
                # summary (the report follows it; corner-case windows are cut after).
                summary["harness_cost"].update(start_s=round((stats.wall_start_ns - began_ns) / 1e9, 3),
                                               finish_s=round((clock.now_ns() - stats.wall_end_ns) / 1e9, 3))
                if isinstance(rec, CaseRecorder):
                    summary["corner_cases"] = {"written": rec.cases_written, "errors": list(rec.errors),
                                               "triggers_dropped": rec.triggers_dropped}
                if can_log is not None:
                    summary["can_log"] = can_log.summary(out_dir)
                vc = cfg.verdict
                summary["verdict"] = verdict_json(summary, fail_on=parse_fail_on(vc.fail_on),
                                                  deadline_miss_fraction=vc.deadline_miss_fraction,
                                                  drop_fraction=vc.drop_fraction)
                main_rec.add_metadata("summary", {"json": json.dumps(summary, sort_keys=True)})
                guard.summary_ready = True
            reserve.unlink(missing_ok=True)  # room for the summary and the report
            final = main_rec.stats
            if guard.error is not None:
                summary["recorder_error"] = guard.error
                if summary.get("ended_by") == "duration":
                    summary["ended_by"] = f"the recording failed: {guard.error}"
            summary["recorder"] = {"written": final.written, "derived": final.derived, "dropped": final.dropped,
                                   "enqueued": final.enqueued, "bytes_written": final.bytes_written}
            if isinstance(rec, CaseRecorder) and rec.cases_written and guard.error is not None:
                summary["corner_cases"]["errors"].append(
                    "case windows not cut: the recording failed (is the disk full?); once there is room: "
                    f"hil cases {out_dir} --window ID")  # the space left is the summary's and the report's
            elif isinstance(rec, CaseRecorder) and rec.cases_written:
                # Windows are cut from the finalized run.mcap, after the run (nothing
                # of a case's history is held during it).
                from hil.harness.cases.windows import write_case_windows

                cut_ns = clock.now_ns()
                try:
                    summary["corner_cases"]["errors"] += write_case_windows(out_dir, limit=cc.windows)
                except HilError as err:
                    summary["corner_cases"]["errors"].append(str(err))
                summary["harness_cost"]["windows_s"] = round((clock.now_ns() - cut_ns) / 1e9, 3)
            if cfg.recording.rosbag2:  # ROS 2's bag beside run.mcap, cut from it (harness/report/rosbag2.py)
                summary["rosbag2"] = _write_rosbag2(mcap_path, out_dir)
        finally:
            fleet.close()
            if can_log is not None:
                can_log.close()
            if engine is not None:
                engine.close()
            restore_affinity(affinity)
            if reserve is not None:
                reserve.unlink(missing_ok=True)
    batches = _target_batches(out_dir)
    if batches is not None:
        summary["target_batches"] = batches
    # From the loop's last step to this file (case windows included: ``windows_s``).
    summary["harness_cost"]["summary_s"] = round((clock.now_ns() - stats.wall_end_ns) / 1e9, 3)
    summary_path.write_text(json.dumps(summary, indent=2, sort_keys=True) + "\n")
    write_report(out_dir)
    return RunResult(out_dir, mcap_path, summary_path, summary)


def _write_rosbag2(mcap_path: Path, out_dir: Path) -> dict[str, Any]:
    """``rosbag2/`` from the finished ``run.mcap``: what it holds, or why it could not be written."""
    from hil.harness.report.rosbag2 import export

    try:
        return export(mcap_path, out_dir / "rosbag2").to_json()
    except (HilError, OSError, ValueError, KeyError) as err:
        return {"error": f"rosbag2 not written: {type(err).__name__}: {err}"}


def _install_stop_handlers(loop: Any) -> Callable[[], None]:
    """SIGTERM (and SIGINT) end the loop cleanly; returns a function restoring the
    previous handlers."""

    def on_signal(signum: int, _frame: object) -> None:
        loop.request_stop(f"stopped by {signal.Signals(signum).name}")

    prev = {s: signal.signal(s, on_signal) for s in (signal.SIGTERM, signal.SIGINT)}

    def restore() -> None:
        for s, h in prev.items():
            signal.signal(s, h)

    return restore


__all__ = ["RunResult", "build_world", "default_out_dir", "execute", "prepare_out_dir"]
