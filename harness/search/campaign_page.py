"""``CAMPAIGN/summary.json`` and ``CAMPAIGN/report.html``.

The page is self-contained (inline CSS and hand-written SVG; it loads nothing): the
key figures, corner cases by cause and kind, scatter plots of the searched
parameters two by two with every episode a dot (grey: no corner case; blue: timing
only; orange: a perception mismatch; red: a latency mismatch; larger: a higher
score; hover for its values), per parameter a table of its bins (episodes, with
cases, rate as a bar; the densest bin marked), the generations, the slowest and most
anomalous episodes linked to their own reports, and the cases, each with its
recording, its episode's report, the command that replays it, and for the first
few the camera frame nearest to it.
"""

from __future__ import annotations

import itertools
import json
import math
from html import escape
from pathlib import Path
from typing import Any

from hil.common.errors import ConfigError
from hil.harness.report import plots as rp
from hil.harness.search.db import DB_NAME, CampaignDB
from hil.harness.search.summary import build_summary, case_cause, episode_class

SUMMARY_NAME = "summary.json"
REPORT_NAME = "report.html"
CLASS_COLOUR = {"none": "#bab0ac", "timing": "#4c78a8", "perception": "#f58518", "latency": "#e45756"}
MAX_PLOTS = 6
MAX_CASES_LISTED = 300
MAX_THUMBNAILS = 12
_CSS = """
body{font:14px/1.45 system-ui,sans-serif;margin:24px auto;max-width:1150px;color:#222;padding:0 16px}
h1{font-size:22px;margin-bottom:2px}h2{font-size:18px;border-bottom:1px solid #ddd;padding-bottom:3px;margin-top:30px}
table{border-collapse:collapse;margin:6px 0 12px}th,td{border:1px solid #ddd;padding:3px 8px;text-align:left;
vertical-align:top}th{background:#f4f4f4}td.n{text-align:right;font-variant-numeric:tabular-nums}
.muted{color:#777}.grid{display:flex;flex-wrap:wrap;gap:8px}code{font-size:12px}
.warn{background:#fff4e0;border:1px solid #f0b860;padding:8px 12px;border-radius:4px}
.bar{display:inline-block;height:10px;background:#e45756;vertical-align:middle;margin-right:6px}
.hot td{background:#fff0ef}img.thumb{width:160px;height:auto;border:1px solid #ccc}
"""


def write_outputs(folder: Path) -> dict[str, Any]:
    """Compute the summary of the campaign in ``folder`` and write both files.

    Raises:
        ConfigError: not a campaign folder, or the files cannot be written.
    """
    with CampaignDB(folder / DB_NAME, readonly=True) as db:
        summary = build_summary(db)
        eps = db.episodes()
        cases = db.cases()
    try:
        (folder / SUMMARY_NAME).write_text(json.dumps(summary, indent=2, sort_keys=True) + "\n")
        (folder / REPORT_NAME).write_text(build_page(summary, eps, cases, folder), encoding="utf-8")
    except OSError as err:
        raise ConfigError(f"{folder}: cannot write the summary: {err.strerror or err}") from err
    return summary


def _table(head: list[str], rows: list[list[str]], numeric_from: int = 1, numeric_to: int = 99) -> str:
    h = "".join(f"<th>{escape(c)}</th>" for c in head)
    body = "".join("<tr>" + "".join(f'<td{" class=n" if numeric_from <= i < numeric_to else ""}>{c}</td>'
                                    for i, c in enumerate(r)) + "</tr>" for r in rows)
    return f"<table><tr>{h}</tr>{body}</table>"


def _num(v: Any, digits: int = 3) -> str:
    return "–" if not isinstance(v, (int, float)) or isinstance(v, bool) else f"{v:.{digits}f}".rstrip("0").rstrip(".")


def _params(p: dict[str, float]) -> str:
    return escape(", ".join(f"{k}={v:.4g}" for k, v in p.items()))


def build_page(s: dict[str, Any], eps: list[dict[str, Any]], cases: list[dict[str, Any]],
               folder: Path | None = None) -> str:
    """The campaign page; ``folder`` (the campaign folder) lets it link episode
    reports and case recordings that exist and show case thumbnails."""
    c = s["campaign"]
    e = s["episodes"]
    head = [
        ("campaign", f"{escape(c['name'])} <code>{escape(c['id'])}</code>"),
        ("scenario", escape(c["scenario"])),
        ("strategy", _kv_table(c["strategy"])),
        ("seed", str(c["seed"])),
        ("episodes", (f"{e['ran']} of {e['planned']} ran ({escape(_counts(e['by_status']))})"
                      + (f", {e['missing']} missing" if e["missing"] else ""))),
        ("simulated", f"{_num(s['sim_s'], 1)} s, {_num(s['virtual_km'], 3)} virtual km"),
        ("wall time", (f"{_num(s['wall_s'], 1)} s: {_num(s['episodes_per_min'], 1)} episodes/min, "
                      f"{_num(s['km_per_h'], 2)} virtual km/h")),
        ("corner cases", f"{s['cases']['total']} in {s['cases']['episodes_with_cases']} episodes"),
    ]
    parts = ["<table>" + "".join(f"<tr><th>{k}</th><td>{v}</td></tr>" for k, v in head) + "</table>"]
    if not e["complete"]:
        parts.append(f'<p class="warn">incomplete: {e["missing"]} episodes missing (first: '
                     f'{", ".join(map(str, e["missing_first"]))}), statuses {escape(_counts(e["by_status"]))}</p>')
    parts.append("<h2>Corner cases by cause and kind</h2>")
    parts.append(_table(["cause", "cases"], [[k, str(v)] for k, v in s["cases"]["by_cause"].items()]))
    parts.append(_table(["kind", "cases"], [[escape(k), str(v)] for k, v in s["cases"]["by_kind"].items()]))
    parts.append("<h2>Where they cluster</h2>" + _legend() + '<div class="grid">'
                 + "".join(_scatters(s, eps, cases)) + "</div>")
    parts.append(_regions_table(s))
    parts.append("<h2>Generations</h2>" + _table(
        ["generation", "episodes", "with mismatch cases", "rate (%)", "mean score", "origins"],
        [[str(g["generation"]), str(g["episodes"]), str(g["with_mismatch_cases"]), _pct(g["rate"]),
          _num(g["mean_score"]), escape(_counts(g["origins"]))] for g in s["by_generation"]]))
    for title, key in (("Most anomalous episodes", "most_anomalous"), ("Slowest episodes", "slowest")):
        parts.append(f"<h2>{title}</h2>" + _table(
            ["episode", "score", "cases", "anomalies", "min gap (m)", "wall (s)", "sim (s)", "params"],
            [[_episode_link(folder, b["dir"]), _num(b["score"]), str(b["cases"]), str(b["anomalies"]),
              _num(b["min_gap_m"]), _num(b["wall_s"], 2), _num(b["sim_s"], 2), _params(b["params"])]
             for b in s[key]], numeric_to=7))
    if s["errors"]:
        parts.append("<h2>Episodes that did not finish</h2>" + _table(
            ["episode", "status", "why"], [[str(x["episode"]), x["status"], escape(str(x["error"]))]
                                           for x in s["errors"]]))
    thumbs = _thumbnails(folder, cases[:MAX_THUMBNAILS])
    parts.append(f"<h2>Cases ({len(cases)})</h2>" + _table(
        ["episode", "case", "kind", "cause", "severity", "sim time (s)", "summary", "recording", "replay", "frame"],
        [[_episode_link(folder, k["episode_dir"], str(k["episode"])), str(k["case_id"]), escape(str(k["kind"])),
          case_cause(k), escape(str(k["severity"])), _num((k["sim_time_ns"] or 0) / 1e9, 2),
          escape(str(k["summary"])), _file_link(folder, k.get("mcap_path")),
          f"<code>hil replay CAMPAIGN/{escape(k['episode_dir'])} {k['case_id']}</code>",
          thumbs.get((k["episode"], k["case_id"]), "")]
         for k in cases[:MAX_CASES_LISTED]], numeric_from=99))
    if len(cases) > MAX_CASES_LISTED:
        parts.append(f'<p class="muted">{len(cases) - MAX_CASES_LISTED} more in campaign.sqlite</p>')
    return ("<!DOCTYPE html><html lang=en><head><meta charset=utf-8>"
            f"<title>hil search: {escape(c['name'])}</title><style>{_CSS}</style></head><body>"
            f"<h1>hil search: {escape(c['name'])}</h1>" + "".join(parts) + "</body></html>\n")


def _legend() -> str:
    items = [("none", "no corner case"), ("timing", "timing anomaly only"), ("perception", "perception mismatch"),
             ("latency", "latency mismatch")]
    return "<p>" + " &nbsp; ".join(f'<span style="color:{CLASS_COLOUR[k]}">&#9679;</span> {v}'
                                   for k, v in items) + "</p>"


def _scatters(s: dict[str, Any], eps: list[dict[str, Any]], cases: list[dict[str, Any]]) -> list[str]:
    dims = s["campaign"]["dims"]
    causes: dict[int, set[str]] = {}
    for k in cases:
        causes.setdefault(int(k["episode"]), set()).add(case_cause(k))
    points = [(e, episode_class(causes.get(e["episode"], set()))) for e in eps]
    if len(dims) == 1:
        score_dim = {"name": "score", "lo": 0.0, "hi": max([p["score"] or 0.0 for p, _ in points] + [1.0]),
                     "unit": ""}
        return [_scatter(dims[0], score_dim, points)]
    # The dimensions whose bins differ most in case rate first: that is where cases cluster.
    def spread(d: dict[str, Any]) -> float:
        rates = [b["rate"] for b in s["regions"].get(d["name"], {}).get("bins", []) if b["rate"] is not None]
        return (max(rates) - min(rates)) if rates else 0.0
    ranked = sorted(dims, key=spread, reverse=True)[:4]
    return [_scatter(a, b, points) for a, b in itertools.islice(itertools.combinations(ranked, 2), MAX_PLOTS)]


def _scatter(dx: dict[str, Any], dy: dict[str, Any], points: list[tuple[dict[str, Any], str]],
             *, width: int = 360, height: int = 300) -> str:
    left, right, top, bottom = 52, 12, 12, 40
    pw, ph = width - left - right, height - top - bottom

    def sx(v: float) -> float:
        return float(left + (v - dx["lo"]) / ((dx["hi"] - dx["lo"]) or 1.0) * pw)

    def sy(v: float) -> float:
        return float(top + ph - (v - dy["lo"]) / ((dy["hi"] - dy["lo"]) or 1.0) * ph)

    body = [f'<rect x="{left}" y="{top}" width="{pw}" height="{ph}" fill="#fafafa" stroke="#ccc"/>']
    for t in rp.nice_ticks(dx["lo"], dx["hi"], 5):
        body.append(f'<text x="{sx(t):.1f}" y="{top + ph + 14}" text-anchor="middle">{rp.fmt(t)}</text>')
    for t in rp.nice_ticks(dy["lo"], dy["hi"], 5):
        body.append(f'<line x1="{left}" x2="{left + pw}" y1="{sy(t):.1f}" y2="{sy(t):.1f}" stroke="#eee"/>'
                    f'<text x="{left - 4}" y="{sy(t) + 4:.1f}" text-anchor="end">{rp.fmt(t)}</text>')
    xl, yl = _label(dx["name"], dx.get("unit", "")), _label(dy["name"], dy.get("unit", ""))
    body.append(f'<text x="{left + pw / 2:.0f}" y="{height - 6}" text-anchor="middle">{escape(xl)}</text>'
                f'<text transform="translate(12 {top + ph / 2:.0f}) rotate(-90)" text-anchor="middle">'
                f"{escape(yl)}</text>")
    order = {"none": 0, "timing": 1, "perception": 2, "latency": 3}
    for e, cls in sorted(points, key=lambda p: order[p[1]]):  # cases drawn on top
        x = e["params"].get(dx["name"])
        y = e["score"] if dy["name"] == "score" else e["params"].get(dy["name"])
        if x is None or y is None:
            continue
        r = 2.5 + min(5.0, math.sqrt(max(e["score"] or 0.0, 0.0)))
        title = (f"e{e['episode']:05d} {cls} score {e['score']:g} cases {e['cases']} "
                 + ", ".join(f"{k}={v:.4g}" for k, v in e["params"].items()))
        body.append(f'<circle cx="{sx(x):.1f}" cy="{sy(y):.1f}" r="{r:.1f}" fill="{CLASS_COLOUR[cls]}" '
                    f'fill-opacity="0.75" stroke="#333" stroke-width="0.4"><title>{escape(title)}</title></circle>')
    return (f'<svg viewBox="0 0 {width} {height}" width="{width}" height="{height}" role="img" '
            f'aria-label="{escape(xl)} against {escape(yl)}" font-family="system-ui,sans-serif" font-size="11">'
            + "".join(body) + "</svg>")


def _label(name: str, unit: str) -> str:
    return f"{name} ({unit})" if unit else name


def _regions_table(s: dict[str, Any]) -> str:
    """Per searched dimension, its bins: episodes, those with a mismatch case, and
    the rate as a bar; the densest bin marked."""
    out = ["<h3>Episodes with a mismatch case, per parameter bin</h3>"]
    for name, r in s["regions"].items():
        hot = r["hot"]
        unit = f" ({r['unit']})" if r["unit"] else ""
        rows = []
        for b in r["bins"]:
            is_hot = hot is not None and b["lo"] == hot["lo"] and b["hi"] == hot["hi"]
            rate = b["rate"]
            bar = "" if rate is None else f'<span class="bar" style="width:{round(rate * 120)}px"></span>'
            rows.append(f'<tr{" class=hot" if is_hot else ""}><td>{b["lo"]:.4g} – {b["hi"]:.4g}</td>'
                        f'<td class=n>{b["episodes"]}</td><td class=n>{b["with_cases"]}</td>'
                        f"<td>{bar}{_pct(rate)}{' ★ densest' if is_hot else ''}</td></tr>")
        span = "" if r["case_span"] is None else \
            f' <span class="muted">cases found in [{r["case_span"][0]:.4g}, {r["case_span"][1]:.4g}]{escape(unit)}' \
            + ("" if hot is None else f", all bins {hot['overall_rate']:.0%}") + "</span>"
        out.append(f"<p><b>{escape(name)}</b>{escape(unit)}{span}</p><table><tr><th>bin{escape(unit)}</th>"
                   f"<th>episodes</th><th>with cases</th><th>rate (%)</th></tr>{''.join(rows)}</table>")
    return "".join(out)


def _pct(v: Any) -> str:
    return "–" if not isinstance(v, (int, float)) or isinstance(v, bool) else f"{v:.0%}"


def _counts(d: dict[str, Any]) -> str:
    return ", ".join(f"{k} {v}" for k, v in d.items()) or "–"


def _kv_table(d: dict[str, Any], prefix: str = "") -> str:
    """A nested mapping as a two-column table (nested keys joined with dots)."""
    rows: list[tuple[str, str]] = []

    def walk(x: dict[str, Any], pre: str) -> None:
        for k, v in x.items():
            if isinstance(v, dict) and v:
                walk(v, f"{pre}{k}.")
            else:
                rows.append((f"{pre}{k}", _num(v, 4) if isinstance(v, float) else str(v)))

    walk(d, prefix)
    return "<table>" + "".join(f"<tr><th>{escape(k)}</th><td>{escape(v)}</td></tr>" for k, v in rows) + "</table>"


def _episode_link(folder: Path | None, rel: str, text: str | None = None) -> str:
    label = escape(text if text is not None else rel)
    if folder is not None and (folder / rel / "report.html").is_file():
        return f'<a href="{escape(rel)}/report.html">{label}</a>'
    return f"<code>{label}</code>"


def _file_link(folder: Path | None, rel: Any) -> str:
    if not isinstance(rel, str) or not rel:
        return "–"
    if folder is not None and (folder / rel).is_file():
        return f'<a href="{escape(rel)}">{escape(Path(rel).name)}</a>'
    return escape(rel)


def _thumbnails(folder: Path | None, cases: list[dict[str, Any]]) -> dict[tuple[Any, Any], str]:
    """The camera frame nearest to each case (``<img>`` at its aspect ratio), read
    from its episode's run.mcap; cases whose frame cannot be read get none."""
    if folder is None:
        return {}
    from hil.harness.record.run_folder import read_run
    from hil.harness.report.case_section import thumbnail_for_case

    out: dict[tuple[Any, Any], str] = {}
    runs: dict[str, Any] = {}
    for k in cases:
        d = k["episode_dir"]
        try:
            if d not in runs:
                runs[d] = read_run(folder / d)
            img = thumbnail_for_case(runs[d], {"vehicle": k.get("vehicle"), "sim_time_ns": k.get("sim_time_ns")},
                                     width=160, alt=f"camera frame of case {k['case_id']}")
        except (ConfigError, OSError):
            continue
        if img:
            out[(k["episode"], k["case_id"])] = img
    return out


__all__ = ["REPORT_NAME", "SUMMARY_NAME", "build_page", "write_outputs"]
