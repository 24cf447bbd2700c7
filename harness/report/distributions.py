"""Distribution charts of the HTML report: a box per row and small histograms
(SVG strings, as :mod:`hil.harness.report.plots`; values in ms)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from html import escape

import numpy as np

from hil.harness.report.plots import Scale, colour_for, log_ticks, nice_ticks, svg_element, tick_labels


def box_chart(rows: Sequence[tuple[str, np.ndarray]], *, x_label: str, width: int = 1000,
              title: str = "", colours: dict[str, str] | None = None) -> str:
    """One horizontal box per row: box p25–p75, bar p50, whiskers p1–p99, circle max.
    Log axis when the values span more than two decades."""
    rows = [(label, np.asarray(v, float)) for label, v in rows if np.asarray(v).size]
    left, right, top, row_h = 110, 14, 22, 22
    height = top + row_h * max(len(rows), 1) + 44
    pw = width - left - right
    if not rows:
        return svg_element(width, height, [f'<text x="{left}" y="{top + 14}">no latency samples</text>'], title)
    allv = np.concatenate([v for _, v in rows])
    pos = allv[allv > 0]
    lo, hi = (float(pos.min()), float(allv.max())) if pos.size else (0.0, 1.0)
    log = pos.size > 0 and hi / lo > 100
    if log:
        sx = Scale(10 ** math.floor(math.log10(lo)), 10 ** math.ceil(math.log10(hi)), left, left + pw, log=True)
        ticks = log_ticks(sx.lo, sx.hi)
    else:
        sx = Scale(min(0.0, float(allv.min())), hi * 1.05 or 1.0, left, left + pw)
        ticks = nice_ticks(sx.lo, sx.hi, 8)
    bottom = top + row_h * len(rows)
    body = [f'<rect x="{left}" y="{top}" width="{pw}" height="{bottom - top}" fill="#fafafa" stroke="#ccc"/>']
    for t, label in zip(ticks, tick_labels(ticks)):
        x = sx(t)
        body.append(f'<line x1="{x:.1f}" x2="{x:.1f}" y1="{top}" y2="{bottom}" stroke="#e4e4e4"/>'
                    f'<text x="{x:.1f}" y="{bottom + 14}" text-anchor="middle">{label}</text>')
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
    return svg_element(width, height, body, title or x_label)


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
        return svg_element(width, height, body, label)
    lo, hi = float(v.min()), float(np.percentile(v, 99.9))
    if hi <= lo:
        hi = lo + max(abs(lo) * 0.01, 1e-3)
    over = int((v > hi).sum())
    counts, edges = np.histogram(v[v <= hi], bins=bins, range=(lo, hi))
    sx = Scale(lo, hi, left, left + pw)
    sy = Scale(0, float(counts.max()) * 1.1 or 1.0, top + ph, top)
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
    ht = nice_ticks(lo, hi, 4)
    for t, label in zip(ht, tick_labels(ht)):
        body.append(f'<text x="{sx(t):.1f}" y="{top + ph + 12}" text-anchor="middle" font-size="9">{label}</text>')
    body.append(f'<text x="{left + pw / 2:.0f}" y="{height - 3}" text-anchor="middle" font-size="9">ms '
                f'(dashed p50, dotted p99{f"; {over} beyond p99.9" if over else ""})</text>'
                f'<text x="{left - 3}" y="{top + 8}" text-anchor="end" font-size="9">{int(counts.max())}</text>')
    return svg_element(width, height, body, label)


__all__ = ["box_chart", "histogram"]
