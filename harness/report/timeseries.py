"""The run report's charts over time: end-to-end latency with the events under it,
frames per second, and the target clock's offset (with the skew and its bound).

Frames per second are counted in bins of a whole number of camera periods, edged
half a period before a frame is due: a run on pace puts the same number of frames
in every bin and shows its true rate (0.25 s bins at 10 fps held 2 or 3 frames and
drew 8/s and 12/s around a steady 10/s).
"""

from __future__ import annotations

import json
import math
from html import escape
from pathlib import Path
from typing import Any

import numpy as np

from hil.harness.record import event_text as et
from hil.harness.record.run_folder import CONFIG_NAME, ClockPoint, RecordedEvent, RunData
from hil.harness.report import fleet
from hil.harness.report import plots as rp
from hil.harness.report.tables import ms, table
from hil.harness.vocab.figures import ClockFigures


def event_title(e: RecordedEvent, t_s: float) -> str:
    """The hover text of an event's tick: kind, times, vehicles, frames, value, cause."""
    sim = e.data.get("sim_time_ns")
    parts = [f"{e.kind} at {t_s:.3f} s"]
    if isinstance(sim, int):
        parts.append(f"sim {sim / 1e9:.3f} s")
    if e.vehicles:
        parts.append(", ".join(e.vehicles))
    for label, text in (("frame", et.frames(e.data)), ("", et.value_vs_threshold(e.data)), ("", et.cause(e.data))):
        if text != "–":
            parts.append(f"{label} {text}".strip())
    return parts[0] + (" — " + et.fit(parts[1:], 300) if parts[1:] else "")


def strips(d: RunData, vehicle: str | None) -> list[rp.Strip]:
    """One row of event ticks per event kind (of ``vehicle``, or all)."""
    t0 = d.t_start_ns
    rows: dict[str, list[rp.Mark]] = {}
    for e in d.events:
        if vehicle is not None and e.vehicles and vehicle not in e.vehicles:
            continue
        t = (e.t_ns - t0) / 1e9
        rows.setdefault(e.kind, []).append(rp.Mark(t, rp.severity_colour(e.severity, e.kind), event_title(e, t)))
    return [rp.Strip(k, rows[k]) for k in sorted(rows)]


def time_span(d: RunData) -> tuple[float, float]:
    """0 to the last capture of any vehicle (s since the first frame)."""
    t0 = d.t_start_ns
    ends = [(r["t0_ns"] - t0) / 1e9 for recs in d.pipeline.values() for r in recs if isinstance(r.get("t0_ns"), int)]
    return (0.0, max(ends, default=1.0))


def timeline_section(d: RunData) -> str:
    out = ['<h2 id="timeline">End-to-end latency over time</h2>',
           ('<p class="muted">t0′−t0 of each frame at its capture time; dashed: the end-to-end deadline and '
            "the estimate timeout (named above the chart when they lie beyond the data); under each chart one "
            "row per event kind (hover a tick for details; coloured by severity where the event has one). All "
            "vehicles share one time axis.</p>")]
    left = fleet.chart_left(d, strips)
    span = time_span(d)
    for vehicle in d.vehicles:
        x, y = fleet.e2e(d, vehicle)
        series = [rp.Series(f"{vehicle} end-to-end (ms)", x, y, fleet.vehicle_colours(d.vehicles)[vehicle], "points")]
        out.append(rp.line_chart(series=series, strips=strips(d, vehicle), x_label="time since first frame (s)",
                                 y_label="end-to-end (ms)", title=vehicle, rules=fleet.e2e_rules(d, [vehicle]),
                                 left=left, x_range=span))
    if not d.vehicles and d.events:
        out.append(rp.line_chart(series=[], strips=strips(d, None), x_label="time (s)", y_label="", title="events"))
    return "".join(out)


# --- frames per second ------------------------------------------------------------------


def camera_period_s(run_dir: Path, sent_s: np.ndarray) -> float | None:
    """The camera period (s): ``camera.fps`` of ``RUN/config.json``, else the median
    gap between the frames sent; ``None`` with fewer than two frames and no config."""
    try:
        fps = json.loads((run_dir / CONFIG_NAME).read_text())["camera"]["fps"]
        if isinstance(fps, (int, float)) and fps > 0:
            return 1.0 / float(fps)
    except (OSError, ValueError, KeyError, TypeError):
        pass
    gaps = np.diff(np.sort(sent_s))
    gaps = gaps[gaps > 0]
    return float(np.median(gaps)) if gaps.size else None


def frames_per_bin(period_s: float, span_s: float) -> int:
    """Whole camera periods per bin: about 1 s, or a twentieth of a run shorter than
    20 s (at least one period)."""
    width = 1.0 if span_s >= 20 else max(0.25, span_s / 20)
    return max(1, round(width / period_s))


def rate_bins(times_s: np.ndarray, *, start_s: float, period_s: float, frames: int,
              end_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Events per second in bins of ``frames`` camera periods from ``start_s``, the
    last bin cut short at a whole period so that it still ends after ``end_s``; a last
    bin under half the others is left out when there are others (a few events over a
    short bin read as a jump: 10 estimates a second among bins of 4 and 8).
    Returns the bin centres (s) and the rates (1/s)."""
    periods = max(1, math.ceil((end_s - start_s) / period_s - 1e-9))
    cuts = np.r_[np.arange(0, periods, frames), periods]
    if len(cuts) > 2 and 2 * (cuts[-1] - cuts[-2]) < frames:
        cuts = cuts[:-1]
    edges = start_s + cuts * period_s
    counts, _ = np.histogram(times_s, bins=edges)
    return (edges[:-1] + edges[1:]) / 2, counts / np.diff(edges)


def fps_section(d: RunData) -> str:
    out = ['<h2 id="fps">Frames per second over time</h2>',
           ('<p class="muted">Frames sent (by capture time t0) and estimates applied (by t_apply) per second, '
            "counted in bins of a whole number of camera periods (in each chart's title), each beginning half a "
            "period before a frame is due (for estimates, shifted by their median delay t_apply−t0): on pace, "
            "every bin holds the same number of frames.</p>")]
    t0 = d.t_start_ns
    left, span = fleet.chart_left(d, strips), time_span(d)  # once: each goes over every vehicle's records
    for vehicle in d.vehicles:
        recs = d.pipeline.get(vehicle, [])
        sent = np.array([(r["t0_ns"] - t0) / 1e9 for r in recs if isinstance(r.get("t0_ns"), int)])
        ok = [r for r in recs if r.get("status") == "ok" and isinstance(r.get("t_apply_ns"), int)
              and isinstance(r.get("t0_ns"), int)]
        applied = np.array([(r["t_apply_ns"] - t0) / 1e9 for r in ok])
        period = camera_period_s(d.run_dir, sent) if sent.size else None
        if period is None:
            out.append(f"<p>{escape(vehicle)}: {'no frames recorded' if not sent.size else 'one frame recorded'}</p>")
            continue
        k = frames_per_bin(period, float(sent.max() - sent.min()))
        start = float(sent.min()) - period / 2
        xs, ys = rate_bins(sent, start_s=start, period_s=period, frames=k, end_s=float(sent.max()))
        series = [rp.Series("frames sent/s", xs, ys, "#4c78a8", width=4.0)]
        if applied.size:
            lag = float(np.median([(r["t_apply_ns"] - r["t0_ns"]) / 1e9 for r in ok]))
            xa, ya = rate_bins(applied, start_s=start + lag, period_s=period, frames=k,
                               end_s=float(max(applied.max(), sent.max() + lag)))
            series.append(rp.Series("estimates applied/s", xa, ya, "#f58518"))
        floor = fleet.limits(d.run_dir, vehicle).get("fps_floor")
        rules = [] if floor is None else [rp.Rule(f"frame-rate floor {floor:g}/s", floor, "#d62728")]
        out.append(rp.line_chart(series=series, rules=rules, x_label="time since first frame (s)",
                                 y_label="per second",
                                 title=f"{vehicle} (bins of {k} frame period{'s' if k != 1 else ''}, "
                                       f"{k * period:.3g} s)", height=200, headroom=0.25,
                                 left=left, x_range=span))
    return "".join(out)


# --- the target clock ---------------------------------------------------------------------


def skew_ppm(points: list[ClockPoint], given: ClockFigures | None = None) -> tuple[float, float | None] | None:
    """The target clock's skew (ppm) and its bound (± ppm, ``None`` where the source
    gave none): the summary's final fit (``given``: ``vehicles.<name>.clock``), else the
    newest ``/V/clock`` estimate, else a fit over the samples whose uncertainty is within
    twice the smallest (a minimum-delay filter), bounded by the first and last of them
    (their uncertainties over the time between them)."""
    if given is not None and given.skew_ppm is not None:
        unc = given.skew_uncertainty_ppm
        return float(given.skew_ppm), None if unc is None else float(unc)
    told = [p for p in points if p.skew_ppm is not None]
    if told:
        return float(told[-1].skew_ppm or 0.0), told[-1].skew_uncertainty_ppm
    if len(points) < 3:
        return None
    u = np.array([p.uncertainty_ns for p in points])
    good = [p for p, ui in zip(points, u) if ui <= 2 * max(u.min(), 1.0)]
    t = np.array([p.t_ns for p in good], float)
    if len(good) < 3 or t.max() - t.min() < 1e9:
        return None
    off = np.array([p.offset_ns for p in good])
    slope = np.polyfit(t - t.mean(), off - off.mean(), 1)[0]
    first, last = good[int(np.argmin(t))], good[int(np.argmax(t))]
    bound = (first.uncertainty_ns + last.uncertainty_ns) / (last.t_ns - first.t_ns)
    return float(slope * 1e6), float(bound * 1e6)


def _skew_text(skew: tuple[float, float | None] | None) -> str:
    if skew is None:
        return "–"
    value, bound = skew
    return f"{value:+.2f} ± {bound:.2f}" if bound is not None else f"{value:+.2f} (no bound recorded)"


def clock_section(d: RunData) -> str:
    out = ['<h2 id="clock">Target clock: offset and uncertainty</h2>',
           ('<p class="muted">Offset of each target clock from the harness clock (target − harness), '
            "plotted relative to its median; the band is ± the uncertainty (half the round trip of "
            "each sample, or the estimator's own). Skew: the rate difference in parts per million, ± its "
            "bound.</p>")]
    if not d.clock:
        return "".join(out) + "<p>no clock samples recorded</p>"
    t0 = d.t_start_ns
    left, span = fleet.chart_left(d, strips), time_span(d)
    rows = []
    vs = {} if d.summary is None else d.summary.vehicles
    colours = fleet.vehicle_colours(d.vehicles)
    for vehicle in d.vehicles + sorted(v for v in d.clock if v not in d.vehicles):
        pts = d.clock.get(vehicle)
        if not pts:
            continue
        med = float(np.median([p.offset_ns for p in pts]))
        x = np.array([(p.t_ns - t0) / 1e9 for p in pts])
        y = np.array([(p.offset_ns - med) / 1e3 for p in pts])
        u = np.array([p.uncertainty_ns / 1e3 for p in pts])
        c = colours.get(vehicle) or rp.colour_for(vehicle)  # the fleet charts' colour
        out.append(rp.line_chart(series=[rp.Series("offset − median (µs)", x, y, c, "line"),
                                         rp.Series("samples", x, y, c, "points")],
                                 bands=[rp.Band("± uncertainty", x, y - u, y + u, c)],
                                 x_label="time since first frame (s)", y_label="µs", y_zero=False,
                                 title=f"{vehicle} ({d.clock_source.get(vehicle, '?')})", height=200,
                                 left=left, x_range=span))
        vf = vs.get(vehicle)
        fin = None if vf is None or vf.clock is None else vf.clock
        final = ("–" if fin is None or fin.offset_ns is None else
                 f"{fin.offset_ns / 1e6:+.3f}" + ("" if fin.uncertainty_ns is None else
                                                  f" ± {fin.uncertainty_ns / 1e6:.3f}"))
        rows.append([escape(vehicle), escape(d.clock_source.get(vehicle, "?")), str(len(pts)),
                     f"{med / 1e6:.3f}", escape(final), ms(float(u.min()), 1), ms(float(np.median(u)), 1),
                     ms(float(np.ptp(y)), 1),
                     escape(_skew_text(skew_ppm(pts, None if vf is None else vf.clock)))])
    # The samples' median offset, and the summary's final fit (clock.offset_ns at its
    # ref_ns): a skewed clock's offset moves over the run, so the two differ.
    out.append(table(["vehicle", "source", "samples", "median offset (ms)", "final offset (ms, summary.json)",
                      "min uncertainty (µs)", "median uncertainty (µs)", "offset spread (µs)", "skew (ppm)"], rows,
                     numeric_from=2))
    return "".join(out)


__all__ = ["camera_period_s", "clock_section", "event_title", "fps_section", "frames_per_bin", "rate_bins",
           "skew_ppm", "strips", "time_span", "timeline_section"]
