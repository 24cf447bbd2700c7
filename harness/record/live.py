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

Viewers connect to :class:`hil.harness.record.live_front.LiveFront` on the address
asked for (``--live HOST:PORT``; default 127.0.0.1, a free port), which serves both
``foxglove.sdk.v1`` and ``foxglove.websocket.v1`` and relays to the SDK's server on
a private loopback port. Closing takes at most about ``CLOSE_BUDGET_S`` whatever the
viewers do: what is still queued is sent for a third of it, then dropped (counted), the
front drops every viewer,
and the SDK server's stop is waited for only that long (a client that reached the
SDK's port directly and stopped reading is abandoned with it, and said so in the
``live_view`` metadata).

Raises: :class:`hil.common.errors.ConfigError` when foxglove-sdk is missing or the
address cannot be bound.
"""

from __future__ import annotations

import contextlib
import logging
import queue
import threading
import time
from dataclasses import dataclass
from typing import Any

from hil.common.errors import ConfigError

DEFAULT_HOST = "127.0.0.1"
CLOSE_BUDGET_S = 1.0  # the longest close() takes, whatever the viewers do
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
        from hil.harness.record.live_front import LiveFront

        self._foxglove = foxglove
        self._ctx = foxglove.Context()
        try:  # the SDK's own server: loopback only, reached through the front
            self._server = foxglove.start_server(name="hil", host="127.0.0.1", port=0, context=self._ctx)
        except Exception as err:  # the SDK raises its own error types for bind failures
            raise ConfigError(f"live view cannot start its server on 127.0.0.1: {err}") from err
        port_attr = self._server.port  # a property in foxglove-sdk 0.30, a method in some releases
        try:
            self._front = LiveFront(host=host, port=port,
                                    upstream_port=int(port_attr() if callable(port_attr) else port_attr))
        except BaseException:
            self._server.stop()
            raise
        self.host = host
        self.port = self._front.port
        self._queue: queue.Queue[tuple[str, str, bytes, bytes, int] | None] = queue.Queue(maxsize=queue_size)
        self._channels: dict[str, Any] = {}
        self._lock = threading.Lock()
        self._offered = self._sent = self._dropped = self._errors = 0
        self._closed = False
        self._close_note = ""
        self._close_ms: float | None = None
        self._deadline: float | None = None
        self._thread = threading.Thread(target=self._run, name="live-view", daemon=True)
        self._thread.start()

    @property
    def url(self) -> str:
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"ws://{host}:{self.port}"

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

    def close(self, *, timeout_s: float = CLOSE_BUDGET_S) -> LiveStats:
        """Stop taking messages, send what is queued for up to 30 % of ``timeout_s``
        (the rest is dropped and counted), drop every viewer, stop the server: within
        about ``timeout_s`` whatever the viewers do. Idempotent."""
        with self._lock:
            if self._closed:
                return LiveStats(self._offered, self._sent, self._dropped, self._errors)
            self._closed = True
        t0 = time.monotonic()
        self._deadline = t0 + timeout_s * 0.3  # what is queued is sent until then, dropped after
        try:
            self._queue.put(_STOP, timeout=timeout_s * 0.3)
        except queue.Full:  # the sender is stuck: make room by dropping the oldest (counted)
            with contextlib.suppress(queue.Empty):
                self._queue.get_nowait()
                with self._lock:
                    self._dropped += 1
            self._queue.put_nowait(_STOP)  # nothing else puts once closed
        self._thread.join(max(0.0, self._deadline - time.monotonic()))
        # Dropping the viewers resets the SDK's connections, which it reports as errors
        # on the Python logger "foxglove.websocket": expected now, so not shown.
        logging.getLogger("foxglove.websocket").setLevel(logging.CRITICAL)
        self._front.close(timeout_s=timeout_s * 0.3)
        stopper = threading.Thread(target=self._server.stop, name="live-view-stop", daemon=True)
        stopper.start()
        stopper.join(max(0.0, timeout_s - (time.monotonic() - t0)))
        if stopper.is_alive():  # only a client on the SDK's own port can hold it
            self._close_note = (f"the server did not stop within {timeout_s:g} s (a client on its private port "
                                "was not reading); abandoned")
        self._close_ms = (time.monotonic() - t0) * 1e3
        return self.stats

    def metadata(self) -> dict[str, str]:
        """The counters as an MCAP metadata record."""
        s = self.stats
        out = {"url": self.url, "offered": str(s.offered), "sent": str(s.sent), "dropped": str(s.dropped),
               "errors": str(s.errors), "viewers": str(self._front.viewers),
               "viewers_refused": str(self._front.refused),
               "subprotocols": ",".join(f"{k}={v}" for k, v in sorted(self._front.protocols.items()))}
        if self._close_ms is not None:
            out["close_ms"] = f"{self._close_ms:.1f}"
        if self._close_note:
            out["close"] = self._close_note
        return out

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
            if self._deadline is not None and time.monotonic() > self._deadline:
                with self._lock:
                    self._dropped += 1  # closing, out of time: counted, not sent
                continue
            try:
                self._channel(topic, schema_name, schema).log(data, log_time=log_ns)
            except Exception:  # a bad message must not stop the view
                with self._lock:
                    self._errors += 1
                continue
            with self._lock:
                self._sent += 1
