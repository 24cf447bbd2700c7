"""A day-long run stays bounded (issue 26, item 8): the MCAP writer's chunk indexes
go to a file beside the recording instead of memory, and the file is still exactly
what mcap would have written, with a summary and chunk indexes that read back."""

from __future__ import annotations

import io
import json
import tracemalloc
from pathlib import Path

from mcap.reader import SeekingReader, make_reader
from mcap.writer import CompressionType, Writer

from hil.harness.record import chunk_index
from hil.harness.record.recorder import Recorder

CHANNELS = 20  # a chunk index holds one message-index offset per channel in the chunk
CHUNKS = 3000


def _write(f: io.BufferedIOBase, *, spill_in: Path | None, chunks: int) -> tuple[int, chunk_index.ChunkIndexSpill | None]:
    """Write ``chunks`` chunks of one message per channel; returns the traced memory
    growth (bytes) between the first tenth and the end, and the spill if any."""
    w = Writer(f, chunk_size=1 << 30, compression=CompressionType.NONE)
    w.start(library="test")
    spill = chunk_index.install(w, spill_in) if spill_in is not None else None
    schema = w.register_schema(name="x", encoding="jsonschema", data=b"{}")
    ids = [w.register_channel(topic=f"/c{i}", message_encoding="json", schema_id=schema) for i in range(CHANNELS)]
    base = 0
    for c in range(chunks):
        if c == chunks // 10:
            base = tracemalloc.get_traced_memory()[0]
        for i in ids:
            w.add_message(channel_id=i, log_time=c * 1000 + i, publish_time=c, data=b'{"v":1}')
        w.flush()  # one chunk (and its index) per round, as the recorder's time-based chunks
    grown = tracemalloc.get_traced_memory()[0] - base
    w.finish()
    return grown, spill


def test_chunk_indexes_stay_on_disk_and_the_file_is_unchanged(tmp_path: Path):
    tracemalloc.start()
    try:
        with open(tmp_path / "plain.mcap", "wb") as f:
            grown_plain, _ = _write(f, spill_in=None, chunks=CHUNKS)
        with open(tmp_path / "spilled.mcap", "wb") as f:
            grown_spilled, spill = _write(f, spill_in=tmp_path, chunks=CHUNKS)
    finally:
        tracemalloc.stop()
    assert spill is not None and spill.count == CHUNKS
    print(f"memory growth over {CHUNKS * 0.9:.0f} chunks: mcap's list {grown_plain / 1e6:.2f} MB, "
          f"spilled {grown_spilled / 1e3:.1f} KB")
    per_chunk_plain = grown_plain / (CHUNKS * 0.9)
    assert per_chunk_plain > 1000, grown_plain  # the library holds ~KBs per chunk: what is measured can fail
    assert grown_spilled < 64 * 1024, (grown_spilled, grown_plain)  # flat: a write buffer, not a list
    # byte for byte what mcap writes by itself
    assert (tmp_path / "spilled.mcap").read_bytes() == (tmp_path / "plain.mcap").read_bytes()
    with open(tmp_path / "spilled.mcap", "rb") as f:
        reader = SeekingReader(f, validate_crcs=True)
        summary = reader.get_summary()
        assert summary is not None and len(summary.chunk_indexes) == CHUNKS == summary.statistics.chunk_count
        assert all(len(ci.message_index_offsets) == CHANNELS for ci in summary.chunk_indexes)
        assert sum(1 for _ in reader.iter_messages(topics=["/c7"])) == CHUNKS  # through the indexes
    spill.close()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["plain.mcap", "spilled.mcap"]  # the side file has no name


def test_the_recorder_spills_its_chunk_indexes(tmp_path: Path):
    with Recorder(tmp_path / "run.mcap", chunk_size=256, compression="zstd") as rec:
        rec.register_json_channel("/a", "hil.A", {"type": "object"})
        for i in range(2000):
            rec.write_json("/a", {"i": i, "pad": "x" * 64}, log_time_ns=i, publish_time_ns=i)
    with open(tmp_path / "run.mcap", "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        meta = {m.name: m.metadata for m in reader.iter_metadata()}
        assert [json.loads(m.data)["i"] for _, _, m in reader.iter_messages()] == list(range(2000))
    chunks = summary.statistics.chunk_count
    assert chunks > 100 and len(summary.chunk_indexes) == chunks
    assert meta["recorder"]["chunk_indexes_spilled"] == str(chunks)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run.mcap"]  # nothing left beside it
