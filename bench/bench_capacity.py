"""How many vehicles does this host carry? Issue 24's capacity goals, measured in one
call against floors of the same call (written for a GPU host; runs anywhere).

One after another (never two at once):

* floor: the physics process alone pacing the largest world (``--vehicles``' last N,
  ``hil_configs/scale.yaml``) for ``--floor-s`` seconds (``bench_realtime.floor``), on
  the core and at the nice value a run gives it;
* real time: ``hil run hil_configs/scale.yaml`` with N vehicles at ``--fps``, echo
  targets, for each N of ``--vehicles``; then the same with the OpenCV target for each
  N of ``--cv``;
* lockstep: each N of ``--lockstep``, echo targets, against the bare rendering floor
  of the same N cameras (``bench_lockstep.floor``, one process, measured just before).

Per run, beside the summary's figures: the whole machine's CPU (``/proc/stat``, all
processes, targets included) per frame and how busy it was, and the GPU's mean
utilisation (``nvidia-smi``, where there is one): what saturates when a run does not
keep up. Goals (issue 24, GPU host): with echo targets, N=64 at 20 fps with no more
physics steps > 10 ms late than the floor and p99 no worse than the floor's (0.5 ms
slack), every vehicle >= 19.5 frames/s, frames dropped <= 0.1 %, no recording or
analysis message dropped, summary and report within 10 s of the last step (the
corner cases' windows aside: the summary's ``windows_s``); lockstep >= 1,500 frames/s
at N=64 and >= 0.8 x its floor;
the harness's capture->send p50 at the largest N within 2x of N=1. A row whose run did
not happen (refused, failed) reads so, never "met".

    python bench/bench_capacity.py [--vehicles 1 16 32 64] [--fps 20] [--seconds 10]
        [--cv 16 32] [--lockstep 64] [--set engine.shards=4] [--json FILE] [--logs DIR] [--keep DIR]

Per run also: capture→send part by part, and the CPU of the run's processes by role
every quarter second (``cpu_by_role`` in the JSON rows); ``bench/late_frames.py`` reads
a kept run folder.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

import bench_lockstep  # noqa: E402
import bench_realtime  # noqa: E402

from hil.harness.run.vehicle_state import SEND_PARTS  # noqa: E402

P99_SLACK_MS = 0.5


def _cpu_jiffies() -> tuple[int, int]:
    """(busy, total) jiffies of the whole machine."""
    f = [int(x) for x in open("/proc/stat").readline().split()[1:]]
    idle = f[3] + (f[4] if len(f) > 4 else 0)
    return sum(f) - idle, sum(f)


class GpuSampler(threading.Thread):
    """nvidia-smi's utilisation every half second while a run goes (nothing where
    there is no nvidia-smi)."""

    def __init__(self) -> None:
        super().__init__(daemon=True)
        self.samples: list[float] = []
        self.stop = threading.Event()
        self.exe = shutil.which("nvidia-smi")

    def run(self) -> None:
        while self.exe and not self.stop.wait(0.5):
            p = subprocess.run([self.exe, "--query-gpu=utilization.gpu", "--format=csv,noheader,nounits"],
                               capture_output=True, text=True, check=False)
            try:
                self.samples.append(float(p.stdout.split()[0]))
            except (IndexError, ValueError):
                return

    def mean(self) -> float | None:
        return statistics.fmean(self.samples) if self.samples else None


class CpuByRole(threading.Thread):
    """Every ``period_s``, the CPU the run's processes used since the last sample, by
    role: the run process; its spawned children that have children (shards, whose
    children are targets) and the others (physics, render workers, multiprocessing's
    resource tracker); the targets (the run's other children and everything further
    down); in cores (1.0: one core busy the whole period)."""

    def __init__(self, root: int, period_s: float = 0.25) -> None:
        super().__init__(daemon=True)
        self.root, self.period_s = root, period_s
        self.samples: list[tuple[float, dict[str, float]]] = []
        self.stop = threading.Event()

    @staticmethod
    def _procs() -> dict[int, tuple[int, int]]:
        out = {}
        for d in Path("/proc").iterdir():
            if not d.name.isdigit():
                continue
            try:
                f = (d / "stat").read_text().rsplit(")", 1)[1].split()
                out[int(d.name)] = (int(f[1]), int(f[11]) + int(f[12]))  # ppid, utime + stime
            except (OSError, IndexError, ValueError):
                continue
        return out

    def _roles(self, procs: dict[int, tuple[int, int]]) -> dict[int, str]:
        kids: dict[int, list[int]] = {}
        for pid, (ppid, _) in procs.items():
            kids.setdefault(ppid, []).append(pid)
        roles = {self.root: "run"}
        for c in kids.get(self.root, []):
            try:
                spawned = b"spawn_main" in Path(f"/proc/{c}/cmdline").read_bytes()
            except OSError:
                continue
            roles[c] = ("shards" if kids.get(c) else "physics+render") if spawned else "targets"
            stack = list(kids.get(c, []))
            while stack:
                g = stack.pop()
                roles[g] = "targets"
                stack.extend(kids.get(g, []))
        return roles

    def run(self) -> None:
        hz, t0 = os.sysconf("SC_CLK_TCK"), time.monotonic()
        last = self._procs()
        while not self.stop.wait(self.period_s):
            now = self._procs()
            by: dict[str, float] = {}
            for pid, role in self._roles(now).items():
                used = now[pid][1] - last.get(pid, (0, 0))[1]
                by[role] = by.get(role, 0.0) + used / hz / self.period_s
            self.samples.append((round(time.monotonic() - t0, 2), {k: round(v, 2) for k, v in by.items()}))
            last = now


def hil_run(n: int, *, fps: float, seconds: float, target: str, lockstep: bool = False,
            timeout_s: float = 600.0, extra: tuple[str, ...] = (), logs: Path | None = None,
            keep: Path | None = None) -> dict[str, Any]:
    """One ``hil run`` of scale.yaml; its summary's figures, or ``{"failed": why}``.

    ``logs``: a folder for the run's whole output, written as it comes (seconds after
    the start on each line), so a bench stopped from outside still says where the run
    was; a run stopped at the timeout first gets SIGUSR2, which makes each harness
    process print every thread's stack there, and its targets' logs are kept beside it.
    ``keep``: a folder the run folder is moved into (as ``<label>``), to read after."""
    label = f"{'lockstep' if lockstep else 'rt'}-{target}-{n}"
    sets = [f"scenario.params.n_vehicles={n}", f"camera.fps={fps:g}", f"duration_s={seconds:g}",
            f'target.command=["{{python}}", "-m", "hil.targets.{target}"]', "target.startup_timeout_s=120"]
    if lockstep:
        sets += ["mode=lockstep", "truth.visible_boxes=false"]
    sets += extra
    with tempfile.TemporaryDirectory() as d:
        out = Path(d) / "run"
        args = [sys.executable, "-m", "hil.harness.cli.main", "run", "hil_configs/scale.yaml", "--no-progress",
                "--out", str(out)]
        for s in sets:
            args += ["--set", s]
        load0, (busy0, all0) = bench_realtime._load(), _cpu_jiffies()
        gpu = GpuSampler()
        gpu.start()
        t = time.monotonic()
        # Its own process group: a run stopped at the timeout takes its targets and
        # workers with it (they would load the next run).
        p = subprocess.Popen(args, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                             start_new_session=True)
        lines: list[tuple[float, str]] = []
        reader = threading.Thread(target=_read_lines, args=(p, t, lines, logs / f"{label}.log" if logs else None),
                                  daemon=True)
        reader.start()
        roles = CpuByRole(p.pid)
        roles.start()
        stopped = False
        try:
            p.wait(timeout_s)
        except subprocess.TimeoutExpired:
            stopped = True
            _end_group(p, dump=logs is not None)
        finally:  # the bench itself stopped (SIGTERM, Ctrl-C): the run's group goes too
            gpu.stop.set()
            roles.stop.set()
            if p.poll() is None:
                _end_group(p)
        reader.join(5)
        wall = time.monotonic() - t
        busy1, all1 = _cpu_jiffies()
        log = [f"{at:7.1f} s  {ln[:200]}" for at, ln in lines if ln.strip()]
        log = log if len(log) <= 30 else [*log[:10], "...", *log[-20:]]
        if logs and (stopped or not (out / "summary.json").exists()):
            _keep_target_logs(out, logs / f"{label}-targets.log")
        if not (out / "summary.json").exists():
            why = f"no summary within {timeout_s:g} s" if stopped else (
                log[-1][10:] if log else f"exit {p.returncode}")
            return {"failed": why[:300], "log": log}
        summary_at = (out / "summary.json").stat().st_mtime - (time.time() - (time.monotonic() - t))
        report = out / "report.html"  # written after the summary
        report_s = report.stat().st_mtime - (out / "summary.json").stat().st_mtime if report.exists() else None
        s = json.loads((out / "summary.json").read_text())
        if keep:
            shutil.move(out, keep / label)
    hz = os.sysconf("SC_CLK_TCK")
    vs = list(s["vehicles"].values())
    frames = sum(v["frames_sent"] for v in vs)
    dropped = sum(v["dropped"] for v in vs)
    cost, r = s.get("harness_cost", {}), s["realtime"]

    def p50s(stage: str) -> list[float]:
        return sorted(v["latency_ms"][stage]["p50_ms"] for v in vs if v["latency_ms"].get(stage, {}).get("count"))

    by_stage = {k: p50s(k) for k in sorted({k for v in vs for k in v["latency_ms"]})}
    c2s, apply = by_stage.get("capture_to_send", []), by_stage.get("apply_delay", [])
    parts = {part: statistics.median(x) for part in SEND_PARTS
             if (x := [v["capture_to_send_parts_ms"][part]["p50_ms"] for v in vs
                       if v.get("capture_to_send_parts_ms", {}).get(part, {}).get("count")])}
    return {
        "n": n, "fps": fps, "target": target, "lockstep": lockstep, "frames": frames, "dropped": dropped,
        "drop_pct": 100.0 * dropped / max(1, frames + dropped),
        "min_fps": min((v["frames_per_s"] for v in vs), default=0.0),
        "steps": sum(int(c) for c in r.get("lateness_histogram", {}).get("bins", {}).values()),
        "over10": r["steps_over_10ms"], "p99": r["lateness_ms"]["p99"], "max": r["max_lateness_ms"],
        "factor": r["achieved_factor"], "kept": r.get("kept_realtime"), "sched": r.get("physics_scheduling"),
        "late_frames": r.get("camera", {}).get("late_frames", 0),
        "workers": r.get("render_workers"), "shards": r.get("shards"),
        "mcap_dropped": s["recorder"]["dropped"], "analysis_dropped": cost.get("analysis_tasks_dropped"),
        "c2s_p50": statistics.median(c2s) if c2s else None, "c2s_worst": c2s[-1] if c2s else None,
        "apply_p50": statistics.median(apply) if apply else None,
        "c2s_parts_p50": parts,  # median over vehicles of each part's p50 (ms)
        "stages_p50_ms": {k: statistics.median(x) for k, x in by_stage.items() if x},  # median over vehicles
        "run_us": cost.get("run_us_per_frame"), "start_s": cost.get("start_s"), "finish_s": cost.get("finish_s"),
        "summary_s": cost.get("summary_s"), "windows_s": cost.get("windows_s"), "report_s": report_s,
        "loop_wall_s": s["wall_time_s"], "command_s": wall, "summary_at_s": summary_at, "log": log,
        "exited": not stopped,
        "fps_total": frames / s["wall_time_s"] if s["wall_time_s"] else 0.0,
        "cpu_busy_pct": 100.0 * (busy1 - busy0) / max(1, all1 - all0),
        "cpu_us_per_frame": (busy1 - busy0) / hz * 1e6 / max(1, frames), "gpu_pct": gpu.mean(),
        "cpu_by_role": roles.samples,  # (seconds after the command's start, {role: cores})
        "load": f"{load0} / {bench_realtime._load()}",
    }


def _read_lines(p: subprocess.Popen[str], t: float, lines: list[tuple[float, str]], log: Path | None) -> None:
    with open(log, "w", buffering=1) if log else open(os.devnull, "w") as f:
        for ln in p.stdout or ():
            at = time.monotonic() - t
            lines.append((at, ln.rstrip()))
            f.write(f"{at:8.2f} {ln}")


def _keep_target_logs(out: Path, to: Path, tail: int = 30) -> None:
    """The last lines of each target's log of a run that did not finish."""
    with open(to, "w") as f:
        for log in sorted(out.glob("target-*.log")):
            text = log.read_text(errors="replace").splitlines()
            f.write(f"== {log.name} ({len(text)} lines)\n" + "".join(ln + "\n" for ln in text[-tail:]))


def _dump_group(pgid: int) -> None:
    """SIGUSR2 to each process of the run's group, one at a time (their stacks share
    one pipe): each harness process prints its threads' stacks and goes on."""
    pids = []
    for d in Path("/proc").iterdir():
        try:  # the run and its spawned children (SIGUSR2 would end any other process)
            if d.name.isdigit() and os.getpgid(int(d.name)) == pgid and (
                    int(d.name) == pgid or b"spawn_main" in (d / "cmdline").read_bytes()):
                pids.append(int(d.name))
        except OSError:
            continue
    for pid in sorted(pids, key=lambda x: x != pgid):  # the run process first
        try:
            os.kill(pid, signal.SIGUSR2)
        except OSError:
            continue
        time.sleep(0.2)


def _end_group(p: subprocess.Popen[str], *, dump: bool = False) -> None:
    """SIGTERM to the run's process group, SIGKILL to what is left 10 s later;
    ``dump``: SIGUSR2 first, so each harness process prints its threads' stacks."""
    if dump:
        _dump_group(p.pid)
    for sig, wait in ((signal.SIGTERM, 10.0), (signal.SIGKILL, 5.0)):
        try:
            os.killpg(p.pid, sig)
        except ProcessLookupError:
            return
        deadline = time.monotonic() + wait
        while time.monotonic() < deadline:
            p.poll()  # reaps the leader: a zombie still counts in its group
            try:
                os.killpg(p.pid, 0)
            except ProcessLookupError:
                return
            time.sleep(0.2)


def _f(x: Any, fmt: str = ".2f") -> str:
    return "–" if x is None else format(x, fmt)


END_OF_RUN_S = 10.0  # summary and report after the last frame, case windows aside (issue 24)


def end_of_run_s(r: dict[str, Any]) -> float | None:
    """Seconds from the run's last step to its summary and report, the corner cases'
    windows aside (the issue's bound); None where the run did not say."""
    if r.get("summary_s") is None or r.get("report_s") is None:
        return None
    return r["summary_s"] - (r.get("windows_s") or 0.0) + r["report_s"]


def realtime_goals(r: dict[str, Any], fl: dict[str, Any]) -> str:
    """The issue's capacity goals for one real-time run against the floor: 'met' or
    what was missed."""
    if "failed" in r:
        return "not measured"
    miss = []
    if r["over10"] > fl["steps_over_10ms"] or r["p99"] > fl["p99_ns"] / 1e6 + P99_SLACK_MS:
        miss.append("physics lateness")
    if r["min_fps"] < 0.975 * r["fps"]:
        miss.append("frames/s")
    if r["drop_pct"] > 0.1:
        miss.append("drops")
    if r["mcap_dropped"] or r["analysis_dropped"]:
        miss.append("messages dropped")
    if (end := end_of_run_s(r)) is None or end > END_OF_RUN_S:
        miss.append("end of run" if end is not None else "end of run not measured")
    return "met" if not miss else "**not met**: " + ", ".join(miss)


def print_realtime(rows: list[dict[str, Any]], fl: dict[str, Any]) -> None:
    print("| N | target | steps | > 10 ms late | p99 ms | max ms | factor | min vehicle frames/s | frames | dropped % "
          "| MCAP / analysis dropped | capture→send p50 ms (median, worst vehicle) | its parts p50 ms (encode / "
          "hand-off / queue / send) | t0'→apply p50 ms | run-side µs "
          "per frame | machine CPU µs per frame (busy %) | GPU % | workers / shards | start s | finish s "
          "| after the last step s: summary (case windows) + report | command s (summary written at) | goals "
          "| load before / after |")
    print("|" + "---:|" * 2 + "---:|" * 21 + "---|---|")
    for r in rows:
        if "failed" in r:
            print(f"| {r['n']} | {r['target']} | {r['failed']} |" + " |" * 21 + " not measured | |")
            continue
        stopped = "" if r["exited"] else ", stopped at the timeout"
        print(f"| {r['n']} | {r['target']} | {r['steps']} | {r['over10']} | {r['p99']:.2f} | {r['max']:.2f} | "
              f"{r['factor']:.3f} | {r['min_fps']:.2f} | {r['frames']} | {r['drop_pct']:.3f} | {r['mcap_dropped']} / "
              f"{r['analysis_dropped']} | {_f(r['c2s_p50'])}, {_f(r['c2s_worst'])} | "
              f"{' / '.join(_f(r['c2s_parts_p50'].get(k)) for k in SEND_PARTS)} | "
              f"{_f(r['apply_p50'])} | "
              f"{_f(r['run_us'], '.0f')} | {r['cpu_us_per_frame']:.0f} ({r['cpu_busy_pct']:.0f}) | "
              f"{_f(r['gpu_pct'], '.0f')} | {r['workers']} / {r['shards']} | {_f(r['start_s'])} | "
              f"{_f(r['finish_s'])} | {_f(r['summary_s'], '.1f')} ({_f(r['windows_s'], '.1f')}) + "
              f"{_f(r['report_s'], '.1f')} | {r['command_s']:.1f} ({r['summary_at_s']:.1f}{stopped}) | "
              f"{realtime_goals(r, fl)} | {r['load']} |", flush=True)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--vehicles", type=int, nargs="*", default=[1, 16, 32, 64])
    ap.add_argument("--cv", type=int, nargs="*", default=[16, 32])
    ap.add_argument("--lockstep", type=int, nargs="*", default=[64])
    ap.add_argument("--fps", type=float, default=20.0)
    ap.add_argument("--seconds", type=float, default=10.0, help="simulated seconds per run")
    ap.add_argument("--lockstep-seconds", type=float, default=4.0)
    ap.add_argument("--floor-s", type=float, default=10.0)
    ap.add_argument("--floor-images", type=int, default=1280)
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="a config override for every run (e.g. engine.shards=4), repeatable")
    ap.add_argument("--run-timeout", type=float, default=600.0, help="seconds before a run counts as failed")
    ap.add_argument("--json", type=Path, help="also write every row here (JSON lines)")
    ap.add_argument("--keep", type=Path, help="a folder each finished run's folder is moved into")
    ap.add_argument("--logs", type=Path, help="a folder for each run's whole output (and, for a run that did not "
                    "finish, its threads' stacks and its targets' logs)")
    a = ap.parse_args()
    for d in (a.logs, a.keep):
        if d:
            d.mkdir(parents=True, exist_ok=True)
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))  # unwinds, so a run in flight is ended
    gpu = GpuSampler().exe
    name = (subprocess.run([gpu, "--query-gpu=name", "--format=csv,noheader"], capture_output=True, text=True,
                           check=False).stdout.strip() if gpu else "no GPU")
    print(f"machine: {os.cpu_count()} cores, {name}, MUJOCO_GL={os.environ.get('MUJOCO_GL', '(auto)')}, "
          f"load before {bench_realtime._load()}; overrides for every run: {' '.join(a.set) or 'none'}\n")
    rows: list[dict[str, Any]] = []

    def keep(*new: dict[str, Any]) -> None:  # written as they come: a bench stopped keeps its rows
        rows.extend(new)
        if a.json:
            a.json.write_text("".join(json.dumps(r) + "\n" for r in rows))

    big = max([*a.vehicles, *a.cv, 1])
    fl: dict[str, Any] = bench_realtime.floor(a.floor_s, config="hil_configs/scale.yaml",
                                              overrides=(f"scenario.params.n_vehicles={big}",), as_run=True)
    keep({"floor": "physics", "n": big, **fl})
    print(f"## floor: the physics process alone, {big} vehicles' world, {a.floor_s:g} s\n")
    print("| steps | > 10 ms late | p99 ms | max ms | scheduling |\n|---:|---:|---:|---:|---|")
    print(f"| {fl['steps']} | {fl['steps_over_10ms']} | {float(fl['p99_ns']) / 1e6:.3f} | "
          f"{float(fl['max_ns']) / 1e6:.3f} | {fl['scheduling']} |\n", flush=True)
    for title, ns, target in (("echo targets", a.vehicles, "echo"), ("OpenCV targets", a.cv, "cv_baseline")):
        if not ns:
            continue
        print(f"## real time, {a.fps:g} fps, {a.seconds:g} s, {title}\n")
        rt = []
        for n in ns:
            r = hil_run(n, fps=a.fps, seconds=a.seconds, target=target, timeout_s=a.run_timeout,
                        extra=tuple(a.set), logs=a.logs, keep=a.keep)
            rt.append({"n": n, "target": target, **r})
        keep(*rt)
        print_realtime(rt, fl)
        for r in rt:
            if "failed" in r or not r["exited"]:
                print(f"\nN={r['n']}, {target}: the run's output, seconds after its start\n\n```")
                print("\n".join(r["log"]) + "\n```")
        done = [r for r in rt if "failed" not in r and r["c2s_p50"] is not None]
        if target == "echo" and len(done) > 1:
            lo, hi = done[0], done[-1]
            ratio = hi["c2s_p50"] / lo["c2s_p50"]
            print(f"\nharness's capture→send p50 at N={hi['n']} / N={lo['n']}: {ratio:.2f} (goal <= 2: "
                  f"{'met' if ratio <= 2 else 'not met'})")
        print(flush=True)
    if a.lockstep:
        print(f"## lockstep, echo targets, {a.lockstep_seconds:g} simulated s, no camera truth\n")
        print("| N | floor images/s (bare, one process) | frames/s | ratio | goal (>= 1,500 and >= 0.8) | run-side µs "
              "per frame | machine CPU µs per frame (busy %) | GPU % | workers / shards | start s | finish s | "
              "load |\n|---:|---:|---:|---:|---|---:|---:|---:|---:|---:|---:|---|")
        for n in a.lockstep:
            try:
                floor = bench_lockstep.floor(n, a.floor_images)
            except subprocess.CalledProcessError as e:
                floor = float("nan")
                print(f"(floor failed: {e.stderr.strip().splitlines()[-1:]})")
            r = hil_run(n, fps=a.fps, seconds=a.lockstep_seconds, target="echo", lockstep=True,
                        timeout_s=a.run_timeout, extra=tuple(a.set), logs=a.logs, keep=a.keep)
            keep({"n": n, "floor_images_per_s": floor, **r})
            if "failed" in r:
                print(f"| {n} | {floor:.0f} | {r['failed']} | | not measured | | | | | | | |", flush=True)
                continue
            ratio = r["fps_total"] / floor
            goal = "met" if r["fps_total"] >= 1500 and ratio >= 0.8 else "**not met**"
            print(f"| {n} | {floor:.0f} | {r['fps_total']:.0f} | {ratio:.2f} | {goal} | {_f(r['run_us'], '.0f')} | "
                  f"{r['cpu_us_per_frame']:.0f} ({r['cpu_busy_pct']:.0f}) | {_f(r['gpu_pct'], '.0f')} | "
                  f"{r['workers']} / {r['shards']} | {_f(r['start_s'])} | {_f(r['finish_s'])} | {r['load']} |",
                  flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
