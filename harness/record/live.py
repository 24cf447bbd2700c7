"""``hil run --live``: the run's channels served while it runs, through foxglove-sdk's
WebSocket server, so Foxglove (Open connection → Foxglove WebSocket →
``ws://127.0.0.1:PORT``) shows the cameras with their overlays, the 3D scene,
latency plots and the event log as the run goes.

The recorder's writer thread hands every message it writes (already JSON bytes, on
the wall-clock timeline) to :meth:`LiveView.offer`, which only puts it on a bounded
queue: when the queue is full the message is dropped and counted, so a slow viewer
(or none) never slows the recording, let alone the simulation loop. A thread named
``live-view`` takes messages off the queue and logs them on the server's channels;
the server keeps its own bounded backlog per client (oldest dropped first).

Raises: :class:`hil.common.errors.ConfigError` when foxglove-sdk is missing or the port
cannot be bound.
"""

from __future__ import annotations

import queue
import threading
from dataclasses import dataclass
from typing import Any

from hil.common.errors import ConfigError

DEFAULT_HOST = "127.0.0.1"
_STOP = None


@dataclass(frozen=True)
class LiveStats:
    """Messages offered to the live view, sent to the server, and dropped because its
    queue was full."""

    offered: int
    sent: int
    dropped: int
    errors: int


class LiveView:
    """A foxglove-sdk WebSocket server fed from a bounded queue.

    Args:
        host: address to listen on (default loopback only).
        port: TCP port; 0 picks a free one (see :attr:`port`).
        queue_size: messages waiting for the server before new ones are dropped.

    Raises:
        ConfigError: foxglove-sdk is not installed, or the server cannot start.
    """

    def __init__(self, *, host: str = DEFAULT_HOST, port: int = 0, queue_size: int = 1024) -> None:
        try:
            import foxglove
        except ImportError as err:
            raise ConfigError("the live view needs foxglove-sdk: pip install foxglove-sdk") from err
        self._foxglove = foxglove
        self._ctx = foxglove.Context()
        try:
            self._server = foxglove.start_server(name="hil", host=host, port=port, context=self._ctx)
        except Exception as err:  # the SDK raises its own error types for bind failures
            raise ConfigError(f"live view cannot listen on {host}:{port}: {err}") from err
        self.host = host
        port_attr = self._server.port  # a property in foxglove-sdk 0.30, a method in some releases
        self.port = int(port_attr() if callable(port_attr) else port_attr)
        self._queue: queue.Queue[tuple[str, str, bytes, bytes, int] | None] = queue.Queue(maxsize=queue_size)
        self._channels: dict[str, Any] = {}
        self._lock = threading.Lock()
        self._offered = self._sent = self._dropped = self._errors = 0
        self._closed = False
        self._thread = threading.Thread(target=self._run, name="live-view", daemon=True)
        self._thread.start()

    @property
    def url(self) -> str:
        return f"ws://{self.host}:{self.port}"

    def offer(self, topic: str, schema_name: str, schema: bytes, data: bytes, log_time_ns: int) -> None:
        """Queue one JSON message for the viewers; never blocks (drops when full)."""
        with self._lock:
            self._offered += 1
            if self._closed:
                self._dropped += 1
                return
        try:
            self._queue.put_nowait((topic, schema_name, schema, data, log_time_ns))
        except queue.Full:
            with self._lock:
                self._dropped += 1

    @property
    def stats(self) -> LiveStats:
        with self._lock:
            return LiveStats(self._offered, self._sent, self._dropped, self._errors)

    def close(self, *, timeout_s: float = 5.0) -> LiveStats:
        """Stop taking messages, send what is queued (up to ``timeout_s``), stop the
        server. Idempotent."""
        with self._lock:
            if self._closed:
                return LiveStats(self._offered, self._sent, self._dropped, self._errors)
            self._closed = True
        try:
            self._queue.put(_STOP, timeout=timeout_s)
        except queue.Full:
            pass
        self._thread.join(timeout_s)
        self._server.stop()
        return self.stats

    def metadata(self) -> dict[str, str]:
        """The counters as an MCAP metadata record."""
        s = self.stats
        return {"url": self.url, "offered": str(s.offered), "sent": str(s.sent), "dropped": str(s.dropped),
                "errors": str(s.errors)}

    def _channel(self, topic: str, schema_name: str, schema: bytes) -> Any:
        ch = self._channels.get(topic)
        if ch is None:
            fg = self._foxglove
            ch = fg.Channel(topic, message_encoding="json", context=self._ctx,
                            schema=fg.Schema(name=schema_name, encoding="jsonschema", data=schema))
            self._channels[topic] = ch
        return ch

    def _run(self) -> None:
        while True:
            item = self._queue.get()
            if item is _STOP:
                return
            topic, schema_name, schema, data, log_ns = item
            try:
                self._channel(topic, schema_name, schema).log(data, log_time=log_ns)
            except Exception:  # a bad message must not stop the view
                with self._lock:
                    self._errors += 1
                continue
            with self._lock:
                self._sent += 1
