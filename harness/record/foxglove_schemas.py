"""JSON schemas of the Foxglove message types the recorder writes (JSON encoding).

Foxglove recognises a channel by its schema *name* (``foxglove.CompressedImage``,
``foxglove.SceneUpdate``, ...) and reads the message fields by their names, so the
field names here match Foxglove's own schemas (github.com/foxglove/foxglove-sdk,
``schemas/jsonschema``). Each schema is a faithful subset: the fields we write, with
Foxglove's names, types and units; rarely used parts (triangle lists, embedded 3D
models, lineage) are declared only as far as needed.

Every schema is built fresh by a function (no module-level mutable state); register
it once per channel with ``Recorder.register_json_channel(topic, NAME, schema())``.

Units: times are ``{"sec", "nsec"}`` built from integer nanoseconds with
:func:`ns_to_foxglove_time`; positions and sizes metres; colours 0..1 floats;
quaternions ``(x, y, z, w)``.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

COMPRESSED_IMAGE = "foxglove.CompressedImage"
RAW_IMAGE = "foxglove.RawImage"
FRAME_TRANSFORM = "foxglove.FrameTransform"
SCENE_UPDATE = "foxglove.SceneUpdate"
CAMERA_CALIBRATION = "foxglove.CameraCalibration"
IMAGE_ANNOTATIONS = "foxglove.ImageAnnotations"
LOG = "foxglove.Log"

# foxglove.Log levels and foxglove.PointsAnnotation types (Foxglove's enum values).
LOG_INFO, LOG_WARNING, LOG_ERROR = 2, 3, 4
POINTS_LINE_LOOP = 2

_NS_PER_S = 1_000_000_000


def ns_to_foxglove_time(ns: int) -> dict[str, int]:
    """Integer nanoseconds (``>= 0``) as a Foxglove ``time``: ``{"sec", "nsec"}``.

    Raises:
        ValueError: ``ns`` is negative (a Foxglove time has ``sec >= 0``).
    """
    if ns < 0:
        raise ValueError(f"a Foxglove time must be >= 0 ns, got {ns}; use ns_to_foxglove_duration for offsets")
    sec, nsec = divmod(int(ns), _NS_PER_S)
    return {"sec": sec, "nsec": nsec}


def ns_to_foxglove_duration(ns: int) -> dict[str, int]:
    """Signed integer nanoseconds as a Foxglove ``duration`` (``nsec`` always in
    ``0..999_999_999``, the sign carried by ``sec``, as Foxglove expects)."""
    sec, nsec = divmod(int(ns), _NS_PER_S)
    return {"sec": sec, "nsec": nsec}


# --- building blocks --------------------------------------------------------------

def _time(description: str) -> dict[str, Any]:
    return {
        "type": "object",
        "title": "time",
        "description": description,
        "properties": {
            "sec": {"type": "integer", "minimum": 0},
            "nsec": {"type": "integer", "minimum": 0, "maximum": 999_999_999},
        },
    }


def _duration(description: str) -> dict[str, Any]:
    return {
        "type": "object",
        "title": "duration",
        "description": description,
        "properties": {
            "sec": {"type": "integer"},
            "nsec": {"type": "integer", "minimum": 0, "maximum": 999_999_999},
        },
    }


def _numbers(title: str, description: str, names: str) -> dict[str, Any]:
    return {
        "title": title,
        "description": description,
        "type": "object",
        "properties": {n: {"type": "number"} for n in names},
        "required": list(names),
    }


def _vector3(description: str) -> dict[str, Any]:
    return _numbers("foxglove.Vector3", description, "xyz")


def _point3(description: str) -> dict[str, Any]:
    return _numbers("foxglove.Point3", description, "xyz")


def _quaternion(description: str) -> dict[str, Any]:
    return _numbers("foxglove.Quaternion", description, "xyzw")


def _color(description: str) -> dict[str, Any]:
    return _numbers("foxglove.Color", description, "rgba")


def _pose(description: str) -> dict[str, Any]:
    return {
        "title": "foxglove.Pose",
        "description": description,
        "type": "object",
        "properties": {
            "position": _vector3("Point denoting position in 3D space"),
            "orientation": _quaternion("Quaternion denoting orientation in 3D space"),
        },
        "required": ["position", "orientation"],
    }


def _base64(description: str) -> dict[str, Any]:
    return {"type": "string", "contentEncoding": "base64", "description": description}


def _object(title: str, description: str, properties: Mapping[str, Any]) -> dict[str, Any]:
    return {
        "title": title,
        "description": description,
        "type": "object",
        "properties": dict(properties),
        "required": list(properties),
    }


def _array(items: Mapping[str, Any], description: str) -> dict[str, Any]:
    return {"type": "array", "items": dict(items), "description": description}


def _schema(title: str, description: str, properties: Mapping[str, Any]) -> dict[str, Any]:
    out = _object(title, description, properties)
    out["$comment"] = "Subset of https://github.com/foxglove/foxglove-sdk schemas/jsonschema"
    return out


# --- message schemas --------------------------------------------------------------

def compressed_image_schema() -> dict[str, Any]:
    """``foxglove.CompressedImage``: ``data`` is the base64 of a JPEG/PNG file."""
    return _schema(COMPRESSED_IMAGE, "A compressed image", {
        "timestamp": _time("Timestamp of image"),
        "frame_id": {"type": "string", "description": "Frame of reference for the image."},
        "data": _base64("Compressed image data"),
        "format": {"type": "string", "description": "Image format: jpeg, png, webp or avif"},
    })


def raw_image_schema() -> dict[str, Any]:
    """``foxglove.RawImage``: ``data`` is the base64 of ``height`` rows of ``step``
    bytes (``rgb8``/``bgr8``: ``step = 3 * width``)."""
    return _schema(RAW_IMAGE, "A raw image", {
        "timestamp": _time("Timestamp of image"),
        "frame_id": {"type": "string", "description": "Frame of reference for the image."},
        "width": {"type": "integer", "minimum": 0, "description": "Image width (pixels)"},
        "height": {"type": "integer", "minimum": 0, "description": "Image height (pixels)"},
        "encoding": {"type": "string", "description": "Encoding of the raw image data, e.g. rgb8, bgr8"},
        "step": {"type": "integer", "minimum": 0, "description": "Byte length of a single row"},
        "data": _base64("Raw image data"),
    })


def frame_transform_schema() -> dict[str, Any]:
    """``foxglove.FrameTransform``: pose of ``child_frame_id`` in ``parent_frame_id``
    (translation metres, rotation quaternion)."""
    return _schema(FRAME_TRANSFORM, "A transform between two reference frames in 3D space", {
        "timestamp": _time("Timestamp of transform"),
        "parent_frame_id": {"type": "string", "description": "Name of the parent frame"},
        "child_frame_id": {"type": "string", "description": "Name of the child frame"},
        "translation": _vector3("Translation component of the transform"),
        "rotation": _quaternion("Rotation component of the transform"),
    })


def _cube() -> dict[str, Any]:
    return _object("foxglove.CubePrimitive", "A cube or rectangular prism", {
        "pose": _pose("Position of the center of the cube and orientation of the cube"),
        "size": _vector3("Size of the cube along each axis"),
        "color": _color("Color of the cube"),
    })


def _sphere() -> dict[str, Any]:
    return _object("foxglove.SpherePrimitive", "A sphere or ellipsoid", {
        "pose": _pose("Position of the center of the sphere and orientation of the sphere"),
        "size": _vector3("Size (diameter) of the sphere along each axis"),
        "color": _color("Color of the sphere"),
    })


def _cylinder() -> dict[str, Any]:
    return _object("foxglove.CylinderPrimitive", "A cylinder, cone or truncated cone", {
        "pose": _pose("Position of the center of the cylinder and orientation of the cylinder"),
        "size": _vector3("Size of the cylinder's bounding box"),
        "bottom_scale": {"type": "number", "description": "0-1, ratio of the bottom diameter to size.x/size.y"},
        "top_scale": {"type": "number", "description": "0-1, ratio of the top diameter to size.x/size.y"},
        "color": _color("Color of the cylinder"),
    })


def _arrow() -> dict[str, Any]:
    return _object("foxglove.ArrowPrimitive", "An arrow", {
        "pose": _pose("Position of the arrow's tail and orientation of the arrow (+x)"),
        "shaft_length": {"type": "number", "description": "Length of the arrow shaft"},
        "shaft_diameter": {"type": "number", "description": "Diameter of the arrow shaft"},
        "head_length": {"type": "number", "description": "Length of the arrow head"},
        "head_diameter": {"type": "number", "description": "Diameter of the arrow head"},
        "color": _color("Color of the arrow"),
    })


def _line() -> dict[str, Any]:
    return _object("foxglove.LinePrimitive", "A series of points connected by lines", {
        "type": {
            "title": "foxglove.LineType",
            "description": "0 LINE_STRIP, 1 LINE_LOOP, 2 LINE_LIST",
            "oneOf": [
                {"title": "LINE_STRIP", "const": 0},
                {"title": "LINE_LOOP", "const": 1},
                {"title": "LINE_LIST", "const": 2},
            ],
        },
        "pose": _pose("Origin of lines relative to reference frame"),
        "thickness": {"type": "number", "description": "Width of the line"},
        "scale_invariant": {"type": "boolean", "description": "thickness in pixels (true) or metres"},
        "points": _array(_point3("Point"), "Points along the line"),
        "color": _color("Solid color to use for the whole line"),
        "colors": _array(_color("Color"), "Per-point colors (empty, or one per point)"),
        "indices": _array({"type": "integer", "minimum": 0}, "Indices into points/colors (empty: none)"),
    })


def _text() -> dict[str, Any]:
    return _object("foxglove.TextPrimitive", "A text label", {
        "pose": _pose("Position of the center of the text box and orientation of the text"),
        "billboard": {"type": "boolean", "description": "Always face the camera (true)"},
        "font_size": {"type": "number", "description": "Font size (height of one line of text)"},
        "scale_invariant": {"type": "boolean", "description": "font_size in pixels (true) or metres"},
        "color": _color("Color of the text"),
        "text": {"type": "string", "description": "Text"},
    })


def _key_value() -> dict[str, Any]:
    return _object("foxglove.KeyValuePair", "A key with its associated value", {
        "key": {"type": "string", "description": "Key"},
        "value": {"type": "string", "description": "Value"},
    })


def scene_update_schema() -> dict[str, Any]:
    """``foxglove.SceneUpdate``: entity deletions and entities (cubes, spheres,
    cylinders, arrows, lines, texts; ``triangles`` and ``models`` are declared as
    arrays and written empty). Build entities with :func:`scene_entity`."""
    deletion = _object("foxglove.SceneEntityDeletion", "Command to remove previously published entities", {
        "timestamp": _time("Only matching entities earlier than this timestamp are deleted"),
        "type": {
            "title": "foxglove.SceneEntityDeletionType",
            "description": "0 MATCHING_ID, 1 ALL",
            "oneOf": [{"title": "MATCHING_ID", "const": 0}, {"title": "ALL", "const": 1}],
        },
        "id": {"type": "string", "description": "Identifier which must match if type is MATCHING_ID"},
    })
    entity = _object("foxglove.SceneEntity", "A visual element in a 3D scene", {
        "timestamp": _time("Timestamp of the entity"),
        "frame_id": {"type": "string", "description": "Frame of reference"},
        "id": {"type": "string", "description": "Replaces any prior entity on the same topic with the same id"},
        "lifetime": _duration("Time after timestamp when the entity is removed; zero: until replaced"),
        "frame_locked": {"type": "boolean", "description": "Follow frame_id as it moves (true)"},
        "metadata": _array(_key_value(), "Additional user-provided metadata"),
        "arrows": _array(_arrow(), "Arrow primitives"),
        "cubes": _array(_cube(), "Cube primitives"),
        "spheres": _array(_sphere(), "Sphere primitives"),
        "cylinders": _array(_cylinder(), "Cylinder primitives"),
        "lines": _array(_line(), "Line primitives"),
        "triangles": _array({"title": "foxglove.TriangleListPrimitive", "type": "object"}, "Triangle lists"),
        "texts": _array(_text(), "Text primitives"),
        "models": _array({"title": "foxglove.ModelPrimitive", "type": "object"}, "Model primitives"),
    })
    return _schema(SCENE_UPDATE, "An update to the entities displayed in a 3D scene", {
        "deletions": _array(deletion, "Scene entities to delete"),
        "entities": _array(entity, "Scene entities to add or replace"),
    })


def _numbers_array(description: str) -> dict[str, Any]:
    return _array({"type": "number"}, description)


def camera_calibration_schema() -> dict[str, Any]:
    """``foxglove.CameraCalibration``: pinhole intrinsics (pixels) of the camera
    whose images carry ``frame_id`` (an optical frame: +z forward, +x right, +y down)."""
    return _schema(CAMERA_CALIBRATION, "Camera calibration parameters", {
        "timestamp": _time("Timestamp of calibration data"),
        "frame_id": {"type": "string", "description": "Frame of reference for the camera (optical frame)"},
        "width": {"type": "integer", "minimum": 0, "description": "Image width (pixels)"},
        "height": {"type": "integer", "minimum": 0, "description": "Image height (pixels)"},
        "distortion_model": {"type": "string", "description": "plumb_bob, rational_polynomial or kannala_brandt"},
        "D": _numbers_array("Distortion parameters"),
        "K": _numbers_array("Intrinsic camera matrix (3x3 row-major)"),
        "R": _numbers_array("Rectification matrix (3x3 row-major)"),
        "P": _numbers_array("Projection/camera matrix (3x4 row-major)"),
    })


def _point2(description: str) -> dict[str, Any]:
    return _numbers("foxglove.Point2", description, "xy")


def image_annotations_schema() -> dict[str, Any]:
    """``foxglove.ImageAnnotations``: outlines (``points``) and labels (``texts``)
    in pixel coordinates (origin top-left, pixel centres at +0.5); no circles."""
    points = _object("foxglove.PointsAnnotation", "An array of points on a 2D image", {
        "timestamp": _time("Timestamp of annotation"),
        "type": {
            "title": "foxglove.PointsAnnotationType",
            "description": "0 UNKNOWN, 1 POINTS, 2 LINE_LOOP, 3 LINE_STRIP, 4 LINE_LIST",
            "oneOf": [{"title": t, "const": i} for i, t in
                      enumerate(("UNKNOWN", "POINTS", "LINE_LOOP", "LINE_STRIP", "LINE_LIST"))],
        },
        "points": _array(_point2("Point"), "Points in 2D image coordinates (pixels)"),
        "outline_color": _color("Outline color"),
        "outline_colors": _array(_color("Color"), "Per-point colors"),
        "fill_color": _color("Fill color"),
        "thickness": {"type": "number", "minimum": 0, "description": "Stroke thickness in pixels"},
    })
    text = _object("foxglove.TextAnnotation", "A text label on a 2D image", {
        "timestamp": _time("Timestamp of annotation"),
        "position": _point2("Bottom-left origin of the text label in 2D image coordinates (pixels)"),
        "text": {"type": "string", "description": "Text to display"},
        "font_size": {"type": "number", "description": "Font size in pixels"},
        "text_color": _color("Text color"),
        "background_color": _color("Background fill color"),
    })
    out = _schema(IMAGE_ANNOTATIONS, "Array of annotations for a 2D image", {
        "circles": _array({"title": "foxglove.CircleAnnotation", "type": "object"}, "Circle annotations"),
        "points": _array(points, "Points annotations"),
        "texts": _array(text, "Text annotations"),
    })
    return out


def log_schema() -> dict[str, Any]:
    """``foxglove.Log``: one line for the Log panel (``level`` 1 DEBUG .. 5 FATAL)."""
    return _schema(LOG, "A log message", {
        "timestamp": _time("Timestamp of log message"),
        "level": {
            "title": "foxglove.LogLevel",
            "description": "0 UNKNOWN, 1 DEBUG, 2 INFO, 3 WARNING, 4 ERROR, 5 FATAL",
            "oneOf": [{"title": t, "const": i} for i, t in
                      enumerate(("UNKNOWN", "DEBUG", "INFO", "WARNING", "ERROR", "FATAL"))],
        },
        "message": {"type": "string", "description": "Log message"},
        "name": {"type": "string", "description": "Process or node name"},
        "file": {"type": "string", "description": "Filename"},
        "line": {"type": "integer", "minimum": 0, "description": "Line number in the file"},
    })


def schema_for(name: str) -> dict[str, Any]:
    """The schema named ``name`` (one of the constants above).

    Raises:
        KeyError: the name is not one of ours; the message lists the known names.
    """
    builders = {
        COMPRESSED_IMAGE: compressed_image_schema,
        RAW_IMAGE: raw_image_schema,
        FRAME_TRANSFORM: frame_transform_schema,
        SCENE_UPDATE: scene_update_schema,
        CAMERA_CALIBRATION: camera_calibration_schema,
        IMAGE_ANNOTATIONS: image_annotations_schema,
        LOG: log_schema,
    }
    try:
        return builders[name]()
    except KeyError:
        raise KeyError(f"no Foxglove schema named {name!r}; known: {', '.join(builders)}") from None


# --- message helpers --------------------------------------------------------------

def pose(position: Sequence[float] = (0.0, 0.0, 0.0),
         orientation: Sequence[float] = (0.0, 0.0, 0.0, 1.0)) -> dict[str, Any]:
    """A ``foxglove.Pose`` from ``(x, y, z)`` metres and an ``(x, y, z, w)`` quaternion."""
    x, y, z = position
    qx, qy, qz, qw = orientation
    return {
        "position": {"x": float(x), "y": float(y), "z": float(z)},
        "orientation": {"x": float(qx), "y": float(qy), "z": float(qz), "w": float(qw)},
    }


def scene_entity(*, entity_id: str, frame_id: str, timestamp_ns: int, lifetime_ns: int = 0,
                 frame_locked: bool = False, **primitives: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """A ``foxglove.SceneEntity`` with every primitive list present (empty unless
    given), e.g. ``scene_entity(entity_id="car1", frame_id="world", timestamp_ns=t,
    cubes=[{"pose": pose(...), "size": {...}, "color": {...}}])``.

    Raises:
        ValueError: a keyword is not a SceneEntity primitive list.
    """
    lists = ("metadata", "arrows", "cubes", "spheres", "cylinders", "lines", "triangles", "texts", "models")
    unknown = sorted(set(primitives) - set(lists))
    if unknown:
        raise ValueError(f"unknown SceneEntity field(s) {unknown}; expected some of {list(lists)}")
    entity: dict[str, Any] = {
        "timestamp": ns_to_foxglove_time(timestamp_ns),
        "frame_id": frame_id,
        "id": entity_id,
        "lifetime": ns_to_foxglove_duration(lifetime_ns),
        "frame_locked": frame_locked,
    }
    for name in lists:
        entity[name] = [dict(p) for p in primitives.get(name, ())]
    return entity
