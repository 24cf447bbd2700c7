"""A vehicle's camera rig in the run report (issue 31): camera by camera and per frame set.

From ``summary.json`` (``vehicles.<V>.cameras`` and ``vehicles.<V>.rig``, written by
``hil.timing.rig.RigTracker``), so the page says what the summary says; nothing for a
vehicle with one camera (no ``rig`` in its summary).
"""

from __future__ import annotations

from html import escape
from typing import Any

from hil.harness.report.tables import kv_table, ms, table

_CAMERA_HEAD = ["camera", "frames", "late frames", "sets without it", "render p50 (ms)",
                "capture→send p50 (ms)", "end-to-end p50 (ms)"]


def rig_html(vehicle: dict[str, Any]) -> str:
    """The per-camera table and the frame-set figures of one vehicle's summary
    (``summary.json``'s ``vehicles.<V>``); ``""`` without a rig."""
    rig, cameras = vehicle.get("rig"), vehicle.get("cameras")
    if not isinstance(rig, dict) or not isinstance(cameras, dict):
        return ""
    rows = [[escape(str(name)), _count(c.get("frames")), _count(c.get("late_frames")),
             _count(c.get("missing_in_sets")), ms(c.get("render_p50_ms")), ms(c.get("capture_to_send_p50_ms")),
             ms(c.get("end_to_end_p50_ms"))] for name, c in cameras.items() if isinstance(c, dict)]
    th = rig.get("thresholds") or {}
    sets = [("frame sets", _count(rig.get("sets"))),
            ("complete (every camera answered)", _count(rig.get("complete"))),
            ("desynced", _count(rig.get("desynced"))),
            ("capture skew max (ms)", f"{ms(rig.get('capture_skew_ms_max'))} (limit {ms(th.get('skew_ms'))})"),
            ("arrival spread p50 / max (ms)", f"{ms(rig.get('arrival_spread_ms_p50'))} / "
                                              f"{ms(rig.get('arrival_spread_ms_max'))} "
                                              f"(limit {ms(th.get('spread_ms'))})"),
            ("end-to-end from first capture p50 (ms)", ms(rig.get("e2e_from_first_capture_ms_p50"))),
            ("end-to-end from last capture p50 (ms)", ms(rig.get("e2e_from_last_capture_ms_p50")))]
    return ('<h4>Camera rig</h4><p class="muted">Each camera\'s frames (late: handed to the link later than the '
            "frame tolerance after its capture) and stage medians; a frame set is one trigger of every camera, "
            "measured on the harness clock alone.</p>" + table(_CAMERA_HEAD, rows) + kv_table(sets))


def _count(v: Any) -> str:
    return str(v) if isinstance(v, int) and not isinstance(v, bool) else "–"


__all__ = ["rig_html"]
