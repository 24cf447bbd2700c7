"""The study folder of ``hil study`` (harness/study/study.py): metrics per point, the table
(``results.csv``, ``results.json``), six SVG charts against the number of vehicles
(total frames/s; per-vehicle frames/s, mean and minimum, with the floor; end-to-end
and inference latency p50/p99/std; physics-step lateness p99; physics steps over
10 ms late), ``report.md`` opening with a one-paragraph reading of the results, and
``report.html``, the same as one self-contained page with each point's run report
linked.

Definitions (per point, one run):

* **total frames/s**: the vehicles' frames per second summed (``summary.json``
  ``frames_per_s``: frames sent over the loop's start to its last step).
* **per-vehicle frames/s**: estimates applied per second, per vehicle
  (``estimates_per_s``, over the same seconds; a frame counts once its answer came
  back in time); ``min`` over the vehicles is held against the floor (10 fps, the
  paper's).
* **end-to-end** (``t0' − t0``, capture to the answer's receipt) and **inference**
  (the target's own inference time) latency: pooled over every vehicle's answered
  frames from the run's ``/<vehicle>/pipeline`` records; p50, p99 and std (jitter).
* **uplink p50**: the median over the vehicles of each one's clock-mapped uplink p50
  (``summary.json`` ``splits_ms.uplink.p50_ms``: a target on another host has a clock
  of its own).
* **real-time health**: the summary's ``realtime`` block: physics steps later than
  the tolerance, lateness p99, whether real time was kept.

A point *holds* when its minimum per-vehicle frames/s ≥ the floor and it kept real
time; the study states the largest N that holds (and the largest N that keeps the
floor alone, since on a loaded machine a few late physics steps are common), or
that every N tried held: a larger one was not tried.
"""

from __future__ import annotations

import csv
import json
import os
from html import escape
from pathlib import Path
from typing import Any
from urllib.parse import quote

import numpy as np

from hil.harness.report.plots import PALETTE, Rule, Series, line_chart, standalone

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
    vs = s["vehicles"]
    per = [float(v["estimates_per_s"]) for v in vs.values()]
    e2e, inf = _pooled(run_dir / "run.mcap", list(vs))
    up = [float(u["p50_ms"]) for v in vs.values()
          if (u := (v.get("splits_ms") or {}).get("uplink") or {}).get("p50_ms") is not None]
    rt = s["realtime"]
    e = _stats(e2e)
    i = _stats(inf)
    m = {
        "total_fps": round(sum(float(v["frames_per_s"]) for v in vs.values()), 2),
        "fps_per_vehicle_mean": round(float(np.mean(per)), 2) if per else 0.0,
        "fps_per_vehicle_min": round(min(per), 2) if per else 0.0,
        "e2e_p50_ms": e[0], "e2e_p99_ms": e[1], "e2e_std_ms": e[2],
        "inference_p50_ms": i[0], "inference_p99_ms": i[1], "inference_std_ms": i[2],
        "uplink_p50_ms": round(float(np.median(up)), 3) if up else None,
        "late_steps": rt["late_steps"], "steps_over_10ms": rt.get("steps_over_10ms"),
        "lateness_p99_ms": rt["lateness_ms"]["p99"], "achieved_factor": rt["achieved_factor"],
        "kept_realtime": bool(rt["kept_realtime"]),
    }
    m["floor_kept"] = m["fps_per_vehicle_min"] >= floor_fps
    m["holds"] = m["floor_kept"] and m["kept_realtime"]
    return m


def _pooled(mcap: Path, vehicles: list[str]) -> tuple[list[float], list[float]]:
    """End-to-end and inference values (ms) of every answered frame."""
    from mcap.reader import make_reader

    e2e: list[float] = []
    inf: list[float] = []
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
    return e2e, inf


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
        tried = max(r["vehicles"] for r in rows if f"{r['placement']} @ {r['fps']:g} fps" == g)
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
            f"vehicle with real time kept: {_n(holds[g], tried)}; keeping the fps floor alone (ignoring late "
            f"physics steps): {_n(floor[g], tried)}.")
    late = [r for r in ok if not r["kept_realtime"]]
    if late:
        parts.append(f"{len(late)} of {len(ok)} points did not keep real time (achieved real-time factor down to "
                     f"{min(r['achieved_factor'] for r in late):.2f}, up to {max(r['late_steps'] for r in late)} "
                     f"physics steps late, worst lateness p99 {max(r['lateness_p99_ms'] or 0 for r in late):.2f} "
                     f"ms): their latencies were measured on a slowed simulation.")
    parts.append(f"The whole study took {study_wall_s / 60:.1f} minutes.")
    return " ".join(parts)


def _n(v: int | None, tried: int) -> str:
    if v is None:
        return "none (the smallest N already misses it)"
    if v == tried:
        return f"held at every N tried (up to N = {v}; no larger N was tried)"
    return f"N = {v}"


def _charts(rows: list[dict[str, Any]], floor_fps: float) -> dict[str, str]:
    """The study's charts (SVG elements, no namespace) by file name: one quantity and
    one unit per chart, the numbers of vehicles tried as the x ticks."""
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

    floor = [Rule(f"{floor_fps:g} fps floor", floor_fps, "#d62728")]
    counts = {"fig_late_steps.svg"}
    figs: dict[str, tuple[list[Series], list[Rule], str, str]] = {
        "fig_total_fps.svg": (series("total_fps", ""), [], "total frames/s", "Total rendering throughput"),
        "fig_fps_per_vehicle.svg": ([*series("fps_per_vehicle_mean", "mean"), *series("fps_per_vehicle_min", "min", 1)],
                                    floor, "frames/s per vehicle", "Per-vehicle frames/s"),
        "fig_e2e_latency.svg": ([*series("e2e_p50_ms", "p50"), *series("e2e_p99_ms", "p99", 1),
                                 *series("e2e_std_ms", "std", 2)], [], "end-to-end latency (ms)", "End-to-end latency"),
        "fig_inference_latency.svg": ([*series("inference_p50_ms", "p50"), *series("inference_p99_ms", "p99", 1),
                                       *series("inference_std_ms", "std", 2)], [], "inference (ms)",
                                      "Inference latency"),
        "fig_lateness.svg": (series("lateness_p99_ms", "p99"), [], "physics-step lateness (ms)",
                             "Real-time health: physics-step lateness"),
        "fig_late_steps.svg": (series("steps_over_10ms", "steps > 10 ms late"), [], "physics steps",
                               "Real-time health: physics steps over 10 ms late"),
    }
    return {name: line_chart(series=ss, rules=rules, x_label="vehicles (N)", y_label=ylabel, title=title,
                             width=760, height=260, x_ticks=ns, y_integer=name in counts)
            for name, (ss, rules, ylabel, title) in figs.items()}


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
    charts = _charts(rows, floor_fps)
    for name, svg in charts.items():
        (out / name).write_text(standalone(svg) + "\n")
    reading = _reading(rows, holds, floor, floor_fps, study_wall_s)
    load = " / ".join(loadavg.split()[:3])  # /proc/loadavg's 1, 5 and 15-minute figures (not its run queue, last PID)
    about = (f"Config `{config}`; {len(rows)} points; load average at the end (1 / 5 / 15 min) {load}. Definitions: "
             f"harness/study/study_page.py. Per-point run folders under `points/`.")
    lines = ["# Study: throughput and latency versus the number of vehicles", "", reading, "", about, "",
             "| " + " | ".join(_TABLE) + " |", "|" + "---|" * len(_TABLE)]
    for r in rows:
        lines.append("| " + " | ".join("" if r.get(c) is None else str(r.get(c)) for c in _TABLE) + " |")
    skipped = [r for r in rows if r["status"] != "ok"]
    if skipped:
        lines += ["", "Points not run or failed:"] + [f"- {r['placement']} N={r['vehicles']}: {r['status']}, "
                                                       f"{r['reason']}" for r in skipped]
    lines += ["", "Largest N keeping the floor with real time kept: " + _largest_text(rows, holds), ""]
    lines += [f"![{f}]({f})" for f in charts]
    report = out / "report.md"
    report.write_text("\n".join(lines) + "\n")
    (out / "report.html").write_text(_html(out, rows, charts, reading=reading, about=about,
                                           largest=_largest_text(rows, holds)), encoding="utf-8")
    return report


_TABLE = ("placement", "vehicles", "fps", "status", "total_fps", "fps_per_vehicle_min", "e2e_p50_ms", "e2e_p99_ms",
          "e2e_std_ms", "inference_p50_ms", "inference_p99_ms", "uplink_p50_ms", "late_steps", "lateness_p99_ms",
          "kept_realtime", "holds", "wall_s")


def _largest_text(rows: list[dict[str, Any]], holds: dict[str, int | None]) -> str:
    out = []
    for g, v in holds.items():
        tried = max(r["vehicles"] for r in rows if f"{r['placement']} @ {r['fps']:g} fps" == g)
        out.append(f"{g}: " + ("none" if v is None else f"{v} (every N tried)" if v == tried else str(v)))
    return ", ".join(out)


_CSS = """
body{font:14px/1.45 system-ui,sans-serif;margin:24px auto;max-width:1100px;color:#222;padding:0 16px}
h1{font-size:22px}h2{font-size:18px;border-bottom:1px solid #ddd;padding-bottom:3px;margin-top:30px}
table{border-collapse:collapse;margin:6px 0 12px;font-size:12px}
th,td{border:1px solid #ddd;padding:3px 6px;text-align:left}th{background:#f4f4f4}
td.n{text-align:right;font-variant-numeric:tabular-nums}.muted{color:#777}code{font-size:12px}
.grid{display:flex;flex-wrap:wrap;gap:10px}svg{max-width:100%;height:auto}.wide{overflow-x:auto}
"""


def _html(out: Path, rows: list[dict[str, Any]], charts: dict[str, str], *, reading: str, about: str,
          largest: str) -> str:
    """``report.html``: one self-contained page (inline SVG, no script, nothing loaded):
    the reading, the charts, the table with each point's run report linked."""
    # Column names may break at their underscores: the whole table fits the page (its
    # right third, real time and "holds" among it, was off-screen at 1280 px).
    head = "".join(f"<th>{escape(c).replace('_', '_<wbr>')}</th>" for c in _TABLE)
    body = []
    for r in rows:
        cells = []
        for c in _TABLE:
            v = r.get(c)
            text = "" if v is None else escape(str(v))
            if c == "vehicles" and r.get("run_dir") and (Path(r["run_dir"]) / "report.html").is_file():
                href = quote(Path(os.path.relpath(Path(r["run_dir"]).resolve() / "report.html",
                                                  out.resolve())).as_posix())
                text = f'<a href="{escape(href)}">{text}</a>'
            num = isinstance(v, (int, float)) and not isinstance(v, bool)
            cells.append(f'<td{" class=n" if num else ""}>{text}</td>')
        body.append("<tr>" + "".join(cells) + "</tr>")
    skipped = [r for r in rows if r["status"] != "ok"]
    notes = ("<h2>Points not run or failed</h2><ul>" + "".join(
        f"<li>{escape(r['placement'])} N={r['vehicles']}: {escape(str(r['status']))}, {escape(str(r['reason']))}</li>"
        for r in skipped) + "</ul>") if skipped else ""
    return ("<!DOCTYPE html><html lang=en><head><meta charset=utf-8><title>hil study</title>"
            f"<style>{_CSS}</style></head><body><h1>Study: throughput and latency versus the number of vehicles</h1>"
            f"<p>{escape(reading)}</p><p class=muted>{escape(about.replace('`', ''))}</p>"
            f"<p>Largest N keeping the floor with real time kept: {escape(largest)}</p>"
            f'<h2>Charts</h2><div class="grid">{"".join(charts.values())}</div>'
            f"<h2>Points</h2><p class=muted>A point's number of vehicles links to its run report.</p>"
            f'<div class="wide"><table><tr>{head}</tr>{"".join(body)}</table></div>{notes}</body></html>\n')
