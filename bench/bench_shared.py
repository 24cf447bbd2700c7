"""One shared CNN target for N vehicles against one CNN target per vehicle (issues 18, 30).

    flock -o /tmp/hil-cpu.lock .venv/bin/python bench/bench_shared.py [--vehicles 1,4,8,16] \
        [--seconds 4] [--fps 20] [--device cpu] [--window-ms 2] [--shared-threads 1] [--workers 2] \
        [--placements per-vehicle,shared,shared-processes,shared-threads] [--per-vehicle]

First, in this process (``CnnTarget.infer_batch``, one torch thread), per batch size:
the batch's time and its parts (decode: JPEG decode and the nets' inputs; nets;
post: heatmap decode, ranging, decisions), the **nets alone** on inputs already
made (the floor the nets' part is compared with, measured in the same run), and
the decode part alone in process, on ``--workers`` threads and on ``--workers``
processes (``hil.targets.cnn.pool``).

Then for each N and each placement, the real target program (``python -m
hil.targets.cnn``, one torch thread) serves N vehicles over the local transport:

* **per-vehicle**: N target processes, one ``LocalLink`` each;
* **shared**: one process (``--shared``) that batches frames arriving within
  ``--window-ms`` (``hil.adapters.batching``), N ``SharedLocalLink``s to it,
  decoding in process;
* **shared-processes** / **shared-threads**: the same with ``--decode-workers
  --workers`` worker processes / threads.

Every vehicle sends a labelled simulator frame (``hil.training.dataset``, JPEG, 320x240)
at ``--fps``, all vehicles at the same instants (aligned cameras: the most frames
at once), for ``--seconds`` after a one-second warm-up. Per vehicle, from each
estimate's stamps: ``inference`` = t_infer_end - t_infer_start (target clock; the
batch's, for a shared target), ``queue`` = t_infer_start - t_rx, ``round trip`` =
estimate received - frame handed to the link (harness clock); p50/p99 and jitter
(std) in ms; ``drops`` = frames without an estimate (the newest frame per vehicle
wins when the target is behind). From the shared target's batch log: batch sizes,
and each part's p50 per batch, beside the nets alone at the batch size most
batches had (from the first table). ``target CPU ms/frame``: user + system CPU time
of the target process(es), decode workers included, while frames flowed, per frame
served: what serving costs, which a loaded machine's latencies hide.

Prints markdown tables (one row per N and placement: the median over vehicles of
each vehicle's p50, the worst vehicle's p99, the mean of the vehicles' std) and
with ``--per-vehicle`` one row per vehicle. Load average printed with them.
"""

from __future__ import annotations

import argparse
import csv
import os
import queue
import statistics
import sys
import tempfile
import threading
import time
from collections import Counter
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from hil.scenarios.gl import select_backend

select_backend()

import numpy as np

from hil.adapters.link import Received
from hil.adapters.local.link import LocalLink
from hil.adapters.local.shared_link import SharedLocalLink, SharedLocalTarget
from hil.adapters.wire.messages import CameraInfo, Estimate, ImageEncoding
from hil.timing.clock import MonotonicClock
from hil.training import dataset

WARMUP_S = 1.0


def _frames(n: int) -> list[tuple[bytes, CameraInfo, float]]:
    out = []
    for s in dataset.generate(seed=dataset.HELDOUT_SEED_BASE + 3, n_frames=n):
        fx, fy, cx, cy, mount, pitch = s.camera
        out.append((s.jpeg, CameraInfo(fx, fy, cx, cy, mount, pitch), s.speed_mps))
    return out


def _family(pid: int) -> list[int]:
    """``pid`` and its descendants (a target's decode workers), from /proc."""
    out, todo = [], [pid]
    while todo:
        p = todo.pop()
        out.append(p)
        for task in Path(f"/proc/{p}/task").glob("*"):
            try:
                todo += [int(x) for x in (task / "children").read_text().split()]
            except OSError:
                pass
    return out


def _cpu_s(pids: list[int]) -> float:
    """User + system CPU seconds the processes ``pids`` have used so far (/proc)."""
    tick = os.sysconf("SC_CLK_TCK")
    total = 0
    for pid in pids:
        try:
            fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        total += int(fields[11]) + int(fields[12])  # utime, stime (fields 14, 15)
    return total / tick


def _pct(xs: list[float], q: float) -> float:
    return float(np.percentile(xs, q)) if xs else float("nan")


PLACEMENTS = ("per-vehicle", "shared", "shared-processes", "shared-threads")
POOLS = {"shared-processes": "process", "shared-threads": "thread"}


def batch_cost(frames: list[tuple[bytes, CameraInfo, float]], *, device: str, threads: int, workers: int,
               sizes: tuple[int, ...] = (1, 4, 8, 16), reps: int = 15) -> tuple[list[str], dict[int, float]]:
    """``CnnTarget.infer_batch`` in this process per batch size (p50 ms of the batch
    and of each part), the nets alone on made inputs, the decode part alone in
    process, on threads and on processes; interleaved across sizes so machine noise
    hits all alike. Returns the table and the nets alone per batch size."""
    import torch

    from hil.adapters.wire.messages import Frame
    from hil.targets.cnn.frontend import Frontend
    from hil.targets.cnn.target import CnnTarget, Serving

    torch.set_num_threads(threads)
    # The largest batch timed must fit the CUDA graphs captured (their largest bucket).
    target = CnnTarget(device=device, serving=Serving(max_batch=max(16, *sizes)))
    fronts = {"in process": Frontend(0, slots=max(sizes)),
              "threads": Frontend(workers, kind="thread", slots=max(sizes)),
              "processes": Frontend(workers, kind="process", slots=max(sizes))}
    fs = [Frame(0, i, 0, 0, 0, 320, 240, ImageEncoding.JPEG, cam, speed, jpeg)
          for i, (jpeg, cam, speed) in enumerate(frames)]
    keys = ("batch", "decode", "nets", "post", "nets alone", *(f"decode {k}" for k in fronts))
    times: dict[tuple[int, str], list[float]] = {(b, k): [] for b in sizes for k in keys}

    def timed(fn: object) -> float:
        t0 = time.perf_counter_ns()
        fn()  # type: ignore[operator]
        return (time.perf_counter_ns() - t0) / 1e6

    try:
        for rep in range(reps + 2):
            for b in sizes:
                batch = [fs[(rep + k) % len(fs)] for k in range(b)]
                got = {"batch": timed(lambda: target.infer_batch(batch))}
                got.update(zip(("decode", "nets", "post"), (x / 1e6 for x in target.last_parts_ns)))
                made = fronts["in process"].prepare(batch, ("det", "steer"))
                got["nets alone"] = timed(lambda: (target.nets.steering(made["steer"]), target.nets.detector(made["det"]),
                                                   target.nets.sync()))
                for k, fe in fronts.items():
                    got[f"decode {k}"] = timed(lambda: fe.prepare(batch, ("det", "steer")))
                if rep >= 2:  # warm-up
                    for k, v in got.items():
                        times[(b, k)].append(v)
    finally:
        for fe in fronts.values():
            fe.close()
    med = {key: statistics.median(v) for key, v in times.items()}
    one = med[(sizes[0], "batch")] / sizes[0]
    rows = ["| batch | infer_batch ms | per frame vs batch 1 | decode | nets | post | nets alone (floor) | "
            f"nets / floor | decode alone: in process | {workers} threads | {workers} processes |",
            "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for b in sizes:
        m = {k: med[(b, k)] for k in keys}
        rows.append(f"| {b} | {m['batch']:.2f} | {m['batch'] / b / one:.2f} | {m['decode']:.2f} | {m['nets']:.2f} | "
                    f"{m['post']:.2f} | {m['nets alone']:.2f} | {m['nets'] / m['nets alone']:.2f} | "
                    f"{m['decode in process']:.2f} | {m['decode threads']:.2f} | {m['decode processes']:.2f} |")
    return rows, {b: med[(b, "nets alone")] for b in sizes}


def run_one(n: int, *, placement: str, frames: list[tuple[bytes, CameraInfo, float]], seconds: float, fps: float,
            device: str, window_ms: float, tmp: Path, shared_threads: int = 1, workers: int = 2) -> dict[str, object]:
    """Serve ``n`` vehicles; returns per-vehicle samples, the batch sizes seen and
    each part's per-batch times (ms)."""
    clock = MonotonicClock()
    rx: queue.Queue[Received] = queue.Queue(maxsize=100_000)
    cmd = [sys.executable, "-m", "hil.targets.cnn", "--threads", "1", "--device", device]
    batch_log = tmp / f"batches-{n}-{placement}.csv"
    shared = placement != "per-vehicle"
    host = None
    links = []
    if shared:
        cmd[cmd.index("--threads") + 1] = str(max(1, shared_threads))
        if placement in POOLS:
            cmd += ["--decode-workers", str(workers), "--decode-pool", POOLS[placement]]
        host = SharedLocalTarget([*cmd, "--shared", "--batch-window-ms", str(window_ms), "--max-batch", str(max(16, n))],
                                 log_path=tmp / f"{placement}-{n}.log", env={"HIL_BATCH_LOG": str(batch_log)})
        links = [SharedLocalLink(host=host, vehicle_id=v, clock=clock, rx_queue=rx) for v in range(n)]
    else:
        links = [LocalLink(command=cmd, vehicle_id=v, clock=clock, log_path=tmp / f"own-{n}-{v}.log", rx_queue=rx)
                 for v in range(n)]
    sent: dict[tuple[int, int], int] = {}
    got: dict[int, list[tuple[int, Estimate, int]]] = {v: [] for v in range(n)}
    stop = threading.Event()

    def collect() -> None:
        while not stop.is_set() or not rx.empty():
            try:
                r = rx.get(timeout=0.2)
            except queue.Empty:
                continue
            if isinstance(r.msg, Estimate):
                got[r.msg.vehicle_id].append((r.msg.frame_id, r.msg, r.t_rx_ns))

    try:
        for link in links:
            link.open(hello_timeout_s=120)
        collector = threading.Thread(target=collect, daemon=True)
        collector.start()
        pids = sorted({p for link in links if link.pid is not None for p in _family(link.pid)})
        period_ns = int(1e9 / fps)
        total = int((seconds + WARMUP_S) * fps)
        warm = int(WARMUP_S * fps)
        start = clock.now_ns() + period_ns
        cpu0 = 0.0
        for fid in range(total):
            due = start + fid * period_ns
            while (left := due - clock.now_ns()) > 0:
                time.sleep(left / 1e9)
            if fid == warm:
                cpu0 = _cpu_s(pids)
            jpeg, cam, speed = frames[fid % len(frames)]
            for link in links:
                t_tx = link.send_frame(frame_id=fid, sim_time_ns=0, t0_ns=due, width=320, height=240,
                                       encoding=ImageEncoding.JPEG, camera=cam, ego_speed_mps=speed, data=jpeg)
                sent[(link.vehicle_id, fid)] = t_tx
        time.sleep(0.5)  # the last estimates (bench only)
        cpu_s = _cpu_s(pids) - cpu0
    finally:
        for link in links:
            link.close()
        if host is not None:
            host.close()
        stop.set()
    per_vehicle = {}
    for v in range(n):
        ests = [(fid, e, t) for fid, e, t in got[v] if fid >= warm]
        per_vehicle[v] = {
            "inference": [(e.t_infer_end_target_ns - e.t_infer_start_target_ns) / 1e6 for _, e, _ in ests],
            "queue": [(e.t_infer_start_target_ns - e.t_rx_target_ns) / 1e6 for _, e, _ in ests],
            "rtt": [(t - sent[(v, fid)]) / 1e6 for fid, _, t in ests],
            "sent": total - warm,
            "drops": (total - warm) - len(ests),
        }
    sizes: Counter[int] = Counter()
    parts: dict[str, list[float]] = {}
    if shared and batch_log.is_file():
        batches = {r["batch"]: r for r in csv.DictReader(open(batch_log)) if int(r["frame_id"]) >= warm}
        sizes = Counter(int(r["batch_size"]) for r in batches.values())
        parts = {p: [int(r[f"{p}_ns"]) / 1e6 for r in batches.values() if r.get(f"{p}_ns")]
                 for p in ("decode", "nets", "post")}
    served = sum(total - warm - per_vehicle[v]["drops"] for v in range(n))  # type: ignore[operator]
    return {"vehicles": per_vehicle, "sizes": sizes, "parts": parts, "cpu_ms_per_frame": 1e3 * cpu_s / max(1, served)}


def _row(label: str, vs: list[dict[str, object]], sizes: Counter[int] | None, cpu_ms: float | None = None,
         parts: dict[str, list[float]] | None = None, floors: dict[int, float] | None = None) -> str:
    def agg(key: str) -> tuple[float, float, float]:
        p50 = statistics.median(_pct(v[key], 50) for v in vs)  # type: ignore[arg-type]
        p99 = max(_pct(v[key], 99) for v in vs)  # type: ignore[arg-type]
        std = statistics.fmean(float(np.std(v[key])) if v[key] else float("nan") for v in vs)  # type: ignore[arg-type]
        return p50, p99, std

    inf, qu, rt = agg("inference"), agg("queue"), agg("rtt")
    drops = sum(int(v["drops"]) for v in vs)  # type: ignore[arg-type]
    sent = sum(int(v["sent"]) for v in vs)  # type: ignore[arg-type]
    sz = "-" if not sizes else " ".join(f"{k}:{c}" for k, c in sorted(sizes.items()))
    pt = "-"
    if parts and all(parts.values()):
        pt = " / ".join(f"{_pct(parts[k], 50):.1f}" for k in ("decode", "nets", "post"))
        common = sizes.most_common(1)[0][0] if sizes else None
        if floors and common in floors:
            pt += f" (floor {floors[common]:.1f} at {common})"
    return (f"| {label} | {inf[0]:.1f} | {inf[1]:.1f} | {inf[2]:.1f} | {qu[0]:.1f} | {qu[1]:.1f} | "
            f"{rt[0]:.1f} | {rt[1]:.1f} | {rt[2]:.1f} | {drops}/{sent} | {sz} | {pt} | "
            f"{'-' if cpu_ms is None else f'{cpu_ms:.2f}'} |")


def _loadavg() -> str:
    return " ".join(open("/proc/loadavg").read().split()[:3])


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--vehicles", default="1,4,8,16", help="N values, comma-separated")
    p.add_argument("--seconds", type=float, default=4.0, help="measured seconds per configuration")
    p.add_argument("--fps", type=float, default=20.0, help="frames per second per vehicle")
    p.add_argument("--device", default="cpu", help="torch device of the targets (cpu, cuda, cuda:N, auto)")
    p.add_argument("--window-ms", type=float, default=2.0, help="the shared target's batch window")
    p.add_argument("--shared-threads", type=int, default=1,
                   help="torch threads of the shared target (each per-vehicle target has 1)")
    p.add_argument("--workers", type=int, default=2, help="decode workers of the shared-processes/-threads targets")
    p.add_argument("--placements", default=",".join(PLACEMENTS), help=f"which of {', '.join(PLACEMENTS)} to run")
    p.add_argument("--per-vehicle", action="store_true", help="also one row per vehicle")
    p.add_argument("--batch-only", action="store_true", help="only the in-process batch cost table")
    a = p.parse_args(argv)
    try:
        ns = [int(x) for x in a.vehicles.split(",") if x.strip()]
        if not ns or min(ns) < 1 or max(ns) > 64:
            raise ValueError
    except ValueError:
        print(f"--vehicles {a.vehicles!r}: expected counts 1..64, e.g. 1,4,8,16", file=sys.stderr)
        return 2
    placements = [x.strip() for x in a.placements.split(",") if x.strip()]
    if not placements or not set(placements) <= set(PLACEMENTS):
        print(f"--placements {a.placements!r}: expected some of {', '.join(PLACEMENTS)}", file=sys.stderr)
        return 2
    if a.workers < 1:
        print(f"--workers {a.workers}: expected >= 1", file=sys.stderr)
        return 2
    frames = _frames(16)
    print(f"# bench_shared: {a.fps:g} fps per vehicle, {a.seconds:g} s measured, device {a.device}, "
          f"window {a.window_ms:g} ms, shared target {a.shared_threads} torch thread(s), {a.workers} decode workers "
          f"where placed so, aligned cameras; {os.cpu_count()} cores; loadavg before: {_loadavg()}", flush=True)
    floors: dict[int, float] = {}
    for threads in sorted({1, a.shared_threads}):
        print(f"\nin-process CnnTarget.infer_batch, {threads} torch thread(s), device {a.device}, "
              f"loadavg {_loadavg()} (ms, p50 of 15):\n")
        table, nets = batch_cost(frames, device=a.device, threads=threads, workers=a.workers,
                                 sizes=tuple(sorted({1, *ns})))
        if threads == a.shared_threads:
            floors = nets
        print("\n".join(table), flush=True)
    if a.batch_only:
        return 0
    header = ("| N, placement | inference p50 | inference p99 | inference std | queue p50 | queue p99 | "
              "round trip p50 | round trip p99 | round trip std | drops/frames | batch sizes (size:count) | "
              "parts p50 decode / nets / post | target CPU ms/frame |\n"
              "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    rows, detail = [], []
    with tempfile.TemporaryDirectory(prefix="bench-shared-") as tmp:
        for n in ns:
            for placement in placements:
                res = run_one(n, placement=placement, frames=frames, seconds=a.seconds, fps=a.fps, device=a.device,
                              window_ms=a.window_ms, tmp=Path(tmp), shared_threads=a.shared_threads,
                              workers=a.workers)
                vs = list(res["vehicles"].values())  # type: ignore[union-attr]
                sizes = res["sizes"] if placement != "per-vehicle" else None
                rows.append(_row(f"{n}, {placement}", vs, sizes, res["cpu_ms_per_frame"],  # type: ignore[arg-type]
                                 res["parts"], floors))  # type: ignore[arg-type]
                print(rows[-1], f"(loadavg {_loadavg()})", flush=True)
                for v, data in res["vehicles"].items():  # type: ignore[union-attr]
                    detail.append(_row(f"{n}, {placement}, vehicle {v}", [data], None))
    print(f"\nloadavg after: {_loadavg()}\n")
    print("ms; p50: median over vehicles of each vehicle's p50; p99: the worst vehicle's; std: mean over vehicles; "
          "parts: p50 per batch from the batch log, the floor is the nets alone in this process at the batch size "
          "most batches had\n")
    print(header)
    print("\n".join(rows))
    if a.per_vehicle:
        print("\n" + header)
        print("\n".join(detail))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
