"""Splitting a byte stream (Unix or TCP socket, ISO-TP) into protocol messages.

Stream transports feed whatever bytes arrived; the decoder returns the messages they
completed and resynchronises on the next magic after a bad header (PROTOCOL.md,
"What a receiver does with a bad message"). A stream may also carry one kind of
fixed-size side record between messages, with its own magic (the local transport's
shared-memory notices, PROTOCOL.md section 10): :class:`SideRecord` names it.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Generic, TypeVar

from hil.adapters.wire.messages import Message
from hil.adapters.wire.protocol import (HEADER_SIZE, MAGIC, STREAM_BUFFER_LIMIT, Header, as_view, decode, decode_header,
                                        magic_error)
from hil.common.errors import ProtocolError


R = TypeVar("R")


@dataclass(frozen=True)
class SideRecord(Generic[R]):
    """A fixed-size record that may sit between messages: ``magic`` (4 bytes), its
    ``size`` and ``decode`` (raises ``ProtocolError`` for a bad one)."""

    magic: bytes
    size: int
    decode: Callable[[bytes | bytearray | memoryview], R]


class StreamDecoder(Generic[R]):
    """Splits a byte stream (Unix/TCP socket, ISO-TP) into messages.

    ``feed`` takes whatever bytes arrived and returns the messages completed by them,
    in order, with a ``ProtocolError`` in place of each message that could not be
    decoded. A bad header loses sync: the error is reported once and the decoder skips
    to the next ``MAGIC`` (or side record's magic) after the bad start. With ``side``,
    its records come back decoded, in stream order among the messages (``R`` is their
    type; a decoder without side records is a ``StreamDecoder[NoReturn]``). A good header with a bad payload is
    reported and skipped by its (trusted) length. The buffer never holds more than
    ``STREAM_BUFFER_LIMIT`` (``HEADER_SIZE + MAX_PAYLOAD``) bytes.

    Attributes:
        messages: messages decoded so far.
        errors: ``ProtocolError`` s reported so far.
    """

    def __init__(self, side: SideRecord[R] | None = None) -> None:
        self._side = side
        self._buf = bytearray()
        self._pos = 0  # start of the unconsumed bytes in _buf
        self._header: Header | None = None  # validated header of the message at _pos
        self._skipping = False  # lost sync: skip non-magic bytes without reporting them
        self.messages = 0
        self.errors = 0

    @property
    def buffered(self) -> int:
        """Bytes held that are not yet part of a returned message or error."""
        return len(self._buf) - self._pos

    def wanted(self) -> int:
        """Bytes to read next so that the read ends at the end of the current unit
        (header, message, side record) at the latest, never inside the next one: a
        reader that reads at most this many bytes completes at most one message per
        read, so each message can carry its own receipt stamp. Always >= 1."""
        have = self.buffered
        if self._header is not None:
            return HEADER_SIZE + self._header.payload_len - have
        side = self._side
        if have >= len(MAGIC):  # a unit has begun (the rest was consumed or skipped)
            is_side = side is not None and self._buf[self._pos:self._pos + 4] == side.magic
            return (side.size if is_side and side is not None else HEADER_SIZE) - have
        # Nothing begun, or up to 3 bytes that may begin a magic: a header's worth,
        # or a side record's where that is shorter. A unit is never shorter than
        # this, so the read cannot pass its end even after skipped bytes.
        return (HEADER_SIZE if side is None else min(side.size, HEADER_SIZE)) - have

    def feed(self, data: bytes | bytearray | memoryview) -> list[Message | ProtocolError | R]:
        """Add received bytes; return the messages (and errors, and side records) they
        complete. Never raises for any content of ``data``."""
        side = self._side
        if side is not None and not self.buffered and len(data) == side.size and data[:4] == side.magic:
            try:  # the common case of a side channel: one record per recv
                record = side.decode(data)
            except ProtocolError:
                pass  # reported by the general path below
            else:
                self._skipping = False
                return [record]
        out: list[Message | ProtocolError | R] = []
        with as_view(data) as incoming:
            start, end = 0, incoming.nbytes
            while start < end:
                if self._pos and len(self._buf) + end - start > STREAM_BUFFER_LIMIT:
                    self._compact()
                room = STREAM_BUFFER_LIMIT - len(self._buf)  # >= 1: see _drain
                self._buf += incoming[start:start + room]
                start += room
                self._drain(out)
        if self._pos * 2 >= len(self._buf):
            self._compact()
        return out

    def _compact(self) -> None:
        del self._buf[:self._pos]
        self._pos = 0

    def _fail(self, out: list[Message | ProtocolError | R], err: ProtocolError) -> None:
        out.append(err)
        self.errors += 1
        self._skipping = True
        self._pos = self._next_magic(self._pos + 1)

    def _next_magic(self, start: int) -> int:
        """Where the next magic (of a message or a side record) begins at or after
        ``start``; without one ahead, keep the last 3 bytes: they may begin the next."""
        found = self._buf.find(MAGIC, start)
        if self._side is not None:
            other = self._buf.find(self._side.magic, start)
            if other >= 0 and (found < 0 or other < found):
                found = other
        return found if found >= 0 else max(start, len(self._buf) - 3)

    def _side_record(self, out: list[Message | ProtocolError | R], pos: int, avail: int) -> bool | None:
        """The side record at ``pos``: True when it was consumed (decoded or reported),
        None when more bytes are needed, False when ``pos`` holds none."""
        side = self._side
        if side is None or self._buf[pos:pos + 4] != side.magic:
            return False
        if avail < side.size:
            return None
        try:
            with memoryview(self._buf) as whole, whole[pos:pos + side.size] as raw:
                out.append(side.decode(raw))
        except ProtocolError as err:
            self._fail(out, err)
            return True
        self._pos, self._skipping = pos + side.size, False
        return True

    def _drain(self, out: list[Message | ProtocolError | R]) -> None:
        # Leaves fewer than STREAM_BUFFER_LIMIT unconsumed bytes: a whole message is
        # consumed as soon as it is present, and its length is at most that limit.
        buf = self._buf
        while True:
            pos = self._pos
            avail = len(buf) - pos
            if self._header is None:
                if avail < len(MAGIC):
                    return
                if buf[pos:pos + len(MAGIC)] != MAGIC:
                    side = self._side_record(out, pos, avail)
                    if side is None:
                        return
                    if side:
                        continue
                    if self._skipping:
                        self._pos = self._next_magic(pos + 1)
                    else:
                        self._fail(out, magic_error(bytes(buf[pos:pos + len(MAGIC)])))
                    continue
                if avail < HEADER_SIZE:
                    return
                try:
                    self._header = decode_header(bytes(buf[pos:pos + HEADER_SIZE]))
                except ProtocolError as err:
                    self._fail(out, err)
                    continue
                self._skipping = False
            header = self._header
            total = HEADER_SIZE + header.payload_len
            if avail < total:
                return
            self._header = None
            self._pos = pos + total
            try:
                with memoryview(buf) as whole, whole[pos:pos + total] as one:
                    msg = decode(one, header=header)
            except ProtocolError as err:
                out.append(err)
                self.errors += 1
            else:
                out.append(msg)
                self.messages += 1


__all__ = ["SideRecord", "StreamDecoder"]
