"""The small messages as native CAN FD frames: ``hil.dbc`` <-> ``hil.adapters.wire.messages``.

``hil.dbc`` (shipped next to this module) defines every frame with signals, so an ECU
developer reads and writes them with the usual tools; this module loads it with
cantools and converts frames to and from the message dataclasses.

CAN id layout (29-bit extended ids; lower id wins arbitration)::

    bits 28..26  priority P (0 highest)     bits 25..16  message number M
    bits 15..0   vehicle id V (0..65535)    id = P << 26 | M << 16 | V

``hil.dbc`` lists each message for vehicle 0; add the vehicle id. ``MESSAGE_MASK``
(0x1FFF0000) selects P and M. A message travels as DBC frames only when they carry it
exactly (within the control signals' resolution); otherwise ``HilCan.encode`` returns
None and the transport sends the full PROTOCOL.md encoding over ISO-TP instead:
an ESTIMATE with more than 8 objects, a frame id or sync sequence over 32 bits, a
HELLO name over 52 bytes, an ERROR text or BYE reason over 60 bytes, a vehicle id in
the message other than the link's, or any message with no DBC frame in its direction.

Control is quantized on CAN: steering to 1 µrad (int32), throttle and brake to 1e-4
(uint16, 0..10000). Object geometry and confidence are IEEE float32 signals and all
times int64 ns, so they are exact.
"""

from __future__ import annotations

import math
from collections import OrderedDict
from dataclasses import dataclass, field
from enum import Enum
from pathlib import Path
from typing import Any

try:
    import cantools
except ImportError as err:  # pragma: no cover - depends on the install
    raise ImportError("the CAN transport needs cantools: pip install 'cantools>=39'") from err

from hil.adapters.wire.messages import (Bye, ClockId, Control, DetectedObject, DrivingState, ErrorMsg, Estimate,
                                        Heartbeat, Hello, Message, ObjectClass, SyncRequest, SyncResponse)
from hil.common.errors import ProtocolError

DBC_PATH = Path(__file__).with_name("hil.dbc")
MESSAGE_MASK = 0x1FFF0000  # priority + message number
VEHICLE_MASK = 0xFFFF
MAX_VEHICLE_ID = VEHICLE_MASK
MAX_DBC_OBJECTS = 8
MAX_NAME_BYTES = 52  # HIL_HELLO Name00..Name51
MAX_TEXT_BYTES = 60  # HIL_ERROR_* Text00..59, HIL_BYE_* Reason00..59
MAX_PENDING_ESTIMATES = 8  # partial estimates kept while their frames arrive
_U32 = 0xFFFFFFFF
_I32_MIN, _I32_MAX = -(2**31), 2**31 - 1
_STEERING_SCALE = 1e6  # raw per rad
_UNIT_SCALE = 10_000  # raw per 1.0 of throttle/brake


class Role(Enum):
    """Which side of the link a codec (or peer) sits on."""

    HARNESS = "harness"
    TARGET = "target"


@dataclass(frozen=True)
class CanFrame:
    """One CAN FD frame to send: 29-bit id and data (a valid FD length)."""

    arbitration_id: int
    data: bytes


@dataclass
class _Partial:
    summary: dict[str, Any] | None = None
    stamps: dict[str, Any] | None = None
    objects: dict[int, DetectedObject] = field(default_factory=dict)


# The messages each side sends; the other side receives them.
_SENT_BY = {
    Role.HARNESS: ("HIL_SYNC_REQUEST", "HIL_HEARTBEAT_HARNESS", "HIL_ERROR_HARNESS", "HIL_BYE_HARNESS"),
    Role.TARGET: ("HIL_ESTIMATE", "HIL_ESTIMATE_OBJECT", "HIL_TARGET_TIMESTAMPS", "HIL_SYNC_RESPONSE",
                  "HIL_HEARTBEAT_TARGET", "HIL_HELLO", "HIL_ERROR_TARGET", "HIL_BYE_TARGET"),
}


def load_database() -> Any:
    """``hil.dbc`` as a cantools database whose lookups by frame id ignore the vehicle id."""
    return cantools.database.load_file(str(DBC_PATH), frame_id_mask=MESSAGE_MASK)


class HilCan:
    """DBC codec for one side (``role``) of one vehicle's link.

    ``encode`` turns a message this side sends into CAN frames (or None: send it over
    ISO-TP); ``decode`` turns a received frame into messages, assembling an ESTIMATE
    from its frames. Not thread-safe: one reader decodes.
    """

    def __init__(self, *, role: Role, vehicle_id: int) -> None:
        if not 0 <= vehicle_id <= MAX_VEHICLE_ID:
            raise ValueError(f"vehicle_id={vehicle_id}: the CAN id carries 0..{MAX_VEHICLE_ID}")
        self.role = role
        self.vehicle_id = vehicle_id
        self.db = load_database()
        self._m = {m.name: m for m in self.db.messages}
        peer = Role.TARGET if role is Role.HARNESS else Role.HARNESS
        self._inbound = {self._m[n].frame_id & MESSAGE_MASK: self._m[n] for n in _SENT_BY[peer]}
        self._outbound = set(_SENT_BY[role])
        self._pending: OrderedDict[int, _Partial] = OrderedDict()
        # Bytes no signal covers (all signals are byte-aligned): sent as 0 and checked.
        self._reserved = {m.name: [i for i in range(m.length)
                                   if not any(g.start // 8 <= i < (g.start + g.length) // 8 for g in m.signals)]
                          for m in self._inbound.values()}
        up, down = ("UP", "DOWN") if role is Role.HARNESS else ("DOWN", "UP")
        # ISO-TP ids (this vehicle): data we send + flow control we receive, and back.
        self.isotp_tx_data = self.can_id(f"HIL_ISOTP_{up}_DATA")
        self.isotp_tx_fc = self.can_id(f"HIL_ISOTP_{up}_FC")
        self.isotp_rx_data = self.can_id(f"HIL_ISOTP_{down}_DATA")
        self.isotp_rx_fc = self.can_id(f"HIL_ISOTP_{down}_FC")

    def can_id(self, name: str) -> int:
        """The 29-bit id of DBC message ``name`` for this vehicle."""
        frame_id: int = self._m[name].frame_id  # cantools has no type information
        return (frame_id & 0x1FFFFFFF) | self.vehicle_id

    def is_inbound(self, arbitration_id: int) -> bool:
        """True for a DBC frame the other side sends (whatever its vehicle id)."""
        return (arbitration_id & MESSAGE_MASK) in self._inbound

    # -- encode ------------------------------------------------------------------

    def encode(self, msg: Message) -> list[CanFrame] | None:
        """The DBC frames carrying ``msg`` exactly, in sending order, or None when they
        cannot (the caller then sends the PROTOCOL.md encoding over ISO-TP)."""
        if getattr(msg, "vehicle_id", self.vehicle_id) != self.vehicle_id:
            return None
        try:
            return self._encode(msg)
        except (_NotSent, cantools.database.errors.EncodeError):
            return None

    def _encode(self, msg: Message) -> list[CanFrame] | None:
        side = "HARNESS" if self.role is Role.HARNESS else "TARGET"
        if isinstance(msg, Estimate):
            return self._encode_estimate(msg)
        if isinstance(msg, SyncRequest) and msg.seq <= _U32:
            return self._frames("HIL_SYNC_REQUEST", Seq=msg.seq, T1=msg.t1_ns)
        if isinstance(msg, SyncResponse) and msg.seq <= _U32:
            return self._frames("HIL_SYNC_RESPONSE", Seq=msg.seq, T1=msg.t1_ns, T2=msg.t2_target_ns,
                                T3=msg.t3_target_ns)
        if isinstance(msg, Heartbeat):
            return self._frames(f"HIL_HEARTBEAT_{side}", TSender=msg.t_sender_ns)
        if isinstance(msg, Hello):
            name = msg.target_name.encode("utf-8")
            if len(name) > MAX_NAME_BYTES or not 0 <= msg.protocol_version <= 255:
                return None
            return self._frames("HIL_HELLO", Version=msg.protocol_version, ClockId=int(msg.clock_id),
                                NameLen=len(name), ClockResolutionNs=msg.clock_resolution_ns,
                                Capabilities=msg.capabilities, **_chars("Name", name, MAX_NAME_BYTES))
        if isinstance(msg, ErrorMsg):
            text = msg.message.encode("utf-8")
            if len(text) > MAX_TEXT_BYTES:
                return None
            return self._frames(f"HIL_ERROR_{side}", Code=msg.code, TextLen=len(text),
                                **_chars("Text", text, MAX_TEXT_BYTES))
        if isinstance(msg, Bye):
            text = msg.reason.encode("utf-8")
            if len(text) > MAX_TEXT_BYTES:
                return None
            return self._frames(f"HIL_BYE_{side}", ReasonLen=len(text), **_chars("Reason", text, MAX_TEXT_BYTES))
        return None

    def _encode_estimate(self, e: Estimate) -> list[CanFrame] | None:
        steering_raw = round(e.control.steering_rad * _STEERING_SCALE)
        if (e.frame_id > _U32 or len(e.objects) > MAX_DBC_OBJECTS or any(o.camera for o in e.objects)
                or not _I32_MIN <= steering_raw <= _I32_MAX):  # an object's camera has no signal: ISO-TP
            return None
        frames = self._frames("HIL_ESTIMATE", FrameId=e.frame_id, State=int(e.state), NObjects=len(e.objects),
                              SteeringAngle=steering_raw / _STEERING_SCALE,
                              Throttle=round(e.control.throttle * _UNIT_SCALE) / _UNIT_SCALE,
                              Brake=round(e.control.brake * _UNIT_SCALE) / _UNIT_SCALE)
        for i, o in enumerate(e.objects):
            (x0, y0, x1, y1), (x, y, z) = o.box_px, o.position_m
            frames += self._frames("HIL_ESTIMATE_OBJECT", FrameId=e.frame_id, Index=i, Class=int(o.cls),
                                   Confidence=o.confidence, BoxX0=x0, BoxY0=y0, BoxX1=x1, BoxY1=y1,
                                   PosX=x, PosY=y, PosZ=z)
        frames += self._frames("HIL_TARGET_TIMESTAMPS", FrameId=e.frame_id, TRx=e.t_rx_target_ns,
                               TInferStart=e.t_infer_start_target_ns, TInferEnd=e.t_infer_end_target_ns,
                               TReply=e.t_reply_target_ns)
        return frames

    def _frames(self, name: str, **signals: Any) -> list[CanFrame]:
        if name not in self._outbound:
            raise _NotSent(name)
        m = self._m[name]
        return [CanFrame(self.can_id(name), m.encode(signals, strict=True))]

    # -- decode ------------------------------------------------------------------

    def decode(self, arbitration_id: int, data: bytes) -> list[Message | ProtocolError]:
        """Messages completed by one received DBC frame (an estimate's frames give
        nothing until its last one), or a ``ProtocolError`` per bad frame; its offset
        is the byte offset within the frame's data.

        Raises:
            KeyError: not a frame the other side sends (check ``is_inbound`` first).
        """
        m = self._inbound[arbitration_id & MESSAGE_MASK]
        vid = arbitration_id & VEHICLE_MASK
        where = f"{m.name} (CAN id 0x{arbitration_id:08X})"
        if len(data) != m.length:
            return [ProtocolError(f"{where} has {len(data)} data bytes, expected {m.length}", offset=len(data))]
        for i in self._reserved[m.name]:
            if data[i]:
                return [ProtocolError(f"{where}: reserved byte is {data[i]}, must be 0", offset=i)]
        try:
            s = m.decode(bytes(data), decode_choices=False)
            return self._to_messages(m.name, vid, s)
        except _BadSignal as bad:
            sig = m.get_signal_by_name(bad.signal)
            return [ProtocolError(f"{where}: {bad.signal} {bad.text}", offset=sig.start // 8)]
        except (cantools.database.errors.DecodeError, ValueError) as err:
            return [ProtocolError(f"{where} does not decode: {err}", offset=0)]

    def _to_messages(self, name: str, vid: int, s: dict[str, Any]) -> list[Message | ProtocolError]:
        if name.startswith("HIL_HEARTBEAT_"):
            return [Heartbeat(vid, s["TSender"])]
        if name == "HIL_SYNC_REQUEST":
            return [SyncRequest(vid, s["Seq"], s["T1"])]
        if name == "HIL_SYNC_RESPONSE":
            return [SyncResponse(vid, s["Seq"], s["T1"], s["T2"], s["T3"])]
        if name == "HIL_HELLO":
            name_bytes = _text(s, "Name", "NameLen", MAX_NAME_BYTES)
            return [Hello(name_bytes, s["Version"], _enum(ClockId, s, "ClockId"), s["ClockResolutionNs"],
                          s["Capabilities"])]
        if name.startswith("HIL_ERROR_"):
            return [ErrorMsg(vid, s["Code"], _text(s, "Text", "TextLen", MAX_TEXT_BYTES))]
        if name.startswith("HIL_BYE_"):
            return [Bye(vid, _text(s, "Reason", "ReasonLen", MAX_TEXT_BYTES))]
        return self._estimate_part(name, vid, s)

    def _estimate_part(self, name: str, vid: int, s: dict[str, Any]) -> list[Message | ProtocolError]:
        obj = None
        if name == "HIL_ESTIMATE":
            _enum(DrivingState, s, "State")
            if s["NObjects"] > MAX_DBC_OBJECTS:
                raise _BadSignal("NObjects", f"{s['NObjects']} exceeds {MAX_DBC_OBJECTS}")
            for sig in ("Throttle", "Brake"):
                if not 0.0 <= s[sig] <= 1.0:
                    raise _BadSignal(sig, f"{s[sig]} is outside [0, 1]")
        elif name == "HIL_ESTIMATE_OBJECT":
            obj = _object(s)
        out: list[Message | ProtocolError] = []
        fid = s["FrameId"]
        part = self._pending.get(fid)
        if part is None:
            part = self._pending[fid] = _Partial()
            while len(self._pending) > MAX_PENDING_ESTIMATES:
                old_fid, old = self._pending.popitem(last=False)
                missing = [n for n, v in (("HIL_ESTIMATE", old.summary), ("HIL_TARGET_TIMESTAMPS", old.stamps))
                           if v is None]
                out.append(ProtocolError(f"estimate of frame {old_fid} never completed (missing "
                                         f"{', '.join(missing) or 'objects'})", offset=0))
        if name == "HIL_ESTIMATE":
            part.summary = s
        elif name == "HIL_TARGET_TIMESTAMPS":
            part.stamps = s
        else:
            part.objects[s["Index"]] = obj  # type: ignore[assignment]
        summ, st = part.summary, part.stamps
        if summ is None or st is None or len(part.objects) < summ["NObjects"]:
            return out
        del self._pending[fid]
        n = summ["NObjects"]
        if sorted(part.objects) != list(range(n)):
            out.append(ProtocolError(f"estimate of frame {fid}: object indices {sorted(part.objects)} "
                                     f"do not match NObjects {n}", offset=5))
            return out
        control = Control(summ["SteeringAngle"], summ["Throttle"], summ["Brake"])
        out.append(Estimate(vid, fid, DrivingState(summ["State"]), control,
                            tuple(part.objects[i] for i in range(n)), st["TRx"], st["TInferStart"],
                            st["TInferEnd"], st["TReply"]))
        return out


def _object(s: dict[str, Any]) -> DetectedObject:
    if s["Index"] >= MAX_DBC_OBJECTS:
        raise _BadSignal("Index", f"{s['Index']} exceeds {MAX_DBC_OBJECTS - 1}")
    for k in ("Confidence", "BoxX0", "BoxY0", "BoxX1", "BoxY1", "PosX", "PosY", "PosZ"):
        if not math.isfinite(s[k]):
            raise _BadSignal(k, f"is {s[k]}, must be finite")
    if not 0.0 <= s["Confidence"] <= 1.0:
        raise _BadSignal("Confidence", f"{s['Confidence']} is outside [0, 1]")
    box = (s["BoxX0"], s["BoxY0"], s["BoxX1"], s["BoxY1"])
    return DetectedObject(_enum(ObjectClass, s, "Class"), s["Confidence"], box, (s["PosX"], s["PosY"], s["PosZ"]))


class _NotSent(Exception):
    """The message has no DBC frame in this direction."""


class _BadSignal(Exception):
    def __init__(self, signal: str, text: str) -> None:
        super().__init__(text)
        self.signal, self.text = signal, text


def _chars(prefix: str, raw: bytes, size: int) -> dict[str, int]:
    return {f"{prefix}{i:02d}": (raw[i] if i < len(raw) else 0) for i in range(size)}


def _text(s: dict[str, Any], prefix: str, length_signal: str, limit: int) -> str:
    n = s[length_signal]
    if n > limit:
        raise _BadSignal(length_signal, f"{n} exceeds {limit}")
    for i in range(n, limit):
        if s[f"{prefix}{i:02d}"]:
            raise _BadSignal(f"{prefix}{i:02d}", "follows the text and must be 0")
    try:
        return bytes(s[f"{prefix}{i:02d}"] for i in range(n)).decode("utf-8")
    except UnicodeDecodeError as err:
        raise _BadSignal(f"{prefix}{err.start:02d}", "is not valid UTF-8") from err


def _enum(cls: type[Enum], s: dict[str, Any], signal: str) -> Any:
    try:
        return cls(s[signal])
    except ValueError as err:
        valid = ", ".join(f"{m.name}={m.value}" for m in cls)
        raise _BadSignal(signal, f"{s[signal]} is not one of {valid}") from err


__all__ = ["CanFrame", "DBC_PATH", "HilCan", "MAX_DBC_OBJECTS", "MAX_NAME_BYTES", "MAX_TEXT_BYTES",
           "MAX_VEHICLE_ID", "MESSAGE_MASK", "Role", "VEHICLE_MASK", "load_database"]
