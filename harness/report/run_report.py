"""``hil report RUN``: one self-contained HTML page about a run.

``RUN/report.html`` holds everything inline (CSS, SVG charts, JPEG thumbnails as
``data:`` URIs): it opens offline, can be mailed or attached to a CI job, and loads
nothing from anywhere. Sections:

* the run: name, scenario, parameters, seed, versions, how it ended, real-time
  health, recorder counters, per-vehicle counters;
* latency per vehicle and stage: exact p50/p90/p99/max (ms) from the per-frame
  ``/V/pipeline`` records (frames whose estimate was applied, as ``summary.json``),
  box plots and histograms;
* end-to-end latency over time per vehicle, with every ``/events`` kind marked
  under it (coloured by ``severity`` when the event has one);
* frames sent and estimates applied per second over time;
* the target clock's offset and its uncertainty over time (``/V/clock`` when the run
  has it, else the raw ``/V/clock_sync`` samples: uncertainty = round trip / 2);
* the events, counted and listed;
* corner cases from ``RUN/corner_cases.sqlite`` (table ``cases``), each with the
  camera frame nearest to its simulated time.

A truncated ``run.mcap`` (a killed run) is reported from its complete chunks, with a
note saying so. :func:`write_report` is what ``hil.harness.run.driver`` calls after a run.

Raises: :class:`hil.common.errors.ConfigError` (one line, exit 2 from the CLI) for a
path that is not a run, a foreign ``summary.json`` or ``run.mcap``, or a report
file that cannot be written.
"""

from __future__ import annotations

import argparse
import json
import time
from html import escape
from pathlib import Path
from typing import Any

import numpy as np

from hil.common.errors import ConfigError
from hil.harness import __version__
from hil.harness.analysis.verdict import verdict_of
from hil.harness.record.run_folder import ClockPoint, RecordedEvent, RunData, read_run
from hil.harness.report import plots as rp
from hil.harness.report import fleet
from hil.harness.report.cases import case_for_event, cases_section, read_case_rows
from hil.timing.records import STAGES
from hil.timing.stats import summarize_ns

REPORT_NAME = "report.html"
_MAX_EVENTS_LISTED = 1000
_CSS = """
body{font:14px/1.45 system-ui,sans-serif;margin:24px auto;max-width:1100px;color:#222;padding:0 16px}
h1{font-size:22px;margin-bottom:2px}h2{font-size:18px;border-bottom:1px solid #ddd;padding-bottom:3px;margin-top:34px}
h3{font-size:15px;margin:18px 0 6px}table{border-collapse:collapse;margin:6px 0 12px}
th,td{border:1px solid #ddd;padding:3px 8px;text-align:left;vertical-align:top}th{background:#f4f4f4}
td.n{text-align:right;font-variant-numeric:tabular-nums}.note{padding:8px 12px;margin:8px 0;border-radius:4px}
.warn{background:#fff4e0;border:1px solid #f0b860}.bad{background:#fde8e8;border:1px solid #e88}
.ok{color:#2a7a2a;font-weight:bold}.banner{font-size:16px}.nok{color:#c62828;font-weight:bold}.muted{color:#777}
.grid{display:flex;flex-wrap:wrap;gap:6px}code{font-size:12px}details{margin:6px 0}
.case{display:flex;align-items:flex-start;gap:12px;border:1px solid #ddd;padding:8px;margin:8px 0;border-radius:4px}
.case img{flex:none;width:320px;height:auto;border:1px solid #ccc}
svg{max-width:100%;height:auto}:target{background:#fff8d0}
"""  + fleet.NAV_CSS


def _ms(v: Any, digits: int = 3) -> str:
    return "–" if not isinstance(v, (int, float)) else f"{v:.{digits}f}"


def _kv_table(rows: list[tuple[str, str]]) -> str:
    return "<table>" + "".join(f"<tr><th>{escape(k)}</th><td>{v}</td></tr>" for k, v in rows) + "</table>"


def _table(head: list[str], rows: list[list[str]], numeric_from: int = 1) -> str:
    h = "".join(f"<th>{escape(c)}</th>" for c in head)
    body = "".join("<tr>" + "".join(f'<td{" class=n" if i >= numeric_from else ""}>{c}</td>'
                                    for i, c in enumerate(r)) + "</tr>" for r in rows)
    return f"<table><tr>{h}</tr>{body}</table>"


# --- the run -------------------------------------------------------------------------


def _notes(d: RunData) -> list[str]:
    s = d.summary or {}
    notes = []
    if d.truncated:
        notes.append(("bad", (f"run.mcap is truncated (no MCAP footer: the run was killed or the disk filled). "
                              f"This report shows the {d.messages} messages of its complete chunks "
                              f"({d.mcap_bytes / 1e6:.2f} MB on disk); what came after the last complete "
                              "chunk is lost.")))
    if not d.mcap_present:
        notes.append(("bad", "run.mcap is missing: only the figures of summary.json are shown."))
    if d.summary_problem:
        notes.append(("warn", f"{d.summary_problem}: run details and counters come from run.mcap alone."))
    ended = s.get("ended_by")
    if ended is not None and ended != "duration":
        notes.append(("bad", f"The run ended early: {ended}."))
    dropped = (s.get("recorder") or {}).get("dropped")
    if dropped:
        notes.append(("warn", f"The recorder dropped {dropped} messages (queue full): run.mcap misses them."))
    return [f'<div class="note {c}">{escape(t)}</div>' for c, t in notes]


def _run_section(d: RunData) -> str:
    s = d.summary or {}
    meta = {**d.meta, **s}

    def get(key: str) -> Any:
        return meta.get(key, "unknown")

    params = get("scenario_params")
    params_text = ", ".join(f"{k}={v:g}" if isinstance(v, float) else f"{k}={v}" for k, v in params.items()) \
        if isinstance(params, dict) else str(params)
    rows = [("name", escape(str(get("name")))), ("scenario", escape(str(get("scenario")))),
            ("parameters", escape(params_text)), ("seed", escape(str(get("seed")))),
            ("config hash", f"<code>{escape(str(get('config_hash')))}</code>"),
            ("ended by", escape(str(s.get("ended_by", "unknown (no summary.json)"))))]
    if s:
        rt = s.get("realtime") or {}
        kept = rt.get("kept_realtime")
        lagging = rt.get("lagging")
        badge = ('<span class="ok">kept</span>' if kept else '<span class="nok">NOT kept</span>'
                 + (f" ({escape(', '.join(lagging))} lagged)" if lagging else ""))
        cam = rt.get("camera") or {}
        rows += [("simulated / wall time", f"{_ms(s.get('sim_time_s'), 2)} s / {_ms(s.get('wall_time_s'), 2)} s"),
                 ("mode", escape(str(rt.get("mode")))),
                 ("real-time health", (f"{badge}: physics factor {rt.get('achieved_factor')} of "
                                       f"{rt.get('requested_factor')}, late steps {rt.get('late_steps')}, "
                                       f"max lateness {rt.get('max_lateness_ms')} ms"
                                       + (f"; camera frames late {cam.get('late_frames')} of {cam.get('frames')} "
                                          f"(over {cam.get('tolerance_ms')} ms after their instant, worst "
                                          f"{cam.get('worst_lag_ms')} ms)" if cam else "")))]
        lat = rt.get("lateness_ms") or {}
        if lat:
            rows.append(("physics-step lateness", escape(
                f"p50 {_ms(lat.get('p50'))} ms, p99 {_ms(lat.get('p99'))} ms, p99.9 {_ms(lat.get('p999'))} ms, "
                f"max {_ms(rt.get('max_lateness_ms'))} ms; {rt.get('late_steps')} steps over "
                f"{rt.get('late_tolerance_ms')} ms, {rt.get('steps_over_10ms')} over 10 ms")))
            rows.append(("processes", escape(
                f"physics: {rt.get('physics_scheduling', '?')}; render workers: {rt.get('render_workers', '?')}")))
        cost = s.get("harness_cost") or {}
        if cost:
            rows.append(("harness cost per frame", escape(
                f"loop thread {cost.get('loop_thread_us_per_frame')} µs, analysis thread "
                f"{cost.get('analysis_thread_us_per_frame')} µs (CPU), analysis tasks dropped "
                f"{cost.get('analysis_tasks_dropped')}")))
        rec = s.get("recorder") or {}
        rows.append(("recorder", escape(", ".join(f"{k} {v}" for k, v in rec.items()))))
        rows.append(("collisions", str(len(s.get("collisions") or []))))
    rows.append(("run.mcap", f"{d.mcap_bytes / 1e6:.2f} MB, {d.messages} messages"
                             + (' <span class="nok">(truncated)</span>' if d.truncated else "")))
    rows.append(("GL backend", escape(str(get("gl_backend")))))
    vers = get("versions")
    if isinstance(vers, dict):
        rows.append(("versions", escape(", ".join(f"{k} {v}" for k, v in vers.items()))))
    out = ['<h2 id="run">Run</h2>', _kv_table(rows)]
    vs = s.get("vehicles") or {}
    if vs:
        head = ["vehicle", "frames sent", "applied", "dropped", "stale", "late", "drop rate (%)", "frames/s",
                "order violations", "target (clock)", "min gap (m)", "final speed (m/s)", "collisions"]
        rows2 = []
        for name, v in vs.items():
            o = v.get("outcome") or {}
            t = v.get("target") or {}
            drop = v.get("drop_rate")
            fps = v.get("frames_per_s")
            rows2.append([escape(name)] + [escape(str(v.get(k, "–"))) for k in
                                           ("frames_sent", "estimates_applied", "dropped", "stale",
                                            "late_estimates")]
                         + ["–" if not isinstance(drop, (int, float)) else f"{drop:.1%}", _ms(fps, 1),
                            escape(str(v.get("order_violations", "–")))]
                         + [escape(f"{t.get('name', '?')} ({t.get('clock', '?')})"), _ms(o.get("min_gap_m"), 2),
                            _ms(o.get("final_speed_mps"), 2), escape(str(o.get("collisions", "–")))])
        out += ["<h3>Vehicles</h3>", _table(head, rows2)]
    return "".join(out)


# --- latency ------------------------------------------------------------------------


def _stage_values(recs: list[dict[str, Any]]) -> dict[str, np.ndarray]:
    """Stage durations (ns) of the frames whose estimate was applied, in STAGES order
    then any other stage the records carry."""
    vals: dict[str, list[int]] = {}
    for r in recs:
        if r.get("status") != "ok" or not isinstance(r.get("stages_ns"), dict):
            continue
        for k, v in r["stages_ns"].items():
            if isinstance(v, int):
                vals.setdefault(k, []).append(v)
    order = [s for s in STAGES if s in vals] + sorted(k for k in vals if k not in STAGES)
    return {k: np.asarray(vals[k], np.int64) for k in order}


def _latency_section(d: RunData) -> str:
    out = ['<h2 id="latency">Latency per stage</h2>',
           ('<p class="muted">Exact percentiles over the frames whose estimate was applied, in ms. '
            "Stages: render = the world state at the camera instant to the encoded image (t_state→), "
            "capture_to_send = t_tx−t0, transport = (t0′−t_tx)−(t_reply−t_rx), target_queue, "
            "inference, target_total = t_reply−t_rx, apply_delay = t_apply−t0′, end_to_end = t0′−t0, "
            "to_apply = t_apply−t0.</p>")]
    head = ["stage", "frames", "p50 (ms)", "p90 (ms)", "p99 (ms)", "max (ms)", "min (ms)", "mean (ms)", "std (ms)"]
    keys = ("count", "p50_ms", "p90_ms", "p99_ms", "max_ms", "min_ms", "mean_ms", "std_ms")
    for vehicle in d.vehicles:
        out.append(f'<h3 id="latency-{escape(vehicle)}">{escape(vehicle)}</h3>')
        values = _stage_values(d.pipeline.get(vehicle, []))
        if values:
            stats = {k: summarize_ns(v.tolist()) for k, v in values.items()}
        else:  # no records (no run.mcap): the summary's figures
            stats = ((d.summary or {}).get("vehicles", {}).get(vehicle, {}) or {}).get("latency_ms", {})
        rows = [[escape(stage)] + [str(st.get("count", 0)) if k == "count" else _ms(st.get(k)) for k in keys]
                for stage, st in stats.items()]
        out.append(_table(head, rows) if rows else "<p>no latency samples</p>")
        if values:
            ms = {k: v / 1e6 for k, v in values.items()}
            out.append(rp.box_chart(list(ms.items()), x_label="ms", title=f"{vehicle}: latency per stage"))
            out.append('<div class="grid">' + "".join(
                rp.histogram(v, label=k, colour=rp.colour_for(k)) for k, v in ms.items()) + "</div>")
    return "".join(out)


# --- over time ------------------------------------------------------------------------


def _event_title(e: RecordedEvent, t_s: float) -> str:
    sim = e.data.get("sim_time_ns")
    parts = [f"{e.kind} at {t_s:.3f} s"]
    if isinstance(sim, int):
        parts.append(f"sim {sim / 1e9:.3f} s")
    if e.vehicles:
        parts.append(", ".join(e.vehicles))
    frames = _frames(e.data)
    if frames != "–":
        parts.append(f"frame {frames}")
    vt = _value_vs_threshold(e.data)
    if vt != "–":
        parts.append(vt)
    cause = _cause(e.data)
    if cause != "–":
        parts.append(cause)
    return ": ".join(parts[:1]) + (" — " + "; ".join(parts[1:]) if parts[1:] else "")[:300]


def _strips(d: RunData, vehicle: str | None) -> list[rp.Strip]:
    t0 = d.t_start_ns
    rows: dict[str, list[rp.Mark]] = {}
    for e in d.events:
        if vehicle is not None and e.vehicles and vehicle not in e.vehicles:
            continue
        t = (e.t_ns - t0) / 1e9
        rows.setdefault(e.kind, []).append(rp.Mark(t, rp.severity_colour(e.severity, e.kind), _event_title(e, t)))
    return [rp.Strip(k, rows[k]) for k in sorted(rows)]


def _timeline_section(d: RunData) -> str:
    out = ['<h2 id="timeline">End-to-end latency over time</h2>',
           ('<p class="muted">t0′−t0 of each frame at its capture time; dashed: the end-to-end deadline and '
            "the estimate timeout; under each chart one row per event kind (hover a tick for details; coloured "
            "by severity where the event has one). All vehicles share one time axis.</p>")]
    t0 = d.t_start_ns
    left = fleet.chart_left(d, _strips)
    span = _time_span(d)
    for vehicle in d.vehicles:
        recs = [r for r in d.pipeline.get(vehicle, []) if r.get("status") == "ok"
                and isinstance((r.get("stages_ns") or {}).get("end_to_end"), int)]
        x = np.array([(r["t0_ns"] - t0) / 1e9 for r in recs])
        y = np.array([r["stages_ns"]["end_to_end"] / 1e6 for r in recs])
        series = [rp.Series(f"{vehicle} end-to-end (ms)", x, y, fleet.vehicle_colours(d.vehicles)[vehicle], "points")]
        out.append(rp.line_chart(series=series, strips=_strips(d, vehicle), x_label="time since first frame (s)",
                                 y_label="end-to-end (ms)", title=vehicle, rules=fleet.e2e_rules(d.run_dir, vehicle),
                                 left=left, x_range=span))
    if not d.vehicles and d.events:
        out.append(rp.line_chart(series=[], strips=_strips(d, None), x_label="time (s)", y_label="", title="events"))
    return "".join(out)


def _time_span(d: RunData) -> tuple[float, float]:
    """0 to the last capture of any vehicle (s since the first frame)."""
    t0 = d.t_start_ns
    ends = [(r["t0_ns"] - t0) / 1e9 for recs in d.pipeline.values() for r in recs if isinstance(r.get("t0_ns"), int)]
    return (0.0, max(ends, default=1.0))


def _bin_s(end_s: float) -> float:
    """Rate bin width: 1 s, narrower for runs shorter than 20 s (at least 0.25 s)."""
    return 1.0 if end_s >= 20 else max(0.25, round(end_s / 20, 2))


def _rate(times_s: np.ndarray, end_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Counts per second in bins of :func:`_bin_s` from 0 to ``end_s`` (a last
    partial bin of at least half the width is scaled to a rate)."""
    width = _bin_s(end_s)
    edges = np.arange(0.0, end_s + 1e-9, width)
    if edges.size == 0 or end_s - edges[-1] >= width / 2:
        edges = np.r_[edges, end_s]
    if edges.size < 2:
        return np.zeros(0), np.zeros(0)
    counts, _ = np.histogram(times_s, bins=edges)
    return (edges[:-1] + edges[1:]) / 2, counts / np.diff(edges)


def _fps_section(d: RunData) -> str:
    out = ['<h2 id="fps">Frames per second over time</h2>',
           ('<p class="muted">Frames sent (by capture time t0) and estimates applied (by t_apply) per '
            "second, counted in bins of harness time (width in each chart's title).</p>")]
    t0 = d.t_start_ns
    for vehicle in d.vehicles:
        recs = d.pipeline.get(vehicle, [])
        sent = np.array([(r["t0_ns"] - t0) / 1e9 for r in recs if isinstance(r.get("t0_ns"), int)])
        applied = np.array([(r["t_apply_ns"] - t0) / 1e9 for r in recs
                            if r.get("status") == "ok" and isinstance(r.get("t_apply_ns"), int)])
        if sent.size == 0:
            out.append(f"<p>{escape(vehicle)}: no frames recorded</p>")
            continue
        end = float(max(sent.max(), applied.max() if applied.size else 0.0))
        xs, ys = _rate(sent, end)
        xa, ya = _rate(applied, end)
        floor = fleet.limits(d.run_dir, vehicle).get("fps_floor")
        rules = [] if floor is None else [rp.Rule(f"frame-rate floor {floor:g}/s", floor, "#d62728")]
        out.append(rp.line_chart(series=[rp.Series("frames sent/s", xs, ys, "#4c78a8"),
                                         rp.Series("estimates applied/s", xa, ya, "#f58518")], rules=rules,
                                 x_label="time since first frame (s)", y_label="per second",
                                 title=f"{vehicle} ({_bin_s(end):g} s bins)", height=200,
                                 left=fleet.chart_left(d, _strips), x_range=_time_span(d)))
    return "".join(out)


def _skew_ppm(points: list[ClockPoint]) -> float | None:
    """Skew fitted over the samples whose uncertainty is within twice the smallest
    (a minimum-delay filter), in ppm; or the source's own when it gives one."""
    given = [p.skew_ppm for p in points if p.skew_ppm is not None]
    if given:
        return given[-1]
    if len(points) < 3:
        return None
    u = np.array([p.uncertainty_ns for p in points])
    good = [p for p, ui in zip(points, u) if ui <= 2 * max(u.min(), 1.0)]
    t = np.array([p.t_ns for p in good], float)
    if len(good) < 3 or t.max() - t.min() < 1e9:
        return None
    off = np.array([p.offset_ns for p in good])
    slope = np.polyfit(t - t.mean(), off - off.mean(), 1)[0]
    return float(slope * 1e6)


def _clock_section(d: RunData) -> str:
    out = ['<h2 id="clock">Target clock: offset and uncertainty</h2>',
           ('<p class="muted">Offset of each target clock from the harness clock (target − harness), '
            "plotted relative to its median; the band is ± the uncertainty (half the round trip of "
            "each sample, or the estimator's own).</p>")]
    if not d.clock:
        return "".join(out) + "<p>no clock samples recorded</p>"
    t0 = d.t_start_ns
    rows = []
    for vehicle in d.vehicles + sorted(v for v in d.clock if v not in d.vehicles):
        pts = d.clock.get(vehicle)
        if not pts:
            continue
        med = float(np.median([p.offset_ns for p in pts]))
        x = np.array([(p.t_ns - t0) / 1e9 for p in pts])
        y = np.array([(p.offset_ns - med) / 1e3 for p in pts])
        u = np.array([p.uncertainty_ns / 1e3 for p in pts])
        c = rp.colour_for(vehicle)
        out.append(rp.line_chart(series=[rp.Series("offset − median (µs)", x, y, c, "line"),
                                         rp.Series("samples", x, y, c, "points")],
                                 bands=[rp.Band("± uncertainty", x, y - u, y + u, c)],
                                 x_label="time since first frame (s)", y_label="µs", y_zero=False,
                                 title=f"{vehicle} ({d.clock_source.get(vehicle, '?')})", height=200,
                                 left=fleet.chart_left(d, _strips), x_range=_time_span(d)))
        skew = _skew_ppm(pts)
        rows.append([escape(vehicle), escape(d.clock_source.get(vehicle, "?")), str(len(pts)),
                     f"{med / 1e6:.3f}", _ms(float(u.min()), 1), _ms(float(np.median(u)), 1),
                     _ms(float(np.ptp(y)), 1), "–" if skew is None else f"{skew:+.2f}"])
    out.append(_table(["vehicle", "source", "samples", "median offset (ms)", "min uncertainty (µs)",
                       "median uncertainty (µs)", "offset spread (µs)", "skew (ppm)"], rows, numeric_from=2))
    return "".join(out)


def _value_vs_threshold(data: dict[str, Any]) -> str:
    """``measured`` against ``threshold`` with their unit, e.g. ``61.2 ms > 50 ms``."""
    m, th, unit = data.get("measured"), data.get("threshold"), data.get("unit")
    if not isinstance(m, (int, float)) or isinstance(m, bool):
        return "–"
    u = f" {unit}" if isinstance(unit, str) and unit else ""
    if not isinstance(th, (int, float)) or isinstance(th, bool):
        return f"{m:.4g}{u}"
    return f"{m:.4g}{u} {'>' if m > th else '≤'} {th:.4g}{u}"


def _cause(data: dict[str, Any]) -> str:
    parts = [str(data[k]) for k in ("cause", "stage", "entity") if isinstance(data.get(k), str) and data[k]]
    detail = data.get("detail")
    if isinstance(detail, str) and detail:
        parts.append(detail)
    return "; ".join(parts) or "–"


def _frames(data: dict[str, Any]) -> str:
    ids = data.get("frame_ids")
    if isinstance(ids, list) and ids:
        return ", ".join(str(i) for i in ids[:3]) + (f" (+{len(ids) - 3})" if len(ids) > 3 else "")
    fid = data.get("frame_id")
    return str(fid) if isinstance(fid, int) else "–"


def _events_section(d: RunData) -> str:
    out = ['<h2 id="events">Events</h2>']
    if not d.events:
        return "".join(out) + "<p>no events recorded</p>"
    t0 = d.t_start_ns
    groups: dict[tuple[str, str, str], list[RecordedEvent]] = {}
    for e in d.events:
        key = (e.kind, "" if e.severity is None else str(e.severity), ", ".join(e.vehicles) or "(run)")
        groups.setdefault(key, []).append(e)
    rows = [[f'<span style="color:{rp.severity_colour(g[0].severity, k)}">■</span> {escape(k)}', escape(sev or "–"),
             escape(who), str(len(g)), f"{(g[0].t_ns - t0) / 1e9:.3f}", f"{(g[-1].t_ns - t0) / 1e9:.3f}"]
            for (k, sev, who), g in sorted(groups.items())]
    out.append(_table(["kind", "severity", "vehicle", "events", "first (s)", "last (s)"], rows, numeric_from=3))
    cases = read_case_rows(d.run_dir)
    listed = sorted(d.events, key=lambda e: e.t_ns)[:_MAX_EVENTS_LISTED]
    more = len(d.events) - len(listed)
    items = []
    for e in listed:
        sim = e.data.get("sim_time_ns")
        case = case_for_event(cases, e)
        link = "–" if case is None else f'<a href="#case-{escape(str(case))}">case {escape(str(case))}</a>'
        items.append([f"{(e.t_ns - t0) / 1e9:.3f}",
                      "–" if not isinstance(sim, int) else f"{sim / 1e9:.3f}",
                      f'<span style="color:{rp.severity_colour(e.severity, e.kind)}">■</span> {escape(e.kind)}',
                      escape(", ".join(e.vehicles) or "–"), escape(_frames(e.data)),
                      escape("–" if e.severity is None else str(e.severity)),
                      escape(_value_vs_threshold(e.data)), escape(_cause(e.data)[:300]), link])
    out.append(f"<details open><summary>{len(listed)} event{'s' if len(listed) != 1 else ''}"
               + (f" (the first {len(listed)}; {more} more in run.mcap)" if more else "") + "</summary>"
               + _table(["time (s)", "sim time (s)", "kind", "vehicle", "frame", "severity", "value vs threshold",
                         "cause / detail", "case"], items, numeric_from=99)
               + "</details>")
    return "".join(out)


def _verdict_section(d: RunData) -> str:
    """The first screen: a collision banner, then every check, met or missed, with its
    figures (``summary.json``'s ``verdict``, or one rebuilt from its figures)."""
    if not d.summary:
        return ""
    v = verdict_of(d.summary)
    out = ['<h2 id="verdict">Verdict</h2>']
    by = {c["name"]: c for c in v["checks"]}
    col = by.get("collision")
    if col is not None and not col["ok"]:
        out.append(f'<div class="note bad banner"><b>COLLISION</b> — {escape(col["headline"])}</div>')
    fails = set(v.get("fails_run") or [])
    head = ("all checks passed" if v["passed"]
            else f"{len(v['failed'])} check{'s' if len(v['failed']) != 1 else ''} failed: {', '.join(v['failed'])}")
    out.append(f'<p class="{"ok" if v["passed"] else "nok"}">{escape(head)}</p>')
    rows = []
    for c in v["checks"]:
        mark = ('<span class="ok">met</span>' if c["ok"] else
                '<span class="nok">FAILED (fails the run)</span>' if c["name"] in fails else
                '<span class="nok">missed</span>')
        rows.append([escape(c["name"]), mark, escape(c["headline"])])
    out.append(_table(["check", "verdict", "what the figures say"], rows, numeric_from=99))
    return "".join(out)


# --- the page ---------------------------------------------------------------------------


def build_report(d: RunData) -> str:
    """The whole HTML page for ``d``."""
    name = (d.summary or {}).get("name") or d.meta.get("name") or d.run_dir.name
    parts = [_run_section(d), fleet.fleet_section(d, left=fleet.chart_left(d, _strips)), _latency_section(d)]
    if d.mcap_present:
        parts += [_timeline_section(d), _fps_section(d), _clock_section(d), _events_section(d)]
    parts.append(cases_section(d))
    return ("<!DOCTYPE html><html lang=en><head><meta charset=utf-8>"
            f"<title>hil report: {escape(str(name))}</title><style>{_CSS}</style></head><body>"
            f"{fleet.nav(d.vehicles)}<h1>hil report: {escape(str(name))}</h1>"
            f'<p class="muted">{escape(str(d.run_dir))} · generated {time.strftime("%Y-%m-%d %H:%M:%S")} '
            f"by hil {__version__}</p>" + _verdict_section(d) + "".join(_notes(d)) + "".join(parts)
            + "</body></html>\n")


def write_report(run_dir: Path, *, out: Path | None = None) -> Path:
    """Write ``run_dir/report.html`` (or ``out``) and return its path.

    Raises:
        ConfigError: ``run_dir`` is not a run folder, holds a foreign summary.json
            or run.mcap, or the report cannot be written.
    """
    return _write(read_run(run_dir), out)


def _write(d: RunData, out: Path | None) -> Path:
    path = out if out is not None else d.run_dir / REPORT_NAME
    html = build_report(d)
    try:
        path.write_text(html, encoding="utf-8")
    except OSError as err:
        raise ConfigError(f"cannot write report {path}: {err.strerror or err}") from err
    return path


def add_parser(sub: Any) -> None:
    """Register ``hil report`` on the CLI's subparsers."""
    p = sub.add_parser("report", help="write RUN/report.html: one self-contained HTML page about a run")
    p.add_argument("run", help="a run folder (or its run.mcap / summary.json)")
    p.add_argument("--out", type=Path, default=None, help="where to write the page (default RUN/report.html)")


def cmd(args: argparse.Namespace) -> int:
    """``hil report``: 0 when written; ConfigError (exit 2) for a bad input."""
    d = read_run(Path(args.run))
    path = _write(d, args.out)
    print(f"report: {path} ({path.stat().st_size / 1e3:.0f} KB)")
    if d.truncated:
        print(f"note: {d.run_dir / 'run.mcap'} is truncated; reported from its {d.messages} complete messages")
    if d.summary_problem:
        print(f"note: {d.summary_problem}")
    return 0


__all__ = ["REPORT_NAME", "add_parser", "build_report", "cmd", "write_report"]
