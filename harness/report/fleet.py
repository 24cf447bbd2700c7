"""The report's navigation and fleet overview: every vehicle on one chart, p50/p99
end-to-end latency and frames per second per vehicle, before the per-vehicle
sections; and the run's limits (deadlines, estimate timeout) read from
``RUN/config.json`` for the charts' reference lines.
"""

from __future__ import annotations

import json
from html import escape
from pathlib import Path
from typing import Any

import numpy as np

from hil.harness.record.run_folder import RunData
from hil.harness.report import plots as rp
from hil.harness.report.distributions import box_chart
from hil.harness.report.tables import ms, table

SECTIONS = (("run", "Run"), ("fleet", "Fleet"), ("latency", "Latency per stage"), ("timeline", "Latency over time"),
            ("fps", "Frames per second"), ("clock", "Target clock"), ("events", "Events"), ("cases", "Corner cases"))
NAV_CSS = ("nav.top{position:sticky;top:0;background:#fff;border-bottom:1px solid #ddd;padding:6px 0;z-index:2;"
           "font-size:13px}nav.top a{margin-right:12px;color:#245;text-decoration:none}"
           "nav.top a:hover{text-decoration:underline}")


def vehicle_colours(vehicles: list[str]) -> dict[str, str]:
    """One distinct palette colour per vehicle, in order (no hash collisions)."""
    return {v: rp.PALETTE[i % len(rp.PALETTE)] for i, v in enumerate(vehicles)}


def nav(vehicles: list[str]) -> str:
    """A sticky bar of links to every section and to each vehicle's latency."""
    links = "".join(f'<a href="#{k}">{escape(t)}</a>' for k, t in SECTIONS)
    per = "".join(f'<a href="#latency-{escape(v)}">{escape(v)}</a>' for v in vehicles) if len(vehicles) > 1 else ""
    return f'<nav class="top">{links}{" · vehicles: " + per if per else ""}</nav>'


def limits(run_dir: Path, vehicle: str) -> dict[str, float]:
    """The run's limits for ``vehicle`` in ms: ``deadline.<stage>`` per stage
    deadline and ``timeout`` (the estimate timeout: older estimates are dropped); and
    ``fps_floor``, the frame-rate floor (per second), in a real-time run only.
    Empty when ``config.json`` is missing or unreadable (an old or foreign run)."""
    try:
        cfg = json.loads((run_dir / "config.json").read_text())
    except (OSError, ValueError):
        return {}
    out: dict[str, float] = {}
    try:
        from hil.harness.config.model import Mode
        from hil.harness.config.timing import TimingConfig

        th = TimingConfig.model_validate(cfg.get("timing") or {}).thresholds_for(vehicle)
        out.update({f"deadline.{k}": float(v) for k, v in th.deadline_ms.items()})
        if Mode(cfg.get("mode", Mode.REALTIME)).judges_rate_floor:
            out["fps_floor"] = float(th.frame_rate_floor_hz)
    except Exception:  # a config of another version: no deadline lines, the rest stands
        pass
    timeout = (cfg.get("target") or {}).get("estimate_timeout_s")
    if isinstance(timeout, (int, float)):
        out["timeout"] = float(timeout) * 1e3
    return out


def e2e_rules(d: RunData, vehicles: list[str]) -> list[rp.Rule]:
    """Reference lines for an end-to-end chart of ``vehicles``: each end-to-end budget
    (``summary.json``'s ``budgets``, with how many frames went over it; else the
    config's deadline) and the estimate timeout (frames are dropped beyond it)."""
    budgets: dict[float, list[int]] = {}
    timeouts: set[float] = set()
    for v in vehicles:
        vf = None if d.summary is None else d.summary.vehicles.get(v)
        b = None if vf is None or vf.budgets is None else vf.budgets.get("end_to_end")
        lim = limits(d.run_dir, v)
        if b is not None:
            counts = budgets.setdefault(float(b.budget_ms), [0, 0])
            counts[0] += b.over
            counts[1] += b.frames
        elif "deadline.end_to_end" in lim:
            budgets.setdefault(lim["deadline.end_to_end"], [])
        if "timeout" in lim:
            timeouts.add(lim["timeout"])
    rules = [rp.Rule(f"deadline {b:g} ms" + (f" ({c[0]} of {c[1]} frames over)" if c else ""), b, "#d62728")
             for b, c in sorted(budgets.items())]
    rules += [rp.Rule(f"estimate timeout {t:g} ms (dropped beyond)", t, "#7f0000", stretch=False)
              for t in sorted(timeouts)]
    return rules


def e2e(d: RunData, vehicle: str) -> tuple[np.ndarray, np.ndarray]:
    """A vehicle's applied frames: capture time (s since the first frame) and
    end-to-end latency (ms)."""
    t0 = d.t_start_ns
    recs = [r for r in d.pipeline.get(vehicle, []) if r.get("status") == "ok"
            and isinstance((r.get("stages_ns") or {}).get("end_to_end"), int) and isinstance(r.get("t0_ns"), int)]
    return (np.array([(r["t0_ns"] - t0) / 1e9 for r in recs]),
            np.array([r["stages_ns"]["end_to_end"] / 1e6 for r in recs]))


def fleet_section(d: RunData, *, left: int = 0) -> str:
    """Every vehicle's end-to-end latency on one chart, a box per vehicle, and a
    table of p50/p99 (ms), frames per second and drop rate (%) per vehicle."""
    out = ['<h2 id="fleet">Fleet overview</h2>']
    if not d.vehicles:
        return "".join(out) + "<p>no vehicles recorded</p>"
    colours = vehicle_colours(d.vehicles)
    series, boxes, rows = [], [], []
    vs = {} if d.summary is None else d.summary.vehicles
    for v in d.vehicles:
        x, y = e2e(d, v)
        series.append(rp.Series(f"{v} end-to-end (ms)", x, y, colours[v], "points"))
        if y.size:
            boxes.append((v, y))
        s = vs.get(v)
        p50 = float(np.percentile(y, 50)) if y.size else None
        p99 = float(np.percentile(y, 99)) if y.size else None
        drop = None if s is None else s.drop_rate
        rows.append([f'<span style="color:{colours[v]}">■</span> <a href="#latency-{escape(v)}">{escape(v)}</a>',
                     str(y.size), ms(p50, 1), ms(p99, 1), ms(None if s is None else s.frames_per_s, 1),
                     ms(None if s is None else s.estimates_per_s, 1), "–" if drop is None else f"{drop:.1%}"])
    rules = e2e_rules(d, d.vehicles)
    out.append('<p class="muted">End-to-end latency (t0′−t0, ms) of every applied frame of every vehicle, '
               "on an axis scaled to the data; dashed lines: the end-to-end deadline (with the frames over it) and "
               "the estimate timeout of the run's config, named above the chart when they lie beyond the data.</p>")
    end = max((float(np.max(s.xs)) for s in series if len(s.xs)), default=1.0)
    out.append(rp.line_chart(series=series, rules=rules, x_label="time since first frame (s)",
                             y_label="end-to-end (ms)", title="all vehicles", left=left, x_range=(0.0, end)))
    if boxes:
        out.append(box_chart(boxes, x_label="end-to-end ms", title="end-to-end latency per vehicle",
                                colours=colours))
    head = ["vehicle", "applied frames", "p50 (ms)", "p99 (ms)", "frames sent/s", "estimates applied/s",
            "drop rate (%)"]
    out.append(table(head, rows))
    return "".join(out)


_LEFT = 130  # left margin of every time chart, so charts of all vehicles line up


def chart_left(d: RunData, strips_of: Any) -> int:
    """The left margin for every time chart of the report: wide enough for every
    vehicle's event-strip labels."""
    return max([_LEFT] + [rp.strip_margin(strips_of(d, v)) for v in d.vehicles])

