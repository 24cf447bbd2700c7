"""``hil target-check``'s malformed-message checks (PROTOCOL.md sections 2, 6, 8
and 9): each bad message gets one ERROR naming the right byte offset and code, from
the vehicle the target serves, and the session goes on; on a stream, the next magic
is decoded and one run of garbage is reported once."""

from __future__ import annotations

import time
import zlib

from hil.adapters.wire import protocol
from hil.adapters.wire.messages import CameraInfo, ErrorMsg, Estimate, Frame, ImageEncoding, SyncRequest
from hil.harness.check.target_session import Session

CAM = CameraInfo(277.0, 277.0, 160.0, 120.0, 1.3)


def _still_alive(s: Session) -> str | None:
    """None when a SYNC_REQUEST is still answered, else why not."""
    return None if s.link.sync_exchange(timeout_s=s.timeout_s) else "no SYNC_RESPONSE afterwards"


def _expect_error(s: Session, name: str, section: str, raw: bytes, codes: tuple[int, ...], offset: int | None) -> None:
    s.drain()
    s.link.send_raw(raw)
    r = s.wait_for(lambda r: isinstance(r.msg, (ErrorMsg, Estimate)))
    p: list[str] = []
    if r is None:
        p.append(f"no ERROR within {s.timeout_s:g} s")
    elif isinstance(r.msg, Estimate):
        p.append(f"answered the bad message with an ESTIMATE (frame {r.msg.frame_id}): it must be dropped")
    else:
        m = r.msg
        assert isinstance(m, ErrorMsg)  # what wait_for was asked for: an ERROR or an ESTIMATE
        if m.code not in codes:
            p.append(f"ERROR code (offset 64) is {m.code}, expected {' or '.join(map(str, codes))}")
        if offset is not None and str(offset) not in m.message:
            p.append(f"ERROR text does not name byte offset {offset}: {m.message!r}")
        if m.vehicle_id != s.link.vehicle_id:  # the vehicle it serves, never one read from the bad header
            p.append(f"ERROR vehicle_id (offset 8) is {m.vehicle_id}, expected the served vehicle {s.link.vehicle_id}")
    if (gone := _still_alive(s)) is not None:
        p.append(f"session did not go on: {gone}")
    s.add(name, section, p, f"ERROR {r.msg.code}: {r.msg.message[:70]!r}" if r is not None and
          isinstance(r.msg, ErrorMsg) else "")


def check_malformed(s: Session) -> None:
    vid = s.link.vehicle_id
    good = bytearray(protocol.encode(SyncRequest(vid, 900, s.link.clock.now_ns())))
    bad_crc = bytearray(good)
    bad_crc[60] ^= 0xFF
    _expect_error(s, "bad header CRC", "2, 8", bytes(bad_crc), (protocol.ErrorCode.MALFORMED,), 60)
    v2 = bytearray(good)
    v2[4] = 2
    v2[60:64] = zlib.crc32(bytes(v2[:60])).to_bytes(4, "little")
    _expect_error(s, "unsupported version", "8, 9", bytes(v2), (protocol.ErrorCode.UNSUPPORTED_VERSION,), 4)
    frame = bytearray(protocol.encode(Frame(vid, 950, 0, 1, 2, 8, 8, ImageEncoding.RGB8, CAM, 0.0, bytes(192)),
                                      payload_crc=True))
    frame[120] ^= 0x01
    _expect_error(s, "bad payload CRC (frame dropped)", "6, 8", bytes(frame), (protocol.ErrorCode.MALFORMED,), 64)
    if s.link.transport_name in ("local", "tcp"):  # a stream: bytes before a magic are skipped
        _expect_error(s, "bytes without a magic", "8", b"\x00junk!" + bytes(protocol.encode(SyncRequest(vid, 901, 5))),
                      (protocol.ErrorCode.MALFORMED,), 0)
    check_flagless_crc(s)
    if s.link.transport_name in ("local", "tcp"):
        check_garbage_once(s)


def _answered(s: Session, seq: int) -> bool:
    """Whether the SYNC_REQUEST ``seq`` sent raw gets its SYNC_RESPONSE in time."""
    deadline = time.monotonic() + s.timeout_s
    while time.monotonic() < deadline:
        if any(m.seq == seq for m in s.link.sync_samples()):
            return True
        if s.wait_for(lambda r: False, timeout_s=0.05) is None and not s.link.alive:
            return False
    return False


def _errors(s: Session, quiet_s: float = 0.3) -> list[ErrorMsg]:
    s.wait_for(lambda r: False, timeout_s=quiet_s)  # what came meanwhile is kept by wait_for
    return [r.msg for r in s.drain() if isinstance(r.msg, ErrorMsg)]


def check_flagless_crc(s: Session) -> None:
    """PROTOCOL.md 2 and 8: a non-zero ``payload_crc`` with its flag clear is a bad
    header: one ERROR naming offset 56, then the next magic (a stream) is decoded."""
    vid = s.link.vehicle_id
    bad = bytearray(protocol.encode(SyncRequest(vid, 902, s.link.clock.now_ns())))
    bad[56:60] = (0x0BADC0DE).to_bytes(4, "little")
    bad[60:64] = zlib.crc32(bytes(bad[:60])).to_bytes(4, "little")
    good = protocol.encode(SyncRequest(vid, 903, s.link.clock.now_ns()))
    s.drain()
    if s.link.transport_name in ("local", "tcp"):
        s.link.send_raw(bytes(bad) + good)  # one write: the target resyncs on the good one's magic
    else:
        s.link.send_raw(bytes(bad))
        s.link.send_raw(good)
    answered = _answered(s, 903)
    errors = _errors(s)
    p = [] if answered else ["the SYNC_REQUEST right after it was not answered (resync on its magic)"]
    if len(errors) != 1:
        p.append(f"{len(errors)} ERRORs, expected one")
    elif "56" not in errors[0].message:
        p.append(f"ERROR text does not name byte offset 56: {errors[0].message!r}")
    s.add("payload_crc without its flag", "2, 8", p, f"ERROR {errors[0].code}: {errors[0].message[:60]!r}"
          if len(errors) == 1 else "")


def check_garbage_once(s: Session) -> None:
    """PROTOCOL.md 8: garbage is reported once, even when it arrives in pieces (the
    search goes on silently after keeping the last 3 bytes)."""
    vid = s.link.vehicle_id
    s.drain()
    s.link.send_raw(b"garbage, part one ")
    first = s.wait_for(lambda r: isinstance(r.msg, ErrorMsg))
    s.link.send_raw(b"and part two" + protocol.encode(SyncRequest(vid, 904, s.link.clock.now_ns())))
    answered = _answered(s, 904)
    errors = [first.msg] if first is not None and isinstance(first.msg, ErrorMsg) else []
    errors += _errors(s)
    p = [] if answered else ["the SYNC_REQUEST after the garbage was not answered"]
    if len(errors) != 1:
        p.append(f"{len(errors)} ERRORs for one run of garbage in two writes, expected one")
    s.add("garbage reported once", "8", p, "one ERROR, then the next message decoded" if not p else "")


__all__ = ["check_malformed"]
