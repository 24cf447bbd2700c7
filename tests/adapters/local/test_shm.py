"""The local transport's shared-memory frame ring (adapters/local/shm.py, PROTOCOL.md 10.1.1):
the notice and ring formats, the stream of messages and notices, negotiation with a
target that can and one that cannot read the ring, slot reuse with its generation
counter, and cleanup. The conformance suite runs again with every frame through a
slot, and against a target that does not know the ring."""

from __future__ import annotations

import contextlib
import os
import signal
import sys
import textwrap
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from hil.adapters.link import Link, open_link
from hil.adapters.local import shm
from hil.adapters.local.link import LocalLink
from hil.adapters.local.options import LocalOptions
from hil.adapters.local.shm import (NOTICE_SIZE, NOTICES, SHM_FRAMES, Notice, ShmReader, ShmRing, decode_notice,
                                    encode_notice)
from hil.adapters.wire import protocol
from hil.adapters.wire.messages import CameraInfo, Estimate, Frame, Hello, ImageEncoding, SyncRequest
from hil.adapters.wire.stream import StreamDecoder
from hil.common.errors import ProtocolError, TransportError
from hil.timing.clock import MonotonicClock
from tests.adapters import test_conformance as conformance

ROOT = Path(__file__).resolve().parents[3]
CAM = CameraInfo(277.0, 277.0, 160.0, 120.0, 1.3)

# The conformance suite again, with this module's ``pair`` fixture (below).
test_hello = conformance.test_hello
test_frame_round_trip_is_stamped = conformance.test_frame_round_trip_is_stamped
test_inference_time_is_measured_on_the_target = conformance.test_inference_time_is_measured_on_the_target
test_clock_sync_exchange = conformance.test_clock_sync_exchange
test_sequence_of_frames_all_answered = conformance.test_sequence_of_frames_all_answered
test_corrupt_message_is_counted_and_link_goes_on = conformance.test_corrupt_message_is_counted_and_link_goes_on
test_vanished_target_is_noticed_within_a_second = conformance.test_vanished_target_is_noticed_within_a_second
test_close_is_idempotent = conformance.test_close_is_idempotent

# A target built on the SDK's Endpoint that reads the socket the way version-1
# targets did, without the ring: it never advertises SHM_FRAMES.
LEGACY_TARGET = textwrap.dedent("""
    import os, socket, sys
    sys.path.insert(0, sys.argv[1])
    import argparse
    from hil.adapters.sdk import Endpoint
    from hil.targets.echo import Echo
    assert "HIL_LOCAL_SHM" in os.environ  # offered, and ignored
    p = argparse.ArgumentParser()
    for opt in ("--infer-ms", "--throttle", "--brake"):
        p.add_argument(opt, type=float, default=0.0)
    p.add_argument("--name", default="echo")
    p.add_argument("--exit-after-frames", type=int, default=None)
    a = p.parse_args(sys.argv[2:])
    echo = Echo(infer_ms=a.infer_ms, throttle=a.throttle, brake=a.brake, exit_after_frames=a.exit_after_frames)
    ep = Endpoint(echo.infer, target_name=a.name)
    sock = socket.socket(fileno=int(os.environ["HIL_LOCAL_FD"]))
    ep.start(sock.sendall)
    while not ep.stopped:
        data = sock.recv(1 << 20)
        if not data:
            break
        ep.on_bytes(data, ep.clock.now_ns())
    ep.join()
""")


@contextlib.contextmanager
def local(tmp_path: Path, command: list[str], **options: Any) -> Iterator[LocalLink]:
    """An open local link to ``command``; ``options``: ``LocalOptions``' (the ring)."""
    link = open_link("local", command=command, vehicle_id=0, clock=MonotonicClock(),
                     log_path=tmp_path / "target.log", options=LocalOptions(**options))
    assert isinstance(link, LocalLink)
    try:
        link.open(hello_timeout_s=20)
        yield link
    finally:
        link.close()


def echo(*args: str) -> list[str]:
    return [sys.executable, "-m", "hil.targets.echo", *args]


def legacy(tmp_path: Path, *args: str) -> list[str]:
    prog = tmp_path / "legacy_target.py"
    prog.write_text(LEGACY_TARGET)
    return [sys.executable, str(prog), str(ROOT), *args]


@pytest.fixture(params=["all-frames-in-shm", "target-without-shm"])
def pair(request: pytest.FixtureRequest, tmp_path: Path):
    if request.param == "all-frames-in-shm":
        def factory(echo_args=()):
            return local(tmp_path, echo(*echo_args), shm_inline_below=0)
    else:
        def factory(echo_args=()):
            return local(tmp_path, legacy(tmp_path, *echo_args))
    return factory


def send(link: Link, frame_id: int, *, w: int = 320, h: int = 240, fill: int = 0) -> int:
    return link.send_frame(frame_id=frame_id, sim_time_ns=0, t0_ns=link.clock.now_ns(), width=w, height=h,
                           encoding=ImageEncoding.RGB8, camera=CAM, ego_speed_mps=0.0, data=bytes([fill]) * (w * h * 3))


def estimates(link: Link, want: int, timeout_s: float = 5.0) -> list[int]:
    """Frame ids of estimates until ``want`` arrived (or the timeout)."""
    got: list[int] = []
    deadline = time.monotonic() + timeout_s
    while len(got) < want and (left := deadline - time.monotonic()) > 0:
        r = link.recv(timeout_s=left)
        if r is not None and isinstance(r.msg, Estimate):
            got.append(r.msg.frame_id)
    return got


def frame_message(frame_id: int = 1, size: int = 16) -> bytes:
    return protocol.encode(Frame(0, frame_id, 0, 0, 0, size, size, ImageEncoding.RGB8, CAM, 0.0,
                                 bytes(range(256)) * (size * size * 3 // 256) + bytes(size * size * 3 % 256)))


def memfd_mapped() -> bool:
    with open("/proc/self/maps") as f:
        return "memfd:hil-local-frames" in f.read()


# ---------------------------------------------------------------- formats


def test_notice_round_trips_and_checks_its_crc_and_reserved_bytes():
    n = Notice(slot=3, length=230_504, seq=2**40 + 1)
    raw = encode_notice(n)
    assert len(raw) == NOTICE_SIZE and raw[:4] == b"HILS"
    assert decode_notice(raw) == n
    bad = bytearray(raw)
    bad[9] ^= 1
    with pytest.raises(ProtocolError) as e:
        decode_notice(bytes(bad))
    assert e.value.offset == 28
    with pytest.raises(ProtocolError):
        decode_notice(raw[:31])


def test_ring_slot_round_trip_updates_consumed():
    with ShmRing(slots=2, slot_bytes=4096) as ring:
        reader = ShmReader(os.dup(ring.fd))
        try:
            msg = frame_message(5)
            notice = decode_notice(ring.put(msg))
            assert (notice.slot, notice.length, notice.seq) == (0, len(msg), 1)
            assert ring.consumed == 0
            got = reader.read(notice)
            assert isinstance(got, Frame) and got.frame_id == 5 and got.data == protocol.decode(msg).data
            assert ring.consumed == 1 and reader.stats.read == 1
        finally:
            reader.close()


def test_overwritten_slot_is_detected_not_read():
    with ShmRing(slots=2, slot_bytes=4096) as ring:
        reader = ShmReader(os.dup(ring.fd))
        try:
            notices = [decode_notice(ring.put(frame_message(i))) for i in range(1, 6)]
            assert ring.stats.overwritten_unread == 3  # seq 3, 4, 5 reused unread slots
            got = [reader.read(n) for n in notices]
            assert got[:3] == [None, None, None] and reader.stats.stale == 3
            assert [g.frame_id for g in got[3:]] == [4, 5]
        finally:
            reader.close()


def test_slot_overwritten_while_read_is_torn(monkeypatch):
    with ShmRing(slots=1, slot_bytes=4096) as ring:
        reader = ShmReader(os.dup(ring.fd))
        try:
            notice = decode_notice(ring.put(frame_message(1)))
            real_decode = shm.decode

            def decode_racing_the_harness(view):
                ring.put(frame_message(2))  # the harness laps the ring mid-read
                return real_decode(view)

            monkeypatch.setattr(shm, "decode", decode_racing_the_harness)
            assert reader.read(notice) is None
            assert reader.stats.torn == 1 and ring.consumed == 0
        finally:
            reader.close()


def test_notice_outside_the_ring_is_an_error():
    with ShmRing(slots=2, slot_bytes=4096) as ring:
        reader = ShmReader(os.dup(ring.fd))
        try:
            assert isinstance(reader.read(Notice(slot=2, length=100, seq=1)), ProtocolError)
            assert isinstance(reader.read(Notice(slot=0, length=5000, seq=1)), ProtocolError)
            assert reader.stats.bad_notices == 2
        finally:
            reader.close()


def test_reader_refuses_memory_that_is_not_a_ring(tmp_path):
    path = tmp_path / "not-a-ring"
    path.write_bytes(b"HILX" + bytes(4092))
    with pytest.raises(TransportError, match="not a version-1 frame ring"):
        ShmReader(os.open(path, os.O_RDWR))
    assert ShmReader.from_env({"HIL_LOCAL_SHM": "not-a-number"}) is None


def test_ring_options_are_checked():
    with pytest.raises(TransportError, match="slots=0"):
        ShmRing(slots=0)
    with pytest.raises(TransportError, match="slot_bytes=10"):
        ShmRing(slot_bytes=10)


# ---------------------------------------------------------------- stream


def _stream_items(chunks: list[bytes]) -> list[object]:
    d = StreamDecoder(NOTICES)
    out: list[object] = []
    for c in chunks:
        out += d.feed(c)
    return out


def _shape(items: list[object]) -> list[object]:
    return [type(i).__name__ if isinstance(i, ProtocolError) else i for i in items]


@pytest.mark.parametrize("stream", [
    b"HILP" + bytes(60) + protocol.encode(SyncRequest(0, 1, 5)),
    b"junkjunk" + protocol.encode(SyncRequest(0, 2, 5)) + b"HI",
    protocol.encode(SyncRequest(0, 3, 5))[:40] + frame_message(1) + b"HILP" + bytes(10),
])
def test_without_notices_it_decodes_as_the_stream_decoder(stream):
    for step in (1, 7, len(stream)):
        chunks = [stream[i:i + step] for i in range(0, len(stream), step)]
        ref = StreamDecoder()
        expected = [x for c in chunks for x in ref.feed(c)]
        assert _shape(_stream_items(chunks)) == _shape(expected)


def test_notices_between_messages_in_any_chunking():
    n1, n2 = encode_notice(Notice(0, 100, 1)), encode_notice(Notice(1, 100, 2))
    sync = protocol.encode(SyncRequest(0, 9, 5))
    stream = n1 + sync + frame_message(4) + n2
    for step in (1, 5, 32, len(stream)):
        items = _stream_items([stream[i:i + step] for i in range(0, len(stream), step)])
        assert [type(i).__name__ for i in items] == ["Notice", "SyncRequest", "Frame", "Notice"]
        assert items[0].seq == 1 and items[3].seq == 2


def test_bad_notice_is_reported_once_and_the_stream_resyncs():
    bad = bytearray(encode_notice(Notice(0, 100, 1)))
    bad[20] ^= 0xFF
    sync = protocol.encode(SyncRequest(0, 9, 5))
    items = _stream_items([bytes(bad) + b"xx" + sync + encode_notice(Notice(1, 100, 2))])
    assert [type(i).__name__ for i in items] == ["ProtocolError", "SyncRequest", "Notice"]
    assert _stream_items([bytes(bad)]) and isinstance(_stream_items([bytes(bad)])[0], ProtocolError)


# ---------------------------------------------------------------- over a real child


def test_raw_frames_go_through_shared_memory_and_all_are_answered(tmp_path):
    with local(tmp_path, echo("--throttle", "0.5")) as link:
        assert link.shm_active and link.hello.capabilities & SHM_FRAMES
        for i in range(20):
            send(link, i, fill=i)
            assert estimates(link, 1) == [i]
        assert link.local_stats.frames_shm == 20 and link.local_stats.frames_inline == 0
        assert link.stats.protocol_errors == 0 and link.stats.target_errors == 0


def test_small_frames_stay_inline(tmp_path):
    with local(tmp_path, echo()) as link:
        send(link, 1, w=32, h=32)  # 3 KB, under the inline threshold
        assert estimates(link, 1) == [1]
        assert link.local_stats.frames_inline == 1 and link.local_stats.frames_shm == 0


def test_frame_larger_than_a_slot_goes_inline_and_is_counted(tmp_path):
    with local(tmp_path, echo(), shm_slot_bytes=64 * 1024) as link:
        send(link, 1)  # 230 KB
        assert estimates(link, 1) == [1]
        send(link, 2, w=100, h=100)  # 30 KB: fits
        assert estimates(link, 1) == [2]
        st = link.local_stats
        assert (st.too_big_for_slot, st.frames_inline, st.frames_shm) == (1, 1, 1)


def test_shm_off_offers_nothing_and_the_target_does_not_advertise(tmp_path):
    with local(tmp_path, echo(), shm=False) as link:
        assert not link.shm_active and not link.hello.capabilities & SHM_FRAMES
        send(link, 1)
        assert estimates(link, 1) == [1]
        assert link.local_stats.frames_inline == 1


def test_legacy_target_gets_frames_inline(tmp_path):
    with local(tmp_path, legacy(tmp_path)) as link:
        assert link.hello.target_name == "echo" and not link.shm_active
        assert not memfd_mapped()  # the offered ring was released at HELLO
        send(link, 1)
        assert estimates(link, 1) == [1]
        assert link.local_stats.frames_inline == 1


def test_stopped_target_loses_overwritten_frames_and_counts_them(tmp_path):
    with local(tmp_path, echo(), shm_slots=2) as link:
        send(link, 0)
        assert estimates(link, 1) == [0]
        os.kill(link.pid, signal.SIGSTOP)  # our own child, by PID
        try:
            for i in range(1, 7):
                send(link, i)
        finally:
            os.kill(link.pid, signal.SIGCONT)
        got: list[int] = []
        deadline = time.monotonic() + 5
        while 6 not in got and time.monotonic() < deadline:
            got += estimates(link, 1, timeout_s=deadline - time.monotonic())
        assert link.local_stats.overwritten_unread == 4  # frames 1..4: their slots were reused unread
        assert 6 in got and set(got) <= {5, 6}


def test_ring_is_gone_after_close_and_after_a_crash(tmp_path):
    before = set(os.listdir("/dev/shm")) if os.path.isdir("/dev/shm") else set()
    with local(tmp_path, echo()) as link:
        assert link.shm_active and memfd_mapped()
    assert not memfd_mapped()
    with local(tmp_path, echo("--exit-after-frames", "1")) as link:
        send(link, 0)
        assert estimates(link, 1) == [0]
        send(link, 1)  # the target dies on this one
        deadline = time.monotonic() + 2
        while link.alive and time.monotonic() < deadline:
            link.recv(timeout_s=0.05)
        assert not link.alive
    assert not memfd_mapped()
    if before:
        assert not {n for n in set(os.listdir("/dev/shm")) - before if "hil" in n}


def test_hello_capability_is_added_only_to_the_hello():
    from hil.adapters.local.target import _advertising

    sent: list[bytes] = []
    wrapped = _advertising(sent.append, SHM_FRAMES)
    hello = protocol.encode(Hello("t", protocol.VERSION, 0, 1, 0))
    wrapped(hello)
    wrapped(hello)
    first, second = (protocol.decode(b) for b in sent)
    assert first.capabilities == SHM_FRAMES and second.capabilities == 0


def test_a_reader_that_first_runs_after_the_link_closed_leaves_quietly():
    # A stop (SIGTERM, Ctrl-C) while the target starts can close the link before its
    # reader thread ran a line: a fresh clone's suite printed that thread's traceback
    # (an assertion on the closed socket) under "hil: interrupted". As that late thread:
    link = LocalLink(command=[sys.executable, "-c", "import time; time.sleep(30)"], vehicle_id=0,
                     clock=MonotonicClock())
    link.start()
    link.close()
    link._read_loop()  # noqa: SLF001 - what the reader thread runs: it returns, raising nothing


def test_link_checks_ring_options_before_starting_anything():
    with pytest.raises(TransportError, match="shm slots=65"):
        LocalLink(command=["true"], vehicle_id=0, clock=MonotonicClock(), options=LocalOptions(shm_slots=65))
    with pytest.raises(TransportError, match="shm_inline_below=-1"):
        LocalLink(command=["true"], vehicle_id=0, clock=MonotonicClock(), options=LocalOptions(shm_inline_below=-1))
