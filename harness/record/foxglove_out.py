"""Foxglove views of a run, so ``run.mcap`` opens in Foxglove with cameras, overlays,
3D scene, latency plots and a log.

Written from the analysis thread (:func:`write`): every entity as a cube in
``/scene`` (``foxglove.SceneUpdate``, frame ``world``) and every vehicle's pose as a
``foxglove.FrameTransform`` (``world`` → ``<vehicle>``) in ``/tf``.

Derived on the recorder's writer thread (:class:`FoxgloveViews`, installed by
:func:`hil.harness.record.channels.register_all`), from the hil.* messages, so they cost the
producers nothing:

- ``/<V>/camera_info`` ``foxglove.CameraCalibration`` and, on ``/tf``, ``<V>`` →
  ``<V>/camera_ground`` (the AI's object frame: on the road under the camera) →
  ``<V>/camera`` (the optical frame of the images), at each ``/ground_truth``;
- ``/<V>/annotations`` ``foxglove.ImageAnnotations``: the true visible boxes (green)
  and the AI's boxes (magenta), labelled with class and distance, stamped with the
  frame's image timestamp, written when the frame's answer (or its drop) and, with
  ``truth.visible_boxes``, its camera truth are known (the truth, rendered after the
  frame, often comes after a quick answer); a rig's other cameras each on
  ``/<V>/annotations/<name>`` from ``/<V>/truth/<name>``
  (the AI's boxes on the camera their ``camera`` names; a fused set's answer draws
  every frame of the set);
- ``/<V>/estimate_scene`` ``foxglove.SceneUpdate``: the AI's objects as spheres in
  ``<V>/camera_ground``, beside the true cubes of ``/scene``;
- ``/<V>/latency`` ``hil.Latency``: stage latencies of each frame in ms (Plot panel);
- ``/log`` ``foxglove.Log``: every ``/events`` message as a line people read
  (:func:`hil.harness.record.event_text.event_line`; level from its severity).

Foxglove times (``timestamp`` fields) are on the recorder's wall-clock timeline
(monotonic + ``offset_ns``), as ``log_time`` is.
"""

from __future__ import annotations

import math
from collections import OrderedDict
from collections.abc import Iterable, Mapping
from typing import Any

import numpy as np

from hil.harness.record import foxglove_schemas as fx
from hil.harness.record.event_text import event_line
from hil.harness.record.rig_views import (RigView, annotations_topic, calibration, calibration_topic, camera_topic,
                                          truth_topic)
from hil.scenarios.ground_truth import GroundTruth

# Colours by class (RGBA 0..1); ego vehicles blue as in the render.
_COLOURS = {"vehicle": (0.8, 0.15, 0.1, 0.9), "pedestrian": (1.0, 0.6, 0.0, 0.9), "obstacle": (0.6, 0.6, 0.6, 0.9)}
_EGO = (0.1, 0.25, 0.8, 0.9)
TRUTH_RGBA = (0.15, 0.95, 0.25, 1.0)   # true boxes: green
AI_RGBA = (1.0, 0.2, 0.85, 1.0)        # the AI's boxes: magenta
_WHITE = {"r": 1.0, "g": 1.0, "b": 1.0, "a": 1.0}
_BACKDROP = {"r": 0.0, "g": 0.0, "b": 0.0, "a": 0.6}
_LEVEL = {"info": fx.LOG_INFO, "warning": fx.LOG_WARNING, "critical": fx.LOG_ERROR}
_PENDING_FRAMES = 256  # truth boxes kept per vehicle while the frame's answer is awaited
_ESTIMATE_LIFETIME_NS = 300_000_000
# A frame's annotations before its truth: (topic, t0 ns, AI objects, note, log time, publish time).
_Drawing = tuple[str, int, list[dict[str, Any]], str, int, int]

LATENCY = {"$schema": "https://json-schema.org/draft/2020-12/schema", "title": "hil.Latency", "type": "object",
           "description": "Latency of one frame (ms); stages as in hil.PipelineRecord.stages_ns",
           "properties": {"frame_id": {"type": "integer"}, "status": {"type": "string"},
                          "sim_time_s": {"type": ["number", "null"]},
                          "deadline_ms": {"type": ["number", "null"], "description": "end-to-end deadline"},
                          "stages_ms": {"type": "object", "additionalProperties": {"type": "number"}}},
           "required": ["frame_id", "status", "stages_ms"]}


def yaw_quaternion(yaw: float) -> tuple[float, float, float, float]:
    return (0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2))


def _rgba(c: tuple[float, float, float, float]) -> dict[str, float]:
    return dict(zip("rgba", c))


def _offset(rec: Any) -> int:
    """The wall-clock offset of ``rec`` (a Recorder, or a stand-in wrapping one as ``rec``)."""
    inner = getattr(rec, "rec", rec)
    return int(getattr(inner, "log_time_offset_ns", 0))


def register(rec: Any) -> None:
    rec.register_json_channel("/scene", fx.SCENE_UPDATE, fx.scene_update_schema())
    rec.register_json_channel("/tf", fx.FRAME_TRANSFORM, fx.frame_transform_schema())
    rec.register_json_channel("/log", fx.LOG, fx.log_schema())


def register_vehicle(rec: Any, v: str) -> None:
    rec.register_json_channel(f"/{v}/camera_info", fx.CAMERA_CALIBRATION, fx.camera_calibration_schema())
    rec.register_json_channel(f"/{v}/annotations", fx.IMAGE_ANNOTATIONS, fx.image_annotations_schema())
    rec.register_json_channel(f"/{v}/estimate_scene", fx.SCENE_UPDATE, fx.scene_update_schema())
    rec.register_json_channel(f"/{v}/latency", "hil.Latency", LATENCY)


def write(rec: Any, gt: GroundTruth, *, egos: set[str], t_ns: int) -> None:
    """One SceneUpdate of every entity and one FrameTransform per vehicle (``t_ns``
    monotonic; the message timestamps are put on the recorder's wall clock)."""
    ts = fx.ns_to_foxglove_time(t_ns + _offset(rec))
    entities = []
    for e in gt.entities:
        rgba = _EGO if e.name in egos else _COLOURS.get(e.cls, _COLOURS["obstacle"])
        q = yaw_quaternion(e.heading_rad)
        length, width, height = e.size_m
        cube = {"pose": fx.pose((e.x_m, e.y_m, 0.1 + height / 2), q),
                "size": {"x": length, "y": width, "z": height},
                "color": dict(zip("rgba", rgba))}
        label = {"pose": fx.pose((e.x_m, e.y_m, 0.3 + height), q), "billboard": True, "font_size": 14.0,
                 "scale_invariant": True, "color": _WHITE, "text": e.name}
        entity = fx.scene_entity(entity_id=e.name, frame_id="world", timestamp_ns=0, cubes=[cube], texts=[label])
        entity["timestamp"] = ts
        entities.append(entity)
        if e.cls == "vehicle":
            rec.write_json("/tf", {"timestamp": ts, "parent_frame_id": "world", "child_frame_id": e.name,
                                   "translation": {"x": e.x_m, "y": e.y_m, "z": 0.0},
                                   "rotation": dict(zip("xyzw", q))}, log_time_ns=t_ns, publish_time_ns=t_ns)
    rec.write_json("/scene", {"deletions": [], "entities": entities}, log_time_ns=t_ns, publish_time_ns=t_ns)


def optical_quaternion(pitch_rad: float) -> tuple[float, float, float, float]:
    """Rotation (x, y, z, w) from a vehicle-aligned frame (+x forward, +y left, +z up)
    to a camera optical frame (+z forward, +x right, +y down) pitched down by
    ``pitch_rad``."""
    r0 = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])  # columns: optical axes
    c, s = math.cos(pitch_rad), math.sin(pitch_rad)
    ry = np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])
    m = ry @ r0
    w = math.sqrt(max(0.0, 1.0 + m[0, 0] + m[1, 1] + m[2, 2])) / 2
    if w > 1e-6:
        return ((m[2, 1] - m[1, 2]) / (4 * w), (m[0, 2] - m[2, 0]) / (4 * w), (m[1, 0] - m[0, 1]) / (4 * w), w)
    # 180-degree rotations do not occur for |pitch| <= 45 degrees (config bound)
    raise ValueError(f"camera pitch {pitch_rad} rad gives a degenerate rotation")


class FoxgloveViews:
    """The derivations listed in the module docstring, for one run. Runs on the
    recorder's writer thread only (its buffers are not locked).

    Args:
        vehicles: the ego vehicles' names.
        camera: the run config's ``camera`` section as JSON (``width``, ``height``,
            ``fovy_deg``, ``mount_*_m``, ``pitch_deg``); ``None``: no calibration.
        offset_ns: the recorder's wall-clock offset (ns).
        deadline_ms: each vehicle's end-to-end deadline (ms), written beside its
            latencies (``/V/latency.deadline_ms``) so a plot can draw it.
        rig: a camera rig's cameras, camera 0 first (:func:`hil.harness.record.rig_views.rig_views`):
            each one's calibration and mount in place of ``camera``'s (None: the one camera).
        truth: every frame sent has a camera truth (``truth.visible_boxes``): a frame's
            annotations wait for it (bounded: beyond ``_PENDING_FRAMES`` frames, drawn
            without it).
    """

    def __init__(self, vehicles: Iterable[str], *, camera: Mapping[str, Any] | None, offset_ns: int,
                 deadline_ms: Mapping[str, float] | None = None, rig: tuple[RigView, ...] | None = None,
                 truth: bool = False) -> None:
        self.vehicles = set(vehicles)
        self.deadline_ms = dict(deadline_ms or {})
        self.offset_ns = offset_ns
        self._truth: dict[str, OrderedDict[int, list[dict[str, Any]]]] = {v: OrderedDict() for v in self.vehicles}
        self._t0: dict[str, OrderedDict[int, int]] = {v: OrderedDict() for v in self.vehicles}
        # A rig's frames awaiting their answer: frame id -> its camera (pipeline ``camera``).
        self._camera: dict[str, OrderedDict[int, int]] = {v: OrderedDict() for v in self.vehicles}
        self.truth = truth
        # Annotations of answered frames whose camera truth is still to come: frame id ->
        # (topic, t0, AI objects, note, log time, publish time).
        self._untruthed: dict[str, OrderedDict[int, _Drawing]] = {v: OrderedDict() for v in self.vehicles}
        self._calib: dict[str, Any] | None = None
        self._mount: tuple[float, float, float, float] | None = None
        self.rig = rig
        if camera is not None and rig is None:
            self._calib = calibration(int(camera["width"]), int(camera["height"]), float(camera["fovy_deg"]))
            self._mount = (float(camera.get("mount_forward_m", 0.0)), float(camera.get("mount_lateral_m", 0.0)),
                           float(camera.get("mount_height_m", 0.0)), math.radians(float(camera.get("pitch_deg", 0.0))))

    def install(self, rec: Any) -> None:
        """Add the derivations to a ``Recorder`` whose topics are registered."""
        rec.add_derivation("/events", self.on_event)
        rec.add_derivation("/ground_truth", self.on_ground_truth)
        for v in sorted(self.vehicles):
            for cam in (self.rig or ())[1:]:
                rec.register_json_channel(calibration_topic(v, cam.name), fx.CAMERA_CALIBRATION,
                                          fx.camera_calibration_schema())
                rec.register_json_channel(annotations_topic(v, cam.name), fx.IMAGE_ANNOTATIONS,
                                          fx.image_annotations_schema())
                rec.add_derivation(truth_topic(v, cam.name), self.on_truth)
            rec.add_derivation(f"/{v}/truth", self.on_truth)
            rec.add_derivation(f"/{v}/pipeline", self.on_pipeline)
            rec.add_derivation(f"/{v}/estimate", lambda m, lt, pt, v=v: self.on_estimate(v, m, lt, pt))

    def _ts(self, t_ns: int) -> dict[str, int]:
        return fx.ns_to_foxglove_time(t_ns + self.offset_ns)

    # -- derivations: (message, log_time_ns, publish_time_ns) -> [(topic, msg, log, pub)] ---------

    def on_event(self, ev: Mapping[str, Any], log_ns: int, pub_ns: int) -> list[tuple[str, Any, int, int]]:
        log = {"timestamp": self._ts(log_ns), "level": _LEVEL.get(str(ev.get("severity")), fx.LOG_INFO),
               "message": event_line(ev), "name": str(ev.get("vehicle") or "harness"), "file": "", "line": 0}
        return [("/log", log, log_ns, pub_ns)]

    def on_ground_truth(self, gt: Mapping[str, Any], log_ns: int, pub_ns: int) -> list[tuple[str, Any, int, int]]:
        if self.rig is not None:
            return self._rig_views(gt, log_ns, pub_ns)
        if self._calib is None or self._mount is None:
            return []
        fwd, lat, height, pitch = self._mount
        ts = self._ts(log_ns)
        q = optical_quaternion(pitch)
        out: list[tuple[str, Any, int, int]] = []
        for e in gt.get("egos", ()):
            v = e.get("vehicle")
            if v not in self.vehicles:
                continue
            out.append(("/tf", {"timestamp": ts, "parent_frame_id": v, "child_frame_id": f"{v}/camera_ground",
                                "translation": {"x": fwd, "y": lat, "z": 0.0},
                                "rotation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0}}, log_ns, pub_ns))
            out.append(("/tf", {"timestamp": ts, "parent_frame_id": f"{v}/camera_ground",
                                "child_frame_id": f"{v}/camera", "translation": {"x": 0.0, "y": 0.0, "z": height},
                                "rotation": dict(zip("xyzw", q))}, log_ns, pub_ns))
            out.append((f"/{v}/camera_info", {"timestamp": ts, "frame_id": f"{v}/camera", **self._calib},
                        log_ns, pub_ns))
        return out

    def _rig_views(self, gt: Mapping[str, Any], log_ns: int, pub_ns: int) -> list[tuple[str, Any, int, int]]:
        """Each rig camera's mount on ``/tf`` and its calibration, per vehicle."""
        ts = self._ts(log_ns)
        out: list[tuple[str, Any, int, int]] = []
        for e in gt.get("egos", ()):
            v = e.get("vehicle")
            if v not in self.vehicles:
                continue
            for cam in self.rig or ():
                out.extend(("/tf", tf, log_ns, pub_ns) for tf in cam.transforms(v, ts))
                frame = camera_topic(v, cam.name)[1:]  # the optical frame is named as the image topic
                out.append((calibration_topic(v, cam.name), {"timestamp": ts, "frame_id": frame, **cam.calib},
                            log_ns, pub_ns))
        return out

    def on_truth(self, ct: Mapping[str, Any], log_ns: int, pub_ns: int) -> list[tuple[str, Any, int, int]]:
        v = ct.get("vehicle")
        pending = self._truth.get(str(v))
        if pending is None:
            return []
        frame, boxes = int(ct["frame_id"]), list(ct.get("boxes", ()))
        drawing = self._untruthed[str(v)].pop(frame, None)
        if drawing is not None:  # answered already: drawn now
            return [self._drawn(drawing, boxes)]
        pending[frame] = boxes
        while len(pending) > _PENDING_FRAMES:
            pending.popitem(last=False)
        return []

    def _draw(self, v: str, frame: int, drawing: _Drawing) -> list[tuple[str, Any, int, int]]:
        """Frame ``frame``'s annotations, now if its truth is here (or none comes), else
        once it does."""
        boxes = self._truth[v].pop(frame, None)
        if boxes is not None or not self.truth:
            return [self._drawn(drawing, boxes or [])]
        waiting = self._untruthed[v]
        waiting[frame] = drawing
        out = []
        while len(waiting) > _PENDING_FRAMES:  # its truth never came: drawn without it
            out.append(self._drawn(waiting.popitem(last=False)[1], []))
        return out

    def _drawn(self, d: _Drawing, boxes: list[dict[str, Any]]) -> tuple[str, Any, int, int]:
        topic, t0, objects, note, log_ns, pub_ns = d
        return topic, self._annotations(t0, boxes, objects, note=note), log_ns, pub_ns

    def on_pipeline(self, rec: Mapping[str, Any], log_ns: int, pub_ns: int) -> list[tuple[str, Any, int, int]]:
        v, frame = str(rec.get("vehicle")), int(rec["frame_id"])
        stages = rec.get("stages_ns") or {}
        sim = rec.get("sim_time_ns")
        out: list[tuple[str, Any, int, int]] = [(f"/{v}/latency", {
            "frame_id": frame, "status": rec.get("status"),
            "sim_time_s": sim / 1e9 if isinstance(sim, int) else None, "deadline_ms": self.deadline_ms.get(v),
            "stages_ms": {k: ns / 1e6 for k, ns in stages.items() if isinstance(ns, (int, float))}},
            log_ns, pub_ns)]
        t0s = self._t0.get(v)
        if t0s is None:
            return out
        camera = rec.get("camera")
        if rec.get("status") != "dropped":
            t0s[frame] = int(rec["t0_ns"])  # the estimate follows: it draws the overlay
            while len(t0s) > _PENDING_FRAMES:
                t0s.popitem(last=False)
            if isinstance(camera, int):
                cams = self._camera[v]
                cams[frame] = camera
                while len(cams) > _PENDING_FRAMES:
                    cams.popitem(last=False)
        else:  # no answer: the truth alone, labelled
            out += self._draw(v, frame, (self._annotations_topic(v, camera if isinstance(camera, int) else 0),
                                         int(rec["t0_ns"]), [], f"frame {frame}: no answer ({rec.get('status')})",
                                         log_ns, pub_ns))
        return out

    def _annotations_topic(self, v: str, camera: int) -> str:
        rig = self.rig or ()
        return annotations_topic(v, rig[camera].name if 0 < camera < len(rig) else None)

    def _answered(self, v: str, frame: int) -> list[tuple[int, int]]:
        """(frame id, camera) of each frame an estimate of ``frame`` answers: that one,
        and for a fused set's answer (``frame`` its set id) the set's other frames."""
        cams = self._camera[v]
        out = [(frame, cams.pop(frame, 0))]
        for k in range(1, len(self.rig or ())):
            if cams.get(frame + k) == k:
                out.append((frame + k, cams.pop(frame + k)))
        return out

    def on_estimate(self, v: str, m: Mapping[str, Any], log_ns: int, pub_ns: int) -> list[tuple[str, Any, int, int]]:
        frame = int(m["frame_id"])
        objects = list(m.get("objects", ()))
        out: list[tuple[str, Any, int, int]] = []
        for f, k in self._answered(v, frame):
            mine = objects if self.rig is None else [o for o in objects if o.get("camera", 0) == k]
            out += self._draw(v, f, (self._annotations_topic(v, k), self._t0[v].pop(f, log_ns), mine,
                                     f"frame {f}: AI {m.get('state')}", log_ns, pub_ns))
        entities = []
        for i, o in enumerate(objects):
            x, y, z = (list(o.get("position_m") or (0.0, 0.0, 0.0)) + [0.0, 0.0, 0.0])[:3]
            ent = fx.scene_entity(entity_id=f"{v}/ai/{i}", frame_id=f"{v}/camera_ground", timestamp_ns=0,
                                  lifetime_ns=_ESTIMATE_LIFETIME_NS, spheres=[{
                                      "pose": fx.pose((x, y, z + 0.5)), "size": {"x": 1.0, "y": 1.0, "z": 1.0},
                                      "color": _rgba(AI_RGBA[:3] + (0.7,))}],
                                  texts=[{"pose": fx.pose((x, y, z + 1.4)), "billboard": True, "font_size": 13.0,
                                          "scale_invariant": True, "color": _rgba(AI_RGBA),
                                          "text": f"AI {o.get('cls', '?')} {math.hypot(x, y):.1f} m"}])
            ent["timestamp"] = self._ts(log_ns)
            entities.append(ent)
        out.append((f"/{v}/estimate_scene", {"deletions": [], "entities": entities}, log_ns, pub_ns))
        return out

    def _annotations(self, t0_ns: int, boxes: list[dict[str, Any]], objects: list[dict[str, Any]], *,
                     note: str) -> dict[str, Any]:
        ts = self._ts(t0_ns)
        points, texts = [], []
        for b in boxes:
            x0, y0, x1, y1 = (float(c) for c in b.get("box_px", (0, 0, 0, 0)))
            points.append(_box(ts, x0, y0, x1, y1, TRUTH_RGBA))
            dist = b.get("path_s_m")
            d = f" {dist:.1f} m" if isinstance(dist, (int, float)) else ""
            texts.append(_label(ts, x0, y1 + 12.0, f"truth {b.get('cls', '?')}{d}", TRUTH_RGBA))
        for o in objects:
            x0, y0, x1, y1 = (float(c) for c in o.get("box_px", (0, 0, 0, 0)))
            points.append(_box(ts, x0, y0, x1, y1, AI_RGBA))
            pos = o.get("position_m") or (0.0, 0.0)
            conf = o.get("confidence")
            c = f" {conf:.0%}" if isinstance(conf, (int, float)) else ""
            texts.append(_label(ts, x0, max(12.0, y0 - 2.0),
                                f"AI {o.get('cls', '?')} {math.hypot(pos[0], pos[1]):.1f} m{c}", AI_RGBA))
        texts.append(_label(ts, 4.0, 14.0, note, (1.0, 1.0, 1.0, 1.0)))
        return {"circles": [], "points": points, "texts": texts}


def _box(ts: dict[str, int], x0: float, y0: float, x1: float, y1: float,
         rgba: tuple[float, float, float, float]) -> dict[str, Any]:
    return {"timestamp": ts, "type": fx.POINTS_LINE_LOOP,
            "points": [{"x": x0, "y": y0}, {"x": x1, "y": y0}, {"x": x1, "y": y1}, {"x": x0, "y": y1}],
            "outline_color": _rgba(rgba), "outline_colors": [], "fill_color": _rgba(rgba[:3] + (0.0,)),
            "thickness": 2.0}


def _label(ts: dict[str, int], x: float, y: float, text: str, rgba: tuple[float, float, float, float]) -> dict[str, Any]:
    return {"timestamp": ts, "position": {"x": x, "y": y}, "text": text, "font_size": 12.0,
            "text_color": _rgba(rgba), "background_color": _BACKDROP}

