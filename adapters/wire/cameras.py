"""Which camera a FRAME came from, and its frame set (PROTOCOL.md 4.2): the rules of
FRAME bytes 69 (``camera_index``) and 70 (``camera_count``), shared by the encoder, the
decoder and the SDK's set assembly (``hil.adapters.frame_sets``).

A frame set is the images of one capture instant of a vehicle's cameras. Its frames
carry consecutive ``frame_id``s in camera order, so the set's id is ``frame_id -
camera_index`` (the ``frame_id`` of its camera 0), the same ``sim_time`` and the same
``camera_count``. ``camera_count`` 0 is a single camera, not a set: what every
version-1 harness sends, byte for byte.
"""

from __future__ import annotations

import operator
from typing import Any

from hil.common.errors import ProtocolError

MAX_CAMERAS = 32  # cameras in one frame set
CAMERA_INDEX_OFFSET = 69  # absolute byte offsets in a FRAME
CAMERA_COUNT_OFFSET = 70
OBJECT_CAMERA_REL = 1  # byte of an ESTIMATE's object record, relative to the record


def _u8(value: Any, name: str, offset: int) -> int:
    try:
        v = operator.index(value)
    except TypeError as err:
        raise ProtocolError(f"{name} must be an integer, got {value!r}", offset=offset) from err
    if not 0 <= v <= 255:
        raise ProtocolError(f"{name}={v} is outside 0..255", offset=offset)
    return v


def check_camera(index: Any, count: Any, frame_id: int) -> tuple[int, int]:
    """``(camera_index, camera_count)`` of a FRAME, checked.

    Raises:
        ProtocolError: ``camera_count`` 1 or above ``MAX_CAMERAS`` (offset 70); an
            index not below the count, non-zero without a set, or above ``frame_id``
            (the set id would be negative; offset 69).
    """
    i = _u8(index, "camera_index", CAMERA_INDEX_OFFSET)
    n = _u8(count, "camera_count", CAMERA_COUNT_OFFSET)
    if n == 1 or n > MAX_CAMERAS:
        raise ProtocolError(f"camera_count={n}: 0 for a single camera, 2..{MAX_CAMERAS} for a frame set",
                            offset=CAMERA_COUNT_OFFSET)
    if n == 0 and i:
        raise ProtocolError(f"camera_index={i} with camera_count 0: a single camera is camera 0",
                            offset=CAMERA_INDEX_OFFSET)
    if n and i >= n:
        raise ProtocolError(f"camera_index={i} is outside 0..{n - 1} (camera_count {n})",
                            offset=CAMERA_INDEX_OFFSET)
    if i > frame_id:
        raise ProtocolError(f"camera_index={i} exceeds frame_id {frame_id}: the set id frame_id - camera_index "
                            "would be negative", offset=CAMERA_INDEX_OFFSET)
    return i, n


def check_object_camera(value: Any, at: int) -> int:
    """An ESTIMATE object's ``camera`` (record byte +1): below ``MAX_CAMERAS``.

    Raises:
        ProtocolError: out of range (offset of that byte).
    """
    v = _u8(value, "object camera", at + OBJECT_CAMERA_REL)
    if v >= MAX_CAMERAS:
        raise ProtocolError(f"object camera={v} is outside 0..{MAX_CAMERAS - 1}", offset=at + OBJECT_CAMERA_REL)
    return v


__all__ = ["CAMERA_COUNT_OFFSET", "CAMERA_INDEX_OFFSET", "MAX_CAMERAS", "check_camera", "check_object_camera"]
