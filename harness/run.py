"""The run driver: validate, start targets, run the loop, write the run folder.

A run folder holds ``run.mcap`` (everything, Foxglove-readable), ``summary.json``
and ``target-<vehicle>.log`` (the targets' own output). Whatever happens after the
recorder opens (a target dying, Ctrl-C, SIGTERM) the MCAP is finalized and the
summary written with what was recorded.
"""

from __future__ import annotations

import json
import platform
import queue
import signal
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from importlib import metadata
from pathlib import Path
from typing import Any

from harness import __version__
from harness.config import RunConfig, config_hash, dump_config
from timing.clock import MonotonicClock
from timing.errors import ConfigError

SYNC_WARMUP_SAMPLES = 8


@dataclass(frozen=True)
class RunResult:
    out_dir: Path
    mcap_path: Path
    summary_path: Path
    summary: dict[str, Any]


def default_out_dir(cfg: RunConfig, *, root: Path = Path("runs")) -> Path:
    return root / f"{cfg.name}-{time.strftime('%Y%m%d-%H%M%S')}"


def prepare_out_dir(out: Path) -> Path:
    """Create the run folder; refuse to overwrite an earlier run.

    Raises:
        ConfigError: the folder holds a run already or cannot be created.
    """
    if (out / "run.mcap").exists():
        raise ConfigError(f"--out {out}: holds a run already (run.mcap exists); choose another folder")
    try:
        out.mkdir(parents=True, exist_ok=True)
        probe = out / ".write-test"
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as err:
        raise ConfigError(f"--out {out}: cannot write there: {err.strerror or err}") from err
    return out


def versions() -> dict[str, str]:
    out = {"hil-harness": __version__, "python": platform.python_version()}
    for pkg in ("mujoco", "numpy", "opencv-python-headless", "mcap", "eclipse-zenoh", "python-can"):
        try:
            out[pkg] = metadata.version(pkg)
        except metadata.PackageNotFoundError:
            out[pkg] = "not installed"
    return out


def target_command(cfg: RunConfig) -> list[str]:
    return [sys.executable if part == "{python}" else part for part in cfg.target.command] + list(cfg.target.args)


def execute(cfg: RunConfig, *, out_dir: Path, gl_backend: str,
            on_progress: Callable[..., None] | None = None,
            install_signal_handlers: bool = True) -> RunResult:
    """Run ``cfg`` and write its folder. The MuJoCo GL backend must already be chosen.

    Raises:
        ConfigError: bad scenario name/parameters or overlapping vehicles (before
            anything starts).
        TargetError: a target could not start (before the loop; nothing recorded).
        SimulationError: the world cannot be built or rendered.
    """
    import scenarios
    from adapters.link import Received, open_link
    from harness.channels import register_all
    from harness.loop import SimLoop
    from harness.recorder import Recorder
    from harness.summary import build_summary
    from harness.vehicle_state import VehicleRun
    from scenarios.sim import Simulation
    from scenarios.world import CameraSpec

    sdef = scenarios.get(cfg.scenario.name)
    params = sdef.resolve(cfg.scenario.params)
    cam = cfg.camera
    world = sdef.build(params=params, seed=cfg.seed, physics_step_s=cfg.physics_step_s,
                       camera=CameraSpec(width=cam.width, height=cam.height, fovy_deg=cam.fovy_deg,
                                         mount_forward_m=cam.mount_forward_m,
                                         mount_height_m=cam.mount_height_m),
                       shadows=cam.shadows, reflections=cam.reflections)
    clock = MonotonicClock()
    rx: queue.Queue[Received] = queue.Queue(maxsize=4096)
    mcap_path = out_dir / "run.mcap"
    summary_path = out_dir / "summary.json"
    meta = {
        "name": cfg.name, "scenario": cfg.scenario.name, "scenario_params": params, "seed": cfg.seed,
        "config_hash": config_hash(cfg), "gl_backend": gl_backend, "versions": versions(),
    }
    with Simulation(world) as sim:
        sim.open_renderer()
        for name in sim.egos:  # first render compiles shaders; keep it out of the loop
            sim.render(name)
        vehicles: list[VehicleRun] = []
        try:
            for i, name in enumerate(sim.egos):
                link = open_link(cfg.target.transport.value, command=target_command(cfg), vehicle_id=i,
                                 clock=clock, log_path=out_dir / f"target-{name}.log", rx_queue=rx)
                vehicles.append(VehicleRun(name, i, link))
                link.open(hello_timeout_s=cfg.target.startup_timeout_s)
            warmup = {v.name: [s for _ in range(SYNC_WARMUP_SAMPLES)
                               if (s := v.link.sync_exchange(timeout_s=0.5)) is not None]
                      for v in vehicles}
            with Recorder(mcap_path, queue_size=cfg.recording.queue_size, compression="zstd", metadata={
                "run": {k: json.dumps(val) if not isinstance(val, str) else val for k, val in meta.items()},
                "config": {"yaml_json": json.dumps(dump_config(cfg), sort_keys=True)},
            }) as rec:
                register_all(rec, [v.name for v in vehicles])
                for name, samples in warmup.items():
                    for s in samples:
                        rec.write_json(f"/{name}/clock_sync", {
                            "seq": s.seq, "t1_ns": s.t1_ns, "t2_target_ns": s.t2_target_ns,
                            "t3_target_ns": s.t3_target_ns, "t4_ns": s.t4_ns, "offset_ns": s.offset_ns,
                            "delay_ns": s.delay_ns, "warmup": True}, log_time_ns=s.t4_ns, publish_time_ns=s.t1_ns)
                loop = SimLoop(cfg, sim, vehicles, rx, rec, clock)
                if on_progress is not None:
                    loop.on_tick = lambda: on_progress(now_ns=clock.now_ns(), sim_time_s=sim.sim_time_ns / 1e9,
                                                       duration_s=cfg.duration_s, vehicles=vehicles)
                restore = _install_stop_handlers(loop) if install_signal_handlers else None
                try:
                    stats = loop.run()
                finally:
                    if restore is not None:
                        restore()
                for v in vehicles:
                    v.link.close()
                rec.flush()
                rec_stats = rec.stats
                summary = build_summary(loop=loop, stats=stats, recorder_stats={
                    "written": rec_stats.written, "dropped": rec_stats.dropped, "enqueued": rec_stats.enqueued},
                    meta=meta)
                rec.add_metadata("summary", {"json": json.dumps(summary, sort_keys=True)})
            final = rec.stats
            summary["recorder"] = {"written": final.written, "dropped": final.dropped,
                                   "enqueued": final.enqueued, "bytes_written": final.bytes_written}
        finally:
            for v in vehicles:
                v.link.close()
    summary_path.write_text(json.dumps(summary, indent=2, sort_keys=True) + "\n")
    return RunResult(out_dir, mcap_path, summary_path, summary)


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


__all__ = ["RunResult", "default_out_dir", "execute", "prepare_out_dir"]
