"""Foxglove-native recordings: the wall-clock anchor, the derived Foxglove views,
and every ``foxglove.*`` message checked against the official foxglove-sdk message
types (built field by field: an unknown field or a wrong type raises)."""

from __future__ import annotations

import json
import math
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from mcap.reader import make_reader

from hil.common.errors import ConfigError
from hil.harness.record import foxglove_out
from hil.harness.record.channels import register_all
from hil.harness.record.recorder import Recorder, TimeAnchor

ANCHOR = TimeAnchor(realtime_ns=1_795_000_000_000_000_000, monotonic_ns=2_000_000_000)
CAMERA = {"width": 320, "height": 240, "fovy_deg": 60.0, "mount_forward_m": 2.3, "mount_lateral_m": 0.0,
          "mount_height_m": 1.3, "pitch_deg": 5.0}


def _messages(path: Path) -> Iterator[tuple[str, str, Any, Any]]:
    with open(path, "rb") as f:
        for schema, channel, msg in make_reader(f).iter_messages():
            yield channel.topic, schema.name, msg, json.loads(msg.data)


# --- the official types (foxglove-sdk) ------------------------------------------

# field name -> SDK class name, for fields holding a nested message
_NESTED = {"translation": "Vector3", "rotation": "Quaternion", "orientation": "Quaternion", "position": None,
           "outline_color": "Color", "fill_color": "Color", "text_color": "Color", "background_color": "Color",
           "color": "Color", "pose": "Pose", "size": "Vector3"}
_LISTS = {("ImageAnnotations", "points"): "PointsAnnotation", ("ImageAnnotations", "texts"): "TextAnnotation",
          ("ImageAnnotations", "circles"): "CircleAnnotation", ("PointsAnnotation", "points"): "Point2",
          ("PointsAnnotation", "outline_colors"): "Color", ("SceneUpdate", "entities"): "SceneEntity",
          ("SceneUpdate", "deletions"): "SceneEntityDeletion", ("SceneEntity", "cubes"): "CubePrimitive",
          ("SceneEntity", "spheres"): "SpherePrimitive", ("SceneEntity", "texts"): "TextPrimitive",
          ("SceneEntity", "arrows"): "ArrowPrimitive", ("SceneEntity", "lines"): "LinePrimitive",
          ("SceneEntity", "cylinders"): "CylinderPrimitive", ("SceneEntity", "metadata"): "KeyValuePair",
          ("SceneEntity", "triangles"): "TriangleListPrimitive", ("SceneEntity", "models"): "ModelPrimitive"}
_ENUMS = {("PointsAnnotation", "type"): "PointsAnnotationType", ("Log", "level"): "LogLevel"}


def to_sdk(type_name: str, d: dict[str, Any]) -> Any:
    """``d`` (a JSON message) built as foxglove-sdk's ``type_name``; raises
    ``TypeError`` on an unknown field or a wrong type."""
    fm = pytest.importorskip("foxglove.messages")
    kwargs: dict[str, Any] = {}
    for k, v in d.items():
        if k in ("timestamp", "lifetime"):
            cls = fm.Timestamp if k == "timestamp" else fm.Duration
            assert 0 <= v["nsec"] < 1_000_000_000
            kwargs[k] = cls(v["sec"], v["nsec"])
        elif (type_name, k) in _ENUMS:
            enum = getattr(fm, _ENUMS[(type_name, k)])
            members = [getattr(enum, n) for n in dir(enum) if not n.startswith("_") and n not in ("name", "value")]
            kwargs[k] = next(m for m in members if m.value == v)
        elif (type_name, k) in _LISTS:
            kwargs[k] = [to_sdk(_LISTS[(type_name, k)], x) for x in v]
        elif k in _NESTED and isinstance(v, dict):
            nested = _NESTED[k] or ("Point2" if set(v) == {"x", "y"} else "Vector3")
            kwargs[k] = to_sdk(nested, v)
        else:
            kwargs[k] = v
    return getattr(fm, type_name)(**kwargs)


def check_foxglove_messages(path: Path) -> dict[str, int]:
    """Build every ``foxglove.*`` message of ``path`` with the SDK and encode it
    (protobuf); returns counts per schema name."""
    counts: dict[str, int] = {}
    for topic, name, _msg, d in _messages(path):
        if not name.startswith("foxglove."):
            continue
        if name in ("foxglove.CompressedImage", "foxglove.RawImage"):
            d = {**d, "data": b""}  # base64 in JSON, bytes in the SDK
        obj = to_sdk(name.split(".", 1)[1], d)
        assert isinstance(obj.encode(), bytes), topic
        counts[name] = counts.get(name, 0) + 1
    return counts


# --- a recording fed with hil.* messages -----------------------------------------

def _record(path: Path) -> None:
    with Recorder(path, metadata={"config": {"yaml_json": json.dumps({"camera": CAMERA})}}) as rec:
        register_all(rec, ["ego0"], anchor=ANCHOR)
        t = 2_100_000_000
        gt = {"sim_time_ns": 0, "initial": True, "entities": [],
              "egos": [{"vehicle": "ego0", "gap_m": 20.0, "obstacle": "car1", "speed_mps": 5.0,
                        "ref_state": "SAFE", "obstacle_speed_mps": 0.0, "ttc_s": 4.0}], "collisions": []}
        rec.write_json("/ground_truth", gt, log_time_ns=t, publish_time_ns=t)
        box = {"entity": "car1", "id": 3, "cls": "vehicle", "box_px": [100, 90, 140, 120], "visible_px": 900,
               "visible_fraction": 1.0, "truncated": False, "path_s_m": 19.5, "path_lateral_m": 0.0}
        for frame in (0, 1):
            rec.write_json("/ego0/truth", {"vehicle": "ego0", "frame_id": frame, "sim_time_ns": 0, "boxes": [box],
                                           "ego": gt["egos"][0]}, log_time_ns=t + 1, publish_time_ns=t + 1)
        pipe = {"vehicle": "ego0", "frame_id": 0, "status": "ok", "sim_time_ns": 0, "t0_ns": t - 5_000_000,
                "t_tx_ns": t, "stages_ns": {"end_to_end": 30_000_000}}
        rec.write_json("/ego0/pipeline", pipe, log_time_ns=t + 2, publish_time_ns=t)
        est = {"frame_id": 0, "state": "SAFE", "control": {"steering_rad": 0.0, "throttle": 0.1, "brake": 0.0},
               "objects": [{"cls": "VEHICLE", "confidence": 0.8, "box_px": [98.0, 88.0, 141.0, 121.0],
                            "position_m": [18.0, 0.5, 0.0]}]}
        rec.write_json("/ego0/estimate", est, log_time_ns=t + 3, publish_time_ns=7)
        rec.write_json("/ego0/pipeline", {**pipe, "frame_id": 1, "status": "dropped", "stages_ns": {}},
                       log_time_ns=t + 4, publish_time_ns=t)
        rec.write_json("/events", {"kind": "latency_spike", "vehicle": "ego0", "severity": "critical",
                                   "measured": 61.0}, log_time_ns=t + 5, publish_time_ns=t + 5)


def test_log_time_is_on_the_wall_clock_and_the_anchor_maps_it_back(tmp_path: Path) -> None:
    path = tmp_path / "a.mcap"
    _record(path)
    with open(path, "rb") as f:
        reader = make_reader(f)
        meta = {m.name: m.metadata for m in reader.iter_metadata()}
    anchor = meta["time_anchor"]
    off = int(anchor["log_time_offset_ns"])
    assert off == ANCHOR.realtime_ns - ANCHOR.monotonic_ns
    assert int(anchor["realtime_ns"]) == ANCHOR.realtime_ns and int(anchor["monotonic_ns"]) == ANCHOR.monotonic_ns
    gts = [(m, d) for topic, _n, m, d in _messages(path) if topic == "/ground_truth"]
    assert gts[0][0].log_time == 2_100_000_000 + off  # exactly the monotonic time given, shifted
    assert gts[0][0].publish_time == 2_100_000_000  # publish time and *_ns fields unchanged
    pipes = [d for topic, _n, _m, d in _messages(path) if topic == "/ego0/pipeline"]
    assert pipes[0]["t0_ns"] == 2_095_000_000


def test_anchor_after_the_first_message_is_refused(tmp_path: Path) -> None:
    with Recorder(tmp_path / "b.mcap") as rec:
        rec.register_json_channel("/x", "x", {"type": "object"})
        rec.write_json("/x", {}, log_time_ns=1, publish_time_ns=1)
        with pytest.raises(ConfigError, match="before the first message"):
            rec.set_time_anchor(ANCHOR)


def test_capture_reads_both_clocks_together() -> None:
    import time
    a = TimeAnchor.capture()
    assert abs((time.time_ns() - time.monotonic_ns()) - a.offset_ns) < 50_000_000


def test_views_overlay_truth_and_ai_on_the_frame_and_log_events(tmp_path: Path) -> None:
    path = tmp_path / "c.mcap"
    _record(path)
    off = ANCHOR.offset_ns
    by_topic: dict[str, list[Any]] = {}
    for topic, name, _m, d in _messages(path):
        by_topic.setdefault(topic, []).append((name, d))
    ann = [d for _n, d in by_topic["/ego0/annotations"]]
    assert len(ann) == 2  # frame 0 answered, frame 1 dropped
    texts = [t["text"] for t in ann[0]["texts"]]
    assert "truth vehicle 19.5 m" in texts and any(t.startswith("AI VEHICLE 18.0 m") for t in texts)
    colours = {(p["outline_color"]["r"], p["outline_color"]["g"]) for p in ann[0]["points"]}
    assert len(colours) == 2  # truth and AI in distinct colours
    # stamped with the frame's image time (t0) on the wall clock, so it pairs with the image
    ts = ann[0]["points"][0]["timestamp"]
    assert ts["sec"] * 1_000_000_000 + ts["nsec"] == 2_095_000_000 + off
    assert any("no answer (dropped)" in t["text"] for t in ann[1]["texts"])
    assert [t["text"] for t in ann[1]["texts"]].count("truth vehicle 19.5 m") == 1
    log = [d for _n, d in by_topic["/log"]]
    assert log[0]["level"] == 4 and log[0]["name"] == "ego0" and "latency_spike" in log[0]["message"]
    cal = by_topic["/ego0/camera_info"][0][1]
    assert cal["frame_id"] == "ego0/camera" and cal["K"][0] == pytest.approx(120 / math.tan(math.radians(30)))
    tfs = {(d["parent_frame_id"], d["child_frame_id"]) for _n, d in by_topic["/tf"]}
    assert {("ego0", "ego0/camera_ground"), ("ego0/camera_ground", "ego0/camera")} <= tfs
    lat = [d for _n, d in by_topic["/ego0/latency"]]
    assert lat[0]["stages_ms"]["end_to_end"] == 30.0
    assert lat[0]["deadline_ms"] == 100.0  # the default end-to-end deadline, for the plot's line
    scene = by_topic["/ego0/estimate_scene"][0][1]
    assert scene["entities"][0]["frame_id"] == "ego0/camera_ground"


def test_log_lines_read_as_words_not_python_reprs(tmp_path: Path) -> None:
    # A state mismatch as the detector publishes it: states as numbers, evidence nested,
    # an unknown entity as None (the /log text once read "entity=None, evidence={...cut").
    from hil.harness.vocab.events import Event, EventKind, Severity

    evidence = {"frame_id": 48, "sim_time_t0_ns": 4_800_000_000, "sim_time_apply_ns": 4_814_000_000,
                "latency_sim_ns": 14_000_000, "latency_ns": 4_368_142, "belief": {"state": "STOP"},
                "truth_t0": {"state": "SLOW"}, "truth_apply": {"state": "SLOW"}}
    ev = Event(EventKind("mismatch.state_mismatch"), 1_004_749_682_789, "ego0", (46, 47, 48), 4_800_000_000, 2.0, 1.0,
               "state", Severity.INFO, "perception", (), "AI said STOP where truth says SLOW",
               {"entity": None, "evidence": evidence})
    path = tmp_path / "log.mcap"
    with Recorder(path) as rec:
        register_all(rec, ["ego0"], anchor=ANCHOR)
        rec.write_json("/events", ev.to_json(), log_time_ns=3_000_000_000, publish_time_ns=3_000_000_000)
    (line,) = [d["message"] for topic, _n, _m, d in _messages(path) if topic == "/log"]
    for repr_bit in ("None", "=[", "={", "'", "2 state", "harness_time"):
        assert repr_bit not in line, (repr_bit, line)
    assert line.startswith("mismatch.state_mismatch ego0, frames 46, 47, 48, sim 4.800 s: AI STOP, truth SLOW")
    # the evidence whole, each time in seconds and each duration in ms
    for part in ("frame id 48", "sim time t0 4.800 s", "sim time apply 4.814 s", "latency sim 14 ms",
                 "latency 4.368 ms", "belief (state STOP)", "truth apply (state SLOW))"):
        assert part in line, (part, line)


def test_optical_frame_looks_forward_and_down() -> None:
    q = foxglove_out.optical_quaternion(math.radians(10))
    x, y, z, w = q
    # the optical +z axis in the vehicle frame: third column of the rotation matrix
    zx, zz = 2 * (x * z + w * y), 1 - 2 * (x * x + y * y)
    assert zx == pytest.approx(math.cos(math.radians(10))) and zz == pytest.approx(-math.sin(math.radians(10)))


def test_every_foxglove_message_is_a_valid_official_message(tmp_path: Path) -> None:
    path = tmp_path / "d.mcap"
    _record(path)
    counts = check_foxglove_messages(path)
    assert {"foxglove.ImageAnnotations", "foxglove.Log", "foxglove.CameraCalibration",
            "foxglove.FrameTransform", "foxglove.SceneUpdate"} <= set(counts)


def test_a_bad_field_is_caught_by_the_check() -> None:
    with pytest.raises(TypeError):
        to_sdk("Log", {"level": 2, "message": "x", "bogus": 1})


def test_shipped_layout_is_current_and_names_topics_the_run_writes(tmp_path: Path) -> None:
    pytest.importorskip("foxglove.layouts")
    from hil.harness.record.foxglove_layout import build_layout

    root = Path(__file__).resolve().parents[3]
    shipped = json.loads((root / "hil_configs" / "foxglove_layout.json").read_text())
    assert shipped == json.loads(build_layout(["ego0"])), "regenerate: python -m hil.harness.record.foxglove_layout ego0"
    path = tmp_path / "e.mcap"
    _record(path)
    written = {topic for topic, *_ in _messages(path)} | {"/ego0/camera", "/scene"}  # written by the loop
    text = json.dumps(shipped)
    named = set(__import__("re").findall(r'"(/[a-z0-9_/]+?)(?:\.[a-z_.]+)?"', text))
    assert named and named <= written, named - written
