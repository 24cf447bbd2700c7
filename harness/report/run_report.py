"""``hil report RUN``: one self-contained HTML page about a run.

``RUN/report.html`` holds everything inline (CSS, SVG charts, JPEG thumbnails as
``data:`` URIs): it opens offline, can be mailed or attached to a CI job, and loads
nothing from anywhere. Sections:

* the run: name, scenario, parameters, seed, versions, how it ended, real-time
  health, recorder counters, per-vehicle counters;
* latency per vehicle and stage: exact p50/p90/p99/max (ms) from the per-frame
  ``/V/pipeline`` records (frames whose estimate was applied, as ``summary.json``),
  box plots and histograms; a vehicle with a camera rig, its cameras and frame sets
  (:mod:`hil.harness.report.rig_section`);
* end-to-end latency over time per vehicle, with every ``/events`` kind marked
  under it (coloured by ``severity`` when the event has one);
* frames sent and estimates applied per second over time, in bins of whole camera
  periods (these three: :mod:`hil.harness.report.timeseries`);
* the target clock's offset and its uncertainty over time (``/V/clock`` when the run
  has it, else the raw ``/V/clock_sync`` samples: uncertainty = round trip / 2), and
  its skew ± bound;
* the events, counted and listed in words (:mod:`hil.harness.record.event_text`);
* corner cases from ``RUN/corner_cases.sqlite`` (table ``cases``), each with the
  camera frame nearest to its simulated time.

A truncated ``run.mcap`` (a killed run) is reported from its complete chunks, with a
note saying so, and what ran from ``RUN/config.json``. A page written elsewhere
(``--out``) links the run's files relative to its own folder. :func:`write_report` is what ``hil.harness.run.driver`` calls after a run.

Raises: :class:`hil.common.errors.ConfigError` (one line, exit 2 from the CLI) for a
path that is not a run, a foreign ``summary.json`` or ``run.mcap``, or a report
file that cannot be written.
"""

from __future__ import annotations

import argparse
import time
from html import escape
from pathlib import Path
from typing import Any

import numpy as np

from hil.common.errors import ConfigError
from hil.harness import __version__
from hil.harness.vocab.figures import RealtimeFigures, RecorderFigures, StageFigures
from hil.harness.record import event_text as et
from hil.harness.record.run_folder import RecordedEvent, RunData, read_run
from hil.harness.report import fleet, timeseries
from hil.harness.report import plots as rp
from hil.harness.report.case_section import case_for_event, cases_section, read_case_rows
from hil.harness.report.distributions import box_chart, histogram
from hil.harness.report.rig_section import rig_html
from hil.harness.report.tables import kv_table, ms, table
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
.soft{color:#a35f00;font-weight:bold}.grid{display:flex;flex-wrap:wrap;gap:6px}code{font-size:12px}details{margin:6px 0}
.case{display:flex;align-items:flex-start;gap:12px;border:1px solid #ddd;padding:8px;margin:8px 0;border-radius:4px}
.case img{flex:none;width:320px;height:auto;border:1px solid #ccc}
svg{max-width:100%;height:auto}:target{background:#fff8d0}
"""  + fleet.NAV_CSS


# --- the run -------------------------------------------------------------------------


def _notes(d: RunData) -> list[str]:
    s = d.summary
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
    ended = None if s is None else s.ended_by
    if ended is not None and ended != "duration":
        notes.append(("bad", f"The run ended early: {ended}."))
    dropped = None if s is None or s.recorder is None else s.recorder.dropped
    if dropped:
        notes.append(("warn", f"The recorder dropped {dropped} messages (queue full): run.mcap misses them."))
    return [f'<div class="note {c}">{escape(t)}</div>' for c, t in notes]


def _recorder_text(rec: RecorderFigures | None, in_file: int | None) -> str:
    """The recorder's counters in words: every message written (the Foxglove views among
    them), drops, bytes; ``in_file``: the messages of the complete ``run.mcap``, when
    they differ (a harness before the count included the views)."""
    if rec is None or rec.written is None:
        known = {} if rec is None else {k: v for k, v in (("derived", rec.derived), ("enqueued", rec.enqueued),
                                                          ("dropped", rec.dropped),
                                                          ("bytes_written", rec.bytes_written)) if v is not None}
        return ", ".join(f"{k} {v}" for k, v in {**known, **(rec.extra if rec else {})}.items()) or "–"
    if rec.derived is None and in_file is not None and in_file != rec.written:
        return (f"{rec.written} messages counted, {'?' if rec.dropped is None else rec.dropped} dropped; run.mcap "
                f"holds {in_file}: the harness that wrote it did not count the Foxglove views derived from the hil "
                "channels")
    parts = [f"{rec.written} messages written"
             + (f" ({rec.derived} of them Foxglove views derived from the hil channels)" if rec.derived else "")]
    if rec.dropped is not None:
        parts.append(f"{rec.dropped} dropped (queue full)")
    if rec.bytes_written is not None:
        parts.append(f"{rec.bytes_written / 1e6:.2f} MB")
    return ", ".join(parts)


def _run_section(d: RunData) -> str:
    s = d.summary

    def get(key: str) -> Any:  # what ran: the summary's, else the recording's metadata
        v = None if s is None else getattr(s, key)
        return d.meta.get(key, "unknown") if v is None else v

    params = get("scenario_params")
    params_text = ", ".join(f"{k}={v:g}" if isinstance(v, float) else f"{k}={v}" for k, v in params.items()) \
        if isinstance(params, dict) else str(params)
    rows = [("name", escape(str(get("name")))), ("scenario", escape(str(get("scenario")))),
            ("parameters", escape(params_text)), ("seed", escape(str(get("seed")))),
            ("config hash", f"<code>{escape(str(get('config_hash')))}</code>"),
            ("ended by", escape(str("unknown (no summary.json)" if s is None or s.ended_by is None
                                    else s.ended_by)))]
    if d.meta.get("meta_source") and s is None:
        rows.insert(0, ("read from", escape(f"{d.meta['meta_source']} (run.mcap holds no run metadata: the run "
                                            "did not finish)")))
    if s is not None:
        rows.append(("simulated / wall time", f"{ms(s.sim_time_s, 2)} s / {ms(s.wall_time_s, 2)} s"))
        if s.realtime is not None:
            rows += _realtime_rows(s.realtime)
        cost = s.harness_cost
        if cost is not None:
            rows.append(("harness cost per frame", escape(
                f"loop thread {cost.loop_thread_us_per_frame} µs, analysis thread "
                f"{cost.analysis_thread_us_per_frame} µs (CPU), analysis tasks dropped "
                f"{cost.analysis_tasks_dropped}")))
            if cost.threads_us_per_frame:
                rows.append(("harness CPU by thread", escape(", ".join(
                    f"{role} {us} µs" for role, us in sorted(cost.threads_us_per_frame.items(),
                                                             key=lambda kv: -(kv[1] or 0)))
                    + " per frame (CPU up to the last step), the costliest first")))
            if cost.start_s is not None and cost.summary_s is not None:
                windows = "" if cost.windows_s is None else f", of it {ms(cost.windows_s, 2)} s cutting case windows"
                rows.append(("start and end", escape(
                    f"{ms(cost.start_s, 2)} s from the command to the first step; {ms(cost.summary_s, 2)} s from the "
                    f"last step to summary.json{windows}")))
        rows.append(("recorder", escape(_recorder_text(s.recorder,
                                                       None if d.truncated or not d.mcap_present else d.messages))))
        rows.append(("collisions", str(len(s.collisions))))
    rows.append(("run.mcap", f"{d.mcap_bytes / 1e6:.2f} MB, {d.messages} messages"
                             + (' <span class="nok">(truncated)</span>' if d.truncated else "")))
    rows.append(("GL backend", escape(str(get("gl_backend")))))
    vers = get("versions")
    if isinstance(vers, dict):
        rows.append(("versions", escape(", ".join(f"{k} {v}" for k, v in vers.items()))))
    out = ['<h2 id="run">Run</h2>', kv_table(rows)]
    vs = {} if s is None else s.vehicles
    if vs:
        head = ["vehicle", "frames sent", "applied", "dropped", "stale", "late", "drop rate (%)", "frames/s",
                "order violations", "target (clock)", "min gap (m)", "final speed (m/s)", "collisions"]
        rows2 = []
        for name, v in vs.items():
            o, t = v.outcome, v.target
            rows2.append([escape(name)] + [escape(str(n)) for n in
                                           (v.frames_sent, v.estimates_applied, v.dropped, v.stale, v.late_estimates)]
                         + ["–" if v.drop_rate is None else f"{v.drop_rate:.1%}", ms(v.frames_per_s, 1),
                            escape(str(v.order_violations))]
                         + [escape("? (?)" if t is None else f"{t.name} ({t.clock})"),
                            ms(None if o is None else o.min_gap_m, 2), ms(None if o is None else o.final_speed_mps, 2),
                            escape("–" if o is None else str(o.collisions))])
        out += ["<h3>Vehicles</h3>", table(head, rows2)]
    return "".join(out)


def _realtime_rows(rt: RealtimeFigures) -> list[tuple[str, str]]:
    """The run table's real-time rows: mode, health (physics and cameras), lateness, processes."""
    badge = ('<span class="ok">kept</span>' if rt.kept_realtime else '<span class="nok">NOT kept</span>'
             + (f" ({escape(', '.join(rt.lagging))} lagged)" if rt.lagging else ""))
    if rt.mode == "lockstep":  # as the verdict says: nothing to keep, the figures as they were
        badge = "not applicable (lockstep waits for every answer)"
    cam = rt.camera
    rows = [("mode", escape(rt.mode)),
            ("real-time health", (f"{badge}: physics factor {rt.achieved_factor} of "
                                  f"{rt.requested_factor}, late steps {rt.late_steps}, "
                                  f"max lateness {rt.max_lateness_ms} ms"
                                  + (f"; camera frames late {cam.late_frames} of {cam.frames} "
                                     f"(over {cam.tolerance_ms} ms after their instant, worst "
                                     f"{cam.worst_lag_ms} ms)" if cam is not None else "")))]
    lat = rt.lateness_ms
    if lat:
        rows.append(("physics-step lateness", escape(
            f"p50 {ms(lat.get('p50'))} ms, p99 {ms(lat.get('p99'))} ms, p99.9 {ms(lat.get('p999'))} ms, "
            f"max {ms(rt.max_lateness_ms)} ms; {rt.late_steps} steps over "
            f"{rt.late_tolerance_ms} ms, {rt.steps_over_10ms} over 10 ms")))
        rows.append(("processes", escape(
            f"physics: {'?' if rt.physics_scheduling is None else rt.physics_scheduling}; render workers: "
            f"{'?' if rt.render_workers is None else rt.render_workers}")))
    return rows


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
        figures = None if d.summary is None else d.summary.vehicles.get(vehicle)
        if values:
            stats = {k: StageFigures.of(summarize_ns(v.tolist())) for k, v in values.items()}
        else:  # no records (no run.mcap): the summary's figures
            stats = {} if figures is None else dict(figures.latency_ms)
        rows = [[escape(stage)] + [str(st.count) if k == "count" else ms(st.figure(k)) for k in keys]
                for stage, st in stats.items()]
        out.append(table(head, rows) if rows else "<p>no latency samples</p>")
        out.append(rig_html(figures))
        if values:
            in_ms = {k: v / 1e6 for k, v in values.items()}
            out.append(box_chart(list(in_ms.items()), x_label="ms", title=f"{vehicle}: latency per stage"))
            out.append('<div class="grid">' + "".join(
                histogram(v, label=k, colour=rp.colour_for(k)) for k, v in in_ms.items()) + "</div>")
    return "".join(out)


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
    out.append(table(["kind", "severity", "vehicle", "events", "first (s)", "last (s)"], rows, numeric_from=3))
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
                      escape(", ".join(e.vehicles) or "–"), escape(et.frames(e.data)),
                      escape("–" if e.severity is None else str(e.severity)),
                      escape(et.value_vs_threshold(e.data)), escape(et.cause(e.data)), link])
    out.append(f"<details open><summary>{len(listed)} event{'s' if len(listed) != 1 else ''}"
               + (f" (the first {len(listed)}; {more} more in run.mcap)" if more else "") + "</summary>"
               + table(["time (s)", "sim time (s)", "kind", "vehicle", "frame", "severity", "value vs threshold",
                         "cause / detail", "case"], items, numeric_from=99)
               + "</details>")
    return "".join(out)


def _verdict_section(d: RunData) -> str:
    """The first screen: a collision banner, then every check, met or missed, with its
    figures (``summary.json``'s ``verdict``, or one rebuilt from its figures)."""
    if d.summary is None:
        return ""
    v = d.summary.verdict
    out = ['<h2 id="verdict">Verdict</h2>']
    col = v.check("collision")
    if col is not None and not col.ok:
        out.append(f'<div class="note bad banner"><b>COLLISION</b> — {escape(col.headline)}</div>')
    tone = "ok" if v.passed else "nok" if v.fails_run else "soft"  # failed checks that are only warnings: amber
    out.append(f'<p class="{tone}">{escape(v.headline)}</p>')
    rows = []
    for c in v.checks:
        mark = ('<span class="ok">ok</span>' if c.ok else
                '<span class="nok">FAILED (fails the run)</span>' if c.name in v.fails_run else
                '<span class="soft">warning</span>')  # the terminal's warn
        rows.append([escape(c.name), mark, escape(c.headline)])
    out.append(table(["check", "verdict", "what the figures say"], rows, numeric_from=99))
    return "".join(out)


# --- the page ---------------------------------------------------------------------------


def build_report(d: RunData, *, page_dir: Path | None = None) -> str:
    """The whole HTML page for ``d``; its links to the run's files (the corner cases'
    recordings) are relative to ``page_dir``, the folder the page is written to
    (default: the run folder)."""
    name = (None if d.summary is None else d.summary.name) or d.meta.get("name") or d.run_dir.name
    parts = [_run_section(d), fleet.fleet_section(d, left=fleet.chart_left(d, timeseries.strips)), _latency_section(d)]
    if d.mcap_present:
        parts += [timeseries.timeline_section(d), timeseries.fps_section(d), timeseries.clock_section(d),
                  _events_section(d)]
    parts.append(cases_section(d, page_dir=page_dir))
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
    html = build_report(d, page_dir=path.parent)
    try:
        path.write_text(html, encoding="utf-8")
    except OSError as err:
        raise ConfigError(f"cannot write report {path}: {err.strerror or err}") from err
    return path


def add_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
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
