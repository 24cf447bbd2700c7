"""The JSON-schema channels of ``run.mcap``: one place that names every topic.

Topics per vehicle ``V``: ``/V/camera`` (foxglove.CompressedImage or RawImage; a rig's
other cameras ``/V/camera/<name>``, :mod:`hil.harness.record.rig_views`),
``/V/estimate``, ``/V/pipeline``, ``/V/clock_sync``, ``/V/truth`` (the camera's
visible boxes; a rig's other cameras ``/V/truth/<name>``); shared: ``/ground_truth``
and ``/events``; and the Foxglove views of :mod:`hil.harness.record.foxglove_out`
(``/scene``, ``/tf``, ``/log``, ``/V/camera_info`` and a rig's ``/V/camera_info/<name>``,
``/V/annotations`` and a rig's ``/V/annotations/<name>``, ``/V/estimate_scene``,
``/V/latency``). ``log_time`` is always
the harness clock (receipt or capture), shifted onto the wall clock by the
recorder's time anchor (metadata ``time_anchor``);
``publish_time`` the source's time (``t0`` for frames and records, the target's
``t_reply`` for estimates, ``t1`` for clock-sync samples).
"""

from __future__ import annotations

import json
import sys
from collections.abc import Iterable
from typing import Any

from hil.harness.vocab.events import EVENT_SCHEMA
from hil.harness.record import foxglove_out
from hil.harness.record.recorder import Recorder, TimeAnchor
from hil.harness.record.rig_views import rig_views, truth_topic
from hil.timing.sync import SyncSample


def _obj(title: str, props: dict[str, Any], required: Iterable[str] = ()) -> dict[str, Any]:
    return {"$schema": "https://json-schema.org/draft/2020-12/schema", "title": title,
            "type": "object", "properties": props, "required": list(required)}


_INT = {"type": "integer"}
_NUM = {"type": "number"}
_NINT = {"type": ["integer", "null"]}

ESTIMATE = _obj("hil.Estimate", {
    "frame_id": _INT, "state": {"enum": ["SAFE", "SLOW", "STOP"]},
    "control": _obj("hil.Control", {"steering_rad": _NUM, "throttle": _NUM, "brake": _NUM}),
    "objects": {"type": "array", "items": _obj("hil.DetectedObject", {
        "cls": {"type": "string"}, "confidence": _NUM,
        "box_px": {"type": "array", "items": _NUM}, "position_m": {"type": "array", "items": _NUM},
        "camera": {"type": "integer", "description": "the rig camera whose image box_px is in (absent: 0)"}})},
}, ["frame_id", "state", "control", "objects"])

PIPELINE = _obj("hil.PipelineRecord", {
    "vehicle": {"type": "string"}, "frame_id": _INT, "status": {"enum": ["ok", "dropped", "stale", "pending"]},
    "sim_time_ns": _INT, "t0_ns": _INT, "t_tx_ns": _INT, "t_rx_target_ns": _NINT,
    "t_infer_start_target_ns": _NINT, "t_infer_end_target_ns": _NINT, "t_reply_target_ns": _NINT,
    "t0p_ns": _NINT, "t_apply_ns": _NINT, "sim_time_apply_ns": _NINT, "t_state_ns": _NINT,
    "t0p_uncertainty_ns": _INT, "stages_ns": {"type": "object", "additionalProperties": _INT}, "render_worker": _INT,
}, ["vehicle", "frame_id", "status", "t0_ns", "t_tx_ns"])

CLOCK_SYNC = _obj("hil.ClockSyncSample", {
    "seq": _INT, "t1_ns": _INT, "t2_target_ns": _INT, "t3_target_ns": _INT, "t4_ns": _INT,
    "offset_ns": _NUM, "delay_ns": _INT, "warmup": {"type": "boolean"}})

_EGO_TRUTH = _obj("hil.EgoTruth", {
    "vehicle": {"type": "string"}, "gap_m": {"type": ["number", "null"]},
    "obstacle": {"type": ["string", "null"]}, "speed_mps": _NUM,
    "ref_state": {"enum": ["SAFE", "SLOW", "STOP"]}, "obstacle_speed_mps": _NUM,
    "ttc_s": {"type": ["number", "null"]}})

# entities: every entity's state in the first record ("initial"), then only those that changed.
GROUND_TRUTH = _obj("hil.GroundTruth", {
    "sim_time_ns": _INT, "initial": {"type": "boolean"},
    "entities": {"type": "array", "items": _obj("hil.EntityState", {
        "id": _INT, "name": {"type": "string"}, "cls": {"type": "string"}, "x_m": _NUM, "y_m": _NUM,
        "vx_mps": _NUM, "vy_mps": _NUM, "heading_rad": _NUM, "size_m": {"type": "array", "items": _NUM},
        "sim_time_ns": _INT})},
    "egos": {"type": "array", "items": _EGO_TRUTH},
    "collisions": {"type": "array", "items": _obj("hil.Collision", {
        "sim_time_ns": _INT, "a": {"type": "string"}, "b": {"type": "string"}, "force_n": _NUM,
        "closing_speed_mps": _NUM, "striker": {"type": ["string", "null"]}})},
}, ["sim_time_ns", "entities", "egos"])

CAMERA_TRUTH = _obj("hil.CameraTruth", {
    "vehicle": {"type": "string"}, "frame_id": _INT, "sim_time_ns": _INT,
    "boxes": {"type": "array", "items": _obj("hil.VisibleBox", {
        "entity": {"type": "string"}, "id": _INT, "cls": {"type": "string"},
        "box_px": {"type": "array", "items": _INT}, "visible_px": _INT, "visible_fraction": _NUM,
        "truncated": {"type": "boolean"}, "path_s_m": _NUM, "path_lateral_m": _NUM})},
    "ego": _EGO_TRUTH,
}, ["vehicle", "frame_id", "sim_time_ns", "boxes", "ego"])

# Every event (hil.harness.vocab.events): the promised fields, then its kind's extras.
EVENT = _obj("hil.Event", EVENT_SCHEMA["properties"], EVENT_SCHEMA["required"])


CLOCK_STATE = _obj("hil.ClockState", {
    "offset_ns": _INT, "ref_ns": _INT, "skew_ppm": _NUM, "skew_uncertainty_ppm": _NUM,
    "uncertainty_ns": _INT, "delay_ns": _NINT, "samples_used": _INT, "synced": {"type": "boolean"}},
    ["offset_ns", "skew_ppm", "uncertainty_ns", "synced"])


def sync_sample_json(s: SyncSample, *, warmup: bool = False) -> dict[str, Any]:
    """The ``/<vehicle>/clock_sync`` message of one exchange."""
    return {"seq": s.seq, "t1_ns": s.t1_ns, "t2_target_ns": s.t2_target_ns, "t3_target_ns": s.t3_target_ns,
            "t4_ns": s.t4_ns, "offset_ns": s.offset_ns, "delay_ns": s.delay_ns, "warmup": warmup}


def register_all(rec: Any, vehicles: Iterable[str], *, anchor: TimeAnchor | None = None,
                 views: bool = True) -> None:
    """Declare every JSON channel of a run; put the recording on the wall clock
    (``anchor``, captured now if not given; skipped if messages were already
    written) and install the Foxglove views (:class:`hil.harness.record.foxglove_out.FoxgloveViews`;
    the camera calibration comes from the recorder's ``config`` metadata); with
    ``recording.live`` in that config, start the live view (harness/record/live.py) on the
    recorder's writer thread and print its address on stderr.

    ``rec`` may be a stand-in wrapping the Recorder as ``rec.rec`` (CaseRecorder):
    the anchor and the derivations go to the Recorder itself.
    """
    vehicles = list(vehicles)
    inner = getattr(rec, "rec", rec)
    rec.register_json_channel("/ground_truth", "hil.GroundTruth", GROUND_TRUTH)
    rec.register_json_channel("/events", "hil.Event", EVENT)
    foxglove_out.register(rec)
    for v in vehicles:
        rec.register_json_channel(f"/{v}/estimate", "hil.Estimate", ESTIMATE)
        rec.register_json_channel(f"/{v}/pipeline", "hil.PipelineRecord", PIPELINE)
        rec.register_json_channel(f"/{v}/clock_sync", "hil.ClockSyncSample", CLOCK_SYNC)
        rec.register_json_channel(f"/{v}/clock", "hil.ClockState", CLOCK_STATE)
        rec.register_json_channel(f"/{v}/truth", "hil.CameraTruth", CAMERA_TRUTH)
        foxglove_out.register_vehicle(rec, v)
    if not isinstance(inner, Recorder):
        return
    if inner.stats.enqueued == 0:
        inner.set_time_anchor(anchor or TimeAnchor.capture())
    cfg = _run_config(inner)
    cam = cfg.get("camera")
    rig = (rig_views(cam) if isinstance(cam, dict) else None) or ()
    for v in vehicles:  # a rig's other cameras' truth (the views draw it on their annotations)
        for view in rig[1:]:
            rec.register_json_channel(truth_topic(v, view.name), "hil.CameraTruth", CAMERA_TRUTH)
    if views:
        views_of(cfg, vehicles, offset_ns=inner.log_time_offset_ns).install(inner)
    recording = cfg.get("recording") or {}
    if recording.get("live") is True:
        from hil.harness.record.live import DEFAULT_HOST, LiveView
        from hil.harness.record.live_front import split_address

        address = recording.get("live_address")
        host, port = split_address(address) if isinstance(address, str) else (DEFAULT_HOST, 0)
        live = LiveView(host=host, port=port)
        inner.add_tap("live_view", live)
        print(f"live view: {live.url} (Foxglove: Open connection -> Foxglove WebSocket; "
              "layout hil_configs/foxglove_layout.json)", file=sys.stderr, flush=True)


def views_of(cfg: dict[str, Any], vehicles: list[str], *, offset_ns: int) -> foxglove_out.FoxgloveViews:
    """The Foxglove views of ``vehicles`` under the run config ``cfg`` (as JSON):
    the camera calibration, each one's end-to-end deadline, and whether its frames
    have camera truth (``truth.visible_boxes``, default on)."""
    cam = cfg.get("camera")
    ok = isinstance(cam, dict) and all(k in cam for k in ("width", "height", "fovy_deg"))
    truth = cfg.get("truth")
    boxes = truth.get("visible_boxes") if isinstance(truth, dict) else None
    return foxglove_out.FoxgloveViews(vehicles, camera=cam if ok else None, offset_ns=offset_ns,
                                      deadline_ms=_deadlines(cfg, vehicles),
                                      rig=rig_views(cam) if isinstance(cam, dict) else None, truth=boxes is not False)


def _deadlines(cfg: dict[str, Any], vehicles: list[str]) -> dict[str, float]:
    """Each vehicle's end-to-end deadline (ms) under the run's timing config."""
    from hil.harness.config.timing import TimingConfig

    try:
        timing = TimingConfig.model_validate(cfg.get("timing") or {})
    except ValueError:
        return {}
    out = {}
    for v in vehicles:
        ms = timing.thresholds_for(v).deadline_ms.get("end_to_end")
        if ms is not None:
            out[v] = float(ms)
    return out


def _run_config(rec: Recorder) -> dict[str, Any]:
    """The run config in the recorder's ``config`` metadata (empty if none)."""
    meta = rec.metadata_record("config") or {}
    try:
        cfg = json.loads(meta["yaml_json"])
    except (KeyError, ValueError, TypeError):
        return {}
    return cfg if isinstance(cfg, dict) else {}
