"""The C reference target (targets/c): built with the system compiler, warnings as
errors, and run under AddressSanitizer + UBSan against real harness links (tcp and
local) and real harness runs."""

from __future__ import annotations

import contextlib
import os
import socket
import subprocess
import time
import zlib
from collections.abc import Iterator
from pathlib import Path

import pytest

from hil.adapters.link import Link
from hil.adapters.local.link import LocalLink
from hil.adapters.tcp.link import TcpLink
from hil.adapters.tcp.options import TcpOptions
from hil.adapters.wire import protocol
from hil.adapters.wire.messages import (Bye, CameraInfo, ClockId, Command, Control, DrivingState, ErrorMsg, Estimate,
                                        Frame, ImageEncoding, SyncRequest)
from hil.timing.clock import MonotonicClock
from tests.targets import c_build

pytestmark = pytest.mark.skipif(c_build.unavailable() is not None, reason=str(c_build.unavailable()))

ROOT = Path(__file__).resolve().parents[2]
CAM = CameraInfo(277.0, 277.0, 160.0, 120.0, 1.3)
W, H = 64, 48


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@contextlib.contextmanager
def c_link(transport: str, tmp_path: Path, *, extra: tuple[str, ...] = ()) -> Iterator[tuple[Link, Path]]:
    """An open link to the sanitized C target; on exit checks the log is clean."""
    exe = str(c_build.build().asan)
    log = tmp_path / f"c-{transport}.log"
    env = dict(os.environ, **c_build.SAN_ENV)
    proc = None
    if transport == "tcp":
        address = f"127.0.0.1:{_free_port()}"
        with open(log, "ab") as f:
            proc = subprocess.Popen([exe, "--transport", "tcp", "--listen", address, "--once", "--verbose", *extra],
                                    stdout=f, stderr=f, stdin=subprocess.DEVNULL, env=env)
        link: Link = TcpLink(vehicle_id=4, clock=MonotonicClock(), options=TcpOptions(connect=address))
    else:
        link = LocalLink(command=[exe, "--verbose", *extra], vehicle_id=4, clock=MonotonicClock(), log_path=log,
                         env=env)
    try:
        link.open(hello_timeout_s=20)
        yield link, log
    finally:
        link.close()
        if proc is not None:
            try:
                assert proc.wait(timeout=10) == 0, log.read_text()
            finally:
                if proc.poll() is None:
                    proc.kill()
                    proc.wait()
    assert c_build.sanitizer_report(log.read_text()) is None, log.read_text()


def frame(link: Link, fid: int, *, value: int = 128, encoding: ImageEncoding = ImageEncoding.RGB8,
          data: bytes | None = None) -> None:
    img = data if data is not None else bytes([value]) * (W * H * 3)
    link.send_frame(frame_id=fid, sim_time_ns=fid * 50_000_000, t0_ns=link.clock.now_ns(), width=W, height=H,
                    encoding=encoding, camera=CAM, ego_speed_mps=3.0, data=img)


def next_of(link: Link, kind: type, timeout_s: float = 5.0):
    deadline = time.monotonic() + timeout_s
    while (left := deadline - time.monotonic()) > 0:
        r = link.recv(timeout_s=left)
        if r is not None and isinstance(r.msg, kind):
            return r.msg
    raise AssertionError(f"no {kind.__name__} within {timeout_s} s")


def test_builds_with_warnings_as_errors():
    b = c_build.build()
    assert b.plain.is_file() and os.access(b.plain, os.X_OK)
    assert b.asan.is_file() and os.access(b.asan, os.X_OK)


@pytest.mark.parametrize(("argv", "line"), [
    (["--bogus"], "hil_target: --bogus: unknown option (see --help)"),  # was "an option is missing its value"
    (["--name"], "hil_target: --name: missing its value (see --help)"),
    (["--clock", "tai"], "hil_target: --clock: takes monotonic or realtime (see --help)"),
    (["--transport", "udp", "--once"], "hil_target: --transport: takes local or tcp (see --help)"),
])
def test_a_bad_option_is_one_line_naming_it_and_exit_2(argv, line):
    p = subprocess.run([str(c_build.build().asan), *argv], capture_output=True, text=True, timeout=30,
                       env={**os.environ, **c_build.SAN_ENV})
    assert (p.returncode, p.stderr, p.stdout) == (2, line + "\n", "")
    h = subprocess.run([str(c_build.build().plain), "--help"], capture_output=True, text=True, timeout=30)
    assert h.returncode == 0 and h.stdout.startswith("usage: hil_target ") and "--token-env NAME" in h.stdout


@pytest.mark.parametrize("transport", ["tcp", "local"])
def test_session_over_transport(transport, tmp_path):
    with c_link(transport, tmp_path) as (link, _log):
        hello = link.hello
        assert hello is not None and hello.target_name == "c-reference"
        assert hello.clock_id == ClockId.MONOTONIC and hello.clock_resolution_ns >= 1
        # no SHM_FRAMES: it reads frames inline; CAP_CAMERAS: it answers every camera of a rig
        assert hello.capabilities == protocol.CAP_COMMANDS | protocol.CAP_CAMERAS
        frame(link, 1, value=10)  # dark centre: brake
        dark = next_of(link, Estimate)
        frame(link, 2, value=200, encoding=ImageEncoding.BGR8)
        bright = next_of(link, Estimate)
        assert (dark.frame_id, dark.vehicle_id, dark.state, dark.control.brake) == (1, 4, DrivingState.STOP, 1.0)
        assert (bright.frame_id, bright.state, bright.control.brake) == (2, DrivingState.SAFE, 0.0)
        for e in (dark, bright):
            assert e.t_rx_target_ns <= e.t_infer_start_target_ns <= e.t_infer_end_target_ns <= e.t_reply_target_ns
        assert dark.t_reply_target_ns < bright.t_rx_target_ns
        samples = [link.sync_exchange(timeout_s=2.0) for _ in range(5)]
        assert all(s is not None and s.t2_target_ns <= s.t3_target_ns for s in samples)
        assert [s.seq for s in samples] == [1, 2, 3, 4, 5]


def test_only_the_image_centre_counts(tmp_path):
    img = bytearray([10]) * (W * H * 3)  # dark everywhere ...
    for y in range(H // 3, H - H // 3):  # ... but a bright centre ninth
        for x in range(W // 3, W - W // 3):
            img[(y * W + x) * 3:(y * W + x) * 3 + 3] = b"\xc8\xc8\xc8"
    with c_link("tcp", tmp_path) as (link, _log):
        frame(link, 1, data=bytes(img))
        assert next_of(link, Estimate).state == DrivingState.SAFE
        frame(link, 2, encoding=ImageEncoding.JPEG, data=b"\xff\xd8" + bytes(8000) + b"\xff\xd9")
        assert next_of(link, Estimate).state == DrivingState.SAFE  # opaque JPEG: 8 KB for 64x48 is not dark
        frame(link, 3, encoding=ImageEncoding.JPEG, data=b"\xff\xd8\xff\xd9")
        assert next_of(link, Estimate).state == DrivingState.STOP


def _payload_crc_broken() -> bytes:
    buf = bytearray(protocol.encode(Frame(4, 9, 0, 1, 2, W, H, ImageEncoding.RGB8, CAM, 1.0, bytes(W * H * 3)),
                                    payload_crc=True))
    buf[200] ^= 0xFF  # inside the image: the payload CRC no longer matches
    return bytes(buf)


def _header(raw: bytearray) -> bytes:
    raw[60:64] = zlib.crc32(bytes(raw[:60])).to_bytes(4, "little")
    return bytes(raw)


def test_bad_messages_are_reported_with_offsets_and_the_session_goes_on(tmp_path):
    bad_reserved = bytearray(protocol.encode(Frame(4, 8, 0, 1, 2, W, H, ImageEncoding.RGB8, CAM, 1.0,
                                                   bytes(W * H * 3))))
    bad_reserved[71] = 1  # FRAME reserved byte 71 (69 and 70 are the camera: test_c_rig.py)
    bad_reserved = bytearray(_header(bad_reserved[:64]) + bytes(bad_reserved[64:]))
    estimate_to_target = protocol.encode(Estimate(4, 5, DrivingState.SAFE, Control(), (), 1, 2, 3, 4))
    cases = [
        (b"\x00garbage" + b"HILP" + bytes(60), 2, "at byte offset 4"),  # bad magic, then version 0
        (_payload_crc_broken(), 1, "payload CRC mismatch (at byte offset 64)"),
        (bytes(bad_reserved), 1, "reserved byte is 1, must be 0 (at byte offset 71)"),
        (estimate_to_target, 3, "(at byte offset 5)"),
    ]
    with c_link("tcp", tmp_path) as (link, _log):
        for i, (raw, code, text) in enumerate(cases):
            link.send_raw(raw)
            err = next_of(link, ErrorMsg)
            if i == 0:  # the garbage is reported once (bad magic), then the HILP header
                assert err.code == protocol.ErrorCode.MALFORMED and "at byte offset 0" in err.message
                err = next_of(link, ErrorMsg)
            assert (err.code, text in err.message) == (code, True), err
            frame(link, 100 + i)
            assert next_of(link, Estimate).frame_id == 100 + i  # one bad message never ends a session
        link.send_command("status")
        reply = next_of(link, Command)
        assert reply.seq == 1 and reply.text.startswith("ok frames=4") and "bad=5" in reply.text


def test_stream_split_anywhere_is_reassembled(tmp_path):
    msgs = b"".join(protocol.encode(SyncRequest(4, seq, 1000 + seq)) for seq in range(1, 4))
    with c_link("local", tmp_path) as (link, _log):
        for k in range(0, len(msgs), 7):  # 7-byte writes cut headers anywhere
            link.send_raw(msgs[k:k + 7])
        got = []
        deadline = time.monotonic() + 5
        while len(got) < 3 and time.monotonic() < deadline:
            got += [(s.seq, s.t1_ns) for s in link.sync_samples()]
            link.recv(timeout_s=0.02)
        assert got == [(1, 1001), (2, 1002), (3, 1003)]


def test_bye_ends_the_target_cleanly(tmp_path):
    exe = str(c_build.build().asan)
    address = f"127.0.0.1:{_free_port()}"
    log = tmp_path / "bye.log"
    with open(log, "ab") as f:
        proc = subprocess.Popen([exe, "--transport", "tcp", "--listen", address, "--once"], stdout=f, stderr=f,
                                env=dict(os.environ, **c_build.SAN_ENV))
    try:
        link = TcpLink(vehicle_id=0, clock=MonotonicClock(), options=TcpOptions(connect=address, heartbeat_idle_s=0))
        link.open(hello_timeout_s=20)
        link.send_raw(protocol.encode(Bye(0, "done")))
        assert proc.wait(timeout=10) == 0
        link.close()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert "frames=0" in log.read_text() and c_build.sanitizer_report(log.read_text()) is None


@pytest.mark.slow
@pytest.mark.parametrize("transport", ["tcp", "local"])
def test_real_run(transport, tmp_path, monkeypatch):
    """A whole harness run against the sanitized C target, raw frames (its AI looks
    at them): every frame accounted for, target times in order, clock synced, no
    anomalies, and a clean sanitizer log."""
    from hil.harness.config.loading import load_config
    from hil.harness.run.driver import execute, prepare_out_dir
    from tests.conftest import GL_BACKEND, read_mcap

    for k, v in c_build.SAN_ENV.items():
        monkeypatch.setenv(k, v)  # the harness starts the target with this environment
    exe = str(c_build.build().asan)
    cfg_path = tmp_path / "c.yaml"
    cfg_path.write_text("name: c-target\n")
    overrides = ["duration_s=2", "progress=false", "camera.encoding=raw", f"target.transport={transport}"]
    if transport == "tcp":  # the shipped example, its Python target swapped for the C one
        cfg_path = ROOT / "hil_configs" / "tcp.yaml"
        overrides += [f"target.tcp.base_port={_free_port()}",
                      f'target.command=["{exe}", "--transport", "tcp", "--listen", "127.0.0.1:{{port}}"]']
    else:
        overrides += [f'target.command=["{exe}"]']
    result = execute(load_config(cfg_path, overrides=overrides), out_dir=prepare_out_dir(tmp_path / "r"),
                     gl_backend=GL_BACKEND, install_signal_handlers=False)
    v = result.summary["vehicles"]["ego0"]
    assert result.summary["ended_by"] == "duration"
    assert v["target"]["name"] == "c-reference"
    assert v["frames_sent"] == 40 and v["frames_accounted"] == 40
    assert v["estimates_applied"] + v["dropped"] + v["stale"] == 40 and v["estimates_applied"] >= 36
    assert v["anomalies"] == {} and v["order_violations"] == 0
    assert v["link"]["protocol_errors"] == 0 and v["link"]["target_errors"] == 0
    assert v["clock"]["synced"]
    recs = [d for _, d in read_mcap(result.mcap_path)["/ego0/pipeline"]]
    assert sorted(d["frame_id"] for d in recs) == list(range(40))
    answered = [d for d in recs if d["status"] == "ok"]
    assert len(answered) >= 36
    for d in answered:
        assert d["t0_ns"] <= d["t_tx_ns"] <= d["t0p_ns"]
        assert d["t_rx_target_ns"] <= d["t_infer_start_target_ns"] <= d["t_infer_end_target_ns"] \
            <= d["t_reply_target_ns"]
    log = (tmp_path / "r" / "target-ego0.log").read_text()
    assert "frames=40 estimates=40" in log, log
    if transport == "tcp":  # t_rx and t2 are the kernel's receive times there (a Unix socket has none)
        assert int(log.rsplit("kernel_stamps=", 1)[1].split()[0]) > 0, log
    assert c_build.sanitizer_report(log) is None, log


def test_large_frames_and_oversized_lengths(tmp_path):
    """A 640x480 frame (more than the target's first buffer) is answered; a header
    announcing more than MAX_PAYLOAD is refused at offset 12 before any allocation;
    an idle target sends HEARTBEATs."""
    from hil.adapters.wire.messages import Heartbeat

    big = bytearray(protocol.encode(SyncRequest(4, 1, 5)))
    big[12:16] = (protocol.MAX_PAYLOAD + 1).to_bytes(4, "little")
    with c_link("tcp", tmp_path) as (link, _log):
        link.send_frame(frame_id=7, sim_time_ns=0, t0_ns=link.clock.now_ns(), width=640, height=480,
                        encoding=ImageEncoding.RGB8, camera=CAM, ego_speed_mps=0.0, data=bytes(640 * 480 * 3))
        est = next_of(link, Estimate)
        assert (est.frame_id, est.state) == (7, DrivingState.STOP)
        link.send_raw(_header(big))
        err = next_of(link, ErrorMsg)
        assert "exceeds MAX_PAYLOAD" in err.message and "(at byte offset 12)" in err.message
        frame(link, 8, value=200)
        assert next_of(link, Estimate).frame_id == 8
        hb = next_of(link, Heartbeat, timeout_s=3.0)  # after 1 s without sending
        assert hb.vehicle_id == 4 and hb.t_sender_ns > est.t_reply_target_ns


def test_random_bytes_never_break_the_target(tmp_path):
    """Fuzz the stream decoder under the sanitizers: random bytes, random bytes after
    magics, and headers with valid CRCs over random fields; the session goes on."""
    import random

    rng = random.Random(16)
    chunks = []
    for _ in range(300):
        kind = rng.randrange(3)
        if kind == 0:
            chunks.append(rng.randbytes(rng.randrange(1, 300)))
        elif kind == 1:
            chunks.append(b"HILP" + rng.randbytes(rng.randrange(0, 120)))
        else:  # a header that passes the CRC, with random type, lengths and slots
            h = bytearray(b"HILP\x01" + rng.randbytes(59))
            h[5] = rng.randrange(0, 11)
            h[6:8] = rng.choice([b"\x00\x00", b"\x01\x00"])
            h[12:16] = rng.randrange(0, 200).to_bytes(4, "little")
            chunks.append(_header(h) + rng.randbytes(int.from_bytes(h[12:16], "little")))
    with c_link("local", tmp_path) as (link, log):
        for c in chunks:
            link.send_raw(c)
        link.send_raw(bytes(3))  # never a magic: the next message starts clean
        frame(link, 77)
        assert next_of(link, Estimate, timeout_s=10).frame_id == 77
        assert link.alive
