"""The report's corner-case section: the rows of the run's corner-case database,
each with the camera frame nearest to the case's simulated time.

The database is ``RUN/corner_cases.sqlite`` (or the first ``RUN/corner_cases/*.sqlite``),
table ``cases`` with columns ``id, run, scenario, seed, params, config_hash, vehicle,
sim_time_ns, kind, cause, severity, summary, events, mcap_path`` and the window in
sim time (``window_start_ns``, ``window_end_ns``); missing columns show as "–". A database
that cannot be read is reported in the section, never raised: the rest of the report
stands.
"""

from __future__ import annotations

import bisect
import sqlite3
from html import escape
from pathlib import Path
from typing import Any

from harness.corner_cases import query_cases
from harness.run_folder import CORNER_DB_NAME, MCAP_NAME, RunData, camera_images

MAX_ROWS = 500
MAX_THUMBNAILS = 100
_SHOWN = ("kind", "cause", "severity", "vehicle", "sim_time_ns", "summary", "events", "scenario", "seed", "params",
          "config_hash", "run", "mcap_path")
_WINDOW = ("window_start_ns", "window_end_ns", "sim_end_ns")


def find_db(run_dir: Path) -> Path | None:
    """The run's corner-case database, or ``None`` when it has none."""
    p = run_dir / CORNER_DB_NAME
    if p.is_file():
        return p
    folder = run_dir / "corner_cases"
    found = sorted(folder.glob("*.sqlite")) if folder.is_dir() else []
    return found[0] if found else None


def read_cases(db: Path) -> list[dict[str, Any]]:
    """Every row of table ``cases``, ordered by simulated time then id.

    Raises:
        sqlite3.Error: not a database, no table ``cases``.
    """
    rows = query_cases(db)

    def key(r: dict[str, Any]) -> tuple[float, str]:
        t = r.get("sim_time_ns")
        return (float(t) if isinstance(t, (int, float)) else float("inf"), str(r.get("id")))

    return sorted(rows, key=key)


def _frame_t0(d: RunData, vehicle: str, sim_time_ns: int) -> int | None:
    """Capture time ``t0`` of ``vehicle``'s camera frame nearest to ``sim_time_ns``."""
    pairs = sorted((r["sim_time_ns"], r["t0_ns"]) for r in d.pipeline.get(vehicle, [])
                   if isinstance(r.get("sim_time_ns"), int) and isinstance(r.get("t0_ns"), int))
    cams = d.camera_times.get(vehicle)
    if not pairs or not cams:
        return None
    sims = [p[0] for p in pairs]
    i = bisect.bisect_left(sims, sim_time_ns)
    best = min((j for j in (i - 1, i) if 0 <= j < len(pairs)), key=lambda j: abs(sims[j] - sim_time_ns))
    t0 = pairs[best][1]
    k = bisect.bisect_left(cams, t0)
    return min((cams[j] for j in (k - 1, k) if 0 <= j < len(cams)), key=lambda t: abs(t - t0))


def _vehicle(d: RunData, row: dict[str, Any]) -> str | None:
    v = row.get("vehicle")
    if isinstance(v, str) and v:
        return v
    return d.vehicles[0] if len(d.vehicles) == 1 else None


def cases_section(d: RunData) -> str:
    """HTML of the corner-case section (says so when there are none)."""
    out = ["<h2>Corner cases</h2>"]
    db = find_db(d.run_dir)
    if db is None:
        return "".join(out) + "<p>no corner cases recorded</p>"
    try:
        rows = read_cases(db)
    except sqlite3.Error as err:
        return "".join(out) + f'<div class="note warn">{escape(db.name)} cannot be read: {escape(str(err))}</div>'
    if not rows:
        return "".join(out) + f"<p>no corner cases recorded ({escape(db.name)} is empty)</p>"
    out.append(f'<p class="muted">{len(rows)} cases in {escape(str(db.relative_to(d.run_dir)))}'
               + (f"; the first {MAX_ROWS} are shown" if len(rows) > MAX_ROWS else "") + ".</p>")
    rows = rows[:MAX_ROWS]
    frames: dict[int, tuple[str, int]] = {}
    for i, r in enumerate(rows[:MAX_THUMBNAILS]):
        v, t = _vehicle(d, r), r.get("sim_time_ns")
        if v is not None and isinstance(t, (int, float)):
            t0 = _frame_t0(d, v, int(t))
            if t0 is not None:
                frames[i] = (v, t0)
    images = camera_images(d.run_dir / MCAP_NAME, frames.values()) if frames and d.mcap_present else {}
    for i, r in enumerate(rows):
        img = images.get(frames.get(i, ("", -1)))
        if img is not None:
            fmt, b64 = img
            pic = f'<img alt="camera frame" src="data:image/{escape(fmt)};base64,{b64}">'
        elif i < MAX_THUMBNAILS:
            pic = '<div class="muted" style="width:240px">no camera frame recorded near this time</div>'
        else:
            pic = ""
        cells = []
        for k in _SHOWN:
            v = r.get(k)
            if k == "sim_time_ns" and isinstance(v, (int, float)):
                cells.append(("sim time", f"{v / 1e9:.3f} s"))
            else:
                cells.append((k, "–" if v is None else escape(str(v))))
        lo, hi = r.get("window_start_ns"), r.get("window_end_ns")
        if isinstance(lo, int) and isinstance(hi, int):  # the case's data: this sim-time range of mcap_path
            cells.append(("window", f"{lo / 1e9:.2f}–{hi / 1e9:.2f} s sim time"))
        extra = [(k, escape(str(v))) for k, v in r.items() if k not in _SHOWN and k not in _WINDOW and k != "id"]
        table = "<table>" + "".join(f"<tr><th>{escape(k)}</th><td>{v}</td></tr>" for k, v in cells + extra) + "</table>"
        out.append(f'<div class="case" id="case-{escape(str(r.get("id")))}">{pic}<div><b>case '
                   f'{escape(str(r.get("id", i)))}</b>{table}</div></div>')
    return "".join(out)


__all__ = ["cases_section", "find_db", "read_cases"]
