"""Hand-written SVG charts for the HTML report: no plotting dependency, vector, small.

Each chart function returns one ``<svg>`` element as a string, ready to inline in
HTML5 (no namespace attribute, so the report holds no address at all). Marks carry
a ``<title>``, which a browser shows on hover. Long series are thinned to the
minimum and maximum per pixel column, so a one-hour run stays a few hundred KB.

Why not a plotting library (zoom, pan, hover values): measured on 2026-11-23 in
headless Chromium 150 on this 2-core machine (load average 7-9), the report of a
4-vehicle 4 s run is 198 KB and reaches its load event in ~0.26 s; a page of 10
simple charts with plotly.js inlined (plotly 7.1.0's plotly.min.js, 4.8 MB, the
only way to stay one offline file) is 4.85 MB and takes ~1.7 s. Every report and
every mailed copy would carry 4.8 MB of script for hover values the SVG ``<title>``
tooltips already give.
"""

from __future__ import annotations

import math
import zlib
from collections.abc import Sequence
from dataclasses import dataclass
from html import escape
from typing import Any

import numpy as np

PALETTE = ("#4c78a8", "#f58518", "#54a24b", "#b279a2", "#e45756", "#72b7b2", "#eeca3b",
           "#9d755d", "#ff9da6", "#bab0ac")
_SEVERITY = {
    "debug": "#9e9e9e", "info": "#4c78a8", "notice": "#4c78a8", "low": "#72b7b2",
    "minor": "#eeca3b", "warn": "#f58518", "warning": "#f58518", "medium": "#f58518",
    "major": "#e45756", "high": "#e45756", "error": "#d62728", "critical": "#7f0000",
    "fatal": "#7f0000",
}
_FONT = 'font-family="system-ui,sans-serif" font-size="11"'
_MAX_MARKS_PER_ROW = 4000


def colour_for(key: str) -> str:
    """A stable palette colour for a name (a stage, a vehicle, an event kind)."""
    return PALETTE[zlib.crc32(key.encode()) % len(PALETTE)]


def severity_colour(severity: Any, kind: str) -> str:
    """Colour of an event: by its ``severity`` when it has one (a word such as
    ``warning``/``error``, or a number in 0..1 or 0..10), else by its kind."""
    if isinstance(severity, str) and severity.strip().lower() in _SEVERITY:
        return _SEVERITY[severity.strip().lower()]
    if isinstance(severity, (int, float)) and not isinstance(severity, bool) and math.isfinite(severity):
        level = severity if severity <= 1 else severity / 10
        ramp = ("#4c78a8", "#eeca3b", "#f58518", "#e45756", "#7f0000")
        return ramp[min(len(ramp) - 1, max(0, int(level * len(ramp))))]
    return colour_for(kind)


def fmt(v: float) -> str:
    """A short label for an axis value."""
    if v == 0:
        return "0"
    a = abs(v)
    if a >= 1e5 or a < 1e-3:
        return f"{v:.0e}"
    if a >= 100:
        return f"{v:.0f}"
    if a >= 10:
        return f"{v:.1f}".rstrip("0").rstrip(".")
    return f"{v:.3g}"


def nice_ticks(lo: float, hi: float, n: int = 5) -> list[float]:
    """About ``n`` round tick values covering ``[lo, hi]``."""
    if not (math.isfinite(lo) and math.isfinite(hi)) or hi <= lo:
        return [lo]
    raw = (hi - lo) / max(n, 1)
    mag = 10 ** math.floor(math.log10(raw))
    step = next(m * mag for m in (1, 2, 2.5, 5, 10) if m * mag >= raw)
    start = math.ceil(lo / step - 1e-9) * step
    out = []
    v = start
    while v <= hi + step * 1e-9:
        out.append(round(v, 12))
        v += step
    return out


def _log_ticks(lo: float, hi: float) -> list[float]:
    out = []
    for e in range(math.floor(math.log10(lo)), math.ceil(math.log10(hi)) + 1):
        for m in (1, 2, 5):
            v = m * 10.0 ** e
            if lo <= v <= hi:
                out.append(v)
    return out


@dataclass(frozen=True)
class Series:
    """A line (``style="line"``) or dots (``"points"``); NaN in ``ys`` breaks a line."""

    label: str
    xs: Sequence[float] | np.ndarray
    ys: Sequence[float] | np.ndarray
    colour: str
    style: str = "line"


@dataclass(frozen=True)
class Band:
    """A shaded range ``lo..hi`` over ``xs`` (e.g. ± uncertainty)."""

    label: str
    xs: Sequence[float] | np.ndarray
    lo: Sequence[float] | np.ndarray
    hi: Sequence[float] | np.ndarray
    colour: str


@dataclass(frozen=True)
class Mark:
    """One tick in an event strip at ``x``; ``title`` shows on hover."""

    x: float
    colour: str
    title: str


@dataclass(frozen=True)
class Strip:
    """A row of event ticks under a chart's x axis (one per event kind)."""

    label: str
    marks: Sequence[Mark]


@dataclass(frozen=True)
class Rule:
    """A horizontal reference line at ``y`` (a deadline, a threshold), dashed, labelled
    at its right end."""

    label: str
    y: float
    colour: str = "#d62728"
    stretch: bool = True  # False: never widens the y axis; off the chart it is named in a note


class _Scale:
    def __init__(self, lo: float, hi: float, p0: float, p1: float, *, log: bool = False) -> None:
        if hi <= lo:
            lo, hi = lo - 0.5, hi + 0.5
        self.lo, self.hi, self.p0, self.p1, self.log = lo, hi, p0, p1, log
        self._l0, self._l1 = (math.log10(lo), math.log10(hi)) if log else (lo, hi)

    def __call__(self, v: np.ndarray | float) -> Any:
        v = np.log10(np.maximum(v, self.lo)) if self.log else v
        return self.p0 + (v - self._l0) * (self.p1 - self.p0) / (self._l1 - self._l0)


def _thin(x: np.ndarray, y: np.ndarray, px: np.ndarray, columns: int) -> tuple[np.ndarray, np.ndarray]:
    """At most min and max per pixel column (in order), when there are many points."""
    if x.size <= 4 * columns:
        return x, y
    col = np.clip(px.astype(np.int64), 0, columns * 4)
    keep = np.zeros(x.size, bool)
    order = np.lexsort((y, col))  # within a column, by y
    c = col[order]
    starts = np.flatnonzero(np.r_[True, c[1:] != c[:-1]])
    ends = np.r_[starts[1:], c.size] - 1
    keep[order[starts]] = True
    keep[order[ends]] = True
    return x[keep], y[keep]


def _path(xs: np.ndarray, ys: np.ndarray, *, points: bool) -> str:
    parts = []
    pen_up = True
    for x, y in zip(xs.tolist(), ys.tolist()):
        if not math.isfinite(y):
            pen_up = True
            continue
        if points:
            parts.append(f"M{x:.1f} {y:.1f}h0")
        else:
            parts.append(f"{'M' if pen_up else 'L'}{x:.1f} {y:.1f}")
            pen_up = False
    return "".join(parts)


def _svg(width: float, height: float, body: list[str], label: str) -> str:
    return (f'<svg viewBox="0 0 {width:.0f} {height:.0f}" width="{width:.0f}" height="{height:.0f}" '
            f'role="img" aria-label="{escape(label)}" {_FONT}>' + "".join(body) + "</svg>")


def line_chart(*, series: Sequence[Series], bands: Sequence[Band] = (), strips: Sequence[Strip] = (),
               rules: Sequence[Rule] = (), x_label: str, y_label: str, width: int = 1000, height: int = 220,
               y_zero: bool = True, title: str = "", left: int = 0,
               x_range: tuple[float, float] | None = None) -> str:
    """Lines and dots over a shared x axis, optional shaded bands, horizontal rules
    (deadlines, thresholds), and event strips under the axis (one row each).
    ``height`` is the chart without its strips. ``left``: at least this left margin
    (px), so charts drawn with the same value line up; ``x_range``: the x axis span
    (charts of several vehicles on one time axis)."""
    left = max(64, left, strip_margin(strips))
    right, top, bottom = 14, 22, 40
    strip_h = 14 * len(strips) + (6 if strips else 0)
    pw, ph = width - left - right, height - top - bottom
    xs_all = [np.asarray(s.xs, float) for s in series] + [np.asarray(b.xs, float) for b in bands]
    xs_all += [np.asarray([m.x for m in st.marks], float) for st in strips]
    ys_all = [np.asarray(s.ys, float) for s in series]
    ys_all += [np.asarray(b.lo, float) for b in bands] + [np.asarray(b.hi, float) for b in bands]
    ys_all += [np.asarray([r.y for r in rules if r.stretch], float)]
    if x_range is not None:
        xs_all.append(np.asarray(x_range, float))
    xcat = np.concatenate([a[np.isfinite(a)] for a in xs_all] or [np.zeros(0)])
    ycat = np.concatenate([a[np.isfinite(a)] for a in ys_all] or [np.zeros(0)])
    if xcat.size == 0:
        xcat = np.array([0.0, 1.0])
    if ycat.size == 0:
        ycat = np.array([0.0, 1.0])
    x_lo, x_hi = float(xcat.min()), float(xcat.max())
    if 0 < x_lo < 0.02 * (x_hi - x_lo):  # a time axis that starts a hair after zero: show 0
        x_lo = 0.0
    y_lo, y_hi = float(ycat.min()), float(ycat.max())
    if y_zero:
        y_lo, y_hi = min(y_lo, 0.0), max(y_hi, 0.0)
    pad = (y_hi - y_lo) * 0.05 or 1.0
    y_hi += pad
    if not y_zero or y_lo < 0:
        y_lo -= pad
    sx = _Scale(x_lo, x_hi, left, left + pw)
    sy = _Scale(y_lo, y_hi, top + ph, top)
    body = [f'<rect x="{left}" y="{top}" width="{pw}" height="{ph}" fill="#fafafa" stroke="#ccc"/>']
    for t in nice_ticks(sy.lo, sy.hi):
        y = sy(t)
        body.append(f'<line x1="{left}" x2="{left + pw}" y1="{y:.1f}" y2="{y:.1f}" stroke="#e4e4e4"/>'
                    f'<text x="{left - 4}" y="{y + 4:.1f}" text-anchor="end">{fmt(t)}</text>')
    for t in nice_ticks(sx.lo, sx.hi, 8):
        x = sx(t)
        body.append(f'<line x1="{x:.1f}" x2="{x:.1f}" y1="{top}" y2="{top + ph}" stroke="#eee"/>'
                    f'<text x="{x:.1f}" y="{top + ph + 14}" text-anchor="middle">{fmt(t)}</text>')
    body.append(f'<text x="{left + pw / 2:.0f}" y="{top + ph + 30}" text-anchor="middle">{escape(x_label)}</text>'
                f'<text transform="translate(13 {top + ph / 2:.0f}) rotate(-90)" text-anchor="middle">'
                f'{escape(y_label)}</text>')
    for b in bands:
        x = np.asarray(b.xs, float)
        if x.size == 0:
            continue
        o = np.argsort(x, kind="stable")
        px, lo, hi = sx(x[o]), sy(np.asarray(b.lo, float)[o]), sy(np.asarray(b.hi, float)[o])
        pts = " ".join(f"{a:.1f},{c:.1f}" for a, c in zip(np.r_[px, px[::-1]], np.r_[hi, lo[::-1]]))
        body.append(f'<polygon points="{pts}" fill="{b.colour}" fill-opacity="0.22" stroke="none">'
                    f'<title>{escape(b.label)}</title></polygon>')
    for s in series:
        x, y = np.asarray(s.xs, float), np.asarray(s.ys, float)
        if x.size == 0:
            continue
        px = sx(x)
        x, y = _thin(px, y, px - left, pw)
        d = _path(x, sy(y), points=s.style == "points")
        if s.style == "points":
            body.append(f'<path d="{d}" stroke="{s.colour}" stroke-width="3" stroke-linecap="round" '
                        f'fill="none"><title>{escape(s.label)}</title></path>')
        else:
            body.append(f'<path d="{d}" stroke="{s.colour}" stroke-width="1.4" fill="none" '
                        f'stroke-linejoin="round"><title>{escape(s.label)}</title></path>')
    placed: list[float] = []
    off = [r for r in rules if not sy.lo <= r.y <= sy.hi]
    if off:
        body.append(f'<text x="{left + pw - 4}" y="{top + ph - 5}" text-anchor="end" fill="{off[0].colour}" '
                    f'paint-order="stroke" stroke="#fafafa" stroke-width="3">'
                    + escape("; ".join(f"{r.label}: off the chart" for r in off)) + "</text>")
    for r in rules:
        if r in off:
            continue
        y = float(sy(r.y))
        ly = y - 4
        while any(abs(ly - p) < 12 for p in placed):  # rules close together: stack their labels
            ly += 13
        placed.append(ly)
        body.append(f'<line x1="{left}" x2="{left + pw}" y1="{y:.1f}" y2="{y:.1f}" stroke="{r.colour}" '
                    f'stroke-width="1.3" stroke-dasharray="6 4"><title>{escape(r.label)}</title></line>'
                    f'<text x="{left + pw - 4}" y="{ly:.1f}" text-anchor="end" fill="{r.colour}" '
                    f'paint-order="stroke" stroke="#fafafa" stroke-width="3">{escape(r.label)}</text>')
    # legend
    lx = left + 4
    for item in [*series, *bands]:
        body.append(f'<rect x="{lx}" y="6" width="10" height="10" fill="{item.colour}"/>'
                    f'<text x="{lx + 14}" y="15">{escape(item.label)}</text>')
        lx += 24 + 6.2 * len(item.label)
    if title:
        body.append(f'<text x="{left + pw}" y="15" text-anchor="end" font-weight="bold">{escape(title)}</text>')
    y0 = top + ph + 42
    for i, st in enumerate(strips):
        y = y0 + 14 * i
        body.append(f'<line x1="{left}" x2="{left + pw}" y1="{y + 5}" y2="{y + 5}" stroke="#eee"/>'
                    f'<text x="{left - 4}" y="{y + 9}" text-anchor="end" font-size="10">{escape(st.label)}</text>')
        seen: set[tuple[int, str]] = set()
        for m in st.marks:
            x = float(sx(m.x))
            key = (round(x), m.colour)
            if key in seen or len(seen) >= _MAX_MARKS_PER_ROW:
                continue
            seen.add(key)
            body.append(f'<line x1="{x:.1f}" x2="{x:.1f}" y1="{y}" y2="{y + 10}" stroke="{m.colour}" '
                        f'stroke-width="2"><title>{escape(m.title)}</title></line>')
    return _svg(width, height + strip_h, body, title or y_label)


def strip_margin(strips: Sequence[Strip]) -> int:
    """The left margin (px) the labels of ``strips`` need."""
    return 10 + int(6.2 * max((len(st.label) for st in strips), default=0))


def box_chart(rows: Sequence[tuple[str, np.ndarray]], *, x_label: str, width: int = 1000,
              title: str = "", colours: dict[str, str] | None = None) -> str:
    """One horizontal box per row: box p25–p75, bar p50, whiskers p1–p99, circle max.
    Log axis when the values span more than two decades."""
    rows = [(label, np.asarray(v, float)) for label, v in rows if np.asarray(v).size]
    left, right, top, row_h = 110, 14, 22, 22
    height = top + row_h * max(len(rows), 1) + 44
    pw = width - left - right
    if not rows:
        return _svg(width, height, [f'<text x="{left}" y="{top + 14}">no latency samples</text>'], title)
    allv = np.concatenate([v for _, v in rows])
    pos = allv[allv > 0]
    lo, hi = (float(pos.min()), float(allv.max())) if pos.size else (0.0, 1.0)
    log = pos.size > 0 and hi / lo > 100
    if log:
        sx = _Scale(10 ** math.floor(math.log10(lo)), 10 ** math.ceil(math.log10(hi)), left, left + pw, log=True)
        ticks = _log_ticks(sx.lo, sx.hi)
    else:
        sx = _Scale(min(0.0, float(allv.min())), hi * 1.05 or 1.0, left, left + pw)
        ticks = nice_ticks(sx.lo, sx.hi, 8)
    bottom = top + row_h * len(rows)
    body = [f'<rect x="{left}" y="{top}" width="{pw}" height="{bottom - top}" fill="#fafafa" stroke="#ccc"/>']
    for t in ticks:
        x = sx(t)
        body.append(f'<line x1="{x:.1f}" x2="{x:.1f}" y1="{top}" y2="{bottom}" stroke="#e4e4e4"/>'
                    f'<text x="{x:.1f}" y="{bottom + 14}" text-anchor="middle">{fmt(t)}</text>')
    for i, (label, v) in enumerate(rows):
        p1, p25, p50, p75, p99 = np.percentile(v, (1, 25, 50, 75, 99))
        mx = float(v.max())
        yc = top + row_h * i + row_h / 2
        c = (colours or {}).get(label) or colour_for(label)
        tip = escape(f"{label}: n={v.size}, p1 {p1:.3f}, p25 {p25:.3f}, p50 {p50:.3f}, p75 {p75:.3f}, "
                     f"p99 {p99:.3f}, max {mx:.3f} ms")
        x1, x25, x50, x75, x99, xm = (float(sx(q)) for q in (p1, p25, p50, p75, p99, mx))
        body.append(f'<g><title>{tip}</title>'
                    f'<line x1="{x1:.1f}" x2="{x99:.1f}" y1="{yc:.1f}" y2="{yc:.1f}" stroke="#555"/>'
                    f'<line x1="{x1:.1f}" x2="{x1:.1f}" y1="{yc - 4:.1f}" y2="{yc + 4:.1f}" stroke="#555"/>'
                    f'<line x1="{x99:.1f}" x2="{x99:.1f}" y1="{yc - 4:.1f}" y2="{yc + 4:.1f}" stroke="#555"/>'
                    f'<rect x="{x25:.1f}" y="{yc - 7:.1f}" width="{max(x75 - x25, 1):.1f}" height="14" '
                    f'fill="{c}" fill-opacity="0.55" stroke="{c}"/>'
                    f'<line x1="{x50:.1f}" x2="{x50:.1f}" y1="{yc - 7:.1f}" y2="{yc + 7:.1f}" stroke="#000" '
                    f'stroke-width="2"/>'
                    f'<circle cx="{xm:.1f}" cy="{yc:.1f}" r="3" fill="none" stroke="#d62728"/></g>'
                    f'<text x="{left - 6}" y="{yc + 4:.1f}" text-anchor="end">{escape(label)}</text>')
    scale = "log scale" if log else "linear"
    body.append(f'<text x="{left + pw / 2:.0f}" y="{bottom + 30}" text-anchor="middle">{escape(x_label)} '
                f'({scale}; box p25–p75, bar p50, whiskers p1–p99, circle max)</text>')
    if title:
        body.append(f'<text x="{left}" y="15" font-weight="bold">{escape(title)}</text>')
    return _svg(width, height, body, title or x_label)


def histogram(values: np.ndarray, *, label: str, colour: str, width: int = 250, height: int = 130,
              bins: int = 40) -> str:
    """A small histogram of ``values`` (ms) with p50 and p99 marked. The range ends
    just past p99.9 so one outlier cannot squash the shape; values beyond it are
    counted in the label."""
    v = np.asarray(values, float)
    left, right, top, bottom = 34, 16, 18, 30
    pw, ph = width - left - right, height - top - bottom
    body = [f'<text x="{left}" y="12" font-weight="bold">{escape(label)}</text>']
    if v.size == 0:
        body.append(f'<text x="{left}" y="{top + 20}">no samples</text>')
        return _svg(width, height, body, label)
    lo, hi = float(v.min()), float(np.percentile(v, 99.9))
    if hi <= lo:
        hi = lo + max(abs(lo) * 0.01, 1e-3)
    over = int((v > hi).sum())
    counts, edges = np.histogram(v[v <= hi], bins=bins, range=(lo, hi))
    sx = _Scale(lo, hi, left, left + pw)
    sy = _Scale(0, float(counts.max()) * 1.1 or 1.0, top + ph, top)
    body.append(f'<rect x="{left}" y="{top}" width="{pw}" height="{ph}" fill="#fafafa" stroke="#ccc"/>')
    for c, a, b in zip(counts.tolist(), edges[:-1].tolist(), edges[1:].tolist()):
        if c:
            x0, x1, y = sx(a), sx(b), sy(c)
            body.append(f'<rect x="{x0:.1f}" y="{y:.1f}" width="{max(x1 - x0 - 0.5, 0.5):.1f}" '
                        f'height="{top + ph - y:.1f}" fill="{colour}"><title>{a:.3f}–{b:.3f} ms: {c}</title></rect>')
    for q, dash in ((50, "3 2"), (99, "1 2")):
        x = float(sx(np.percentile(v, q)))
        body.append(f'<line x1="{x:.1f}" x2="{x:.1f}" y1="{top}" y2="{top + ph}" stroke="#000" '
                    f'stroke-dasharray="{dash}"><title>p{q}</title></line>')
    for t in nice_ticks(lo, hi, 4):
        body.append(f'<text x="{sx(t):.1f}" y="{top + ph + 12}" text-anchor="middle" font-size="9">{fmt(t)}</text>')
    body.append(f'<text x="{left + pw / 2:.0f}" y="{height - 3}" text-anchor="middle" font-size="9">ms '
                f'(dashed p50, dotted p99{f"; {over} beyond p99.9" if over else ""})</text>'
                f'<text x="{left - 3}" y="{top + 8}" text-anchor="end" font-size="9">{int(counts.max())}</text>')
    return _svg(width, height, body, label)


__all__ = [
    "PALETTE",
    "Band",
    "Mark",
    "Rule",
    "Series",
    "Strip",
    "box_chart",
    "colour_for",
    "fmt",
    "histogram",
    "line_chart",
    "nice_ticks",
    "severity_colour",
    "strip_margin",
]
