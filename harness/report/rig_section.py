"""A vehicle's camera rig in the run report (issue 31): camera by camera and per frame set.

From ``summary.json`` (``vehicles.<V>.cameras`` and ``vehicles.<V>.rig``, written by
``hil.timing.rig.RigTracker``), so the page says what the summary says; nothing for a
vehicle with one camera (no ``rig`` in its summary).
"""

from __future__ import annotations

from html import escape

from hil.harness.report.tables import kv_table, ms, table
from hil.harness.vocab.figures import VehicleFigures

_CAMERA_HEAD = ["camera", "frames", "late frames", "sets without it", "render p50 (ms)",
                "capture→send p50 (ms)", "end-to-end p50 (ms)"]


def rig_html(vehicle: VehicleFigures | None) -> str:
    """The per-camera table and the frame-set figures of one vehicle's summary
    (``summary.json``'s ``vehicles.<V>``); ``""`` without a rig."""
    rig = None if vehicle is None else vehicle.rig
    if vehicle is None or rig is None:
        return ""
    rows = [[escape(name), str(c.frames), str(c.late_frames), str(c.missing_in_sets),
             ms(c.stage_p50_ms.get("render")), ms(c.stage_p50_ms.get("capture_to_send")),
             ms(c.stage_p50_ms.get("end_to_end"))] for name, c in vehicle.cameras.items()]
    th = rig.thresholds
    sets = [("frame sets", str(rig.sets)), ("complete (every camera answered)", str(rig.complete)),
            ("desynced", str(rig.desynced)),
            ("capture skew max (ms)", f"{ms(rig.capture_skew_ms_max)} (limit {ms(th.get('skew_ms'))})"),
            ("arrival spread p50 / max (ms)", f"{ms(rig.arrival_spread_ms_p50)} / {ms(rig.arrival_spread_ms_max)} "
                                              f"(limit {ms(th.get('spread_ms'))})"),
            ("end-to-end from first capture p50 (ms)", ms(rig.e2e_from_first_capture_ms_p50)),
            ("end-to-end from last capture p50 (ms)", ms(rig.e2e_from_last_capture_ms_p50))]
    return ('<h4>Camera rig</h4><p class="muted">Each camera\'s frames (late: handed to the link later than the '
            "frame tolerance after its capture) and stage medians; a frame set is one trigger of every camera, "
            "measured on the harness clock alone.</p>" + table(_CAMERA_HEAD, rows) + kv_table(sets))

__all__ = ["rig_html"]
