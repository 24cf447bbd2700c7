"""``hil run --live``: the recorder's messages served through foxglove-sdk's WebSocket
server (a real server, a real WebSocket client), and dropped and counted, never
waited for, when the viewer falls behind."""

from __future__ import annotations

import json
import re
import struct
import threading
from pathlib import Path
from typing import Any

import pytest

from hil.harness.record.channels import register_all
from hil.harness.record.recorder import Recorder, TimeAnchor

pytest.importorskip("foxglove")
ws_client = pytest.importorskip("websockets.sync.client")

from hil.harness.record.live import LiveView  # noqa: E402

ANCHOR = TimeAnchor(realtime_ns=1_795_000_000_000_000_000, monotonic_ns=2_000_000_000)
CONFIG = {"recording": {"live": True},
          "camera": {"width": 320, "height": 240, "fovy_deg": 60.0, "mount_height_m": 1.3}}


def _until(ws: Any, pred: Any, *, poke: Any = None, timeout_s: float = 10.0) -> Any:
    """Receive until ``pred(message)`` holds; call ``poke()`` between tries."""
    import time

    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if poke is not None:
            poke()
        try:
            m = ws.recv(timeout=0.2)
        except TimeoutError:
            continue
        if pred(m):
            return m
    raise AssertionError("nothing matching arrived")


def test_a_run_recording_is_served_live_with_its_foxglove_views(tmp_path: Path,
                                                               capsys: pytest.CaptureFixture[str]) -> None:
    rec = Recorder(tmp_path / "live.mcap", metadata={"config": {"yaml_json": json.dumps(CONFIG)}})
    try:
        register_all(rec, ["ego0"], anchor=ANCHOR)
        url = re.search(r"live view: (ws://127\.0\.0\.1:\d+)", capsys.readouterr().err).group(1)
        t = [2_000_000_000]

        def event() -> None:
            t[0] += 1_000_000
            rec.write_json("/events", {"kind": "latency_spike", "vehicle": "ego0", "severity": "warning"},
                           log_time_ns=t[0], publish_time_ns=t[0])

        with ws_client.connect(url, subprotocols=["foxglove.sdk.v1"], open_timeout=5) as ws:
            adv = json.loads(_until(ws, lambda m: isinstance(m, str) and '"advertise"' in m and "/log" in m,
                                    poke=event))
            log = next(c for c in adv["channels"] if c["topic"] == "/log")
            assert log["schemaName"] == "foxglove.Log" and log["encoding"] == "json"
            ws.send(json.dumps({"op": "subscribe", "subscriptions": [{"id": 3, "channelId": log["id"]}]}))
            frame = _until(ws, lambda m: isinstance(m, bytes) and m[0] == 1, poke=event)
        op, sub, ts = struct.unpack_from("<BIQ", frame)
        msg = json.loads(frame[13:])
        assert sub == 3 and msg["level"] == 3 and "latency_spike" in msg["message"]
        assert ts > ANCHOR.realtime_ns  # on the wall clock, as in run.mcap
    finally:
        rec.close()
    from mcap.reader import make_reader

    with open(tmp_path / "live.mcap", "rb") as f:
        meta = {m.name: m.metadata for m in make_reader(f).iter_metadata()}
    assert int(meta["live_view"]["sent"]) >= 2 and meta["live_view"]["dropped"] == "0"


class _StuckView(LiveView):
    """A live view whose sending thread stops at its first message until released."""

    def __init__(self, **kw: Any) -> None:
        self.entered, self.release = threading.Event(), threading.Event()
        super().__init__(**kw)

    def _channel(self, topic: str, schema_name: str, schema: bytes) -> Any:
        self.entered.set()
        assert self.release.wait(10)
        return super()._channel(topic, schema_name, schema)


def test_a_slow_viewer_costs_drops_never_waits() -> None:
    view = _StuckView(queue_size=4)
    try:
        view.offer("/x", "x", b"{}", b"{}", 1)
        assert view.entered.wait(10)  # the sender holds message 1 and is stuck
        for i in range(10):
            view.offer("/x", "x", b"{}", b"{}", 2 + i)  # 4 fit the queue, 6 are dropped at once
        assert view.stats.dropped == 6 and view.stats.offered == 11
    finally:
        view.release.set()
        stats = view.close()
    assert stats.sent == 5 and stats.dropped == 6
    view.offer("/x", "x", b"{}", b"{}", 99)
    assert view.stats.dropped == 7  # after close: counted, not queued
