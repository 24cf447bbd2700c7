"""FRAME's camera index and frame set (PROTOCOL.md 4.2), an object's camera (4.3):
round trips, a single camera's bytes unchanged from before the fields existed, and
every bad value refused with its byte offset, on encode and decode alike."""

from __future__ import annotations

import struct
import zlib
from dataclasses import replace

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hil.adapters.wire.cameras import MAX_CAMERAS
from hil.adapters.wire.messages import (CameraInfo, Control, DetectedObject, DrivingState, Estimate, Frame,
                                        ImageEncoding, ObjectClass)
from hil.adapters.wire.protocol import decode, encode
from hil.common.errors import ProtocolError

CAM = CameraInfo(277.0, 276.5, 160.0, 120.0, 1.3, 0.02)
FRAME = Frame(7, 123456, 5_000_000_000, 1_000_000_123, 1_000_000_456, 4, 2, ImageEncoding.RGB8, CAM, 12.5,
              bytes(range(24)))
OBJ = DetectedObject(ObjectClass.VEHICLE, 0.9, (1.0, 2.0, 30.0, 40.0), (12.0, -1.5, 0.0))
ESTIMATE = Estimate(7, 123456, DrivingState.SLOW, Control(0.1, 0.2, 0.0), (OBJ,), 10, 20, 30, 40)
# FRAME and ESTIMATE as the encoder wrote them before FRAME bytes 69-70 and the object's
# byte +1 had a meaning (commit a68bb55): a single camera's messages must stay these bytes.
FRAME_BEFORE = ("48494c5001020000070000004000000040e20100000000007bca9a3b00000000"
                "00f2052a01000000c8cb9a3b00000000000000000000000000000000e38bf27f"
                "040002000000000000808a4300408a43000020430000f0426666a63f0ad7a33c"
                "0000484118000000000102030405060708090a0b0c0d0e0f1011121314151617")
ESTIMATE_BEFORE_SHA256 = "13c29156f6ebc270f61f7285d92099db7979d77c1bdc328c3900e092b244cd76"


def _fix_crc(buf: bytearray) -> bytes:
    buf[60:64] = zlib.crc32(bytes(buf[:60])).to_bytes(4, "little")
    return bytes(buf)


def _patched(buf: bytes, offset: int, value: int) -> bytes:
    out = bytearray(buf)
    out[offset] = value
    return _fix_crc(out)


def test_single_camera_bytes_are_unchanged() -> None:
    import hashlib

    assert encode(FRAME).hex() == FRAME_BEFORE
    assert hashlib.sha256(encode(ESTIMATE)).hexdigest() == ESTIMATE_BEFORE_SHA256
    back = decode(bytes.fromhex(FRAME_BEFORE))
    assert isinstance(back, Frame) and (back.camera_index, back.camera_count, back.set_id) == (0, 0, 123456)


@settings(max_examples=200, deadline=None)
@given(count=st.integers(2, MAX_CAMERAS), data=st.data(), first=st.integers(0, 2**63))
def test_round_trip_of_every_camera_of_a_set(count: int, data: st.DataObject, first: int) -> None:
    index = data.draw(st.integers(0, count - 1))
    f = replace(FRAME, frame_id=first + index, camera_index=index, camera_count=count)
    wire = encode(f, payload_crc=data.draw(st.booleans()))
    assert (wire[69], wire[70], wire[71]) == (index, count, 0)
    back = decode(wire)
    assert isinstance(back, Frame) and encode(back) == encode(f)  # float32 fields come back widened
    assert (back.camera_index, back.camera_count, back.set_id, back.frame_id) == (index, count, first, first + index)


def test_object_camera_round_trip_at_record_byte_1() -> None:
    e = replace(ESTIMATE, objects=(OBJ, replace(OBJ, camera=MAX_CAMERAS - 1)))
    wire = encode(e)
    assert (wire[80 + 1], wire[80 + 36 + 1]) == (0, MAX_CAMERAS - 1)
    back = decode(wire)
    assert isinstance(back, Estimate) and [o.camera for o in back.objects] == [0, MAX_CAMERAS - 1]
    assert encode(back) == wire


BAD_FRAMES = [  # (camera_index, camera_count, frame_id, offset, words of the message)
    (1, 0, 5, 69, "single camera is camera 0"),
    (0, 1, 5, 70, "camera_count=1"),
    (0, MAX_CAMERAS + 1, 5, 70, f"2..{MAX_CAMERAS}"),
    (3, 3, 5, 69, "outside 0..2"),
    (4, 6, 3, 69, "exceeds frame_id 3"),
    (256, 0, 5, 69, "outside 0..255"),
]


@pytest.mark.parametrize(("index", "count", "fid", "offset", "words"), BAD_FRAMES)
def test_bad_camera_fields_name_their_offset(index: int, count: int, fid: int, offset: int, words: str) -> None:
    bad = replace(FRAME, frame_id=fid, camera_index=index, camera_count=count)
    with pytest.raises(ProtocolError, match=words) as enc:
        encode(bad)
    assert enc.value.offset == offset
    if index > 255:
        return
    wire = bytearray(encode(replace(FRAME, frame_id=fid)))
    wire[69], wire[70] = index, count
    with pytest.raises(ProtocolError, match=words) as dec:
        decode(_fix_crc(wire))
    assert dec.value.offset == offset


def test_byte_71_stays_reserved() -> None:
    wire = _patched(encode(replace(FRAME, frame_id=9, camera_index=1, camera_count=2)), 71, 1)
    with pytest.raises(ProtocolError, match="reserved") as info:
        decode(wire)
    assert info.value.offset == 71


def test_bad_object_camera_and_its_reserved_bytes() -> None:
    wire = encode(ESTIMATE)
    with pytest.raises(ProtocolError, match="object camera") as info:
        decode(_patched(wire, 81, MAX_CAMERAS))
    assert info.value.offset == 81
    for at in (82, 83):
        with pytest.raises(ProtocolError, match="reserved") as info:
            decode(_patched(wire, at, 1))
        assert info.value.offset == at
    with pytest.raises(ProtocolError, match="object camera") as info:
        encode(replace(ESTIMATE, objects=(replace(OBJ, camera=MAX_CAMERAS),)))
    assert info.value.offset == 81


def test_frame_meta_layout_is_what_protocol_md_says() -> None:
    """Bytes 64..103 of a set's FRAME read back with PROTOCOL.md 4.2's table."""
    wire = encode(replace(FRAME, frame_id=20, camera_index=2, camera_count=6))
    w, h, enc, index, count, reserved = struct.unpack_from("<HHBBBB", wire, 64)
    assert (w, h, enc, index, count, reserved) == (4, 2, 0, 2, 6, 0)
