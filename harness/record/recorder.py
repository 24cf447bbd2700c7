"""MCAP recorder: producers enqueue, one writer thread serialises and writes.

The simulation loop (and any other producer thread) calls ``write_json``,
``write_image`` or ``write_raw_image``; each call only puts a tuple on a bounded
queue and never blocks or touches the disk. A single thread named ``mcap-writer``
serialises to JSON, base64-encodes images, compresses chunks and writes the file.

Backpressure: the queue holds ``queue_size`` messages; when it is full the *newest*
message is dropped, the call returns ``False``, and the drop is counted. Drops show in
:class:`RecorderStats`, as gaps in the per-channel MCAP sequence numbers (a sequence
number is taken before the enqueue attempt), and in the ``recorder`` metadata record
written at close.

Times: ``log_time_ns`` and ``publish_time_ns`` are integer nanoseconds, written as the
MCAP message ``log_time`` and ``publish_time``; Foxglove plays a file by log time. The
``timestamp`` field inside image messages is the publish time.

Wall-clock timeline: :meth:`Recorder.set_time_anchor` (before the first message)
adds ``realtime_ns - monotonic_ns`` of a :class:`TimeAnchor` to every ``log_time``
and to the ``timestamp`` of the Foxglove images, so Foxglove shows the run at the
date it happened; ``publish_time`` and every ``*_ns`` field inside messages stay on
the monotonic clock. The anchor is written as the ``time_anchor`` metadata record
(``realtime_ns``, ``monotonic_ns``, ``log_time_offset_ns``): ``log_time -
log_time_offset_ns`` is the monotonic time the producer gave.

Derived channels: :meth:`Recorder.add_derivation` runs a function on the writer
thread for every message of one topic; the messages it returns are written too
(Foxglove views of the hil.* channels, see :mod:`hil.harness.record.foxglove_out`). Their cost
stays off the producers.

Bounded memory: the writer's chunk indexes (one per chunk, the only thing of the
file it would otherwise hold for the whole run) go to an unnamed file beside the
recording until close (:mod:`hil.harness.record.chunk_index`).

Crash safety: messages are written in chunks. A chunk is written when it holds
``chunk_size`` bytes (default 1 MiB), when the newest log time written has moved on by
``chunk_duration_ns`` since the chunk began (default 1 s), on :meth:`Recorder.flush`
and at close. Only the newest log time counts: messages whose log time lags (estimates
stamped at capture while the analysis runs behind) once ended a chunk every few
messages, 50 chunks a second, when the lag passed the duration. Chunks go to the file with
unbuffered writes, so after a crash (``kill -9``) every complete chunk is on disk
and only the chunk in progress is lost.

Reading a truncated file (crash, no footer): ``mcap.reader.make_reader`` picks the
seeking reader, which needs the footer and summary, and fails. Read the file linearly
instead, *in file order* (``log_time_order=True``, the default, sorts the whole file
first and so raises before yielding anything), and stop at the first error::

    import struct
    from mcap.exceptions import McapError
    from mcap.reader import NonSeekingReader

    with open(path, "rb") as f:
        it = NonSeekingReader(f, validate_crcs=True).iter_messages(log_time_order=False)
        try:
            for schema, channel, message in it:
                ...
        except (McapError, struct.error):
            pass  # end of the complete chunks

Measured with mcap 1.6.0, cutting a file at every offset: a cut between records or
inside a chunk's data raises ``mcap.exceptions.EndOfFile`` (a partial chunk is never
decompressed); a cut inside a record's fixed-width header field raises
``struct.error``. Either way every message of the complete chunks before the cut has
been yielded. :func:`iter_salvaged_messages` yields the same, read straight off the
file's bytes (``hil.harness.record.mcap_scan``: ~3x faster, the same records; a CRC
that fails ends it too). (The Go ``mcap recover`` command rewrites such a file with a
summary and footer.)

Raises: :class:`hil.common.errors.ConfigError` for an unusable path or option, for a
message on a topic that was never registered; ``RecordingError`` from :meth:`Recorder.close` when
the file could not be written (disk full); bad messages (not JSON-serialisable) are
counted in ``stats.errors`` and skipped, never raised on the producer.
"""

from __future__ import annotations

import base64
import json
import os
import threading
import time
from collections.abc import Callable, Iterable, Iterator, Mapping
from dataclasses import dataclass
from enum import Enum, IntEnum
from pathlib import Path
from types import TracebackType
from typing import Any, BinaryIO, Protocol

import numpy as np
from mcap.exceptions import InvalidMagic
from mcap.records import Channel, Message, Schema
from mcap.writer import LIBRARY_IDENTIFIER, CompressionType, Writer

from hil.common.errors import ConfigError, RecordingError
from hil.harness import __version__
from hil.harness.engine.handoff import Handoff
from hil.harness.record import chunk_index
from hil.harness.record import foxglove_schemas as fx
from hil.harness.record.encoding import dumps

_MESSAGE_ENCODING = "json"
_SCHEMA_ENCODING = "jsonschema"
_SEQUENCE_MASK = 0xFFFF_FFFF  # MCAP sequence numbers are uint32
_IDLE_POLL_S = 0.5


class Compression(str, Enum):
    """Chunk compression."""

    LZ4 = "lz4"
    ZSTD = "zstd"
    NONE = "none"


_MCAP_COMPRESSION = {
    Compression.LZ4: CompressionType.LZ4,
    Compression.ZSTD: CompressionType.ZSTD,
    Compression.NONE: CompressionType.NONE,
}
_IMAGE_FORMATS = ("jpeg", "png")
_RAW_ENCODINGS = ("rgb8", "bgr8")


@dataclass(frozen=True)
class RecorderStats:
    """Counters of one recorder (messages unless named otherwise).

    ``written`` is every message in the file, the ``derived`` ones (written on the
    writer thread by :meth:`Recorder.add_derivation`, e.g. the Foxglove views)
    included: it equals the MCAP statistics record's ``message_count``.
    ``enqueued + dropped`` is every write attempt; once closed (and barring a write
    failure, which also counts in ``errors``), ``written - derived + errors == enqueued``.
    """

    enqueued: int
    written: int
    dropped: int
    errors: int
    bytes_written: int
    max_queue_depth: int
    first_error: str | None
    derived: int = 0


@dataclass(frozen=True)
class TimeAnchor:
    """The realtime clock read beside the monotonic clock (both integer ns)."""

    realtime_ns: int
    monotonic_ns: int

    @classmethod
    def capture(cls) -> TimeAnchor:
        """Read both clocks now (the monotonic read is the mean of two around the
        realtime read, so the pair is within a few hundred ns)."""
        m0 = time.monotonic_ns()
        r = time.time_ns()
        m1 = time.monotonic_ns()
        return cls(realtime_ns=r, monotonic_ns=(m0 + m1) // 2)

    @property
    def offset_ns(self) -> int:
        """Add to a monotonic time to get the wall-clock time (ns)."""
        return self.realtime_ns - self.monotonic_ns

    def to_metadata(self) -> dict[str, str]:
        return {"realtime_ns": str(self.realtime_ns), "monotonic_ns": str(self.monotonic_ns),
                "log_time_offset_ns": str(self.offset_ns), "clock": "CLOCK_MONOTONIC"}


class Tap(Protocol):
    """Something that sees every message the writer thread writes (a live view)."""

    def offer(self, topic: str, schema_name: str, schema: bytes, data: bytes, log_time_ns: int) -> None: ...

    def close(self) -> Any: ...

    def metadata(self) -> dict[str, str]: ...


# A derivation gets (message, log_time_ns, publish_time_ns) with monotonic times and
# returns messages (topic, message, log_time_ns, publish_time_ns) to write as well.
Derivation = Callable[[Mapping[str, Any], int, int], Iterable[tuple[str, Mapping[str, Any], int, int]]]


class _Op(IntEnum):
    JSON = 0
    IMAGE = 1
    RAW = 2
    FLUSH = 3
    STOP = 4
    ENCODED = 5


class _Sink:
    """Unbuffered file for ``mcap.writer.Writer``: every record batch the writer emits
    (a whole chunk, its message indexes) reaches the OS at once, so a killed process
    leaves complete chunks behind. Counts its own position (no ``lseek``)."""

    def __init__(self, raw: BinaryIO | None) -> None:
        self._raw = raw
        self.position = 0

    def write(self, data: bytes | bytearray | memoryview) -> int:
        raw = self._raw
        if raw is None:
            raise OSError("the recording's file is not open")
        view = memoryview(data).cast("B")
        total = len(view)
        while view:
            n = raw.write(view)  # raw writes may be partial
            view = view[n:]
        self.position += total
        return total

    def tell(self) -> int:
        return self.position

    def flush(self) -> None:
        """Nothing is buffered here."""


class Recorder:
    """Writes JSON-encoded channels and Foxglove images to one MCAP file on its own
    thread. A context manager; :meth:`close` is idempotent.

    Args:
        path: the ``.mcap`` file to create (overwritten if it exists).
        queue_size: messages the queue holds before the newest are dropped.
        metadata: MCAP metadata records ``{name: {key: value}}`` written at close.
        chunk_size: bytes of uncompressed messages per chunk.
        compression: ``"lz4"`` (default), ``"zstd"`` or ``"none"``.
        chunk_duration_ns: also end a chunk once the newest log time written has
            moved on by this much (ns) since it began; ``None``: by size only. Bounds
            what a crash loses at low data rates.

    Raises:
        ConfigError: the path's folder does not exist or is not writable, the path
            is a folder, or an option is out of range.
    """

    def __init__(
        self,
        path: str | os.PathLike[str],
        *,
        queue_size: int = 4096,
        metadata: Mapping[str, Mapping[str, str]] | None = None,
        chunk_size: int = 1024 * 1024,
        compression: Compression | str = Compression.LZ4,
        chunk_duration_ns: int | None = 1_000_000_000,
    ) -> None:
        # Everything close() and stats look at exists before anything can fail.
        self._closed = False
        self._stop_sent = False
        self._closing = False
        self._file: BinaryIO | None = None
        self._chunk_indexes: chunk_index.ChunkIndexSpill | None = None
        self._sink = _Sink(None)
        self._thread: threading.Thread | None = None
        self._lock = threading.Lock()
        self._path = Path(path)
        # Producer-side counters and tables (guarded by _lock).
        self._topics: dict[str, tuple[str, bytes]] = {}
        self._next_seq: dict[str, int] = {}
        self._metadata: dict[str, dict[str, str]] = {}
        self._enqueued = 0
        self._dropped = 0
        self._max_depth = 0
        # Writer-side state (touched only by the writer thread once it runs).
        self._written = 0
        self._derived = 0
        self._errors = 0
        self._first_error: str | None = None
        self._io_error: OSError | None = None
        self._io_error_raised = False
        self._channel_ids: dict[str, int] = {}
        self._schema_ids: dict[tuple[str, bytes], int] = {}
        self._chunk_start_ns: int | None = None  # the newest log time when the chunk began
        self._log_high_ns: int | None = None  # the newest log time written
        self._offset_ns = 0
        self._derivations: dict[str, list[Derivation]] = {}
        self._taps: dict[str, Tap] = {}

        if not isinstance(queue_size, int) or queue_size < 1:
            raise ConfigError(f"recorder queue_size must be a positive integer, got {queue_size!r}")
        if not isinstance(chunk_size, int) or chunk_size < 1:
            raise ConfigError(f"recorder chunk_size must be a positive number of bytes, got {chunk_size!r}")
        if chunk_duration_ns is not None and chunk_duration_ns <= 0:
            raise ConfigError(f"recorder chunk_duration_ns must be > 0 or None, got {chunk_duration_ns!r}")
        try:
            self._compression = Compression(compression)
        except ValueError:
            raise ConfigError(
                f"recorder compression {compression!r} is unknown; use one of "
                f"{', '.join(c.value for c in Compression)}"
            ) from None
        self._queue_size = queue_size
        self._chunk_size = chunk_size
        self._chunk_duration_ns = chunk_duration_ns

        self._queue: Handoff[tuple[Any, ...]] = Handoff(queue_size)
        for name, data in (metadata or {}).items():
            self.add_metadata(name, data)

        try:
            self._open()
        except BaseException:
            self.close()
            raise

    def _open(self) -> None:
        path = self._path
        try:
            if path.exists() and not path.is_file():
                raise ConfigError(f"cannot record to {path}: it exists and is not a file; choose a file path")
            if not path.parent.is_dir():
                raise ConfigError(
                    f"cannot record to {path}: folder {path.parent} does not exist; "
                    "create it or choose another path"
                )
            self._file = open(path, "wb", buffering=0)
            self._sink = _Sink(self._file)
            self._writer = Writer(
                self._sink,  # type: ignore[arg-type]  # duck-typed stream
                chunk_size=self._chunk_size,
                compression=_MCAP_COMPRESSION[self._compression],
            )
            self._writer.start(library=f"hil-harness/{__version__}; {LIBRARY_IDENTIFIER}")
            # One chunk index per chunk, on disk until close (hil.harness.record.chunk_index).
            self._chunk_indexes = chunk_index.install(self._writer, path.parent)
        except OSError as err:
            raise ConfigError(f"cannot record to {path}: {err.strerror or err}; choose a writable path") from err
        self._thread = threading.Thread(target=self._run, name="mcap-writer", daemon=False)
        self._thread.start()

    # --- producer API ----------------------------------------------------------------

    @property
    def path(self) -> Path:
        """The file being written."""
        return self._path

    def register_json_channel(self, topic: str, schema_name: str, schema: Mapping[str, Any]) -> None:
        """Declare ``topic`` as a JSON channel with a JSON Schema named
        ``schema_name`` (Foxglove picks its panel by this name, e.g.
        ``foxglove.SceneUpdate``). Idempotent; cheap; never blocks on I/O (the MCAP
        records are written by the writer thread with the topic's first message).

        Raises:
            ConfigError: the topic is empty, already registered with another schema,
                or the schema is not JSON-serialisable.
        """
        if not isinstance(topic, str) or not topic:
            raise ConfigError(f"recorder topic must be a non-empty string, got {topic!r}")
        try:
            data = json.dumps(schema, separators=(",", ":"), sort_keys=True).encode()
        except (TypeError, ValueError) as err:
            raise ConfigError(f"schema {schema_name!r} for topic {topic!r} is not JSON: {err}") from err
        with self._lock:
            known = self._topics.get(topic)
            if known is None:
                self._topics[topic] = (schema_name, data)
                return
        if known != (schema_name, data):
            raise ConfigError(
                f"topic {topic!r} is already registered with schema {known[0]!r}; "
                f"use another topic for {schema_name!r}"
            )

    def write_json(self, topic: str, obj: Mapping[str, Any], *, log_time_ns: int, publish_time_ns: int) -> bool:
        """Enqueue ``obj`` for ``topic``; it is serialised to compact JSON on the writer
        thread, so the caller must not mutate ``obj`` (or anything it holds) after the
        call. numpy scalars and arrays are accepted; NaN and infinities are written as
        ``null`` (JSON has neither). A message that cannot be serialised at all is
        counted in ``stats.errors`` and skipped.

        Returns:
            ``True`` if enqueued, ``False`` if dropped (queue full, or recorder closed).

        Raises:
            ConfigError: ``topic`` was never registered.
        """
        if topic not in self._topics:
            raise ConfigError(
                f"topic {topic!r} is not registered; call register_json_channel({topic!r}, name, schema) first"
            )
        return self._put(_Op.JSON, topic, log_time_ns, publish_time_ns, obj, None, None)

    def write_encoded(self, topic: str, data: bytes, *, log_time_ns: int, publish_time_ns: int,
                      sequence: int | None = None) -> bool:
        """Enqueue a message ``topic``'s producer already encoded (``data``, in the
        topic's encoding): the writer only writes it. ``sequence``: the producer's own
        per-topic sequence number (a producer in another process keeps its own, and
        its drops leave gaps there); None: taken here as for every other write.
        Derivations do not run on it (its producer ran them).

        Returns:
            ``True`` if enqueued, ``False`` if dropped (queue full, or recorder closed).

        Raises:
            ConfigError: ``topic`` was never registered.
        """
        if topic not in self._topics:
            raise ConfigError(f"topic {topic!r} is not registered; register it before writing encoded messages")
        return self._put(_Op.ENCODED, topic, log_time_ns, publish_time_ns, data, None, None, seq=sequence)

    def write_image(self, topic: str, data: bytes, *, fmt: str, frame_id: str,
                    log_time_ns: int, publish_time_ns: int) -> bool:
        """Enqueue an encoded image (``fmt`` ``"jpeg"`` or ``"png"``) as a
        ``foxglove.CompressedImage`` (``timestamp`` = ``publish_time_ns``); the topic is
        registered on first use. Base64 encoding happens on the writer thread.

        Returns:
            ``True`` if enqueued, ``False`` if dropped.

        Raises:
            ConfigError: unknown ``fmt``, or the topic carries another schema.
        """
        if fmt not in _IMAGE_FORMATS:
            raise ConfigError(
                f"image format {fmt!r} is not supported; use one of {', '.join(_IMAGE_FORMATS)}"
            )
        self._ensure_topic(topic, fx.COMPRESSED_IMAGE)
        blob = data if isinstance(data, bytes) else bytes(data)
        return self._put(_Op.IMAGE, topic, log_time_ns, publish_time_ns, blob, fmt, frame_id)

    def write_raw_image(self, topic: str, pixels: np.ndarray, *, encoding: str, frame_id: str,
                        log_time_ns: int, publish_time_ns: int) -> bool:
        """Enqueue an ``H x W x 3`` uint8 image as a ``foxglove.RawImage``
        (``encoding`` ``"rgb8"`` or ``"bgr8"``). The pixels are copied here (one
        memcpy), so the caller may reuse its render buffer at once.

        Returns:
            ``True`` if enqueued, ``False`` if dropped.

        Raises:
            ConfigError: wrong dtype or shape, unknown encoding, or the topic carries
                another schema.
        """
        if encoding not in _RAW_ENCODINGS:
            raise ConfigError(
                f"raw image encoding {encoding!r} is not supported; use one of {', '.join(_RAW_ENCODINGS)}"
            )
        if not (isinstance(pixels, np.ndarray) and pixels.dtype == np.uint8
                and pixels.ndim == 3 and pixels.shape[2] == 3):
            got = f"{pixels.dtype} {pixels.shape}" if isinstance(pixels, np.ndarray) else type(pixels).__name__
            raise ConfigError(f"raw image must be a uint8 array of shape (H, W, 3), got {got}")
        self._ensure_topic(topic, fx.RAW_IMAGE)
        height, width = pixels.shape[:2]
        return self._put(_Op.RAW, topic, log_time_ns, publish_time_ns,
                         pixels.tobytes(), (height, width, encoding), frame_id)

    def add_metadata(self, name: str, data: Mapping[str, str]) -> None:
        """Add an MCAP metadata record ``name`` (string keys and values), written at
        close. Adding the same name again replaces it.

        Raises:
            ConfigError: non-string keys or values, the reserved name ``"recorder"``,
                or the recorder is closed.
        """
        if name == "recorder":
            raise ConfigError(
                "metadata name 'recorder' is reserved for the recorder's own counters; choose another"
            )
        bad = [k for k, v in data.items() if not isinstance(k, str) or not isinstance(v, str)]
        if not isinstance(name, str) or bad:
            raise ConfigError(
                f"metadata {name!r} must map strings to strings; fix keys {bad!r} (use str(value))"
            )
        with self._lock:
            if self._closing:
                raise ConfigError(f"cannot add metadata {name!r}: the recorder {self._path} is closed")
            self._metadata[name] = dict(data)

    def set_time_anchor(self, anchor: TimeAnchor) -> None:
        """Put ``log_time`` (and Foxglove image timestamps) on the wall clock: add
        ``anchor.offset_ns`` to them; record the anchor as metadata ``time_anchor``.

        Raises:
            ConfigError: a message was already enqueued (its log time would be on
                the other timeline), or the recorder is closed.
        """
        with self._lock:
            if self._enqueued or self._dropped or self._closing:
                raise ConfigError("set the recorder's time anchor before the first message")
            self._offset_ns = anchor.offset_ns
            self._metadata["time_anchor"] = anchor.to_metadata()

    def metadata_record(self, name: str) -> dict[str, str] | None:
        """A copy of the metadata record ``name`` added so far, or ``None``."""
        with self._lock:
            got = self._metadata.get(name)
            return None if got is None else dict(got)

    @property
    def log_time_offset_ns(self) -> int:
        """What is added to monotonic times for ``log_time`` (0 without an anchor)."""
        return self._offset_ns

    def add_derivation(self, topic: str, fn: Derivation) -> None:
        """Run ``fn`` on the writer thread for every JSON message of ``topic`` and
        write what it returns (on registered topics). An exception in ``fn`` is
        counted in ``stats.errors``; the source message is written regardless.

        Raises:
            ConfigError: ``topic`` was never registered, or messages were enqueued.
        """
        with self._lock:
            if topic not in self._topics:
                raise ConfigError(f"cannot derive from {topic!r}: it is not registered")
            if self._enqueued:
                raise ConfigError("add derivations before the first message")
            self._derivations.setdefault(topic, []).append(fn)

    def add_tap(self, name: str, tap: Tap) -> None:
        """Hand every message written from now on to ``tap.offer`` (on the writer
        thread: it must not block); at close, ``tap.close()`` is called and
        ``tap.metadata()`` written as the metadata record ``name``.

        Raises:
            ConfigError: the name is taken or reserved, or the recorder is closed.
        """
        with self._lock:
            if self._closing or name in self._taps or name in self._metadata or name == "recorder":
                raise ConfigError(f"cannot add tap {name!r}: name taken or recorder closed")
            self._taps = {**self._taps, name: tap}  # the writer thread reads a snapshot

    @property
    def failure(self) -> str | None:
        """Why the file can no longer be written (e.g. the disk filled), or None."""
        err = self._io_error
        return None if err is None else f"{type(err).__name__}: {err}"

    @property
    def stats(self) -> RecorderStats:
        """A snapshot of the counters (exact once :meth:`close` returned)."""
        with self._lock:
            return RecorderStats(
                enqueued=self._enqueued,
                written=self._written,
                dropped=self._dropped,
                errors=self._errors,
                bytes_written=self._sink.position,
                max_queue_depth=self._max_depth,
                first_error=self._first_error,
                derived=self._derived,
            )

    def flush(self, *, timeout_s: float = 30.0) -> bool:
        """Wait until everything enqueued before this call is written, as a complete
        chunk, to the OS (not fsynced). Ends the chunk in progress early, so calling it
        often costs compression. Blocks (not for the simulation loop).

        Returns:
            ``True`` once flushed; ``False`` on timeout or if the recorder is closed.
        """
        if self._closing or self._thread is None:
            return False
        done = threading.Event()
        if not self._put_control((_Op.FLUSH, done)):
            return False
        return done.wait(timeout_s)

    def close(self) -> RecorderStats:
        """Drain the queue, write the metadata (the ``recorder`` record holds the
        counters) and the MCAP summary and footer, join the writer thread, close the
        file. Idempotent; safe in a ``finally`` after ``KeyboardInterrupt`` (call it
        again if interrupted) and on a half-built recorder.

        Returns:
            The final counters.

        Raises:
            RecordingError: the file could not be written (e.g. disk full); raised once,
                after everything is closed.
        """
        if not self._closed:
            with self._lock:
                self._closing = True
            thread = self._thread
            if thread is not None:
                if not self._stop_sent:
                    self._put_control((_Op.STOP,))
                    self._stop_sent = True
                thread.join()
            if self._file is not None:
                try:
                    self._file.close()
                except OSError as err:  # pragma: no cover - close of an unbuffered file
                    self._note_error(err)
            if self._chunk_indexes is not None:
                self._chunk_indexes.close()
            self._closed = True
        if self._io_error is not None and not self._io_error_raised:
            self._io_error_raised = True
            raise RecordingError(
                f"could not write the recording {self._path}: {self._io_error}; "
                "check free disk space and permissions"
            ) from self._io_error
        return self.stats

    def __enter__(self) -> Recorder:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()

    # --- producer internals --------------------------------------------------------------

    def _ensure_topic(self, topic: str, schema_name: str) -> None:
        known = self._topics.get(topic)
        if known is None:
            self.register_json_channel(topic, schema_name, fx.schema_for(schema_name))
        elif known[0] != schema_name:
            raise ConfigError(
                f"topic {topic!r} carries {known[0]!r}; write {schema_name!r} messages to another topic"
            )

    def _put(self, op: _Op, topic: str, log_ns: int, pub_ns: int, a: Any, b: Any, c: Any, *,
             seq: int | None = None) -> bool:
        with self._lock:
            # The sequence number is taken before the attempt: drops leave gaps.
            if seq is None:
                seq = self._next_seq[topic] = (self._next_seq.get(topic, 0) + 1) & _SEQUENCE_MASK
            if self._closing:
                self._dropped += 1
                return False
            if not self._queue.put((op, topic, seq, log_ns, pub_ns, a, b, c)):
                self._dropped += 1
                return False
            self._enqueued += 1
            depth = len(self._queue)
            if depth > self._max_depth:
                self._max_depth = depth
            return True

    def _put_control(self, item: tuple[Any, ...]) -> bool:
        """Queue a command that must not be dropped (past the queue's bound); False if
        the writer thread is gone (then nobody would drain the queue)."""
        thread = self._thread
        if thread is None or not thread.is_alive():
            return False
        self._queue.put_always(item)
        return True

    # --- writer thread ----------------------------------------------------------------

    def _run(self) -> None:
        from hil.harness.engine.procs import lower_thread_priority

        lower_thread_priority()  # the run's frames and controls go first when the cores are busy
        get = self._queue.get
        main = threading.main_thread()
        while True:
            item = get(_IDLE_POLL_S)
            if item is None:
                # Forgotten close(): finish the file at interpreter exit instead of
                # hanging it (this thread is not a daemon).
                if not main.is_alive() and not len(self._queue):
                    break
                continue
            op = item[0]
            if op is _Op.STOP:
                break
            if op is _Op.FLUSH:
                try:
                    if self._io_error is None:
                        self._writer.flush()
                        self._chunk_start_ns = None
                except OSError as err:
                    self._io_error = err
                    self._note_error(err)
                finally:
                    item[1].set()
                continue
            if self._io_error is not None:
                self._note_error(self._io_error)  # the file is unusable: count the loss
                continue
            try:
                self._write_message(item)
            except OSError as err:
                self._io_error = err
                self._note_error(err)
            except Exception as err:  # a bad message must not stop the recording
                self._note_error(err, topic=item[1])
        self._finish()

    def _note_error(self, err: BaseException, *, topic: str | None = None) -> None:
        with self._lock:
            self._errors += 1
            if self._first_error is None:
                where = f" on topic {topic!r}" if topic is not None else ""
                self._first_error = f"{type(err).__name__}{where}: {err}"

    def _write_message(self, item: tuple[Any, ...]) -> None:
        op, topic, seq, log_ns, pub_ns, a, b, c = item
        log_ns += self._offset_ns
        if op is _Op.JSON:
            data = dumps(a)  # NaN and infinities as null
        elif op is _Op.ENCODED:
            data = a
        elif op is _Op.IMAGE:
            data = _image_json(pub_ns + self._offset_ns, c, b'"format":"%s",' % b.encode(), a)
        else:
            height, width, encoding = b
            fields = b'"width":%d,"height":%d,"encoding":"%s","step":%d,' % (
                width, height, encoding.encode(), 3 * width)
            data = _image_json(pub_ns + self._offset_ns, c, fields, a)
        self._add(topic, data, log_ns, pub_ns, seq)
        self._written += 1  # only this thread writes it (derived ones too); stats reads an int
        if op is _Op.JSON and topic in self._derivations:  # (an ENCODED message's producer derived its own)
            self._derive(topic, a, log_ns - self._offset_ns, pub_ns)

    def _derive(self, topic: str, obj: Mapping[str, Any], log_ns: int, pub_ns: int) -> None:
        for fn in self._derivations[topic]:
            try:
                out = list(fn(obj, log_ns, pub_ns))
            except Exception as err:  # a view must never stop the recording
                self._note_error(err, topic=topic)
                continue
            for d_topic, d_obj, d_log, d_pub in out:
                if d_topic not in self._topics:
                    self._note_error(ConfigError(f"derived topic {d_topic!r} is not registered"), topic=topic)
                    continue
                with self._lock:
                    seq = self._next_seq[d_topic] = (self._next_seq.get(d_topic, 0) + 1) & _SEQUENCE_MASK
                self._add(d_topic, dumps(d_obj), d_log + self._offset_ns, d_pub, seq)
                self._written += 1  # every message in the file: the statistics record's count
                with self._lock:
                    self._derived += 1

    def _add(self, topic: str, data: bytes, log_ns: int, pub_ns: int, seq: int) -> None:
        channel_id = self._channel_ids.get(topic)
        if channel_id is None:
            channel_id = self._register(topic)
        before = self._sink.position
        self._writer.add_message(channel_id=channel_id, log_time=log_ns, data=data,
                                 publish_time=pub_ns, sequence=seq)
        if self._taps:
            name, schema = self._topics[topic]
            for tap in self._taps.values():
                try:
                    tap.offer(topic, name, schema, data, log_ns)
                except Exception as err:  # a viewer must never stop the recording
                    self._note_error(err, topic=topic)
        high = self._log_high_ns = log_ns if self._log_high_ns is None else max(self._log_high_ns, log_ns)
        if self._sink.position != before:  # the writer just wrote a full chunk
            self._chunk_start_ns = None
        elif self._chunk_start_ns is None:
            self._chunk_start_ns = high
        elif self._chunk_duration_ns is not None and high - self._chunk_start_ns >= self._chunk_duration_ns:
            self._writer.flush()
            self._chunk_start_ns = None

    def _register(self, topic: str) -> int:
        name, data = self._topics[topic]
        schema_id = self._schema_ids.get((name, data))
        if schema_id is None:
            schema_id = self._writer.register_schema(name=name, encoding=_SCHEMA_ENCODING, data=data)
            self._schema_ids[(name, data)] = schema_id
        channel_id = self._writer.register_channel(
            topic=topic, message_encoding=_MESSAGE_ENCODING, schema_id=schema_id)
        self._channel_ids[topic] = channel_id
        return channel_id

    def _finish(self) -> None:
        """Metadata, summary and footer; on the writer thread, after the queue is drained."""
        taps = {}
        for name, tap in self._taps.items():
            try:
                tap.close()
                taps[name] = tap.metadata()
            except Exception as err:
                self._note_error(err)
        if self._io_error is not None:
            return
        with self._lock:
            self._closing = True  # also when reached at interpreter exit without close()
            user = {**dict(self._metadata), **taps}
            counters = {
                "enqueued": str(self._enqueued),
                "written": str(self._written),
                "dropped": str(self._dropped),
                "errors": str(self._errors),
                "derived": str(self._derived),
                "max_queue_depth": str(self._max_depth),
                "queue_size": str(self._queue_size),
                "chunk_size": str(self._chunk_size),
                "compression": self._compression.value,
                "chunk_indexes_spilled": str(self._chunk_indexes.count if self._chunk_indexes else 0),
            }
            if self._first_error is not None:
                counters["first_error"] = self._first_error
        try:
            for name, data in user.items():
                self._writer.add_metadata(name, data)
            self._writer.add_metadata("recorder", counters)
            self._writer.finish()
        except OSError as err:
            self._io_error = err
            self._note_error(err)


def _image_json(pub_ns: int, frame_id: str, fields: bytes, blob: bytes) -> bytes:
    """A Foxglove image message as JSON bytes, ``timestamp`` = ``pub_ns``."""
    # Built by hand: running a 16 KB base64 string through json.dumps costs a scan
    # and a copy for nothing (base64 never needs escaping).
    sec, nsec = divmod(pub_ns, 1_000_000_000)
    head = b'{"timestamp":{"sec":%d,"nsec":%d},"frame_id":%s,' % (sec, nsec, json.dumps(frame_id).encode())
    return b"".join((head, fields, b'"data":"', base64.b64encode(blob), b'"}'))


def iter_salvaged_messages(path: str | os.PathLike[str]) -> Iterator[tuple[Schema | None, Channel, Message]]:
    """Messages of a possibly truncated MCAP file (a crashed run), in file order, up
    to the last complete chunk. Works on complete files too. A chunk whose CRC fails
    (garbage at the tail after a power loss) ends the salvage like a cut does.

    Raises:
        ConfigError: the file cannot be opened or does not start as MCAP.
    """
    try:
        f = open(path, "rb")
    except OSError as err:
        raise ConfigError(f"cannot read recording {path}: {err.strerror or err}") from err
    from hil.harness.record.mcap_scan import iter_messages

    with f:
        try:
            yield from iter_messages(f)  # the cut (or damage) at the end of a crashed recording ends it
        except InvalidMagic as err:
            raise ConfigError(f"{path} is not an MCAP file: {err}") from err
