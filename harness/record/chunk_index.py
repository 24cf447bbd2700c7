"""The MCAP writer's chunk indexes, kept on disk during the run instead of in memory.

``mcap.writer.Writer`` (mcap 1.6.0) keeps one ``ChunkIndex`` object per chunk until
``finish()`` writes them all into the summary section: a record with a dict of
message-index offsets per channel, ~40 KB a minute at the run's chunk rate, held for
the whole run (~60 MB over 24 h). :class:`ChunkIndexSpill` takes the place of that
list (the writer only appends to it and iterates it once, in ``finish()``): each
index is serialized as its MCAP record the moment the chunk is written and appended
to an unnamed temporary file beside the recording (``O_TMPFILE``: it vanishes with
the process, however it ends); at close the writer reads the records back in order
and copies them into the summary. One ``run.mcap``, byte for byte what the library
would have written; crash safety is unchanged (a crashed file has no summary either
way; its complete chunks are read as before).

What stays in memory: the file's write buffer (8 KiB) and a counter. At close the
writer builds its summary section in memory once (about 0.4 KB per chunk: ~35 MB for
a day at one chunk a second), as it always did.

Raises: ``OSError`` from :meth:`ChunkIndexSpill.append` when the file cannot be
written (a full disk): the recorder treats it as any write failure of the recording.
"""

from __future__ import annotations

import io
import struct
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from mcap.data_stream import RecordBuilder
from mcap.records import ChunkIndex

_HEADER = struct.Struct("<BQ")  # opcode, record length: the MCAP record header
_WRITER_ATTR = "_Writer__chunk_indices"  # mcap.writer.Writer's list (name-mangled private)


class _RawRecord:
    """One serialized record, written as is into the writer's summary builder."""

    __slots__ = ("data",)

    def __init__(self, data: bytes) -> None:
        self.data = data

    def write(self, stream: RecordBuilder) -> None:
        stream.write(self.data)


class ChunkIndexSpill:
    """Stands in for ``mcap.writer.Writer``'s list of chunk indexes (module docstring).

    Args:
        folder: where the unnamed file lives (the recording's folder: the same disk).
    """

    def __init__(self, folder: Path) -> None:
        self._file = tempfile.TemporaryFile(dir=folder, prefix=".hil-chunk-index-")  # noqa: SIM115 (close())
        self.count = 0
        self.bytes = 0

    def append(self, index: ChunkIndex) -> None:
        """Serialize ``index`` and append it to the file.

        Raises:
            OSError: the file cannot be written.
        """
        builder = RecordBuilder()
        index.write(builder)
        data = builder.end()
        self._file.write(data)
        self.count += 1
        self.bytes += len(data)

    def __len__(self) -> int:
        return self.count

    def __iter__(self) -> Iterator[_RawRecord]:
        """The records in the order appended (for the writer's ``finish()``)."""
        self._file.flush()
        self._file.seek(0)
        for _ in range(self.count):
            head = self._file.read(_HEADER.size)
            _, length = _HEADER.unpack(head)
            yield _RawRecord(head + self._file.read(length))
        self._file.seek(0, io.SEEK_END)

    def close(self) -> None:
        self._file.close()


def install(writer: Any, folder: Path) -> ChunkIndexSpill | None:
    """Put a :class:`ChunkIndexSpill` in place of ``writer``'s chunk-index list; None
    (nothing changed) when the writer keeps its indexes elsewhere than mcap 1.6.0 does
    (tests/harness/record/test_chunk_index.py fails then, so an upgrade is noticed)."""
    current = getattr(writer, _WRITER_ATTR, None)
    if not isinstance(current, list) or current:
        return None
    spill = ChunkIndexSpill(folder)
    setattr(writer, _WRITER_ATTR, spill)
    return spill
