"""Splitting a byte stream (Unix or TCP socket, ISO-TP) into protocol messages.

Stream transports feed whatever bytes arrived; the decoder returns the messages they
completed and resynchronises on the next magic after a bad header (PROTOCOL.md,
"What a receiver does with a bad message").
"""

from __future__ import annotations

from hil.adapters.messages import Message
from hil.adapters.protocol import (HEADER_SIZE, MAGIC, STREAM_BUFFER_LIMIT, Header, as_view, decode,
                                   decode_header, magic_error)
from hil.common.errors import ProtocolError


class StreamDecoder:
    """Splits a byte stream (Unix/TCP socket, ISO-TP) into messages.

    ``feed`` takes whatever bytes arrived and returns the messages completed by them,
    in order, with a ``ProtocolError`` in place of each message that could not be
    decoded. A bad header loses sync: the error is reported once and the decoder skips
    to the next ``MAGIC`` after the bad start. A good header with a bad payload is
    reported and skipped by its (trusted) length. The buffer never holds more than
    ``STREAM_BUFFER_LIMIT`` (``HEADER_SIZE + MAX_PAYLOAD``) bytes.

    Attributes:
        messages: messages decoded so far.
        errors: ``ProtocolError`` s reported so far.
    """

    def __init__(self) -> None:
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

    def feed(self, data: bytes | bytearray | memoryview) -> list[Message | ProtocolError]:
        """Add received bytes; return the messages (and errors) they complete. Never
        raises for any content of ``data``."""
        out: list[Message | ProtocolError] = []
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

    def _fail(self, out: list[Message | ProtocolError], err: ProtocolError) -> None:
        out.append(err)
        self.errors += 1
        self._skipping = True
        found = self._buf.find(MAGIC, self._pos + 1)
        # Without a magic ahead, keep the last 3 bytes: they may begin the next one.
        self._pos = found if found >= 0 else max(self._pos + 1, len(self._buf) - 3)

    def _drain(self, out: list[Message | ProtocolError]) -> None:
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
                    if self._skipping:
                        found = buf.find(MAGIC, pos + 1)
                        self._pos = found if found >= 0 else len(buf) - 3
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


__all__ = ["StreamDecoder"]
