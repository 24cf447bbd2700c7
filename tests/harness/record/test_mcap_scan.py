"""The fast linear MCAP reader (``hil.harness.record.mcap_scan``) against the ``mcap``
package's own non-seeking reader: the same schemas, channels and messages in the same
order, on a whole recording (a run's, with camera images in zstd chunks, and an old
one), cut at every kind of offset (the salvage of a crashed run), with a chunk's CRC
damaged, and with the unchunked and lz4 layouts the package can write."""

from __future__ import annotations

import io
import struct
from pathlib import Path

import pytest
from mcap.exceptions import McapError
from mcap.reader import NonSeekingReader
from mcap.stream_reader import CRCValidationError
from mcap.writer import CompressionType, Writer

from hil.common.errors import ConfigError
from hil.harness.record.mcap_scan import iter_messages
from hil.harness.record.recorder import iter_salvaged_messages

FIXTURE = Path(__file__).parent / "fixtures" / "run_before_orjson" / "run.mcap"


def _package(data: bytes) -> list[tuple]:
    out = []
    it = NonSeekingReader(io.BytesIO(data), validate_crcs=True).iter_messages(log_time_order=False)
    try:
        for s, c, m in it:
            out.append((s, c, m))
    except (McapError, struct.error, CRCValidationError):
        pass
    return out


def _ours(path: Path) -> list[tuple]:
    with open(path, "rb") as f:
        return list(iter_messages(f))


def _same(a: list[tuple], b: list[tuple]) -> None:
    assert len(a) == len(b)
    for (sa, ca, ma), (sb, cb, mb) in zip(a, b):
        assert (sa, ca) == (sb, cb)
        assert (ma.channel_id, ma.sequence, ma.log_time, ma.publish_time, ma.data) == \
            (mb.channel_id, mb.sequence, mb.log_time, mb.publish_time, mb.data)


def _written(tmp_path: Path, compression: CompressionType, *, chunk_size: int = 4096,
             use_chunking: bool = True) -> Path:
    path = tmp_path / f"w-{compression.value or 'none'}-{use_chunking}.mcap"
    with open(path, "wb") as f:
        w = Writer(f, compression=compression, chunk_size=chunk_size, use_chunking=use_chunking)
        w.start(profile="", library="test")
        sid = w.register_schema("s", "jsonschema", b"{}")
        chans = [w.register_channel(f"/t{i}", "json", sid) for i in range(3)]
        raw = w.register_channel("/raw", "application/octet-stream", 0)
        for k in range(400):
            w.add_message(chans[k % 3], log_time=k, publish_time=k + 1, data=b'{"k":%d}' % k, sequence=k)
            if k % 7 == 0:
                w.add_message(raw, log_time=k, publish_time=k, data=bytes(range(256)) * 3, sequence=k)
        w.finish()
    return path


def test_a_whole_recording_reads_the_same(tmp_path: Path) -> None:
    data = FIXTURE.read_bytes()
    ours = _ours(FIXTURE)
    assert len(ours) > 100
    _same(ours, _package(data))
    for comp, chunked in ((CompressionType.ZSTD, True), (CompressionType.LZ4, True), (CompressionType.NONE, True),
                          (CompressionType.NONE, False)):
        path = _written(tmp_path, comp, use_chunking=chunked)
        got = _ours(path)
        assert len(got) == 400 + 58
        _same(got, _package(path.read_bytes()))


@pytest.mark.parametrize("chunked", [True, False])
def test_a_cut_recording_yields_what_the_package_salvages(tmp_path: Path, chunked: bool) -> None:
    path = _written(tmp_path, CompressionType.ZSTD if chunked else CompressionType.NONE, use_chunking=chunked)
    data = path.read_bytes()
    cut = tmp_path / "cut.mcap"
    # Every offset of the first 3 KiB (header, schema, channels, the first chunk), then
    # every 97th: inside records' fixed fields, between records, inside chunk data.
    for at in [*range(8, 3072), *range(3072, len(data), 97)]:
        cut.write_bytes(data[:at])
        got = list(iter_salvaged_messages(cut))
        _same(got, _package(data[:at]))


def test_a_damaged_chunk_ends_it_like_a_cut(tmp_path: Path) -> None:
    path = _written(tmp_path, CompressionType.NONE)
    data = bytearray(path.read_bytes())
    # The third chunk's payload: flip a byte of a message's data (its CRC then fails).
    at = data.index(b'{"k":150}') + 2
    data[at] ^= 0xFF
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(bytes(data))
    got = list(iter_salvaged_messages(bad))
    assert 0 < len(got) < 400 and all(m.log_time < 150 for _, _, m in got)
    _same(got, _package(bytes(data)))


def test_not_an_mcap_file_is_a_config_error(tmp_path: Path) -> None:
    for content in (b"", b"\x89MCA", b"PK\x03\x04 not an mcap at all"):
        p = tmp_path / "x.mcap"
        p.write_bytes(content)
        with pytest.raises(ConfigError, match="not an MCAP file"):
            list(iter_salvaged_messages(p))


def test_a_reader_that_stops_early_leaves_nothing_behind(tmp_path: Path) -> None:
    # A consumer that takes a few messages and drops the rest (a search episode's hash
    # did): closing the reader, at once or by the garbage collector, raises nothing.
    import gc
    import sys

    path = _written(tmp_path, CompressionType.NONE)
    raised: list[object] = []
    hook, sys.unraisablehook = sys.unraisablehook, lambda u: raised.append(u.exc_value)
    try:
        for stop_after in (1, 57, 300):
            it = iter_salvaged_messages(path)
            for _ in range(stop_after):
                next(it)
            if stop_after == 57:
                del it
                gc.collect()
            else:
                it.close()
    finally:
        sys.unraisablehook = hook
    assert raised == []
