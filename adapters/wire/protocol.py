"""Wire protocol v1: encode and decode every message, and a decoder for byte streams.

A message is a fixed 64-byte header (magic ``b"HILP"``, version, type, flags, vehicle
id, payload length, frame id, four timestamp slots, payload CRC, header CRC) followed
by ``payload_len`` payload bytes, all little-endian. ``PROTOCOL.md`` has the byte
tables; this module is the reference implementation.

Decoding never trusts a length: each one is checked against its limit and against the
bytes actually present before anything is sliced or allocated by it. Every failure is
a ``ProtocolError`` whose ``offset`` is the absolute byte offset, within the message,
of the bad field. Encoding applies the same rules, so whatever ``encode`` returns,
``decode`` accepts.
"""

from __future__ import annotations

import math
import operator
import struct
import zlib
from collections.abc import Callable
from dataclasses import dataclass
from enum import IntEnum
from typing import Any

from hil.adapters.wire.cameras import check_camera, check_object_camera
from hil.adapters.wire.messages import (Auth, AuthStep, Bye, CameraInfo, ClockId, Command, Control, DetectedObject,
                                        DrivingState, ErrorMsg, Estimate, Frame, Heartbeat, Hello, ImageEncoding,
                                        Message, MsgType, ObjectClass, SyncRequest, SyncResponse)
from hil.common.errors import ProtocolError

MAGIC = b"HILP"
VERSION = 1
SUPPORTED_VERSIONS = (1,)
HEADER_SIZE = 64
MAX_PAYLOAD = 16 * 1024 * 1024  # bytes
MAX_OBJECTS = 256
MAX_NAME_LEN = 64  # bytes of UTF-8
MAX_ERROR_LEN = 1024  # bytes of UTF-8
MAX_REASON_LEN = 256  # bytes of UTF-8
MAX_COMMAND_LEN = 256  # bytes of UTF-8
CAP_COMMANDS = 0x0000_0002  # HELLO capability bit 1: the target accepts COMMAND messages
CAP_AUTH = 0x0000_0004  # HELLO capability bit 2: the target answers an AUTH challenge (section 4.8)
CAP_CAMERAS = 0x0000_0008  # HELLO capability bit 3: the target takes FRAMEs of a frame set (section 4.2)
CAP_FRAME_SETS = 0x0000_0010  # HELLO capability bit 4: ... and answers one ESTIMATE per set, not per camera
AUTH_DATA_SIZE = 32  # bytes of an AUTH challenge or proof
MAX_IMAGE_SIDE = 4096  # pixels
FLAG_PAYLOAD_CRC = 0x0001
KNOWN_FLAGS = FLAG_PAYLOAD_CRC
HELLO_FIXED_SIZE = 12
FRAME_META_SIZE = 40
ESTIMATE_FIXED_SIZE = 16
OBJECT_SIZE = 36
STREAM_BUFFER_LIMIT = HEADER_SIZE + MAX_PAYLOAD  # most bytes a stream.StreamDecoder holds



class ErrorCode(IntEnum):
    """``ErrorMsg.code`` values of v1. Receivers must accept codes they do not know;
    0x8000 and above are free for a target's own use."""

    UNSPECIFIED = 0
    MALFORMED = 1  # a message could not be decoded (the text names the byte offset)
    UNSUPPORTED_VERSION = 2  # the header carried a version this peer does not speak
    UNEXPECTED = 3  # a well-formed message that is not valid in this direction or state
    TARGET_FAILURE = 4  # the target could not process a frame (AI crashed, out of memory)


_P = HEADER_SIZE  # absolute offset of the payload
_U32_MAX = 2**32 - 1
_U64_MAX = 2**64 - 1
_I64_MIN, _I64_MAX = -(2**63), 2**63 - 1
_RAW_ENCODINGS = (ImageEncoding.RGB8, ImageEncoding.BGR8)

_HEADER_BODY = struct.Struct("<4sBBHIIQqqqqI")  # bytes 0..59, covered by header_crc
_U32 = struct.Struct("<I")
_F32 = struct.Struct("<f")
_HELLO = struct.Struct("<BBHII")
_FRAME_META = struct.Struct("<HHBBBB7fI")
_ESTIMATE = struct.Struct("<BBHfff")
_OBJECT = struct.Struct("<BB2s8f")
_ERROR = struct.Struct("<HH")
_BYE = struct.Struct("<H")
_COMMAND = struct.Struct("<H")
_AUTH = struct.Struct("<B3s32s")
_FRAME_FLOATS = ("fx", "fy", "cx", "cy", "mount_height_m", "pitch_rad", "ego_speed_mps")
_BOX_NAMES = ("x0", "y0", "x1", "y1")
_POS_NAMES = ("x", "y", "z")

# Per type: (frame_id slot used, number of leading timestamp slots used).
_SLOTS = {
    MsgType.HELLO: (False, 0), MsgType.FRAME: (True, 3), MsgType.ESTIMATE: (True, 4),
    MsgType.SYNC_REQUEST: (True, 1), MsgType.SYNC_RESPONSE: (True, 3),
    MsgType.HEARTBEAT: (False, 1), MsgType.ERROR: (False, 0), MsgType.BYE: (False, 0),
    MsgType.COMMAND: (True, 1), MsgType.AUTH: (False, 0),
}


@dataclass(frozen=True)
class Header:
    """The fixed 64-byte header, decoded and validated.

    ``ts`` holds the four timestamp slots (integer ns) whose meaning depends on
    ``type``; ``frame_id`` is the frame id, or the sequence number of a sync message.
    ``payload_len`` is in bytes; ``payload_crc`` is 0 unless ``flags`` has
    ``FLAG_PAYLOAD_CRC``.
    """

    version: int
    type: MsgType
    flags: int
    vehicle_id: int
    payload_len: int
    frame_id: int
    ts: tuple[int, int, int, int]
    payload_crc: int


# ---------------------------------------------------------------- encode helpers

def _int(value: Any, lo: int, hi: int, name: str, offset: int) -> int:
    try:
        v = operator.index(value)
    except TypeError as err:
        raise ProtocolError(f"{name} must be an integer, got {value!r}", offset=offset) from err
    if not lo <= v <= hi:
        raise ProtocolError(f"{name}={v} is outside {lo}..{hi}", offset=offset)
    return v


def _i64(value: Any, name: str, offset: int) -> int:
    return _int(value, _I64_MIN, _I64_MAX, f"{name} (ns)", offset)


def _f32(value: Any, name: str, offset: int, *, unit: bool = False) -> float:
    try:
        v = float(value)
        finite = math.isfinite(v)
        if finite:
            _F32.pack(v)  # OverflowError when it would round to infinity in float32
    except (TypeError, ValueError, OverflowError) as err:
        raise ProtocolError(f"{name}={value!r} is not a finite float32", offset=offset) from err
    if not finite:
        raise ProtocolError(f"{name} must be finite, got {v}", offset=offset)
    if unit and not 0.0 <= v <= 1.0:
        raise ProtocolError(f"{name}={v} is outside [0, 1]", offset=offset)
    return v


def _enum(cls: type[IntEnum], value: Any, name: str, offset: int) -> IntEnum:
    try:
        return cls(value)
    except (ValueError, TypeError) as err:
        valid = ", ".join(f"{m.name}={m.value}" for m in cls)
        raise ProtocolError(f"{name}={value!r} is not one of {valid}", offset=offset) from err


def _utf8(text: str, name: str, limit: int, offset: int) -> bytes:
    try:
        raw = text.encode("utf-8")
    except (AttributeError, UnicodeEncodeError) as err:
        raise ProtocolError(f"{name} must be a str encodable as UTF-8", offset=offset) from err
    if len(raw) > limit:
        raise ProtocolError(f"{name} is {len(raw)} bytes of UTF-8; the limit is {limit}", offset=offset)
    return raw


_Parts = tuple[int, int, tuple[int, int, int, int], list[Any]]  # vehicle, frame_id, ts, payload


def _enc_hello(m: Hello) -> _Parts:
    if m.protocol_version != VERSION:
        raise ProtocolError(f"Hello.protocol_version={m.protocol_version!r}; this encoder "
                            f"writes version {VERSION}", offset=4)
    clock = _enum(ClockId, m.clock_id, "clock_id", _P)
    name = _utf8(m.target_name, "target_name", MAX_NAME_LEN, _P + 12)
    res = _int(m.clock_resolution_ns, 0, _U32_MAX, "clock_resolution_ns", _P + 4)
    caps = _int(m.capabilities, 0, _U32_MAX, "capabilities", _P + 8)
    return 0, 0, (0, 0, 0, 0), [_HELLO.pack(clock, 0, len(name), res, caps), name]


def _enc_frame(f: Frame) -> _Parts:
    image = memoryview(f.data)
    if image.ndim != 1 or image.itemsize != 1:
        image = image.cast("B")
    width = _int(f.width, 1, MAX_IMAGE_SIDE, "width (px)", _P)
    height = _int(f.height, 1, MAX_IMAGE_SIDE, "height (px)", _P + 2)
    encoding = _enum(ImageEncoding, f.encoding, "encoding", _P + 4)
    c = f.camera
    values = (c.fx, c.fy, c.cx, c.cy, c.mount_height_m, c.pitch_rad, f.ego_speed_mps)
    floats = [_f32(v, n, _P + 8 + 4 * i) for i, (n, v) in enumerate(zip(_FRAME_FLOATS, values))]
    if encoding in _RAW_ENCODINGS and image.nbytes != width * height * 3:
        raise ProtocolError(f"{encoding.name} image of {width}x{height} px needs "
                            f"{width * height * 3} bytes, data has {image.nbytes}", offset=_P + 36)
    index, count = check_camera(f.camera_index, f.camera_count, _int(f.frame_id, 0, _U64_MAX, "frame_id", 16))
    meta = _FRAME_META.pack(width, height, encoding, index, count, 0, *floats, image.nbytes)
    ts = (_i64(f.t0_ns, "t0_ns", 24), _i64(f.sim_time_ns, "sim_time_ns", 32),
          _i64(f.t_tx_ns, "t_tx_ns", 40), 0)
    return f.vehicle_id, f.frame_id, ts, [meta, image]


def _enc_object(o: DetectedObject, at: int) -> bytes:
    cls = _enum(ObjectClass, o.cls, "object class", at)
    conf = _f32(o.confidence, "confidence", at + 4, unit=True)
    box, pos = tuple(o.box_px), tuple(o.position_m)
    if len(box) != 4:
        raise ProtocolError(f"box_px needs 4 values (x0, y0, x1, y1), got {len(box)}", offset=at + 8)
    if len(pos) != 3:
        raise ProtocolError(f"position_m needs 3 values (x, y, z), got {len(pos)}", offset=at + 24)
    names = _BOX_NAMES + _POS_NAMES
    floats = [_f32(v, n, at + 8 + 4 * i) for i, (n, v) in enumerate(zip(names, box + pos))]
    return _OBJECT.pack(cls, check_object_camera(o.camera, at), b"\0\0", conf, *floats)


def _enc_estimate(e: Estimate) -> _Parts:
    state = _enum(DrivingState, e.state, "state", _P)
    objects = tuple(e.objects)
    if len(objects) > MAX_OBJECTS:
        raise ProtocolError(f"{len(objects)} objects; the limit is {MAX_OBJECTS}", offset=_P + 2)
    ctl = e.control
    head = _ESTIMATE.pack(state, 0, len(objects), _f32(ctl.steering_rad, "steering_rad", _P + 4),
                          _f32(ctl.throttle, "throttle", _P + 8, unit=True),
                          _f32(ctl.brake, "brake", _P + 12, unit=True))
    base = _P + ESTIMATE_FIXED_SIZE
    body = [_enc_object(o, base + OBJECT_SIZE * i) for i, o in enumerate(objects)]
    ts = (_i64(e.t_rx_target_ns, "t_rx_target_ns", 24),
          _i64(e.t_infer_start_target_ns, "t_infer_start_target_ns", 32),
          _i64(e.t_infer_end_target_ns, "t_infer_end_target_ns", 40),
          _i64(e.t_reply_target_ns, "t_reply_target_ns", 48))
    return e.vehicle_id, e.frame_id, ts, [head, *body]


def _enc_sync_request(m: SyncRequest) -> _Parts:
    return m.vehicle_id, m.seq, (_i64(m.t1_ns, "t1_ns", 24), 0, 0, 0), []


def _enc_sync_response(m: SyncResponse) -> _Parts:
    ts = (_i64(m.t1_ns, "t1_ns", 24), _i64(m.t2_target_ns, "t2_target_ns", 32),
          _i64(m.t3_target_ns, "t3_target_ns", 40), 0)
    return m.vehicle_id, m.seq, ts, []


def _enc_heartbeat(m: Heartbeat) -> _Parts:
    return m.vehicle_id, 0, (_i64(m.t_sender_ns, "t_sender_ns", 24), 0, 0, 0), []


def _enc_error(m: ErrorMsg) -> _Parts:
    text = _utf8(m.message, "message", MAX_ERROR_LEN, _P + 4)
    code = _int(m.code, 0, 0xFFFF, "code", _P)
    return m.vehicle_id, 0, (0, 0, 0, 0), [_ERROR.pack(code, len(text)), text]


def _enc_bye(m: Bye) -> _Parts:
    text = _utf8(m.reason, "reason", MAX_REASON_LEN, _P + 2)
    return m.vehicle_id, 0, (0, 0, 0, 0), [_BYE.pack(len(text)), text]


def _enc_command(m: Command) -> _Parts:
    text = _utf8(m.text, "text", MAX_COMMAND_LEN, _P + 2)
    return m.vehicle_id, m.seq, (_i64(m.t_sender_ns, "t_sender_ns", 24), 0, 0, 0), [_COMMAND.pack(len(text)), text]


def _enc_auth(m: Auth) -> _Parts:
    step = _enum(AuthStep, m.step, "step", _P)
    if len(m.data) != AUTH_DATA_SIZE:
        raise ProtocolError(f"AUTH data is {AUTH_DATA_SIZE} bytes, got {len(m.data)}", offset=_P + 4)
    return m.vehicle_id, 0, (0, 0, 0, 0), [_AUTH.pack(step, bytes(3), bytes(m.data))]


_ENCODERS: dict[type, tuple[MsgType, Callable[[Any], _Parts]]] = {
    Hello: (MsgType.HELLO, _enc_hello), Frame: (MsgType.FRAME, _enc_frame),
    Estimate: (MsgType.ESTIMATE, _enc_estimate),
    SyncRequest: (MsgType.SYNC_REQUEST, _enc_sync_request),
    SyncResponse: (MsgType.SYNC_RESPONSE, _enc_sync_response),
    Heartbeat: (MsgType.HEARTBEAT, _enc_heartbeat), ErrorMsg: (MsgType.ERROR, _enc_error),
    Bye: (MsgType.BYE, _enc_bye), Command: (MsgType.COMMAND, _enc_command), Auth: (MsgType.AUTH, _enc_auth),
}


def encode(msg: Message, *, payload_crc: bool = False) -> bytes:
    """Encode one message into its wire bytes (header + payload).

    Args:
        msg: any message of ``hil.adapters.wire.messages``. Times are integer ns (i64), ids
            u32 (vehicle) and u64 (frame, sequence); floats must be finite float32.
        payload_crc: also protect the payload with a CRC-32 (sets ``FLAG_PAYLOAD_CRC``).

    Returns:
        ``HEADER_SIZE + payload_len`` bytes. A frame's image is copied once, into the
        result.

    Raises:
        ProtocolError: a field is out of range or too long for the wire (``offset`` is
            where the field would sit in the message).
        TypeError: ``msg`` is not a message type.
    """
    try:
        mtype, encoder = _ENCODERS[type(msg)]
    except KeyError:
        names = ", ".join(t.__name__ for t in _ENCODERS)
        raise TypeError(f"cannot encode {type(msg).__name__}; expected one of {names}") from None
    vehicle_id, frame_id, ts, parts = encoder(msg)
    vehicle_id = _int(vehicle_id, 0, _U32_MAX, "vehicle_id", 8)
    frame_id = _int(frame_id, 0, _U64_MAX, "frame_id", 16)
    payload_len = sum(len(p) for p in parts)
    if payload_len > MAX_PAYLOAD:
        raise ProtocolError(f"payload of {payload_len} bytes exceeds MAX_PAYLOAD={MAX_PAYLOAD}",
                            offset=12)
    flags = crc = 0
    if payload_crc:
        flags = FLAG_PAYLOAD_CRC
        for part in parts:
            crc = zlib.crc32(part, crc)
    body = _HEADER_BODY.pack(MAGIC, VERSION, mtype, flags, vehicle_id, payload_len, frame_id,
                             *ts, crc)
    return b"".join([body, _U32.pack(zlib.crc32(body)), *parts])


def encode_frame(frame: Frame, *, payload_crc: bool = False) -> bytes:
    """Encode a ``Frame``; same as ``encode`` (the image is copied once). Raises as
    ``encode`` does."""
    if not isinstance(frame, Frame):
        raise TypeError(f"encode_frame needs a Frame, got {type(frame).__name__}")
    return encode(frame, payload_crc=payload_crc)


# ---------------------------------------------------------------- decode

def as_view(buf: bytes | bytearray | memoryview) -> memoryview:
    mv = memoryview(buf)
    return mv if mv.ndim == 1 and mv.itemsize == 1 else mv.cast("B")


def magic_error(first4: bytes) -> ProtocolError:
    return ProtocolError(f"bad magic {first4!r}, expected {MAGIC!r}", offset=0)


def decode_header(buf: bytes | bytearray | memoryview) -> Header:
    """Decode and validate the 64-byte header at the start of ``buf``.

    Checks, in order: length, magic, version, type, flags, ``payload_len`` against
    ``MAX_PAYLOAD`` (before anything is allocated), header CRC, and that
    ``payload_crc`` is 0 when not flagged. Bytes after the header are not looked at.

    Raises:
        ProtocolError: ``offset`` is ``len(buf)`` when shorter than 64 bytes, else the
            offset of the bad field (0, 4, 5, 6, 12, 60 or 56).
    """
    with as_view(buf) as mv:
        n = mv.nbytes
        if n < HEADER_SIZE:
            raise ProtocolError(f"need {HEADER_SIZE} header bytes, got {n}", offset=n)
        magic, version, mtype, flags, vid, plen, fid, t0, t1, t2, t3, pcrc = \
            _HEADER_BODY.unpack_from(mv)
        if magic != MAGIC:
            raise magic_error(magic)
        if version not in SUPPORTED_VERSIONS:
            raise ProtocolError(f"unsupported protocol version {version}; this decoder supports "
                                f"version(s) {', '.join(map(str, SUPPORTED_VERSIONS))}", offset=4)
        try:
            msg_type = MsgType(mtype)
        except ValueError as err:
            raise ProtocolError(f"unknown message type {mtype}", offset=5) from err
        if flags & ~KNOWN_FLAGS:
            raise ProtocolError(f"unknown flag bits 0x{flags & ~KNOWN_FLAGS:04x} (v1 knows "
                                f"0x{KNOWN_FLAGS:04x})", offset=6)
        if plen > MAX_PAYLOAD:
            raise ProtocolError(f"payload_len {plen} exceeds MAX_PAYLOAD={MAX_PAYLOAD}", offset=12)
        (hcrc,) = _U32.unpack_from(mv, 60)
        if zlib.crc32(mv[:60]) != hcrc:
            raise ProtocolError("header CRC mismatch", offset=60)
    if pcrc and not flags & FLAG_PAYLOAD_CRC:
        raise ProtocolError("payload_crc is set but FLAG_PAYLOAD_CRC is not", offset=56)
    return Header(version, msg_type, flags, vid, plen, fid, (t0, t1, t2, t3), pcrc)


def _need(h: Header, size: int) -> None:
    if h.payload_len < size:
        raise ProtocolError(f"payload_len {h.payload_len} too short for {h.type.name} "
                            f"(at least {size})", offset=12)


def _enum_in(cls: type[IntEnum], value: int, name: str, offset: int) -> Any:
    try:
        return cls(value)
    except ValueError as err:
        raise ProtocolError(f"unknown {name} {value}", offset=offset) from err


def _reserved(raw: bytes | int, offset: int) -> None:
    for i, b in enumerate(raw if isinstance(raw, bytes) else (raw,)):
        if b:
            raise ProtocolError(f"reserved byte is {b}, must be 0", offset=offset + i)


def _finite(value: float, name: str, offset: int, *, unit: bool = False) -> float:
    if not math.isfinite(value):
        raise ProtocolError(f"{name} is {value}, must be finite", offset=offset)
    if unit and not 0.0 <= value <= 1.0:
        raise ProtocolError(f"{name}={value} is outside [0, 1]", offset=offset)
    return value


def _length(value: int, limit: int, fixed: int, h: Header, name: str, offset: int) -> None:
    if value > limit:
        raise ProtocolError(f"{name} {value} exceeds the limit {limit}", offset=offset)
    if fixed + value != h.payload_len:
        raise ProtocolError(f"{name} {value} disagrees with payload_len {h.payload_len} "
                            f"(expected {h.payload_len - fixed})", offset=offset)


def _text(mv: memoryview, offset: int, size: int, name: str) -> str:
    try:
        return bytes(mv[offset:offset + size]).decode("utf-8")
    except UnicodeDecodeError as err:
        raise ProtocolError(f"{name} is not valid UTF-8 ({err.reason})",
                            offset=offset + err.start) from err


def _dec_hello(mv: memoryview, h: Header) -> Hello:
    _need(h, HELLO_FIXED_SIZE)
    clock, reserved, name_len, res, caps = _HELLO.unpack_from(mv, _P)
    clock_id = _enum_in(ClockId, clock, "clock_id", _P)
    _reserved(reserved, _P + 1)
    _length(name_len, MAX_NAME_LEN, HELLO_FIXED_SIZE, h, "name_len", _P + 2)
    name = _text(mv, _P + HELLO_FIXED_SIZE, name_len, "target_name")
    return Hello(target_name=name, protocol_version=h.version, clock_id=clock_id,
                 clock_resolution_ns=res, capabilities=caps)


def _dec_frame(mv: memoryview, h: Header) -> Frame:
    _need(h, FRAME_META_SIZE)
    width, height, enc, index, count, reserved, *floats, image_len = _FRAME_META.unpack_from(mv, _P)
    for value, name, at in ((width, "width", _P), (height, "height", _P + 2)):
        if not 1 <= value <= MAX_IMAGE_SIDE:
            raise ProtocolError(f"{name} {value} px is outside 1..{MAX_IMAGE_SIDE}", offset=at)
    encoding = _enum_in(ImageEncoding, enc, "image encoding", _P + 4)
    index, count = check_camera(index, count, h.frame_id)
    _reserved(reserved, _P + 7)
    for i, (name, value) in enumerate(zip(_FRAME_FLOATS, floats)):
        _finite(value, name, _P + 8 + 4 * i)
    if image_len != h.payload_len - FRAME_META_SIZE:
        raise ProtocolError(f"image_len {image_len} disagrees with payload_len {h.payload_len} "
                            f"(expected {h.payload_len - FRAME_META_SIZE})", offset=_P + 36)
    if encoding in _RAW_ENCODINGS and image_len != width * height * 3:
        raise ProtocolError(f"{encoding.name} {width}x{height} image needs {width * height * 3} "
                            f"bytes, image_len is {image_len}", offset=_P + 36)
    fx, fy, cx, cy, mount, pitch, speed = floats
    start = _P + FRAME_META_SIZE
    return Frame(vehicle_id=h.vehicle_id, frame_id=h.frame_id, sim_time_ns=h.ts[1],
                 t0_ns=h.ts[0], t_tx_ns=h.ts[2], width=width, height=height, encoding=encoding,
                 camera=CameraInfo(fx, fy, cx, cy, mount, pitch), ego_speed_mps=speed,
                 data=bytes(mv[start:start + image_len]), camera_index=index, camera_count=count)


def _dec_estimate(mv: memoryview, h: Header) -> Estimate:
    _need(h, ESTIMATE_FIXED_SIZE)
    state, reserved, n, steering, throttle, brake = _ESTIMATE.unpack_from(mv, _P)
    driving_state = _enum_in(DrivingState, state, "driving state", _P)
    _reserved(reserved, _P + 1)
    if n > MAX_OBJECTS:
        raise ProtocolError(f"n_objects {n} exceeds the limit {MAX_OBJECTS}", offset=_P + 2)
    if ESTIMATE_FIXED_SIZE + OBJECT_SIZE * n != h.payload_len:
        raise ProtocolError(f"n_objects {n} needs payload_len {ESTIMATE_FIXED_SIZE + OBJECT_SIZE * n}"
                            f", header says {h.payload_len}", offset=_P + 2)
    control = Control(_finite(steering, "steering_rad", _P + 4),
                      _finite(throttle, "throttle", _P + 8, unit=True),
                      _finite(brake, "brake", _P + 12, unit=True))
    objects = []
    for i in range(n):
        at = _P + ESTIMATE_FIXED_SIZE + OBJECT_SIZE * i
        cls, camera, reserved2, conf, *floats = _OBJECT.unpack_from(mv, at)
        obj_cls = _enum_in(ObjectClass, cls, f"class of object {i}", at)
        check_object_camera(camera, at)
        _reserved(reserved2, at + 2)
        _finite(conf, f"confidence of object {i}", at + 4, unit=True)
        for k, (name, value) in enumerate(zip(_BOX_NAMES + _POS_NAMES, floats)):
            _finite(value, f"{name} of object {i}", at + 8 + 4 * k)
        objects.append(DetectedObject(obj_cls, conf, tuple(floats[:4]), tuple(floats[4:]), camera))
    return Estimate(vehicle_id=h.vehicle_id, frame_id=h.frame_id, state=driving_state,
                    control=control, objects=tuple(objects), t_rx_target_ns=h.ts[0],
                    t_infer_start_target_ns=h.ts[1], t_infer_end_target_ns=h.ts[2],
                    t_reply_target_ns=h.ts[3])


def _empty(h: Header) -> None:
    if h.payload_len:
        raise ProtocolError(f"{h.type.name} has no payload, payload_len is {h.payload_len}",
                            offset=12)


def _dec_sync_request(mv: memoryview, h: Header) -> SyncRequest:
    _empty(h)
    return SyncRequest(vehicle_id=h.vehicle_id, seq=h.frame_id, t1_ns=h.ts[0])


def _dec_sync_response(mv: memoryview, h: Header) -> SyncResponse:
    _empty(h)
    return SyncResponse(vehicle_id=h.vehicle_id, seq=h.frame_id, t1_ns=h.ts[0],
                        t2_target_ns=h.ts[1], t3_target_ns=h.ts[2])


def _dec_heartbeat(mv: memoryview, h: Header) -> Heartbeat:
    _empty(h)
    return Heartbeat(vehicle_id=h.vehicle_id, t_sender_ns=h.ts[0])


def _dec_error(mv: memoryview, h: Header) -> ErrorMsg:
    _need(h, _ERROR.size)
    code, msg_len = _ERROR.unpack_from(mv, _P)
    _length(msg_len, MAX_ERROR_LEN, _ERROR.size, h, "msg_len", _P + 2)
    return ErrorMsg(vehicle_id=h.vehicle_id, code=code,
                    message=_text(mv, _P + _ERROR.size, msg_len, "message"))


def _dec_bye(mv: memoryview, h: Header) -> Bye:
    _need(h, _BYE.size)
    (reason_len,) = _BYE.unpack_from(mv, _P)
    _length(reason_len, MAX_REASON_LEN, _BYE.size, h, "reason_len", _P)
    return Bye(vehicle_id=h.vehicle_id, reason=_text(mv, _P + _BYE.size, reason_len, "reason"))


def _dec_command(mv: memoryview, h: Header) -> Command:
    _need(h, _COMMAND.size)
    (text_len,) = _COMMAND.unpack_from(mv, _P)
    _length(text_len, MAX_COMMAND_LEN, _COMMAND.size, h, "text_len", _P)
    return Command(vehicle_id=h.vehicle_id, seq=h.frame_id, text=_text(mv, _P + _COMMAND.size, text_len, "text"),
                   t_sender_ns=h.ts[0])


def _dec_auth(mv: memoryview, h: Header) -> Auth:
    if h.payload_len != _AUTH.size:
        raise ProtocolError(f"AUTH payload_len must be {_AUTH.size}, got {h.payload_len}", offset=12)
    step, reserved, data = _AUTH.unpack_from(mv, _P)
    step = _enum_in(AuthStep, step, "step", _P)
    _reserved(reserved, _P + 1)
    return Auth(vehicle_id=h.vehicle_id, step=step, data=bytes(data))


_DECODERS: dict[MsgType, Callable[[memoryview, Header], Message]] = {
    MsgType.HELLO: _dec_hello, MsgType.FRAME: _dec_frame, MsgType.ESTIMATE: _dec_estimate,
    MsgType.SYNC_REQUEST: _dec_sync_request, MsgType.SYNC_RESPONSE: _dec_sync_response,
    MsgType.HEARTBEAT: _dec_heartbeat, MsgType.ERROR: _dec_error, MsgType.BYE: _dec_bye,
    MsgType.COMMAND: _dec_command, MsgType.AUTH: _dec_auth,
}


def _check_slots(h: Header) -> None:
    uses_frame_id, n_ts = _SLOTS[h.type]
    if h.type is MsgType.HELLO and h.vehicle_id:
        raise ProtocolError(f"HELLO carries vehicle_id 0, got {h.vehicle_id}", offset=8)
    if not uses_frame_id and h.frame_id:
        raise ProtocolError(f"{h.type.name} leaves frame_id 0, got {h.frame_id}", offset=16)
    for i in range(n_ts, 4):
        if h.ts[i]:
            raise ProtocolError(f"{h.type.name} leaves ts{i} 0, got {h.ts[i]}", offset=24 + 8 * i)


def decode(buf: bytes | bytearray | memoryview, *, header: Header | None = None) -> Message:
    """Decode exactly one whole message. ``header``: the result of ``decode_header``
    on these bytes when the caller has it already (a stream decoder), so the header
    is not checked twice.

    Order of checks: the header (see ``decode_header``), then that ``len(buf)`` is
    exactly ``HEADER_SIZE + payload_len``, the payload CRC if flagged, unused header
    slots being zero, then every payload field.

    Returns:
        The message dataclass; floats are the float32 values widened to Python floats.
        A frame's image is copied once out of ``buf``.

    Raises:
        ProtocolError: for any malformed input, and nothing else; ``offset`` is the
            absolute byte offset within ``buf`` of the bad field (``len(buf)`` when
            truncated, ``HEADER_SIZE + payload_len`` when there are trailing bytes).
    """
    with as_view(buf) as mv:
        try:
            h = header if header is not None else decode_header(mv)
            n, total = mv.nbytes, HEADER_SIZE + h.payload_len
            if n < total:
                raise ProtocolError(f"truncated: header announces {total} bytes, {n} present",
                                    offset=n)
            if n > total:
                raise ProtocolError(f"{n - total} trailing bytes after a {total}-byte message",
                                    offset=total)
            if h.flags & FLAG_PAYLOAD_CRC and zlib.crc32(mv[HEADER_SIZE:]) != h.payload_crc:
                raise ProtocolError("payload CRC mismatch", offset=HEADER_SIZE)
            _check_slots(h)
            return _DECODERS[h.type](mv, h)
        except (struct.error, ValueError, IndexError, OverflowError) as err:
            # Unreachable when the checks above are complete; kept so that a gap in
            # them still surfaces as a ProtocolError, never a library error.
            raise ProtocolError(f"malformed message ({err})", offset=0) from err


__all__ = [
    "AUTH_DATA_SIZE", "CAP_AUTH", "CAP_CAMERAS", "CAP_COMMANDS", "CAP_FRAME_SETS", "ESTIMATE_FIXED_SIZE", "FLAG_PAYLOAD_CRC", "FRAME_META_SIZE",
    "HEADER_SIZE", "HELLO_FIXED_SIZE", "KNOWN_FLAGS", "MAGIC", "MAX_ERROR_LEN", "MAX_IMAGE_SIDE",
    "MAX_COMMAND_LEN", "MAX_NAME_LEN", "MAX_OBJECTS", "MAX_PAYLOAD", "MAX_REASON_LEN", "OBJECT_SIZE",
    "STREAM_BUFFER_LIMIT", "SUPPORTED_VERSIONS", "VERSION", "ErrorCode", "Header",
    "decode", "decode_header", "encode", "encode_frame",
]

