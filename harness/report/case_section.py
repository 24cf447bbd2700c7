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
import json
import os
import sqlite3
from html import escape
from pathlib import Path, PurePosixPath
from typing import Any
from urllib.parse import quote

from hil.harness.cases.casebook import query_cases
from hil.harness.record import event_text as et
from hil.harness.record.run_folder import CORNER_DB_NAME, MCAP_NAME, RunData, camera_images

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


def read_case_rows(run_dir: Path) -> list[dict[str, Any]]:
    """The run's cases (empty when it has none or the database cannot be read)."""
    db = find_db(run_dir)
    if db is None:
        return []
    try:
        return read_cases(db)
    except sqlite3.Error:
        return []


def case_for_event(cases: list[dict[str, Any]], event: Any) -> Any:
    """The id of the case ``event`` (a ``run_folder.RecordedEvent``) belongs to: same kind
    and vehicle, its sim time within the case's first..last trigger (or at the
    case's sim time); ``None`` if none."""
    sim = event.data.get("sim_time_ns")
    if not isinstance(sim, int):
        return None
    for c in cases:
        if c.get("kind") != event.kind or (event.vehicles and c.get("vehicle") not in event.vehicles):
            continue
        start = c.get("sim_time_ns")
        end = c.get("sim_end_ns") if isinstance(c.get("sim_end_ns"), int) else start
        if isinstance(start, int) and start <= sim <= (end if isinstance(end, int) else start):
            return c.get("id")
    return None


def _size(fmt: str, b64: str) -> tuple[int, int] | None:
    """Width and height (px) of a base64 JPEG/PNG, from its header."""
    import base64

    import cv2
    import numpy as np

    try:
        img = cv2.imdecode(np.frombuffer(base64.b64decode(b64), np.uint8), cv2.IMREAD_REDUCED_GRAYSCALE_8)
    except (ValueError, cv2.error):
        return None
    if img is None:
        return None
    return img.shape[1] * 8, img.shape[0] * 8


_THUMB_W = 320


def img_tag(fmt: str, b64: str, *, width: int, alt: str) -> str:
    """An inline ``<img>`` of a base64 image, ``width`` px wide at its own aspect ratio."""
    wh = _size(fmt, b64)
    dims = "" if wh is None else f' width="{width}" height="{round(width * wh[1] / wh[0])}"'
    return f'<img class="thumb" alt="{escape(alt)}"{dims} src="data:image/{escape(fmt)};base64,{b64}">'


def thumbnail_for_case(d: RunData, row: dict[str, Any], *, width: int = _THUMB_W, alt: str = "camera frame") -> str:
    """The ``<img>`` of the camera frame nearest to a case (``vehicle``,
    ``sim_time_ns``) in ``d``'s run.mcap; ``""`` when there is none.

    Raises:
        ConfigError: the run.mcap cannot be read.
    """
    v, t = _vehicle(d, row), row.get("sim_time_ns")
    if v is None or not isinstance(t, (int, float)) or not d.mcap_present:
        return ""
    t0 = _frame_t0(d, v, int(t))
    if t0 is None:
        return ""
    img = camera_images(d.run_dir / MCAP_NAME, [(v, t0)]).get((v, t0))
    return "" if img is None else img_tag(img[0], img[1], width=width, alt=alt)


def _inside(run_dir: Path, rel: str) -> str | None:
    """Why ``rel`` is not a plain relative path to a file inside ``run_dir`` (a scheme
    such as ``javascript:``, an absolute path, ``..``, a symlink leading out, nothing
    there); None when it is."""
    p = PurePosixPath(rel)
    if p.is_absolute() or ".." in p.parts or ":" in rel or "\\" in rel or any(ord(c) < 32 for c in rel):
        return "not a file in the run folder"
    full = (run_dir / p).resolve()
    if not full.is_relative_to(run_dir.resolve()):
        return "not a file in the run folder"
    return None if full.is_file() else "not written"


def _mcap_link(d: RunData, rel: Any, page_dir: Path) -> str:
    """A case's recording, linked so that it works from a page in ``page_dir``: a link
    only to a file inside the run folder (the row may have been tampered with);
    anything else is shown as text."""
    if not isinstance(rel, str) or not rel:
        return "–"
    why = _inside(d.run_dir, rel)
    if why is not None:
        return f'{escape(rel)} <span class="muted">({why})</span>'
    href = quote(Path(os.path.relpath((d.run_dir / rel).resolve(), page_dir.resolve())).as_posix())
    return f'<a href="{escape(href)}">{escape(rel)}</a>'


def cases_section(d: RunData, *, page_dir: Path | None = None) -> str:
    """HTML of the corner-case section (says so when there are none); links relative
    to ``page_dir``, the folder of the page (default: the run folder)."""
    page_dir = d.run_dir if page_dir is None else page_dir
    out = ['<h2 id="cases">Corner cases</h2>']
    db = find_db(d.run_dir)
    if db is None:
        return "".join(out) + "<p>no corner cases recorded</p>"
    try:
        rows = read_cases(db)
    except sqlite3.Error as err:
        return "".join(out) + f'<div class="note warn">{escape(db.name)} cannot be read: {escape(str(err))}</div>'
    if not rows:
        return "".join(out) + f"<p>no corner cases recorded ({escape(db.name)} is empty)</p>"
    n = len(rows)
    out.append(f'<p class="muted">{n} case{"s" if n != 1 else ""} in {escape(str(db.relative_to(d.run_dir)))}'
               + (f"; the first {MAX_ROWS} are shown" if n > MAX_ROWS else "")
               + ". Each links to its recording (open it in Foxglove with hil_configs/foxglove_layout.json).</p>")
    rows = rows[:MAX_ROWS]
    head = ["case", "kind", "vehicle", "sim time (s)", "severity", "cause", "events", "summary", "recording"]
    body = []
    for i, r in enumerate(rows):
        t = r.get("sim_time_ns")
        ev = r.get("events")
        body.append([f'<a href="#case-{escape(str(r.get("id", i)))}">{escape(str(r.get("id", i)))}</a>',
                     escape(str(r.get("kind") or "–")), escape(str(r.get("vehicle") or "–")),
                     f"{t / 1e9:.3f}" if isinstance(t, (int, float)) else "–",
                     escape(str(r.get("severity") or "–")), escape(str(r.get("cause") or "–")),
                     str(ev) if isinstance(ev, int) else "–", escape(str(r.get("summary") or "–")),
                     _mcap_link(d, r.get("mcap_path"), page_dir)])
    h = "".join(f"<th>{escape(c)}</th>" for c in head)
    out.append(f"<table><tr>{h}</tr>" + "".join("<tr>" + "".join(f"<td>{c}</td>" for c in b) + "</tr>"
                                                for b in body) + "</table>")
    run_end_s = None if d.summary is None else d.summary.sim_time_s
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
            pic = img_tag(img[0], img[1], width=_THUMB_W, alt=f"camera frame of case {r.get('id', i)}")
        elif i < MAX_THUMBNAILS:
            pic = f'<div class="muted" style="width:{_THUMB_W}px">no camera frame recorded near this time</div>'
        else:
            pic = ""
        cells = []
        for k in _SHOWN:
            v = r.get(k)
            if k == "sim_time_ns":
                cells.append(("sim time", f"{v / 1e9:.3f} s" if isinstance(v, (int, float)) else "–"))
            elif k == "mcap_path":
                cells.append(("recording", _mcap_link(d, v, page_dir)))
            else:
                cells.append((k, "–" if v is None else escape(str(v))))
        for k, v in r.items():
            if k in _SHOWN or k == "id":
                continue
            if k == "harness_time_ns" and isinstance(v, (int, float)):
                cells.append(("time since first frame (s)", f"{(v - d.t_start_ns) / 1e9:.3f}"))
            elif k == "window_end_ns" and isinstance(v, (int, float)) and run_end_s is not None \
                    and v / 1e9 > run_end_s:  # asked for after_s past the trigger; the run ended first
                cells.append(("window end (s)", f"{run_end_s:.3f} (the run's end; asked {v / 1e9:.3f})"))
            elif k.endswith("_ns") and isinstance(v, (int, float)):
                cells.append((k[:-3].replace("_", " ") + " (s)", f"{v / 1e9:.3f}"))
            elif k == "event" and isinstance(v, str):
                cells.append(("event", _event_cells(v, d.t_start_ns)))
            else:
                cells.append((k, "–" if v is None else escape(str(v))))
        table = "<table>" + "".join(f"<tr><th>{escape(k)}</th><td>{v}</td></tr>" for k, v in cells) + "</table>"
        out.append(f'<div class="case" id="case-{escape(str(r.get("id")))}">{pic}<div><b>case '
                   f'{escape(str(r.get("id", i)))}</b>{table}</div></div>')
    return "".join(out)


def _event_cells(text: str, t_start_ns: int) -> str:
    """A case's event (JSON) in words (:mod:`hil.harness.record.event_text`): its value
    against its threshold, cause, frames and its own fields (a mismatch's evidence) whole;
    its harness time as seconds since the first frame."""
    try:
        ev = json.loads(text)
    except ValueError:
        return escape(text)
    if not isinstance(ev, dict):
        return escape(text)
    parts = [p for p in (et.value_vs_threshold(ev), et.cause(ev)) if p != "–"]
    if et.frames(ev) != "–":
        parts.append(f"frames {et.frames(ev)}")
    if isinstance(ev.get("sim_time_ns"), int):
        parts.append(f"sim time {ev['sim_time_ns'] / 1e9:.3f} s")
    if isinstance(ev.get("harness_time_ns"), int):
        parts.append(f"{(ev['harness_time_ns'] - t_start_ns) / 1e9:.3f} s since the first frame")
    if isinstance(ev.get("links"), list) and ev["links"]:
        parts.append("linked: " + ", ".join(str(x) for x in ev["links"]))
    parts += et.extra_fields(ev)
    return "<br>".join(escape(p) for p in parts)


__all__ = ["case_for_event", "cases_section", "find_db", "img_tag", "read_case_rows", "read_cases",
           "thumbnail_for_case"]
