"""``hil study``: the paper's study with one command.

Sweeps the number of vehicles (and camera fps) of a multi-vehicle configuration, in
one or both placements, runs each point as a short ``hil run`` of its own, and writes
a study folder (``harness/study/study_page.py``): ``report.md`` and ``report.html``
opening with a reading of the results, ``results.csv``/``results.json``, and six SVG
charts against N (total and per-vehicle frames/s with the 10 fps floor, end-to-end
and inference latency p50/p99/std, physics-step lateness, late physics steps)::

    hil study hil_configs/study.yaml --vehicles 1 2 4 8 --placement replicated distributed

Placements:

* ``replicated``: the targets run on the simulator's host, as the config says.
* ``distributed``: the targets run on another host reached over the network with
  Zenoh. On one machine that host is a network namespace joined to this one by a
  veth pair (private 10.231.x.y/30 addresses; nothing leaves the machine), each
  target with its own ``/dev/shm`` so Zenoh cannot take the shared-memory shortcut
  and every byte crosses the veth. Needs root and iproute2; otherwise the points are
  skipped with the reason. On real hardware, run ``hil target NAME --transport zenoh
  --listen tcp/0.0.0.0:{port} --vehicle {vehicle_id}`` there and ``hil run`` with
  ``target.command=[]`` (README, remote host).

Each point's run folder stays under ``points/``. Exit status: 0 when every point
ran, 1 when a point failed or was skipped, 2 for bad input (one line).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from enum import Enum
from pathlib import Path
from typing import Any

from hil.common.errors import ConfigError

ROOT = Path(__file__).resolve().parents[2]


class Placement(str, Enum):
    REPLICATED = "replicated"  # targets on the simulator's host
    DISTRIBUTED = "distributed"  # targets on another (network-namespace) host, over Zenoh


@dataclass(frozen=True)
class Point:
    """One run of the sweep."""

    placement: Placement
    vehicles: int
    fps: float

    @property
    def name(self) -> str:
        return f"{self.placement.value}-n{self.vehicles}-fps{self.fps:g}"


@dataclass
class PointResult:
    point: Point
    status: str  # "ok", "failed", "skipped"
    reason: str | None = None
    run_dir: str | None = None
    wall_s: float = 0.0  # the point's whole run, start-up included
    metrics: dict[str, Any] = field(default_factory=dict)


def add_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser("study", help="sweep the number of vehicles (and fps) and write a study report",
                       description="Sweep N vehicles (and camera fps) in replicated and/or distributed "
                                   "placement; each point is a short run; writes report.md, report.html, "
                                   "results.csv/json and SVG charts against N.")
    p.add_argument("config", help="a multi-vehicle hil_configs/*.yaml (e.g. hil_configs/study.yaml)")
    p.add_argument("--vehicles", type=int, nargs="+", default=[1, 2, 4, 8], metavar="N",
                   help="numbers of vehicles to run (default 1 2 4 8)")
    p.add_argument("--fps", type=float, nargs="+", default=None, metavar="FPS",
                   help="camera frame rates to run (default: the config's camera.fps)")
    p.add_argument("--placement", nargs="+", default=[p.value for p in Placement],
                   choices=[p.value for p in Placement], help="placements to run (default both)")
    p.add_argument("--duration", type=float, default=8.0, metavar="S",
                   help="simulated seconds per point (default 8)")
    p.add_argument("--floor-fps", type=float, default=10.0, help="per-vehicle frames/s to keep (default 10)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="PATH=VALUE",
                   help="override a config field for every point (repeatable)")
    p.add_argument("--out", type=Path, default=None, help="study folder (default runs/study-<name>-<time>/)")
    p.add_argument("--netem", default=None, metavar="ARGS",
                   help="distributed: impair the veth pair with the kernel's tc netem, both directions, e.g. "
                        "'delay 20ms 2ms loss 1%%' (kernels without sch_netem: the points are skipped with the "
                        "reason; target.impair works on any kernel)")
    from hil.harness.report.ci_outputs import add_ci_args

    add_ci_args(p)


MAX_VEHICLES = 64  # multi_vehicle's own limit; beyond 16, real time is measured first (_check_capacity)


def cmd(args: argparse.Namespace) -> int:
    """Run the study. Raises ConfigError (exit 2, one line) for bad input, before any run."""
    from hil.harness.report.ci_outputs import check_ci_args, write_ci_outputs

    check_ci_args(args)
    placements = [Placement(p) for p in dict.fromkeys(args.placement)]
    vehicles = sorted(set(args.vehicles))
    if vehicles[0] < 1 or vehicles[-1] > MAX_VEHICLES:
        raise ConfigError(f"--vehicles: each N must be 1..{MAX_VEHICLES} (got {' '.join(map(str, args.vehicles))})")
    if args.duration <= 0:
        raise ConfigError(f"--duration: must be > 0 s (got {args.duration:g})")
    base = _load(args.config, [*args.overrides, f"duration_s={args.duration:g}"])
    fps_list = sorted(set(args.fps)) if args.fps else [float(base.camera.fps)]
    points = [Point(pl, n, f) for pl in placements for f in fps_list for n in vehicles]
    for pt in points:  # every point's config must load before anything starts
        _load(args.config, _overrides(args, pt, ns=None))
    _check_capacity(args, points)
    out = args.out or ROOT / "runs" / f"study-{base.name}-{time.strftime('%Y%m%d-%H%M%S')}"
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        # An earlier study's report, results and points would mix with this one's
        # (its points of other N stayed, referred to by nothing).
        raise ConfigError(f"--out {out}: {'not a folder' if not out.is_dir() else 'not empty'}; choose a new or "
                          "empty folder")
    out.mkdir(parents=True, exist_ok=True)
    (out / "points").mkdir(exist_ok=True)
    results: list[PointResult] = []
    t_start = time.monotonic()
    from hil.harness.report.progress import WorkProgress, make_console

    # Points cost about their simulated time: the time left is estimated from the pace so far.
    with WorkProgress(make_console(), what="study", total=len(points), unit="points", live=False) as progress:
        for pl in placements:
            pts = [pt for pt in points if pt.placement is pl]
            with _placement_host(pl, netem=args.netem) as (ns, why):
                for pt in pts:
                    if why is not None:
                        results.append(PointResult(pt, "skipped", why))
                        print(f"study: {pt.name}: skipped ({why})", flush=True)
                    else:
                        results.append(_run_point(args, pt, ns=ns, out=out))
                    progress.advance(note=pt.name)
    study_wall_s = time.monotonic() - t_start
    from hil.harness.study.study_page import write_study

    report = write_study(out, results, config=str(args.config), floor_fps=args.floor_fps,
                         study_wall_s=study_wall_s, loadavg=_loadavg())
    print(f"study: {report} ({report.with_suffix('.html').name} beside it)", flush=True)
    code = 0 if all(r.status == "ok" for r in results) else 1
    from hil.harness.study.ci_cases import of_study

    write_ci_outputs(of_study(results, out=out, exit_code=code, wall_s=study_wall_s), args)
    return code


def _check_capacity(args: argparse.Namespace, points: list[Point]) -> None:
    """Beyond 16 vehicles in real time, the largest point must render in time on this
    machine (``hil.harness.run.capacity``), measured before any point runs.

    Raises:
        ConfigError: it would not; the message names the measured limit.
    """
    from hil.harness.run.capacity import UNMEASURED_VEHICLES

    big = max(points, key=lambda pt: (pt.vehicles * pt.fps, pt.vehicles))
    cfg = _load(args.config, _overrides(args, big, ns=None))
    if cfg.mode.value != "realtime" or big.vehicles <= UNMEASURED_VEHICLES:
        return
    from hil.scenarios.gl import select_backend

    select_backend()
    from hil.harness.engine.pool import auto_workers
    from hil.harness.run import capacity
    from hil.harness.run.driver import build_world
    from hil.scenarios.sim import Simulation

    world, rules = build_world(cfg)
    with Simulation(world, rules=rules) as sim:
        line = capacity.check(cfg, sim, workers=cfg.engine.render_workers or auto_workers(len(sim.egos)),
                              cores=os.cpu_count() or 1)
    if line:
        print(f"study: {line}", flush=True)


def _load(config: str, overrides: Sequence[str]) -> Any:
    from hil.harness.config.loading import load_config

    cfg = load_config(config, overrides=overrides)
    from hil import scenarios

    spec = scenarios.get(cfg.scenario.name)
    params = spec.resolve(cfg.scenario.params)
    if "n_vehicles" not in params:
        raise ConfigError(f"study: scenario {cfg.scenario.name!r} has no n_vehicles parameter; use a "
                          f"multi-vehicle scenario (e.g. hil_configs/study.yaml)")
    return cfg


@dataclass(frozen=True)
class _Namespace:
    name: str
    host_ip: str
    target_ip: str


def _overrides(args: argparse.Namespace, pt: Point, *, ns: _Namespace | None) -> list[str]:
    o = [*args.overrides, f"duration_s={args.duration:g}", f"scenario.params.n_vehicles={pt.vehicles}",
         f"camera.fps={pt.fps:g}", f"name=study-{pt.name.replace('.', '_')}"]
    if pt.placement is Placement.DISTRIBUTED:
        base = _load(args.config, args.overrides)
        t = base.target
        if t.transport.value != "local":
            raise ConfigError(f"study: target.transport must be local (got {t.transport.value}); the distributed "
                              f"placement moves the same target program to the other host and reaches it over Zenoh")
        ip = ns.target_ip if ns is not None else "10.231.0.2"
        prog = [*t.command, *t.args]
        # A private /dev/shm: Zenoh cannot take its shared-memory shortcut, every byte crosses the veth.
        wrap = ["ip", "netns", "exec", ns.name if ns else "hilstudy", "unshare", "--mount", "--propagation", "private",
                "sh", "-c", 'mount -t tmpfs -o size=256m tmpfs /dev/shm && exec "$0" "$@"']
        cmd = [*wrap, *prog, "--transport", "zenoh", "--listen", f"tcp/{ip}:{{port}}", "--vehicle", "{vehicle_id}",
               "--once"]
        o += ["target.transport=zenoh", f"target.command={json.dumps(cmd)}", "target.args=[]",
              f'target.zenoh.connect=["tcp/{ip}:{{port}}"]', "target.zenoh.listen=[]"]
    return o


def _run_point(args: argparse.Namespace, pt: Point, *, ns: _Namespace | None, out: Path) -> PointResult:
    run_dir = out / "points" / pt.name
    if run_dir.exists():
        shutil.rmtree(run_dir)
    argv = [sys.executable, "-m", "hil.harness.cli.main", "run", str(args.config), "--out", str(run_dir), "--no-progress"]
    for o in _overrides(args, pt, ns=ns):
        argv += ["--set", o]
    t0 = time.monotonic()
    print(f"study: {pt.name}: running ({args.duration:g} s)", flush=True)
    with open(out / "points" / f"{pt.name}.log", "wb") as log:
        # The caller's working directory: a relative config, --out or override means what it meant there.
        p = subprocess.run(argv, stdout=log, stderr=subprocess.STDOUT,
                           timeout=max(120.0, 6 * args.duration + 60 + 10 * pt.vehicles))
    wall = time.monotonic() - t0
    summary = run_dir / "summary.json"
    if not summary.exists():
        tail = (out / "points" / f"{pt.name}.log").read_text(errors="replace").strip().splitlines()[-1:]
        return PointResult(pt, "failed", f"exit {p.returncode}: {tail[0] if tail else 'no output'}",
                           str(run_dir), wall)
    from hil.harness.study.study_page import point_metrics

    m = point_metrics(run_dir, floor_fps=args.floor_fps)
    print(f"study: {pt.name}: {m['fps_per_vehicle_min']:.1f} fps/vehicle (min), "
          f"e2e p50 {m['e2e_p50_ms']} ms, real time {'kept' if m['kept_realtime'] else 'NOT kept'} "
          f"({wall:.0f} s)", flush=True)
    status = "ok" if p.returncode in (0, 1) else "failed"
    return PointResult(pt, status, None if status == "ok" else f"exit {p.returncode}", str(run_dir), wall, m)


@contextmanager
def _placement_host(pl: Placement, *, netem: str | None = None) -> Iterator[tuple[_Namespace | None, str | None]]:
    """The targets' host: this one (replicated), or a network namespace joined by a
    veth pair (distributed; ``netem``: tc netem arguments for both ends), removed
    afterwards. Yields (namespace, why-skipped)."""
    if pl is Placement.REPLICATED:
        yield None, None
        return
    why = _netns_unavailable()
    if why is not None:
        yield None, why
        return
    tag = os.getpid() % 10000
    octet = 100 + tag % 150
    ns = _Namespace(f"hilst{tag}", f"10.231.{octet}.1", f"10.231.{octet}.2")
    host_if, ns_if = f"hsh{tag}", f"hst{tag}"
    steps = [f"ip netns add {ns.name}",
             f"ip link add {host_if} type veth peer name {ns_if} netns {ns.name}",
             f"ip addr add {ns.host_ip}/30 dev {host_if}", f"ip link set {host_if} up",
             f"ip -n {ns.name} addr add {ns.target_ip}/30 dev {ns_if}", f"ip -n {ns.name} link set {ns_if} up",
             f"ip -n {ns.name} link set lo up"]
    if netem:  # each end's egress: the host's is the uplink, the namespace's the downlink
        steps += [f"tc qdisc add dev {host_if} root netem {netem}",
                  f"ip netns exec {ns.name} tc qdisc add dev {ns_if} root netem {netem}"]
    try:
        for s in steps:
            p = subprocess.run(s.split(), capture_output=True, text=True)
            if p.returncode != 0:
                what = "tc netem is not available here" if " netem " in s else "could not build the namespace host"
                yield None, f"{what} ({s}: {' '.join(p.stderr.split())})"
                return
        yield ns, None
    finally:
        subprocess.run(["ip", "netns", "del", ns.name], capture_output=True)  # takes the veth pair with it
        subprocess.run(["ip", "link", "del", host_if], capture_output=True)


def _netns_unavailable() -> str | None:
    if os.geteuid() != 0:
        return "distributed placement on one machine needs root (ip netns)"
    for tool in ("ip", "unshare"):
        if shutil.which(tool) is None:
            return f"{tool} is not installed"
    probe = f"hilprobe{os.getpid()}"
    p = subprocess.run(["ip", "netns", "add", probe], capture_output=True, text=True)
    if p.returncode != 0:
        return f"ip netns is not permitted here: {p.stderr.strip()}"
    subprocess.run(["ip", "netns", "del", probe], capture_output=True)
    return None


def _loadavg() -> str:
    try:
        return Path("/proc/loadavg").read_text().strip()
    except OSError:
        return "unknown"
