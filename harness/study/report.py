"""The study folder of ``hil study`` (harness/study/study.py): metrics per point, the table
(``results.csv``, ``results.json``), SVG plots like the paper's figures 7-13, and
``report.md`` opening with a one-paragraph reading of the results.

Definitions (per point, one run):

* **total frames/s**: frames sent by all vehicles / the run's wall-clock seconds.
* **per-vehicle frames/s**: estimates applied per wall-clock second, per vehicle (a
  frame counts once its answer came back in time); ``min`` over the vehicles is held
  against the floor (10 fps, the paper's).
* **end-to-end** (``t0' − t0``, capture to the answer's receipt) and **inference**
  (the target's own inference time) latency: pooled over every vehicle's answered
  frames from the run's ``/<vehicle>/pipeline`` records; p50, p99 and std (jitter).
* **real-time health**: the summary's ``realtime`` block: physics steps later than
  the tolerance, lateness p99, whether real time was kept.

A point *holds* when its minimum per-vehicle frames/s ≥ the floor and it kept real
time; the study states the largest N that holds (and the largest N that keeps the
floor alone, since on a loaded machine a few late physics steps are common).
"""

from __future__ import annotations

import csv
import json
from pathlib import Path
from typing import Any

import numpy as np

from hil.harness.report.plots import PALETTE, Series, line_chart

_COLUMNS = ("placement", "vehicles", "fps", "status", "total_fps", "fps_per_vehicle_mean", "fps_per_vehicle_min",
            "e2e_p50_ms", "e2e_p99_ms", "e2e_std_ms", "inference_p50_ms", "inference_p99_ms", "inference_std_ms",
            "uplink_p50_ms", "late_steps", "steps_over_10ms", "lateness_p99_ms", "achieved_factor",
            "kept_realtime", "floor_kept", "holds", "wall_s", "reason")


def _stats(values_ms: list[float]) -> tuple[float | None, float | None, float | None]:
    if not values_ms:
        return None, None, None
    a = np.asarray(values_ms, float)
    return (round(float(np.percentile(a, 50)), 3), round(float(np.percentile(a, 99)), 3),
            round(float(a.std()), 3))


def point_metrics(run_dir: Path, *, floor_fps: float) -> dict[str, Any]:
    """The study's figures of one run folder (see the module docstring)."""
    s = json.loads((run_dir / "summary.json").read_text())
    wall = max(float(s["wall_time_s"]), 1e-9)
    vs = s["vehicles"]
    per = [v["estimates_applied"] / wall for v in vs.values()]
    e2e, inf, up = _pooled(run_dir / "run.mcap", list(vs))
    rt = s["realtime"]
    e = _stats(e2e)
    i = _stats(inf)
    m = {
        "total_fps": round(sum(v["frames_sent"] for v in vs.values()) / wall, 2),
        "fps_per_vehicle_mean": round(float(np.mean(per)), 2) if per else 0.0,
        "fps_per_vehicle_min": round(min(per), 2) if per else 0.0,
        "e2e_p50_ms": e[0], "e2e_p99_ms": e[1], "e2e_std_ms": e[2],
        "inference_p50_ms": i[0], "inference_p99_ms": i[1], "inference_std_ms": i[2],
        "uplink_p50_ms": _stats(up)[0],
        "late_steps": rt["late_steps"], "steps_over_10ms": rt.get("steps_over_10ms"),
        "lateness_p99_ms": rt["lateness_ms"]["p99"], "achieved_factor": rt["achieved_factor"],
        "kept_realtime": bool(rt["kept_realtime"]),
    }
    m["floor_kept"] = m["fps_per_vehicle_min"] >= floor_fps
    m["holds"] = m["floor_kept"] and m["kept_realtime"]
    return m


def _pooled(mcap: Path, vehicles: list[str]) -> tuple[list[float], list[float], list[float]]:
    """End-to-end, inference and uplink values (ms) of every answered frame."""
    from mcap.reader import make_reader

    e2e: list[float] = []
    inf: list[float] = []
    up: list[float] = []
    topics = [f"/{v}/pipeline" for v in vehicles]
    with open(mcap, "rb") as f:
        for _, _, msg in make_reader(f).iter_messages(topics=topics, log_time_order=False):
            rec = json.loads(msg.data)
            if rec.get("status") != "ok":
                continue
            st = rec.get("stages_ns") or {}
            if "end_to_end" in st:
                e2e.append(st["end_to_end"] / 1e6)
            if "inference" in st:
                inf.append(st["inference"] / 1e6)
            if rec.get("t_rx_target_ns") is not None:
                up.append((rec["t_rx_target_ns"] - rec["t_tx_ns"]) / 1e6)  # raw: same-clock targets only
    return e2e, inf, up


def _row(r: Any) -> dict[str, Any]:
    m = r.metrics
    row = {"placement": r.point.placement.value, "vehicles": r.point.vehicles, "fps": r.point.fps,
           "status": r.status, "wall_s": round(r.wall_s, 1), "reason": r.reason, "run_dir": r.run_dir}
    for c in _COLUMNS:
        if c not in row:
            row[c] = m.get(c)
    return row


def largest_holding(rows: list[dict[str, Any]], *, key: str = "holds") -> dict[str, int | None]:
    """Per placement (and fps), the largest N whose point and every smaller one satisfy ``key``."""
    out: dict[str, int | None] = {}
    groups: dict[str, list[dict[str, Any]]] = {}
    for r in rows:
        groups.setdefault(f"{r['placement']} @ {r['fps']:g} fps", []).append(r)
    for g, rs in groups.items():
        best = None
        for r in sorted(rs, key=lambda r: r["vehicles"]):
            if r["status"] != "ok" or not r.get(key):
                break
            best = r["vehicles"]
        out[g] = best
    return out


def _reading(rows: list[dict[str, Any]], holds: dict[str, int | None], floor: dict[str, int | None],
             floor_fps: float, study_wall_s: float) -> str:
    ok = [r for r in rows if r["status"] == "ok"]
    if not ok:
        return "No point of this study ran; see the table for each point's reason."
    parts = []
    for g in holds:
        rs = sorted((r for r in ok if f"{r['placement']} @ {r['fps']:g} fps" == g), key=lambda r: r["vehicles"])
        if not rs:
            continue
        lo, hi = rs[0], rs[-1]
        parts.append(
            f"In the {g} series total throughput went from {lo['total_fps']:.0f} frames/s with "
            f"{lo['vehicles']} vehicle(s) to {hi['total_fps']:.0f} with {hi['vehicles']}, while each vehicle got "
            f"{lo['fps_per_vehicle_min']:.1f} → {hi['fps_per_vehicle_min']:.1f} frames/s (minimum over vehicles); "
            f"end-to-end latency p50 {lo['e2e_p50_ms']} → {hi['e2e_p50_ms']} ms and p99 {lo['e2e_p99_ms']} → "
            f"{hi['e2e_p99_ms']} ms (std {lo['e2e_std_ms']} → {hi['e2e_std_ms']} ms), inference p50 "
            f"{lo['inference_p50_ms']} → {hi['inference_p50_ms']} ms. The largest N keeping ≥ {floor_fps:g} fps per "
            f"vehicle with real time kept is {_n(holds[g])}; keeping the fps floor alone (ignoring late physics "
            f"steps), {_n(floor[g])}.")
    late = [r for r in ok if not r["kept_realtime"]]
    if late:
        parts.append(f"{len(late)} of {len(ok)} points did not keep real time (achieved real-time factor down to "
                     f"{min(r['achieved_factor'] for r in late):.2f}, up to {max(r['late_steps'] for r in late)} "
                     f"physics steps late, worst lateness p99 {max(r['lateness_p99_ms'] or 0 for r in late):.2f} "
                     f"ms): their latencies were measured on a slowed simulation.")
    parts.append(f"The whole study took {study_wall_s / 60:.1f} minutes.")
    return " ".join(parts)


def _n(v: int | None) -> str:
    return "none (the smallest N already misses it)" if v is None else f"N = {v}"


def _plots(out: Path, rows: list[dict[str, Any]], floor_fps: float) -> list[str]:
    groups: dict[str, list[dict[str, Any]]] = {}
    for r in rows:
        if r["status"] == "ok":
            groups.setdefault(f"{r['placement']} {r['fps']:g}fps", []).append(r)
    for g in groups.values():
        g.sort(key=lambda r: r["vehicles"])
    ns = sorted({r["vehicles"] for r in rows}) or [1]

    def series(key: str, label: str, k: int = 0) -> list[Series]:
        return [Series(f"{g} {label}".strip(), [r["vehicles"] for r in rs],
                       [np.nan if r[key] is None else r[key] for r in rs], PALETTE[(i * 3 + k) % len(PALETTE)])
                for i, (g, rs) in enumerate(groups.items())]

    figs = {
        "fig_total_fps.svg": ([*series("total_fps", "")], "total frames/s", "Total rendering throughput"),
        "fig_fps_per_vehicle.svg": ([*series("fps_per_vehicle_mean", "mean"), *series("fps_per_vehicle_min", "min", 1),
                                     Series(f"{floor_fps:g} fps floor", [ns[0], ns[-1]], [floor_fps, floor_fps],
                                            "#d62728")], "frames/s per vehicle", "Per-vehicle frames/s"),
        "fig_e2e_latency.svg": ([*series("e2e_p50_ms", "p50"), *series("e2e_p99_ms", "p99", 1),
                                 *series("e2e_std_ms", "std", 2)], "end-to-end latency (ms)", "End-to-end latency"),
        "fig_inference_latency.svg": ([*series("inference_p50_ms", "p50"), *series("inference_p99_ms", "p99", 1),
                                       *series("inference_std_ms", "std", 2)], "inference (ms)", "Inference latency"),
        "fig_realtime.svg": ([*series("lateness_p99_ms", "lateness p99 (ms)"),
                              *series("steps_over_10ms", "steps > 10 ms late", 1)], "ms / steps",
                             "Real-time health"),
    }
    for name, (ss, ylabel, title) in figs.items():
        (out / name).write_text(line_chart(series=ss, x_label="vehicles (N)", y_label=ylabel, title=title,
                                           width=760, height=260) + "\n")
    return list(figs)


def write_study(out: Path, results: list[Any], *, config: str, floor_fps: float, study_wall_s: float,
                loadavg: str) -> Path:
    """Write the study folder; returns the report's path."""
    rows = [_row(r) for r in results]
    holds = largest_holding(rows)
    floor = largest_holding(rows, key="floor_kept")
    with open(out / "results.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(_COLUMNS), extrasaction="ignore")
        w.writeheader()
        w.writerows(rows)
    doc = {"config": config, "floor_fps": floor_fps, "study_wall_s": round(study_wall_s, 1), "loadavg": loadavg,
           "largest_n_holding": holds, "largest_n_floor_only": floor, "points": rows}
    (out / "results.json").write_text(json.dumps(doc, indent=2) + "\n")
    figs = _plots(out, rows, floor_fps)
    cols = ("placement", "vehicles", "fps", "status", "total_fps", "fps_per_vehicle_min", "e2e_p50_ms",
            "e2e_p99_ms", "e2e_std_ms", "inference_p50_ms", "inference_p99_ms", "uplink_p50_ms", "late_steps",
            "lateness_p99_ms",
            "kept_realtime", "holds", "wall_s")
    lines = ["# Study: throughput and latency versus the number of vehicles", "",
             _reading(rows, holds, floor, floor_fps, study_wall_s), "",
             f"Config `{config}`; {len(rows)} points; load average at the end `{loadavg}`. Definitions: "
             f"harness/study/report.py. Per-point run folders under `points/`.", "",
             "| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    for r in rows:
        lines.append("| " + " | ".join("" if r.get(c) is None else str(r.get(c)) for c in cols) + " |")
    skipped = [r for r in rows if r["status"] != "ok"]
    if skipped:
        lines += ["", "Points not run or failed:"] + [f"- {r['placement']} N={r['vehicles']}: {r['status']}, "
                                                       f"{r['reason']}" for r in skipped]
    lines += ["", "Largest N keeping the floor with real time kept: " +
              ", ".join(f"{g}: {v if v is not None else 'none'}" for g, v in holds.items()), ""]
    lines += [f"![{f}]({f})" for f in figs]
    report = out / "report.md"
    report.write_text("\n".join(lines) + "\n")
    return report
