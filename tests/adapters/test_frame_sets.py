"""A camera rig's target (PROTOCOL.md 4.2, hil.adapters.frame_sets): the SDK's set
assembly on its own, then an SDK target in a child process on real TCP, fed frame sets
by a peer that speaks the wire itself."""

from __future__ import annotations

import os
import time

import pytest

from hil.adapters.frame_sets import CameraMode, FrameSet, RigQueue, camera_mode
from hil.adapters.wire import protocol
from hil.adapters.wire.messages import Bye, DrivingState, ErrorMsg, Estimate, Frame, Hello, SyncRequest
from hil.common.errors import ConfigError
from tests.adapters.tcp.pair import tcp_echo
from tests.adapters.wire_peer import WirePeer, rig_frame
from tests.adapters.zenoh.pair import free_port


def _sets(q: RigQueue, now: float) -> list[FrameSet]:
    out = []
    while isinstance(item := q.take(now), FrameSet):
        out.append(item)
    return out


def test_a_complete_set_is_one_item_in_camera_order() -> None:
    q = RigQueue(CameraMode.SET, timeout_s=1.0)
    for k in (2, 0, 1):  # any order within the set
        assert q.put(rig_frame(30 + k, k, 3, 500), 100 + k, 0.0) == (0, None)
        assert (q.take(0.0) is None) == (k != 1)
    q.put(rig_frame(30, 0, 3, 500), 1, 0.0)  # a frame of an answered set: too late, dropped
    assert q.take(0.0) is None


def test_a_later_set_or_the_timeout_gives_a_set_up_naming_the_missing_camera() -> None:
    q = RigQueue(CameraMode.SET, timeout_s=0.5)
    q.put(rig_frame(10, 0, 3, 7), 1, 0.0)
    q.put(rig_frame(12, 2, 3, 7), 3, 0.1)
    q.put(rig_frame(13, 0, 3, 8), 4, 0.2)  # set 13 begins: set 10 is given up
    (s,) = _sets(q, 0.2)
    assert (s.set_id, s.missing, [f.camera_index for f in s.frames], s.t_rx_ns) == (10, (1,), [0, 2], 3)
    assert s.given_up == "set 13 began" and not s.complete and s.camera(1) is None
    assert q.wait_s(0.2) == pytest.approx(0.5)
    assert _sets(q, 0.69) == []
    (late,) = _sets(q, 0.7)
    assert (late.set_id, late.missing, late.given_up) == (13, (1, 2), "timed out after 0.5 s")


def test_newest_set_wins_and_skips_are_counted() -> None:
    q = RigQueue(CameraMode.SET)
    assert q.put(rig_frame(0, 0, 2, 1), 1, 0.0)[0] == 0
    assert q.put(rig_frame(1, 1, 2, 1), 1, 0.0)[0] == 0  # set 0 ready, not yet taken
    q.put(rig_frame(2, 0, 2, 2), 1, 0.0)
    assert q.put(rig_frame(3, 1, 2, 2), 1, 0.0)[0] == 2  # set 2 replaces set 0: its 2 frames skipped
    assert [s.set_id for s in _sets(q, 0.0)] == [2]


@pytest.mark.parametrize(("frame", "offset", "words"), [
    (rig_frame(41, 1, 3, 9), 70, "camera_count 3 in set 40"),
    (rig_frame(40, 0, 2, 9), 69, "camera 0 of set 40 came twice"),
    (rig_frame(41, 1, 2, 10), 32, "one capture instant has one sim_time"),
])
def test_a_frame_that_contradicts_its_set_is_an_error_naming_the_offset(frame: Frame, offset: int,
                                                                       words: str) -> None:
    q = RigQueue(CameraMode.SET)
    q.put(rig_frame(40, 0, 2, 9), 1, 0.0)
    skipped, error = q.put(frame, 2, 0.0)
    assert error is not None and error.offset == offset and words in str(error)


def test_each_camera_keeps_its_own_newest_frame() -> None:
    q = RigQueue(CameraMode.EACH)
    assert [q.put(rig_frame(i, i % 3, 3, i // 3), i, 0.0)[0] for i in range(6)] == [0, 0, 0, 1, 1, 1]
    taken = [q.take(0.0) for _ in range(4)]
    assert [t[0].frame_id for t in taken if isinstance(t, tuple)] == [3, 4, 5] and taken[3] is None


def test_a_mode_needs_its_function() -> None:
    assert camera_mode(print, None, None) is CameraMode.ONE
    assert camera_mode(None, None, print) is CameraMode.SET
    for infer, cameras, infer_set in ((None, "each", None), (print, "set", None), (print, "each", print),
                                      (print, "all", None)):
        with pytest.raises(ConfigError):
            camera_mode(infer, cameras, infer_set)


# ---------------------------------------------------------------- a real target process


def _env() -> dict[str, str]:
    return {k: v for k, v in os.environ.items() if k not in ("HIL_SESSION_TOKEN", "HIL_SESSION")}


def _estimate(peer: WirePeer, timeout_s: float = 5.0) -> Estimate:
    m = peer.recv_a(Estimate, timeout_s)
    assert isinstance(m, Estimate)
    return m


def _cameras(e: Estimate) -> list[int]:
    return [o.camera for o in e.objects]


def test_an_sdk_target_gets_complete_sets_and_names_the_missing_camera(tmp_path):
    address = f"127.0.0.1:{free_port()}"
    with tcp_echo(tmp_path / "t.log", ["--cameras", "set", "--set-timeout-ms", "300", "--once"], listen=address,
                  env=_env()) as proc:
        peer = WirePeer(address)
        try:
            hello = peer.recv_a(Hello)
            assert isinstance(hello, Hello)
            assert hello.capabilities & (protocol.CAP_CAMERAS | protocol.CAP_FRAME_SETS) == 0x18
            peer.send(*(rig_frame(10 + k, k, 3, 1000) for k in range(3)))
            e = _estimate(peer)
            assert (e.frame_id, _cameras(e), e.state) == (10, [0, 1, 2], DrivingState.SAFE)
            assert e.t_rx_target_ns is not None and e.t_infer_start_target_ns is not None
            assert e.t_rx_target_ns <= e.t_infer_start_target_ns
            peer.send(rig_frame(13, 0, 3, 2000), rig_frame(15, 2, 3, 2000), rig_frame(16, 0, 3, 3000))
            e = _estimate(peer)  # camera 1 of set 13 never came; set 16 began
            assert (e.frame_id, _cameras(e), e.state) == (13, [0, 2], DrivingState.SLOW)
            sent = time.monotonic()
            peer.send(rig_frame(17, 1, 3, 3000))
            e = _estimate(peer)  # camera 2 of set 16 never comes: given up after 300 ms
            assert time.monotonic() - sent >= 0.25
            assert (e.frame_id, _cameras(e), e.state) == (16, [0, 1], DrivingState.SLOW)
            peer.send(rig_frame(40, 0, 2, 4000), rig_frame(40, 0, 2, 4000))  # camera 0 twice
            err = peer.recv_a(ErrorMsg)
            assert isinstance(err, ErrorMsg) and err.code == protocol.ErrorCode.MALFORMED
            assert "byte offset 69" in err.message and "came twice" in err.message
            peer.send(rig_frame(41, 1, 2, 4000))
            e = _estimate(peer)
            assert (e.frame_id, _cameras(e)) == (40, [0, 1])
            peer.send(rig_frame(50, 0, 0, 5000))  # a single camera's frame: a set of its own
            e = _estimate(peer)
            assert (e.frame_id, _cameras(e), e.state) == (50, [0], DrivingState.SAFE)
            peer.send(Bye(0, "test done"))
            assert proc.wait(timeout=10) == 0
        finally:
            peer.close()
    log = (tmp_path / "t.log").read_text()
    assert "capabilities: CAMERAS, FRAME_SETS" in log and "11 frames, 5 estimates" in log


def test_an_sdk_target_answering_each_camera(tmp_path):
    address = f"127.0.0.1:{free_port()}"
    with tcp_echo(tmp_path / "t.log", ["--cameras", "each", "--once"], listen=address, env=_env()) as proc:
        peer = WirePeer(address)
        try:
            hello = peer.recv_a(Hello)
            assert isinstance(hello, Hello) and hello.capabilities & 0x18 == protocol.CAP_CAMERAS
            peer.send(SyncRequest(3, 1, 5))
            peer.recv()  # its SYNC_RESPONSE: the target now serves vehicle 3
            peer.send(*(rig_frame(60 + k, k, 4, 1000) for k in range(4)))
            got = sorted(_estimate(peer).frame_id for _ in range(4))
            assert got == [60, 61, 62, 63]
            peer.send(Bye(3, "test done"))
            assert proc.wait(timeout=10) == 0
        finally:
            peer.close()


def test_an_estimate_of_one_frame_names_its_camera() -> None:
    from hil.adapters.frame_sets import on_camera
    from hil.adapters.wire.messages import Control, DetectedObject, Inference, ObjectClass

    obj = DetectedObject(ObjectClass.VEHICLE, 0.5, (0.0, 0.0, 1.0, 1.0), (5.0, 0.0, 0.0))
    result = Inference(DrivingState.SAFE, Control(), (obj, obj))
    assert [o.camera for o in on_camera(result, rig_frame(7, 2, 3, 0)).objects] == [2, 2]
    assert on_camera(result, rig_frame(7, 0, 0, 0)) is result  # a single camera: nothing to change
