"""Every message of an MCAP file in file order, read straight off the file's bytes.

The readers of a finished run (the report, the case windows, ``hil compare``, replay)
go over every message of ``run.mcap`` once. The ``mcap`` package's stream reader
builds an object for every record (message indexes included) through a stream
wrapper: at 64 vehicles that was most of the report's time (bench/README, issue 24).
This walks the file's bytes with ``struct`` and makes an object only for what it
yields: the same ``Schema``, ``Channel`` and ``Message`` records of
``mcap.records`` the package's reader yields, in the same order, up to the last
complete chunk (a crashed run's file ends anywhere), a chunk whose CRC fails ending
it like a cut. Schema and channel records are parsed by the package itself.
"""

from __future__ import annotations

import io
import struct
import zlib
from collections.abc import Iterator
from typing import BinaryIO

from mcap.data_stream import ReadDataStream
from mcap.exceptions import InvalidMagic
from mcap.records import Channel, Message, Schema

MAGIC = b"\x89MCAP0\r\n"
_OP_SCHEMA, _OP_CHANNEL, _OP_MESSAGE, _OP_CHUNK, _OP_DATA_END, _OP_FOOTER = 0x03, 0x04, 0x05, 0x06, 0x0F, 0x02
_RECORD = struct.Struct("<BQ")          # opcode, content length
_MESSAGE = struct.Struct("<HIQQ")       # channel id, sequence, log time, publish time
_CHUNK = struct.Struct("<QQQI")         # start time, end time, uncompressed size, uncompressed CRC
_U32 = struct.Struct("<I")
_U64 = struct.Struct("<Q")

Item = tuple[Schema | None, Channel, Message]


class Cut(Exception):
    """The file ends (or is damaged) here: what came before stands."""


def iter_messages(f: BinaryIO) -> Iterator[Item]:
    """The messages of the MCAP file open as ``f`` (binary, seekable), in file order, up
    to the last complete chunk. Plain reads and ``bytes`` (no ``mmap`` or ``memoryview``
    outlives a consumer that stops early).

    Raises:
        InvalidMagic: the file does not start as MCAP.
    """
    size = f.seek(0, io.SEEK_END)
    f.seek(0)
    magic = f.read(len(MAGIC))
    if magic != MAGIC:
        raise InvalidMagic(magic)
    scan = _Scan()
    while True:
        head = f.read(_RECORD.size)
        if len(head) < _RECORD.size:
            return  # the end, or the cut inside a record's opcode or length
        op, n = _RECORD.unpack(head)
        if op in (_OP_CHUNK, _OP_SCHEMA, _OP_CHANNEL, _OP_MESSAGE):
            body = f.read(n)
            if len(body) < n:
                return  # the cut: an incomplete record
            if op == _OP_CHUNK:
                try:
                    records = _chunk_records(body)
                except Cut:
                    return
                yield from scan.records(records)
            else:
                yield from scan.records(head + body)
        elif op in (_OP_DATA_END, _OP_FOOTER):
            return  # the summary section repeats schemas and channels only
        elif f.tell() + n > size:
            return
        else:
            f.seek(n, io.SEEK_CUR)  # message indexes, attachments, metadata: not messages


class _Scan:
    def __init__(self) -> None:
        self.schemas: dict[int, Schema] = {}
        self.channels: dict[int, tuple[Schema | None, Channel]] = {}

    def records(self, buf: bytes) -> Iterator[Item]:
        """The messages among the records of ``buf`` (a chunk's, or one record outside
        chunks), learning its schemas and channels."""
        channels, unpack_record, unpack_message = self.channels, _RECORD.unpack_from, _MESSAGE.unpack_from
        at, end = 0, len(buf)
        while at + _RECORD.size <= end:
            op, n = unpack_record(buf, at)
            body, at = at + _RECORD.size, at + _RECORD.size + n
            if at > end:
                return
            if op == _OP_MESSAGE:
                cid, seq, log_time, publish_time = unpack_message(buf, body)
                known = channels.get(cid)
                if known is None:
                    return  # a message before its channel: damaged; stop as the package's reader would
                yield known[0], known[1], Message(channel_id=cid, log_time=log_time, publish_time=publish_time,
                                                  sequence=seq, data=buf[body + _MESSAGE.size:at])
            elif op == _OP_SCHEMA:
                s = Schema.read(ReadDataStream(io.BytesIO(buf[body:at])))
                self.schemas[s.id] = s
            elif op == _OP_CHANNEL:
                c = Channel.read(ReadDataStream(io.BytesIO(buf[body:at])))
                if c.schema_id != 0 and c.schema_id not in self.schemas:
                    return
                channels[c.id] = (self.schemas.get(c.schema_id) if c.schema_id else None, c)


def _chunk_records(body: bytes) -> bytes:
    """A chunk record's records, decompressed and CRC-checked.

    Raises:
        Cut: damaged (CRC, compression, lengths).
    """
    try:
        _start, _end, size, crc = _CHUNK.unpack_from(body, 0)
        at = _CHUNK.size
        (n,) = _U32.unpack_from(body, at)
        compression = body[at + 4:at + 4 + n].decode()
        at += 4 + n
        (n,) = _U64.unpack_from(body, at)
        data = body[at + 8:at + 8 + n]
        if len(data) != n:
            raise Cut
        if compression == "zstd":
            import zstandard

            records: bytes = zstandard.ZstdDecompressor().decompress(data, max_output_size=size)
        elif compression == "lz4":
            import lz4.frame

            records = lz4.frame.decompress(data)
        elif compression == "":
            records = data
        else:
            raise Cut
    except Exception as err:  # noqa: BLE001 - struct, unicode, a decompressor's own error, Cut: damage
        raise Cut from err
    if len(records) != size or (crc and zlib.crc32(records) != crc):
        raise Cut
    return records


__all__ = ["MAGIC", "iter_messages"]
