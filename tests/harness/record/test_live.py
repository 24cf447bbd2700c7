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


# --- closing with a stalled viewer; the subprotocols viewers speak; a fixed address (issue 26 item 3,
# issue 25 item 6) ---------------------------------------------------------------------------------------


def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _stalled_socket(url: str) -> Any:
    """A TCP connection to ``url`` with a small receive buffer: a viewer that stops
    reading closes its TCP window quickly."""
    import socket

    host, port = url.removeprefix("ws://").rsplit(":", 1)
    sock = socket.socket()
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    sock.connect((host, int(port)))
    return sock


def _subscribe_all(ws: Any, *, topics_at_least: int, poke: Any) -> None:
    """Subscribe ``ws`` to every channel advertised until there are ``topics_at_least``."""
    channels: set[int] = set()

    def advertised(m: Any) -> bool:
        if isinstance(m, str) and '"advertise"' in m:
            channels.update(c["id"] for c in json.loads(m)["channels"])
        return len(channels) >= topics_at_least

    _until(ws, advertised, poke=poke)
    ws.send(json.dumps({"op": "subscribe", "subscriptions": [{"id": c, "channelId": c} for c in channels]}))


def test_closing_with_a_stalled_viewer_takes_under_a_second() -> None:
    import time

    view = LiveView()
    big = b'{"a":"' + b"x" * 20_000 + b'"}'

    def poke() -> None:
        for t in range(20):
            view.offer(f"/t{t}", "x", b"{}", big, 1)

    # A real client that stops reading once subscribed (max_queue=1: its reader
    # thread stops taking frames off the socket).
    with ws_client.connect(view.url, sock=_stalled_socket(view.url), subprotocols=["foxglove.sdk.v1"],
                           open_timeout=5, close_timeout=0.2, max_queue=1) as ws:
        _subscribe_all(ws, topics_at_least=20, poke=poke)
        for i in range(20_000):  # far more than the socket, the relay and the server's backlog hold
            view.offer(f"/t{i % 20}", "x", b"{}", big, i)
            if i % 100 == 0:
                view.offer(f"/new{i}", "x", b"{}", big, i)  # new channels: advertisements queue up too
        done = threading.Event()
        t0 = time.monotonic()
        closer = threading.Thread(target=lambda: (view.close(), done.set()), daemon=True)
        closer.start()
        assert done.wait(10), "closing waited for a viewer that does not read"
        assert time.monotonic() - t0 <= 1.0
    meta = view.metadata()
    assert float(meta["close_ms"]) <= 1000 and "close" not in meta and meta["viewers"] == "1"
    s = view.stats
    assert s.sent + s.dropped + s.errors == s.offered  # every message accounted for


@pytest.fixture(scope="session")
def ws_protocol_modules(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """``@foxglove/ws-protocol`` and ``ws`` from npm in a temporary folder (skipped
    with the reason where node or the registry is not available)."""
    import shutil
    import subprocess

    if shutil.which("node") is None or shutil.which("npm") is None:
        pytest.skip("node and npm are needed for the @foxglove/ws-protocol client")
    folder = tmp_path_factory.mktemp("npm")
    p = subprocess.run(["npm", "install", "--no-audit", "--no-fund", "--silent", "--prefix", str(folder),
                        "@foxglove/ws-protocol@0.8.0", "ws@8"], capture_output=True, text=True, timeout=180,
                       check=False)
    if p.returncode != 0:
        pytest.skip(f"npm install @foxglove/ws-protocol failed: {p.stderr.strip()[-300:]}")
    return folder / "node_modules"


@pytest.mark.parametrize("subprotocols", [["foxglove.websocket.v1"], ["foxglove.sdk.v1"],
                                          ["foxglove.websocket.v1", "foxglove.sdk.v1"]])
def test_each_subprotocol_is_served(subprotocols: list[str]) -> None:
    view = LiveView()
    try:
        with ws_client.connect(view.url, subprotocols=subprotocols, open_timeout=5) as ws:
            assert ws.subprotocol == ("foxglove.sdk.v1" if "foxglove.sdk.v1" in subprotocols else subprotocols[0])
            info = json.loads(_until(ws, lambda m: isinstance(m, str) and '"serverInfo"' in m))
            assert info["name"] == "hil"
    finally:
        view.close()
    assert view.metadata()["viewers"] == "1"


def test_the_ws_protocol_client_reads_a_run_live(ws_protocol_modules: Path) -> None:
    import os
    import subprocess

    root = Path(__file__).resolve().parents[3]
    view = LiveView()
    proc = subprocess.Popen(["node", str(root / "tools" / "ws_protocol_client.cjs"), view.url, "/x", "3"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env=dict(os.environ, NODE_PATH=str(ws_protocol_modules)))
    try:
        i = 0
        while proc.poll() is None and i < 400:  # offered until the client has its 3 (or gives up)
            view.offer("/x", "hil.X", b'{"type":"object"}', json.dumps({"i": i}).encode(), 1_000_000_000 + i)
            i += 1
            try:
                proc.wait(0.05)
            except subprocess.TimeoutExpired:
                pass
        out, err = proc.communicate(timeout=10)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        view.close()
    lines = [json.loads(ln) for ln in out.splitlines()]
    assert proc.returncode == 0, (out, err)
    assert lines[0] == {"open": "foxglove.websocket.v1"} and lines[1] == {"serverInfo": "hil"}
    assert lines[2] == {"channel": {"topic": "/x", "encoding": "json", "schemaName": "hil.X"}}
    got = [ln["message"] for ln in lines[3:]]
    assert len(got) == 3 and all(int(m["timestamp"]) == 1_000_000_000 + m["data"]["i"] for m in got)
    assert view.metadata()["subprotocols"] == "foxglove.websocket.v1=1"


def test_a_fixed_address_and_one_taken() -> None:
    from hil.common.errors import ConfigError

    for _ in range(5):  # a port found free may be taken by another process before we bind it
        port = _free_port()
        try:
            view = LiveView(host="127.0.0.1", port=port)
            break
        except ConfigError:
            continue
    else:
        pytest.fail("no free port could be bound in five tries")
    try:
        assert view.url == f"ws://127.0.0.1:{port}"
        with pytest.raises(ConfigError, match=f"cannot listen on 127.0.0.1:{port}: Address already in use"):
            LiveView(host="127.0.0.1", port=port)
    finally:
        view.close()


def test_live_address_mistakes_are_one_line(capsys: pytest.CaptureFixture[str]) -> None:
    from hil.harness.cli.main import main as hil_main

    for bad in ("nohost", "127.0.0.1:99999", "hil_configs/demo.yaml"):
        with pytest.raises(SystemExit) as exit_:
            hil_main(["run", "hil_configs/demo.yaml", "--live", bad])
        err = capsys.readouterr().err
        assert exit_.value.code == 2 and len(err.strip().splitlines()) == 1, err
        assert "--live" in err and "HOST:PORT" in err and "Traceback" not in err


def test_live_before_the_config_serves_on_a_free_port() -> None:
    """``hil run --live CONFIG``: the config is the run's, not the live address."""
    from hil.harness.cli.parser import build_parser, live_before_config

    for argv in (["run", "--live", "hil_configs/demo.yaml"], ["run", "--live", "mine.yaml", "--no-progress"]):
        args = build_parser().parse_args(live_before_config(argv))
        assert args.config == argv[2] and args.live == ""
    args = build_parser().parse_args(live_before_config(["run", "--live", "127.0.0.1:0", "hil_configs/demo.yaml"]))
    assert args.config == "hil_configs/demo.yaml" and args.live == "127.0.0.1:0"


def test_failed_says_the_recording_had_begun(tmp_path: Path) -> None:
    # Killed while closing, a run used to leave FAILED saying "interrupted before the
    # run started" although every frame was in run.mcap.
    from hil.harness.cli.main import mark_failed

    (tmp_path / "run.mcap").write_bytes(b"\x89MCAP0\r\n" + b"\0" * 5000)
    reason = mark_failed(tmp_path, KeyboardInterrupt())
    text = (tmp_path / "FAILED").read_text()
    assert "before the run started" not in text and "after the recording began" in text and "5,008 bytes" in text
    assert reason in text
    empty = tmp_path / "empty"
    empty.mkdir()
    mark_failed(empty, KeyboardInterrupt())
    assert "interrupted before the run started" in (empty / "FAILED").read_text()


def test_hil_run_live_on_a_fixed_address_with_a_stalled_viewer(tmp_path: Path) -> None:
    # The whole path: `hil run --live HOST:PORT`, a viewer that subscribes to everything
    # and stops reading; the run still ends at its duration with its summary and report.
    import os
    import subprocess
    import sys

    from mcap.reader import make_reader

    from tests.conftest import GL_BACKEND

    root = Path(__file__).resolve().parents[3]
    port = _free_port()
    proc = subprocess.Popen([sys.executable, "-m", "hil.harness.cli.main", "run", "hil_configs/demo.yaml",
                             "--live", f"127.0.0.1:{port}", "--no-progress", "--out", str(tmp_path / "run"),
                             "--set", "duration_s=3"],
                            cwd=root, env=dict(os.environ, MUJOCO_GL=GL_BACKEND), stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    try:
        assert proc.stderr is not None
        for line in proc.stderr:  # the address is printed once the recorder serves it
            if "live view:" in line:
                assert f"ws://127.0.0.1:{port}" in line
                break
        url = f"ws://127.0.0.1:{port}"
        with ws_client.connect(url, sock=_stalled_socket(url), subprotocols=["foxglove.websocket.v1"],
                               open_timeout=10, close_timeout=0.2, max_queue=1) as ws:
            _subscribe_all(ws, topics_at_least=10, poke=None)
            out, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 0, err[-2000:]
    run = tmp_path / "run"
    assert (run / "summary.json").is_file() and (run / "report.html").is_file() and not (run / "FAILED").exists()
    assert json.loads((run / "summary.json").read_text())["spill"] == {"failures": 0}
    with open(run / "run.mcap", "rb") as f:
        meta = {m.name: m.metadata for m in make_reader(f).iter_metadata()}
    live = meta["live_view"]
    assert live["subprotocols"] == "foxglove.websocket.v1=1" and float(live["close_ms"]) <= 1000, live
