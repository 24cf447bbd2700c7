"""Shared-memory frame ring of the local transport (PROTOCOL.md section 10.1.1).

A camera frame through the local socket is copied into the kernel, out again in
several ``recv`` calls, into the stream buffer and out of it. With the ring, the
harness writes the encoded FRAME message once into a slot of a shared-memory
segment and sends a 32-byte *notice* on the socket; the target copies the image
out of the slot once, while decoding. Everything else (sync, heartbeats, BYE, the
target's answers) stays on the socket.

Negotiated: the harness creates the segment (an anonymous ``memfd``, so nothing is
ever left behind in ``/dev/shm``, whoever crashes) and passes its descriptor in
``HIL_LOCAL_SHM``; a target that maps it says so with capability bit 0
(``SHM_FRAMES``) in its HELLO. Only then does the harness send notices. A target
that does not know the ring never advertises the bit and gets every frame inline.

The byte layouts (control block, slots, the 32-byte notice whose magic ``HILS``
sets it apart from a message) are in PROTOCOL.md section 10.1.1.

Slot reuse is by ring order (slot ``(seq - 1) % slot_count``) with the slot's ``seq``
as a generation counter, seqlock style: the harness stores 0, writes the message,
stores the new ``seq``; the target checks ``seq`` before and after reading and drops
the frame when it changed (``stale``: overwritten before it was read; ``torn``:
overwritten while it was read). The harness never waits for a slot: a slot whose
previous message the target has not ``consumed`` yet is overwritten all the same
(newest wins, as the SDK's own frame queue does) and counted. Python issues no
memory fences; on x86 (TSO) none are needed, and elsewhere the notice's socket
write orders the slot's bytes before the target can see the notice, so only the
detection of a slot overwritten mid-read relies on store order.

Needs only the standard library: this module runs on the target too.
"""

from __future__ import annotations

import mmap
import os
import struct
import tempfile
import zlib
from collections.abc import Mapping
from dataclasses import dataclass

from hil.adapters.wire.messages import Message
from hil.adapters.wire.protocol import HEADER_SIZE, decode
from hil.adapters.wire.stream import SideRecord
from hil.common.errors import ProtocolError, TransportError

ENV_SHM = "HIL_LOCAL_SHM"
SHM_FRAMES = 0x0000_0001  # HELLO capability bit 0: the target reads frames from the ring
RING_MAGIC = b"HILR"
NOTICE_MAGIC = b"HILS"
LAYOUT_VERSION = 1
NOTICE_VERSION = 1
CONTROL_SIZE = 64
SLOT_HEADER_SIZE = 16
NOTICE_SIZE = 32
MAX_SLOTS = 64
MAX_SLOT_BYTES = HEADER_SIZE + 16 * 1024 * 1024  # one MAX_PAYLOAD message
DEFAULT_SLOTS = 4
DEFAULT_SLOT_BYTES = 1 << 20  # a 640x480 RGB8 FRAME (921 704 bytes) fits
# FRAME messages shorter than this stay inline. Measured (2 CPUs, 1400 interleaved
# round trips each): at 2 KB both ways take the same time, from 4 KB the ring is
# 4-8 % faster (12 KB JPEG: 136 vs 148 µs p50), at 230 KB twice as fast.
DEFAULT_INLINE_BELOW = 4 * 1024

_CONTROL = struct.Struct("<4sHHII")  # magic, version, slot_count, slot_bytes, slot_stride
_U64 = struct.Struct("<Q")
_NOTICE_BODY = struct.Struct("<4sBBHIIQI")  # bytes 0..27
_U32 = struct.Struct("<I")
_CONSUMED_AT = 16


def slot_stride(slot_bytes: int) -> int:
    """Bytes from one slot's start to the next: header + ``slot_bytes``, rounded up to 64."""
    return (SLOT_HEADER_SIZE + slot_bytes + 63) // 64 * 64


@dataclass(frozen=True)
class Notice:
    """'The message with sequence number ``seq`` is in ``slot``, ``length`` bytes.'"""

    slot: int
    length: int
    seq: int


def encode_notice(n: Notice) -> bytes:
    body = _NOTICE_BODY.pack(NOTICE_MAGIC, NOTICE_VERSION, 0, n.slot, n.length, 0, n.seq, 0)
    return body + _U32.pack(zlib.crc32(body))


def decode_notice(buf: bytes | bytearray | memoryview) -> Notice:
    """Decode one 32-byte notice (not yet checked against a ring's geometry).

    Raises:
        ProtocolError: offset of the bad field (CRC 28, version 4, reserved 5/12/24).
    """
    if len(buf) < NOTICE_SIZE:
        raise ProtocolError(f"need {NOTICE_SIZE} notice bytes, got {len(buf)}", offset=len(buf))
    magic, version, r5, slot, length, r12, seq, r24 = _NOTICE_BODY.unpack_from(buf)
    if magic != NOTICE_MAGIC:
        raise ProtocolError(f"bad notice magic {magic!r}, expected {NOTICE_MAGIC!r}", offset=0)
    if _U32.unpack_from(buf, 28)[0] != zlib.crc32(memoryview(buf)[:28]):
        raise ProtocolError("shared-memory notice CRC mismatch", offset=28)
    if version != NOTICE_VERSION:
        raise ProtocolError(f"shared-memory notice version {version}; this reader knows {NOTICE_VERSION}", offset=4)
    for value, at in ((r5, 5), (r12, 12), (r24, 24)):
        if value:
            raise ProtocolError(f"reserved notice field is {value}, must be 0", offset=at)
    if seq == 0:
        raise ProtocolError("notice seq is 0; sequence numbers start at 1", offset=16)
    return Notice(slot, length, seq)


def _anonymous_file(size: int) -> int:
    """A descriptor of ``size`` bytes of shared memory with no name anywhere."""
    if hasattr(os, "memfd_create"):
        fd = os.memfd_create("hil-local-frames", os.MFD_CLOEXEC)
    else:  # pragma: no cover - macOS and others: an unlinked temporary file
        where = "/dev/shm" if os.path.isdir("/dev/shm") else None
        fd, path = tempfile.mkstemp(prefix="hil-local-frames-", dir=where)
        os.unlink(path)
    try:
        os.ftruncate(fd, size)
    except OSError:
        os.close(fd)
        raise
    return fd


@dataclass
class RingStats:
    """Harness-side counters of the ring."""

    written: int = 0
    overwritten_unread: int = 0  # a slot reused before the target had read its message


class ShmRing:
    """Harness side: the segment, and ``put(message) -> notice bytes``.

    Args:
        slots: ring length, 1..64.
        slot_bytes: largest message (header + payload, bytes) a slot holds.

    Raises:
        TransportError: the memory cannot be had (the message says how much).
    """

    def __init__(self, *, slots: int = DEFAULT_SLOTS, slot_bytes: int = DEFAULT_SLOT_BYTES) -> None:
        self._mm: mmap.mmap | None = None
        self._fd: int | None = None
        self.check_options(slots=slots, slot_bytes=slot_bytes)
        self.slots, self.slot_bytes, self.stride = slots, slot_bytes, slot_stride(slot_bytes)
        self.size = CONTROL_SIZE + slots * self.stride
        self.stats = RingStats()
        try:
            self._fd = _anonymous_file(self.size)
            self._mm = mmap.mmap(self._fd, self.size)
        except OSError as err:
            self.close()
            raise TransportError(f"cannot create {self.size} bytes of shared memory for frames: {err}") from err
        _CONTROL.pack_into(self._mm, 0, RING_MAGIC, LAYOUT_VERSION, slots, slot_bytes, self.stride)
        self._seq = 0
        self._slot_seq = [0] * slots

    @staticmethod
    def check_options(*, slots: int, slot_bytes: int) -> None:
        """Raises TransportError: ``slots`` or ``slot_bytes`` out of range (names it)."""
        if not 1 <= slots <= MAX_SLOTS:
            raise TransportError(f"shm slots={slots}: expected 1..{MAX_SLOTS}")
        if not HEADER_SIZE <= slot_bytes <= MAX_SLOT_BYTES:
            raise TransportError(f"shm slot_bytes={slot_bytes}: expected {HEADER_SIZE}..{MAX_SLOT_BYTES}")

    @property
    def fd(self) -> int:
        """The descriptor to hand to the target (until ``release_fd``)."""
        if self._fd is None:
            raise TransportError("the shared-memory ring's descriptor is already released")
        return self._fd

    def release_fd(self) -> None:
        """Close this process's descriptor once the target has inherited it (the
        mapping stays). Idempotent."""
        fd, self._fd = self._fd, None
        if fd is not None:
            os.close(fd)

    @property
    def consumed(self) -> int:
        """Seq of the last message the target finished reading (0: none yet)."""
        return _U64.unpack_from(self._mm, _CONSUMED_AT)[0] if self._mm is not None else 0

    def fits(self, nbytes: int) -> bool:
        return nbytes <= self.slot_bytes

    def put(self, message: bytes | bytearray | memoryview) -> bytes:
        """Write one whole message into the next slot; return the notice to send.

        Raises:
            TransportError: the ring is closed or the message does not fit a slot.
        """
        mm = self._mm
        if mm is None:
            raise TransportError("the shared-memory ring is closed")
        n = len(message)
        if n > self.slot_bytes:
            raise TransportError(f"a {n}-byte message does not fit a {self.slot_bytes}-byte slot")
        self._seq += 1
        seq = self._seq
        slot = (seq - 1) % self.slots
        prev = self._slot_seq[slot]
        if prev and _U64.unpack_from(mm, _CONSUMED_AT)[0] < prev:
            self.stats.overwritten_unread += 1
        at = CONTROL_SIZE + slot * self.stride
        _U64.pack_into(mm, at, 0)  # being written: a reader of the old message sees it change
        mm[at + SLOT_HEADER_SIZE:at + SLOT_HEADER_SIZE + n] = message
        _U64.pack_into(mm, at, seq)
        self._slot_seq[slot] = seq
        self.stats.written += 1
        return encode_notice(Notice(slot, n, seq))

    def close(self) -> None:
        """Unmap and close; idempotent, safe on a half-built ring. The memory goes
        when the target has closed its mapping too (or has exited)."""
        self.release_fd()
        mm, self._mm = getattr(self, "_mm", None), None
        if mm is not None:
            mm.close()

    def __enter__(self) -> ShmRing:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


@dataclass
class ReaderStats:
    """Target-side counters of the ring."""

    read: int = 0
    stale: int = 0  # overwritten before it was read
    torn: int = 0  # overwritten while it was read
    bad_notices: int = 0


class ShmReader:
    """Target side: maps the harness's segment and reads the message a notice names.

    Raises (``__init__``):
        TransportError: the descriptor is not a ring this reader understands.
    """

    def __init__(self, fd: int) -> None:
        self._mm: mmap.mmap | None = None
        self._view: memoryview | None = None
        self.stats = ReaderStats()
        try:
            size = os.fstat(fd).st_size
            if size < CONTROL_SIZE:
                raise TransportError(f"shared memory of {size} bytes has no control block")
            self._mm = mmap.mmap(fd, size)
        except OSError as err:
            raise TransportError(f"cannot map the frame ring (descriptor {fd}): {err}") from err
        finally:
            os.close(fd)  # the mapping stays
        magic, version, slots, slot_bytes, stride = _CONTROL.unpack_from(self._mm, 0)
        problem = None
        if magic != RING_MAGIC or version != LAYOUT_VERSION:
            problem = f"not a version-{LAYOUT_VERSION} frame ring (magic {magic!r}, version {version})"
        elif not 1 <= slots <= MAX_SLOTS or stride < SLOT_HEADER_SIZE + slot_bytes or stride % 64:
            problem = f"bad geometry: {slots} slots of {slot_bytes} bytes, stride {stride}"
        elif CONTROL_SIZE + slots * stride > size:
            problem = f"{slots} slots of stride {stride} do not fit {size} bytes"
        if problem:
            self.close()
            raise TransportError(f"frame ring: {problem}")
        self.slots, self.slot_bytes, self.stride = slots, slot_bytes, stride
        self._view = memoryview(self._mm)

    @classmethod
    def from_env(cls, environ: Mapping[str, str] | None = None) -> ShmReader | None:
        """The ring named by ``HIL_LOCAL_SHM`` (a descriptor number), or None when the
        harness offers none or it cannot be used (frames then come inline)."""
        text = (os.environ if environ is None else environ).get(ENV_SHM, "")
        if not text.isdigit():
            return None
        try:
            return cls(int(text))
        except TransportError:
            return None

    def read(self, n: Notice) -> Message | ProtocolError | None:
        """The message in the notice's slot (a ``ProtocolError`` when it does not
        decode or the notice does not fit the ring), or None when the slot was
        overwritten before or while it was read (counted in ``stale``/``torn``)."""
        view = self._view
        if view is None:
            return None
        if n.slot >= self.slots or not HEADER_SIZE <= n.length <= self.slot_bytes:
            self.stats.bad_notices += 1
            return ProtocolError(f"notice names slot {n.slot} with {n.length} bytes; the ring has "
                                 f"{self.slots} slots of {self.slot_bytes} bytes", offset=6)
        at = CONTROL_SIZE + n.slot * self.stride
        if _U64.unpack_from(view, at)[0] != n.seq:
            self.stats.stale += 1
            return None
        start = at + SLOT_HEADER_SIZE
        try:
            item: Message | ProtocolError = decode(view[start:start + n.length])  # copies the image out
        except ProtocolError as err:
            item = err
        if _U64.unpack_from(view, at)[0] != n.seq:
            self.stats.torn += 1
            return None
        _U64.pack_into(view, _CONSUMED_AT, n.seq)
        self.stats.read += 1
        return item

    def close(self) -> None:
        view, self._view = getattr(self, "_view", None), None
        if view is not None:
            view.release()
        mm, self._mm = getattr(self, "_mm", None), None
        if mm is not None:
            mm.close()


# The local transport's harness -> target stream: messages, and once the ring is
# negotiated, notices between them (one stream decoder: StreamDecoder(NOTICES)).
NOTICES = SideRecord(NOTICE_MAGIC, NOTICE_SIZE, decode_notice)


__all__ = ["DEFAULT_INLINE_BELOW", "DEFAULT_SLOTS", "DEFAULT_SLOT_BYTES", "ENV_SHM", "NOTICES",
           "NOTICE_MAGIC", "NOTICE_SIZE", "Notice", "ReaderStats", "RingStats", "SHM_FRAMES", "ShmReader",
           "ShmRing", "decode_notice", "encode_notice", "slot_stride"]
