"""Recording from another process: encode here, write there.

A shard of a run in a process of its own (``hil.harness.run.shard_proc``) records
through an :class:`EncodingRecorder`: the Recorder's producer calls (``write_json``,
``write_image``, ``write_raw_image``), but each message is encoded in the calling
thread (orjson, ``hil.harness.record.encoding``), its derivations (the Foxglove views
of its vehicles) run there too, it is numbered in its topic, and it travels to the
run's one writer as bytes, batched, over a pipe. The run process hands each to
``Recorder.write_encoded`` (:func:`feed`): the writer only writes. Events go the
same way, in order with the messages, to the run's one event bus.

A batch is a sequence of records: ``<BHIqqI`` (kind: 0 a message, 1 an event; topic
length; sequence number; log time; publish time (ns, monotonic); data length), the
topic (UTF-8) and the data. Nothing in it executes (no pickle).
"""

from __future__ import annotations

import struct
import threading
from collections.abc import Callable, Iterable, Mapping
from typing import Any

import numpy as np

from hil.common.errors import ConfigError
from hil.harness.record import foxglove_schemas as fx
from hil.harness.record.encoding import dumps
from hil.harness.record.recorder import _SEQUENCE_MASK, Derivation, _image_json

_HEAD = struct.Struct("<BHIqqI")
MESSAGE, EVENT = 0, 1
BATCH_BYTES = 256 * 1024  # a batch goes when it holds this much, or at flush()


class EncodingRecorder:
    """The Recorder's producer side, for a process other than the writer's (see the
    module docstring). ``send`` takes a batch (bytes) and may block (the pipe to the
    run process): backpressure stays in the harness, away from the physics.
    ``log_time_offset_ns``: the run recorder's wall-clock offset, for the Foxglove
    timestamps its derivations write."""

    def __init__(self, send: Callable[[bytes], None], *, log_time_offset_ns: int = 0) -> None:
        self._send = send
        self._offset = log_time_offset_ns
        self._topics: dict[str, str] = {}
        self._seq: dict[str, int] = {}
        self._derivations: dict[str, list[Derivation]] = {}
        self._buf: list[bytes] = []
        self._size = 0
        self._lock = threading.Lock()  # the batch being filled
        self._send_lock = threading.Lock()  # the batch being sent (held while ``send`` blocks)
        self.enqueued = 0
        self.errors = 0
        self.first_error: str | None = None
        self.failure: str | None = None  # the run's writer reports its own

    @property
    def log_time_offset_ns(self) -> int:
        return self._offset

    def register_json_channel(self, topic: str, schema_name: str, schema: Mapping[str, Any]) -> None:
        """Note ``topic`` (the run process registers it with the writer)."""
        self._topics[topic] = schema_name

    def add_derivation(self, topic: str, fn: Derivation) -> None:
        """Run ``fn`` here on every JSON message of ``topic``; write what it returns."""
        self._derivations.setdefault(topic, []).append(fn)

    def add_tap(self, name: str, tap: Any) -> None:
        raise ConfigError("a live view taps the run's writer, not a shard's recorder")

    def metadata_record(self, name: str) -> dict[str, str] | None:
        return None

    def write_json(self, topic: str, obj: Mapping[str, Any], *, log_time_ns: int, publish_time_ns: int) -> bool:
        try:
            data = dumps(obj)
        except TypeError as err:  # counted, never raised on the producer (as the Recorder does)
            self._note(err, topic)
            return False
        self._put(MESSAGE, topic, data, log_time_ns, publish_time_ns)
        for fn in self._derivations.get(topic, ()):
            try:
                out = list(fn(obj, log_time_ns, publish_time_ns))
            except Exception as err:  # a view must never stop the recording
                self._note(err, topic)
                continue
            for d_topic, d_obj, d_log, d_pub in out:
                self._put(MESSAGE, d_topic, dumps(d_obj), d_log, d_pub)
        return True

    def write_image(self, topic: str, data: bytes, *, fmt: str, frame_id: str, log_time_ns: int,
                    publish_time_ns: int) -> bool:
        self._topics.setdefault(topic, fx.COMPRESSED_IMAGE)
        blob = _image_json(publish_time_ns + self._offset, frame_id, b'"format":"%s",' % fmt.encode(), data)
        self._put(MESSAGE, topic, blob, log_time_ns, publish_time_ns)
        return True

    def write_raw_image(self, topic: str, pixels: np.ndarray, *, encoding: str, frame_id: str, log_time_ns: int,
                        publish_time_ns: int) -> bool:
        self._topics.setdefault(topic, fx.RAW_IMAGE)
        height, width = pixels.shape[:2]
        fields = b'"width":%d,"height":%d,"encoding":"%s","step":%d,' % (width, height, encoding.encode(), 3 * width)
        self._put(MESSAGE, topic, _image_json(publish_time_ns + self._offset, frame_id, fields, pixels.tobytes()),
                  log_time_ns, publish_time_ns)
        return True

    def write_event(self, event_json: Mapping[str, Any], log_time_ns: int) -> None:
        """An event for the run's bus (which records it on ``/events``)."""
        self._put(EVENT, "", dumps(event_json), log_time_ns, 0)

    def flush(self) -> None:
        """Send what is batched (any thread). One batch at a time: a pipe's message
        over 16 KiB goes in several writes, and two sends at once interleave them; and
        batches leave in the order they were filled."""
        with self._send_lock:
            with self._lock:
                buf, self._buf, self._size = self._buf, [], 0
            if buf:
                self._send(b"".join(buf))

    def _put(self, kind: int, topic: str, data: bytes, log_ns: int, pub_ns: int) -> None:
        t = topic.encode()
        with self._lock:
            seq = 0
            if kind == MESSAGE:
                seq = self._seq[topic] = (self._seq.get(topic, 0) + 1) & _SEQUENCE_MASK
                self.enqueued += 1
            self._buf += (_HEAD.pack(kind, len(t), seq, log_ns, pub_ns, len(data)), t, data)
            self._size += _HEAD.size + len(t) + len(data)
            full = self._size >= BATCH_BYTES
        if full:
            self.flush()

    def _note(self, err: BaseException, topic: str) -> None:
        self.errors += 1
        if self.first_error is None:
            self.first_error = f"{type(err).__name__} on topic {topic!r}: {err}"


def records(batch: bytes) -> Iterable[tuple[int, str, int, int, int, bytes]]:
    """The records of a batch: (kind, topic, sequence, log time, publish time, data).

    Raises:
        ValueError: the batch is cut short (not one of ours).
    """
    view = memoryview(batch)
    at, end = 0, len(batch)
    while at < end:
        if end - at < _HEAD.size:
            raise ValueError(f"recording batch cut short at byte {at}")
        kind, n_topic, seq, log_ns, pub_ns, n_data = _HEAD.unpack_from(view, at)
        at += _HEAD.size
        if at + n_topic + n_data > end:
            raise ValueError(f"recording batch cut short at byte {at}")
        topic = bytes(view[at:at + n_topic]).decode()
        at += n_topic
        yield kind, topic, seq, log_ns, pub_ns, bytes(view[at:at + n_data])
        at += n_data


def feed(batch: bytes, rec: Any, on_event: Callable[[bytes, int], None]) -> int:
    """Hand a batch's messages to the run's ``Recorder`` (``write_encoded``) and its
    events to ``on_event(json, log_time_ns)``; returns the messages the recorder
    could not take (its queue full: counted there too)."""
    refused = 0
    for kind, topic, seq, log_ns, pub_ns, data in records(batch):
        if kind == EVENT:
            on_event(data, log_ns)
        elif not rec.write_encoded(topic, data, log_time_ns=log_ns, publish_time_ns=pub_ns, sequence=seq):
            refused += 1
    return refused


__all__ = ["EncodingRecorder", "feed", "records"]
