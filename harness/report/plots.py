"""Hand-written SVG charts for the HTML report: no plotting dependency, vector, small.

Each chart function returns one ``<svg>`` element as a string, ready to inline in
HTML5 (no namespace attribute, so the report holds no address at all;
:func:`standalone` adds it for a ``.svg`` file). Marks carry
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


def tick_labels(ticks: list[float]) -> list[str]:
    """``fmt`` of each tick, with as many decimals as it takes to tell them apart (ticks
    150.00 to 150.20 ms read "150 150 150 150 150")."""
    labels = [fmt(t) for t in ticks]
    digits = 1
    while len(set(labels)) < len(set(ticks)) and digits <= 6:
        labels = [f"{t:.{digits}f}" for t in ticks]
        digits += 1
    return labels


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


def log_ticks(lo: float, hi: float) -> list[float]:
    out = []
    for e in range(math.floor(math.log10(lo)), math.ceil(math.log10(hi)) + 1):
        for m in (1, 2, 5):
            v = m * 10.0 ** e
            if lo <= v <= hi:
                out.append(v)
    return out


@dataclass(frozen=True)
class Series:
    """A line (``style="line"``) or dots (``"points"``); NaN in ``ys`` breaks a line.
    ``width``: the line's stroke (px); a wider line drawn first stays visible under a
    narrower one on the same values."""

    label: str
    xs: Sequence[float] | np.ndarray
    ys: Sequence[float] | np.ndarray
    colour: str
    style: str = "line"
    width: float = 1.4


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
    """A horizontal reference line at ``y`` (a deadline, a budget, a floor), dashed, and
    named in the chart's legend. ``stretch``: the y axis may widen to show it as long
    as the data keeps at least :data:`DATA_SHARE` of the height; otherwise (and always
    when ``False``) a rule beyond the data's range is named in the legend as above or
    below the chart, never drawn over the data."""

    label: str
    y: float
    colour: str = "#d62728"
    stretch: bool = True


#: A stretching rule may widen the y axis only while the data keeps this share of it.
DATA_SHARE = 2 / 3
CHAR_W = 6.4  # px per character of 11 px system-ui text, a little generous (checked in Chromium)
_ROW_H = 15


class Scale:
    """A linear (or log) map from values to pixels."""

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


def _isolated(ys: np.ndarray, xs: np.ndarray) -> list[tuple[float, float]]:
    """The finite vertices of a line with no finite neighbour (a one-point series, or a
    point between gaps): a line through them draws nothing."""
    ok = np.isfinite(ys)
    out = []
    for i in np.flatnonzero(ok).tolist():
        if not (i > 0 and ok[i - 1]) and not (i + 1 < len(ok) and ok[i + 1]):
            out.append((float(xs[i]), float(ys[i])))
    return out


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


def svg_element(width: float, height: float, body: list[str], label: str) -> str:
    """The ``<svg>`` element around ``body`` (inline HTML5: no namespace)."""
    return (f'<svg viewBox="0 0 {width:.0f} {height:.0f}" width="{width:.0f}" height="{height:.0f}" '
            f'role="img" aria-label="{escape(label)}" {_FONT}>' + "".join(body) + "</svg>")


def standalone(svg: str) -> str:
    """``svg`` as a file of its own (``.svg``, an ``<img src>``, a Markdown image): with
    the SVG namespace, without which a browser shows an XML tree or a broken image."""
    return svg.replace("<svg ", '<svg xmlns="http://www.w3.org/2000/svg" ', 1)


def _header(title: str, keys: Sequence[tuple[str, str, bool]], *, x0: float, x1: float) -> tuple[list[str], int]:
    """The title, then a legend entry per ``(label, colour, dashed)``, left to right from
    ``x0`` and wrapped before ``x1``: nothing is drawn over anything else. Returns the
    SVG and the height it takes (px)."""
    body: list[str] = []
    x, row = x0, 0
    if title:
        body.append(f'<text x="{x0:.0f}" y="15" font-weight="bold">{escape(title)}</text>')
        x = x0 + 7.2 * len(title) + 18
    for label, colour, dashed in keys:
        w = 18 + CHAR_W * len(label)
        if x + w > x1 and x > x0:
            row, x = row + 1, x0
        y = 6 + row * _ROW_H
        if dashed:
            body.append(f'<line x1="{x:.1f}" x2="{x + 12:.1f}" y1="{y + 5}" y2="{y + 5}" stroke="{colour}" '
                        f'stroke-width="1.5" stroke-dasharray="4 2"/>')
        else:
            body.append(f'<rect x="{x:.1f}" y="{y}" width="10" height="10" fill="{colour}"/>')
        body.append(f'<text x="{x + 16:.1f}" y="{y + 9}">{escape(label)}</text>')
        x += w + 10
    return body, 8 + (row + 1) * _ROW_H


def _y_range(data: np.ndarray, rules: Sequence[Rule], *, y_zero: bool,
             headroom: float = 0.05) -> tuple[float, float]:
    """The y axis: the data's range (with 0 when ``y_zero``), widened for stretching
    rules only as far as the data keeps :data:`DATA_SHARE` of the height."""
    if data.size == 0:
        data = np.array([0.0, 1.0])
    lo, hi = float(data.min()), float(data.max())
    if y_zero:
        lo, hi = min(lo, 0.0), max(hi, 0.0)
    span = max(hi - lo, abs(hi) * 1e-3, 1e-9)
    for r in sorted((r for r in rules if r.stretch and math.isfinite(r.y)), key=lambda r: abs(r.y - (lo + hi) / 2)):
        new_lo, new_hi = min(lo, r.y), max(hi, r.y)
        if span / (new_hi - new_lo) >= DATA_SHARE - 1e-9:
            lo, hi = new_lo, new_hi
    pad = (hi - lo) * 0.05 or 1.0
    return (lo - pad if (not y_zero or lo < 0) else lo), hi + ((hi - lo) * headroom or pad)


def _integers(ticks: list[float], lo: float, hi: float) -> list[float]:
    """The whole numbers among ``ticks``, or every whole number in ``[lo, hi]`` when
    fewer than two of them are."""
    whole = [t for t in ticks if float(t).is_integer()]
    return whole if len(whole) >= 2 else [float(v) for v in range(math.ceil(lo), math.floor(hi) + 1)]


def line_chart(*, series: Sequence[Series], bands: Sequence[Band] = (), strips: Sequence[Strip] = (),
               rules: Sequence[Rule] = (), x_label: str, y_label: str, width: int = 1000, height: int = 220,
               y_zero: bool = True, title: str = "", left: int = 0,
               x_range: tuple[float, float] | None = None, x_ticks: Sequence[float] | None = None,
               y_integer: bool = False, headroom: float = 0.05) -> str:
    """Lines and dots over a shared x axis, optional shaded bands, horizontal rules
    (deadlines, thresholds), and event strips under the axis (one row each).
    The y axis is scaled to the data (see :class:`Rule`); the title and a legend of
    every series, band and rule sit above the plot, wrapped onto more rows when
    needed, so no text covers the data or other text. ``height``: the plot area and
    its axes (the legend's rows and the strips come on top). ``left``: at least this
    left margin (px), so charts drawn with the same value line up; ``x_range``: the x
    axis span (charts of several vehicles on one time axis); ``x_ticks``: the x tick
    values (e.g. the numbers of vehicles a study ran), instead of round ones;
    ``y_integer``: y ticks at whole numbers only (counts); ``headroom``: the share of the
    y span left free above the highest value."""
    left = max(64, left, strip_margin(strips))
    right, bottom = 14, 40
    strip_h = 14 * len(strips) + (6 if strips else 0)
    xs_all = [np.asarray(s.xs, float) for s in series] + [np.asarray(b.xs, float) for b in bands]
    xs_all += [np.asarray([m.x for m in st.marks], float) for st in strips]
    ys_all = [np.asarray(s.ys, float) for s in series]
    ys_all += [np.asarray(b.lo, float) for b in bands] + [np.asarray(b.hi, float) for b in bands]
    if x_range is not None:
        xs_all.append(np.asarray(x_range, float))
    if x_ticks is not None:
        xs_all.append(np.asarray(x_ticks, float))
    xcat = np.concatenate([a[np.isfinite(a)] for a in xs_all] or [np.zeros(0)])
    ycat = np.concatenate([a[np.isfinite(a)] for a in ys_all] or [np.zeros(0)])
    if xcat.size == 0:
        xcat = np.array([0.0, 1.0])
    x_lo, x_hi = float(xcat.min()), float(xcat.max())
    if 0 < x_lo < 0.02 * (x_hi - x_lo):  # a time axis that starts a hair after zero: show 0
        x_lo = 0.0
    y_lo, y_hi = _y_range(ycat, rules, y_zero=y_zero, headroom=headroom)
    pw = width - left - right
    shown = [r for r in rules if y_lo <= r.y <= y_hi]
    keys = [(s.label, s.colour, False) for s in series] + [(b.label, b.colour, False) for b in bands]
    keys += [(r.label if r in shown else f"{r.label}: {'above' if r.y > y_hi else 'below'} the chart", r.colour,
              True) for r in rules]
    head, top = _header(title, keys, x0=left, x1=left + pw)
    ph = height - 22 - bottom
    sx = Scale(x_lo, x_hi, left, left + pw)
    sy = Scale(y_lo, y_hi, top + ph, top)
    body = [f'<rect x="{left}" y="{top}" width="{pw}" height="{ph}" fill="#fafafa" stroke="#ccc"/>']
    yt = _integers(nice_ticks(sy.lo, sy.hi), sy.lo, sy.hi) if y_integer else nice_ticks(sy.lo, sy.hi)
    for t, label in zip(yt, tick_labels(yt)):
        y = sy(t)
        body.append(f'<line x1="{left}" x2="{left + pw}" y1="{y:.1f}" y2="{y:.1f}" stroke="#e4e4e4"/>'
                    f'<text x="{left - 4}" y="{y + 4:.1f}" text-anchor="end">{label}</text>')
    xt = list(x_ticks) if x_ticks is not None else nice_ticks(sx.lo, sx.hi, 8)
    for t, label in zip(xt, tick_labels(xt)):
        x = sx(t)
        body.append(f'<line x1="{x:.1f}" x2="{x:.1f}" y1="{top}" y2="{top + ph}" stroke="#eee"/>'
                    f'<text x="{x:.1f}" y="{top + ph + 14}" text-anchor="middle">{label}</text>')
    body.append(f'<text x="{left + pw / 2:.0f}" y="{top + ph + 30}" text-anchor="middle">{escape(x_label)}</text>'
                f'<text transform="translate(13 {top + ph / 2:.0f}) rotate(-90)" text-anchor="middle">'
                f'{escape(y_label)}</text>')
    for r in shown:  # under the data: a series on its rule stays visible
        y = float(sy(r.y))
        body.append(f'<line x1="{left}" x2="{left + pw}" y1="{y:.1f}" y2="{y:.1f}" stroke="{r.colour}" '
                    f'stroke-width="1.3" stroke-dasharray="6 4"><title>{escape(r.label)}</title></line>')
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
            body.append(f'<path d="{d}" stroke="{s.colour}" stroke-width="{s.width:g}" fill="none" '
                        f'stroke-linejoin="round"><title>{escape(s.label)}</title></path>')
            alone = _isolated(np.asarray(sy(y), float), x)  # a vertex with no neighbour draws no line: a dot
            if alone:
                dots = "".join(f"M{a:.1f} {b:.1f}h0" for a, b in alone)
                body.append(f'<path d="{dots}" stroke="{s.colour}" stroke-width="{max(6.0, 3 * s.width):g}" '
                            f'stroke-linecap="round" fill="none"><title>{escape(s.label)}</title></path>')
    body += head
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
    return svg_element(width, top - 22 + height + strip_h, body, title or y_label)


def strip_margin(strips: Sequence[Strip]) -> int:
    """The left margin (px) the labels of ``strips`` need."""
    return 10 + int(6.2 * max((len(st.label) for st in strips), default=0))


__all__ = [
    "DATA_SHARE",
    "PALETTE",
    "Band",
    "Mark",
    "Rule",
    "Scale",
    "Series",
    "Strip",
    "colour_for",
    "fmt",
    "line_chart",
    "log_ticks",
    "nice_ticks",
    "severity_colour",
    "standalone",
    "strip_margin",
    "svg_element",
]
