"""Recorder: round trip through the standard mcap reader, backpressure, errors, and
what a crashed (truncated) recording still yields."""

from __future__ import annotations

import base64
import errno
import io
import json
import os
import signal
import subprocess
import sys
import threading
from pathlib import Path

import cv2
import numpy as np
import pytest
from mcap.exceptions import EndOfFile, McapError
from mcap.reader import NonSeekingReader, make_reader

from hil.common.errors import RecordingError
from hil.common.errors import ConfigError, HilError
from hil.harness.record import foxglove_schemas as fx
from hil.harness.record import recorder as recorder_module
from hil.harness.record.recorder import Recorder, RecorderStats, iter_salvaged_messages

STATE_SCHEMA = {"type": "object", "properties": {"i": {"type": "integer"}}}


@pytest.fixture(autouse=True)
def no_writer_thread_left():
    yield
    left = [t for t in threading.enumerate() if t.name == "mcap-writer"]
    assert not left, "a recorder was not closed"


def _read_all(path: Path):
    with open(path, "rb") as f:
        reader = make_reader(f)
        messages = list(reader.iter_messages(log_time_order=False))
        metadata = {m.name: m.metadata for m in reader.iter_metadata()}
        summary = reader.get_summary()
    return messages, metadata, summary


def _jpeg(height: int = 240, width: int = 320) -> bytes:
    yy, xx = np.mgrid[0:height, 0:width]
    img = np.dstack([xx % 256, yy % 256, (xx + yy) % 256]).astype(np.uint8)
    ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, 85])
    assert ok
    return buf.tobytes()


def test_round_trip_json_and_jpeg(tmp_path: Path) -> None:
    path = tmp_path / "run.mcap"
    jpeg = _jpeg()
    with Recorder(path, metadata={"run": {"scenario": "cut_in", "seed": "7"}}) as rec:
        rec.register_json_channel("/estimate", "hil.Estimate", STATE_SCHEMA)
        rec.register_json_channel("/estimate", "hil.Estimate", STATE_SCHEMA)  # idempotent
        rec.register_json_channel("/events", "hil.Event", {"type": "object"})
        for i in range(50):
            t = 1_000_000_000 + i * 100_000_000
            assert rec.write_json("/estimate", {"i": i, "x": np.float32(0.5), "v": np.arange(2)},
                                  log_time_ns=t, publish_time_ns=t - 7)
            if i % 10 == 0:
                assert rec.write_json("/events", {"kind": "spike", "i": i}, log_time_ns=t, publish_time_ns=t)
            if i % 5 == 0:
                assert rec.write_image("/cam/front", jpeg, fmt="jpeg", frame_id="front",
                                       log_time_ns=t, publish_time_ns=t - 3_000_000)
        rec.add_metadata("versions", {"harness": "0.1.0"})
    stats = rec.stats
    assert (stats.enqueued, stats.written, stats.dropped, stats.errors) == (65, 65, 0, 0)
    assert stats.first_error is None and stats.bytes_written == path.stat().st_size

    messages, metadata, summary = _read_all(path)
    by_topic: dict[str, list] = {}
    for schema, channel, message in messages:
        assert channel.message_encoding == "json" and schema.encoding == "jsonschema"
        by_topic.setdefault(channel.topic, []).append((schema, message))
    assert {t: len(v) for t, v in by_topic.items()} == {"/estimate": 50, "/events": 5, "/cam/front": 10}
    assert {t: v[0][0].name for t, v in by_topic.items()} == {
        "/estimate": "hil.Estimate", "/events": "hil.Event", "/cam/front": fx.COMPRESSED_IMAGE}

    est = by_topic["/estimate"]
    assert [m.sequence for _, m in est] == list(range(1, 51))
    assert [json.loads(m.data)["i"] for _, m in est] == list(range(50))
    assert json.loads(est[3][1].data) == {"i": 3, "x": 0.5, "v": [0, 1]}
    assert est[3][1].log_time == 1_300_000_000 and est[3][1].publish_time == 1_299_999_993

    _, img_msg = by_topic["/cam/front"][1]
    assert img_msg.log_time == 1_500_000_000 and img_msg.publish_time == 1_497_000_000
    img = json.loads(img_msg.data)
    assert img["format"] == "jpeg" and img["frame_id"] == "front"
    assert img["timestamp"] == {"sec": 1, "nsec": 497_000_000}
    decoded = cv2.imdecode(np.frombuffer(base64.b64decode(img["data"]), np.uint8), cv2.IMREAD_COLOR)
    assert decoded.shape == (240, 320, 3)

    assert metadata["run"] == {"scenario": "cut_in", "seed": "7"}
    assert metadata["versions"] == {"harness": "0.1.0"}
    assert metadata["recorder"]["written"] == "65" and metadata["recorder"]["dropped"] == "0"
    assert metadata["recorder"]["queue_size"] == "4096"
    assert summary.statistics.message_count == 65


def test_written_counts_every_message_in_the_file_derived_ones_too(tmp_path: Path) -> None:
    # Derived messages (the Foxglove views) are written on the writer thread; the
    # count must still equal the file's own statistics record (issue 25: a report
    # said "written 2538" of a run.mcap holding 4,340 messages).
    path = tmp_path / "run.mcap"
    with Recorder(path) as rec:
        rec.register_json_channel("/events", "hil.Event", {"type": "object"})
        rec.register_json_channel("/log", "hil.Text", {"type": "object"})
        rec.add_derivation("/events", lambda ev, lt, pt: [("/log", {"text": ev["kind"]}, lt, pt)] * ev["n"])
        for i in range(30):
            rec.write_json("/events", {"kind": "k", "n": i % 3}, log_time_ns=10**9 + i, publish_time_ns=10**9 + i)
    stats = rec.stats
    _, metadata, summary = _read_all(path)
    derived = sum(i % 3 for i in range(30))
    assert summary.statistics.message_count == 30 + derived
    assert (stats.enqueued, stats.written, stats.derived) == (30, 30 + derived, derived)
    assert metadata["recorder"]["written"] == str(stats.written)
    assert metadata["recorder"]["derived"] == str(derived)


def test_raw_image_is_copied_at_the_call(tmp_path: Path) -> None:
    path = tmp_path / "raw.mcap"
    pixels = np.arange(4 * 6 * 3, dtype=np.uint8).reshape(4, 6, 3)
    expected = pixels.copy()
    with Recorder(path) as rec:
        assert rec.write_raw_image("/cam/raw", pixels, encoding="rgb8", frame_id="cam",
                                   log_time_ns=5, publish_time_ns=4)
        pixels[:] = 0  # the caller reuses its render buffer at once
    [(schema, _, message)] = _read_all(path)[0]
    assert schema.name == fx.RAW_IMAGE
    raw = json.loads(message.data)
    assert (raw["width"], raw["height"], raw["step"], raw["encoding"]) == (6, 4, 18, "rgb8")
    got = np.frombuffer(base64.b64decode(raw["data"]), np.uint8).reshape(4, 6, 3)
    assert np.array_equal(got, expected)


def test_full_queue_drops_newest_and_counts_every_drop(tmp_path: Path) -> None:
    path = tmp_path / "overflow.mcap"
    big = np.random.default_rng(0).bytes(1 << 20)  # 1 MiB: the writer needs ~ms each
    attempted = 64
    with Recorder(path, queue_size=16) as rec:
        accepted = [rec.write_image("/big", big, fmt="jpeg", frame_id="f", log_time_ns=i, publish_time_ns=i)
                    for i in range(attempted)]
    stats = rec.stats
    assert stats.dropped > 0
    assert stats.dropped == accepted.count(False)
    assert stats.written + stats.dropped == attempted
    assert stats.enqueued == stats.written and stats.max_queue_depth <= 16

    messages, metadata, _ = _read_all(path)
    assert len(messages) == stats.written
    assert metadata["recorder"]["dropped"] == str(stats.dropped)
    assert metadata["recorder"]["written"] == str(stats.written)
    # Drops show as gaps in the channel's sequence numbers.
    sequences = [m.sequence for _, _, m in messages]
    assert sequences == sorted(sequences)
    assert attempted - len(sequences) == stats.dropped


def test_bad_message_is_counted_and_recording_continues(tmp_path: Path) -> None:
    path = tmp_path / "bad.mcap"
    with Recorder(path) as rec:
        rec.register_json_channel("/s", "S", STATE_SCHEMA)
        assert rec.write_json("/s", {"i": 0}, log_time_ns=1, publish_time_ns=1)
        assert rec.write_json("/s", {"i": {1, 2}}, log_time_ns=2, publish_time_ns=2)  # a set
        assert rec.write_json("/s", {"i": 3, "v": [float("nan"), np.float32("inf"), 1.5]},
                              log_time_ns=3, publish_time_ns=3)
    stats = rec.stats
    assert (stats.written, stats.errors) == (2, 1)
    assert "set" in stats.first_error and "/s" in stats.first_error
    messages, metadata, _ = _read_all(path)
    assert [json.loads(m.data) for _, _, m in messages] == [{"i": 0}, {"i": 3, "v": [None, None, 1.5]}]
    assert metadata["recorder"]["errors"] == "1"
    assert "set" in metadata["recorder"]["first_error"]


def test_write_failure_is_counted_and_raised_once_at_close(tmp_path: Path, monkeypatch) -> None:
    real_write = recorder_module._Sink.write
    disk_full = threading.Event()

    def write(self, data):
        if disk_full.is_set():
            raise OSError(errno.ENOSPC, "No space left on device")
        return real_write(self, data)

    monkeypatch.setattr(recorder_module._Sink, "write", write)
    rec = Recorder(tmp_path / "full.mcap")
    disk_full.set()  # the disk fills up after the header
    rec.register_json_channel("/s", "S", STATE_SCHEMA)
    for i in range(3):
        rec.write_json("/s", {"i": i}, log_time_ns=i, publish_time_ns=i)
    assert rec.flush()
    rec.write_json("/s", {"i": 9}, log_time_ns=9, publish_time_ns=9)
    with pytest.raises(RecordingError, match="No space left") as info:
        rec.close()
    # A full disk is a failure of the run's file system, not of the configuration.
    assert not isinstance(info.value, ConfigError) and isinstance(info.value, HilError)
    assert isinstance(info.value.__cause__, OSError)
    stats = rec.close()  # raised once; now just the counters
    assert stats.errors >= 2 and "No space left" in stats.first_error


def test_close_is_idempotent_and_writes_after_close_are_dropped(tmp_path: Path) -> None:
    rec = Recorder(tmp_path / "c.mcap")
    rec.register_json_channel("/s", "S", STATE_SCHEMA)
    rec.write_json("/s", {"i": 1}, log_time_ns=1, publish_time_ns=1)
    try:
        raise KeyboardInterrupt  # as if Ctrl-C hit the simulation loop
    except KeyboardInterrupt:
        pass
    finally:
        first = rec.close()
    assert isinstance(first, RecorderStats) and first.written == 1
    assert rec.close() == first
    assert rec.flush() is False
    assert rec.write_json("/s", {"i": 2}, log_time_ns=2, publish_time_ns=2) is False
    assert rec.stats.dropped == 1
    with pytest.raises(ConfigError, match="closed"):
        rec.add_metadata("late", {"a": "b"})
    assert len(_read_all(tmp_path / "c.mcap")[0]) == 1


def test_empty_recording_is_a_valid_file(tmp_path: Path) -> None:
    with Recorder(tmp_path / "empty.mcap", compression="zstd"):
        pass
    messages, metadata, _ = _read_all(tmp_path / "empty.mcap")
    assert messages == [] and metadata["recorder"]["compression"] == "zstd"


@pytest.mark.parametrize("make_path", [
    lambda tmp: tmp / "missing" / "run.mcap",
    lambda tmp: tmp,  # a folder, not a file
])
def test_unusable_path_is_one_line_config_error(tmp_path: Path, make_path) -> None:
    bad = make_path(tmp_path)
    with pytest.raises(ConfigError) as info:
        Recorder(bad)
    assert str(bad) in str(info.value) and "\n" not in str(info.value)


def test_os_error_is_wrapped_in_config_error(tmp_path: Path) -> None:
    too_long = tmp_path / ("x" * 300 + ".mcap")  # ENAMETOOLONG, even for root
    with pytest.raises(ConfigError, match="writable") as info:
        Recorder(too_long)
    assert isinstance(info.value.__cause__, OSError) and "\n" not in str(info.value)


@pytest.mark.skipif(os.name != "posix" or os.geteuid() == 0, reason="root may write anywhere")
def test_read_only_folder_wraps_the_os_error(tmp_path: Path) -> None:
    folder = tmp_path / "ro"
    folder.mkdir(mode=0o500)
    try:
        with pytest.raises(ConfigError, match="writable") as info:
            Recorder(folder / "run.mcap")
        assert isinstance(info.value.__cause__, OSError)
    finally:
        folder.chmod(0o700)


def test_misuse_raises_config_error(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="compression"):
        Recorder(tmp_path / "x.mcap", compression="gzip")
    with pytest.raises(ConfigError, match="queue_size"):
        Recorder(tmp_path / "x.mcap", queue_size=0)
    with Recorder(tmp_path / "x.mcap") as rec:
        with pytest.raises(ConfigError, match="register_json_channel"):
            rec.write_json("/nope", {}, log_time_ns=0, publish_time_ns=0)
        rec.register_json_channel("/s", "S", STATE_SCHEMA)
        with pytest.raises(ConfigError, match="already registered"):
            rec.register_json_channel("/s", "T", STATE_SCHEMA)
        with pytest.raises(ConfigError, match="carries"):
            rec.write_image("/s", b"x", fmt="jpeg", frame_id="f", log_time_ns=0, publish_time_ns=0)
        with pytest.raises(ConfigError, match="format"):
            rec.write_image("/img", b"x", fmt="bmp", frame_id="f", log_time_ns=0, publish_time_ns=0)
        with pytest.raises(ConfigError, match="shape"):
            rec.write_raw_image("/raw", np.zeros((4, 4), np.uint8), encoding="rgb8", frame_id="f",
                                log_time_ns=0, publish_time_ns=0)
        with pytest.raises(ConfigError, match="reserved"):
            rec.add_metadata("recorder", {})
    assert issubclass(ConfigError, HilError)


def test_chunks_end_by_log_time_span(tmp_path: Path) -> None:
    path = tmp_path / "span.mcap"
    with Recorder(path, chunk_duration_ns=1_000) as rec:
        rec.register_json_channel("/s", "S", STATE_SCHEMA)
        for i in range(100):  # 100 ns apart: ~10 chunks of 1 µs of log time each
            rec.write_json("/s", {"i": i}, log_time_ns=i * 100, publish_time_ns=i * 100)
    summary = _read_all(path)[2]
    assert 9 <= summary.statistics.chunk_count <= 11


def test_lagging_log_times_do_not_cut_chunks(tmp_path: Path) -> None:
    """A topic whose log times lag the others by more than the chunk duration (the
    analysis behind real time) once ended a chunk every other message."""
    path = tmp_path / "lag.mcap"
    with Recorder(path, chunk_duration_ns=1_000_000_000) as rec:
        rec.register_json_channel("/now", "S", STATE_SCHEMA)
        rec.register_json_channel("/late", "S", STATE_SCHEMA)
        for i in range(300):  # 3 s of log time, 10 ms apart; /late 5 s behind
            t = 10_000_000_000 + i * 10_000_000
            rec.write_json("/now", {"i": i}, log_time_ns=t, publish_time_ns=t)
            rec.write_json("/late", {"i": i}, log_time_ns=t - 5_000_000_000, publish_time_ns=t)
    summary = _read_all(path)[2]
    assert 2 <= summary.statistics.chunk_count <= 4, summary.statistics.chunk_count  # one a second, not 300


def _write_numbered(rec: Recorder, start: int, stop: int) -> None:
    for i in range(start, stop):
        rec.write_json("/s", {"i": i, "pad": "x" * 100}, log_time_ns=i, publish_time_ns=i)
        if i % 50 == 0:
            rec.write_image("/cam", b"\xff\xd8" + bytes(2000), fmt="jpeg", frame_id="c",
                            log_time_ns=i, publish_time_ns=i)


def test_copy_of_open_file_reads_up_to_last_complete_chunk(tmp_path: Path) -> None:
    path = tmp_path / "open.mcap"
    with Recorder(path, chunk_size=16 * 1024, chunk_duration_ns=None) as rec:
        rec.register_json_channel("/s", "S", STATE_SCHEMA)
        _write_numbered(rec, 0, 1000)  # ~140 KB: several complete chunks
        assert rec.flush()
        snapshot = path.read_bytes()  # what a kill -9 right now would leave
        _write_numbered(rec, 1000, 1100)
    assert len(snapshot) < path.stat().st_size

    # make_reader needs the footer; the linear reader yields chunk by chunk.
    with pytest.raises(McapError):
        list(make_reader(io.BytesIO(snapshot)).iter_messages())
    got = []
    with pytest.raises(EndOfFile):
        for _, channel, message in NonSeekingReader(io.BytesIO(snapshot), validate_crcs=True).iter_messages(
                log_time_order=False):
            got.append((channel.topic, message.log_time))
    assert [t for topic, t in got if topic == "/s"] == list(range(1000))
    assert len(got) == 1000 + 20

    # Cut inside the chunk written after the snapshot: the same messages survive.
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(path.read_bytes()[: len(snapshot) + 200])
    assert len(list(iter_salvaged_messages(cut))) == 1020
    assert len(list(iter_salvaged_messages(path))) == 1100 + 22


_CHILD = """
import sys
from hil.harness.record.recorder import Recorder
rec = Recorder(sys.argv[1], chunk_size=4096, chunk_duration_ns=None)
rec.register_json_channel("/s", "S", {})
for i in range(500):
    rec.write_json("/s", {"i": i, "pad": "x" * 100}, log_time_ns=i, publish_time_ns=i)
assert rec.flush()
print("flushed", flush=True)
for i in range(500, 510):  # ~1.3 KB: stays in the unfinished chunk
    rec.write_json("/s", {"i": i, "pad": "x" * 100}, log_time_ns=i, publish_time_ns=i)
sys.stdin.read()
"""


@pytest.mark.skipif(not hasattr(signal, "SIGKILL"), reason="needs SIGKILL")
def test_kill_9_leaves_complete_chunks_readable(tmp_path: Path) -> None:
    path = tmp_path / "killed.mcap"
    proc = subprocess.Popen([sys.executable, "-c", _CHILD, str(path)],
                            stdin=subprocess.PIPE, stdout=subprocess.PIPE)
    try:
        assert proc.stdout.readline() == b"flushed\n"
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=10)
        proc.stdin.close()
        proc.stdout.close()
    assert proc.returncode == -signal.SIGKILL
    got = [json.loads(m.data)["i"] for _, _, m in iter_salvaged_messages(path)]
    assert got == list(range(500))


def test_salvage_rejects_a_file_that_is_not_mcap(tmp_path: Path) -> None:
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"not an mcap file at all")
    with pytest.raises(ConfigError, match="not an MCAP"):
        list(iter_salvaged_messages(junk))


def test_foxglove_helpers() -> None:
    assert fx.ns_to_foxglove_time(1_500_000_001) == {"sec": 1, "nsec": 500_000_001}
    assert fx.ns_to_foxglove_duration(-1) == {"sec": -1, "nsec": 999_999_999}
    with pytest.raises(ValueError):
        fx.ns_to_foxglove_time(-1)
    for name in (fx.COMPRESSED_IMAGE, fx.RAW_IMAGE, fx.FRAME_TRANSFORM, fx.SCENE_UPDATE):
        schema = fx.schema_for(name)
        assert schema["title"] == name
        json.dumps(schema)
    entity_props = fx.scene_update_schema()["properties"]["entities"]["items"]["properties"]
    cube_props = entity_props["cubes"]["items"]["properties"]
    assert set(cube_props) == {"pose", "size", "color"}
    assert set(fx.frame_transform_schema()["properties"]) == {
        "timestamp", "parent_frame_id", "child_frame_id", "translation", "rotation"}
    entity = fx.scene_entity(entity_id="car", frame_id="world", timestamp_ns=5,
                             cubes=[{"pose": fx.pose((1, 2, 0)), "size": {"x": 4, "y": 2, "z": 1.5},
                                     "color": {"r": 1, "g": 0, "b": 0, "a": 1}}])
    assert set(entity) == set(entity_props)
    assert entity["texts"] == [] and entity["cubes"][0]["pose"]["position"] == {"x": 1.0, "y": 2.0, "z": 0.0}
    with pytest.raises(ValueError, match="boxes"):
        fx.scene_entity(entity_id="a", frame_id="w", timestamp_ns=0, boxes=[])
