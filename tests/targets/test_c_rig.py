"""The C reference target speaks a camera rig (PROTOCOL.md 4.2.1): it checks and reads
FRAME bytes 69-71, answers every camera, or with --frame-sets one ESTIMATE per set
whose frame_id is the set id (SLOW with a camera missing), and reports a frame that
contradicts its set with the byte offset; under the sanitizers, over local and tcp."""

from __future__ import annotations

import time
import zlib
from dataclasses import replace

import pytest

from hil.adapters.link import Link
from hil.adapters.wire import protocol
from hil.adapters.wire.messages import Command, DrivingState, ErrorMsg, Estimate, Frame, ImageEncoding
from tests.targets import c_build
from tests.targets.test_c_target import CAM, H, W, c_link, next_of

pytestmark = pytest.mark.skipif(c_build.unavailable() is not None, reason=str(c_build.unavailable()))

BRIGHT = bytes([128]) * (W * H * 3)


def rig(link: Link, fid: int, index: int, count: int, sim_ns: int) -> bytes:
    return protocol.encode(Frame(link.vehicle_id, fid, sim_ns, link.clock.now_ns(), link.clock.now_ns(), W, H,
                                 ImageEncoding.RGB8, CAM, 3.0, BRIGHT, camera_index=index, camera_count=count))


def estimate(link: Link, timeout_s: float = 5.0) -> Estimate:
    m = next_of(link, Estimate, timeout_s)
    assert isinstance(m, Estimate)
    return m


def _status(link: Link) -> str:
    link.send_command("status")
    reply = next_of(link, Command)
    assert isinstance(reply, Command)
    return reply.text


@pytest.mark.parametrize("transport", ["local", "tcp"])
def test_c_target_answers_every_camera(transport, tmp_path):
    with c_link(transport, tmp_path) as (link, _):
        assert link.hello is not None and link.hello.capabilities & 0x18 == protocol.CAP_CAMERAS
        for k in range(3):
            link.send_raw(rig(link, 20 + k, k, 3, 1000))
        assert sorted(estimate(link).frame_id for _ in range(3)) == [20, 21, 22]
        assert "answers=per-camera last_camera=2" in _status(link)


def test_c_target_answers_each_frame_set_once(tmp_path):
    with c_link("tcp", tmp_path, extra=("--frame-sets",)) as (link, log):
        assert link.hello is not None and link.hello.capabilities & 0x18 == 0x18
        link.send_raw(b"".join(rig(link, 30 + k, k, 3, 1000) for k in range(3)))
        e = estimate(link)
        assert (e.frame_id, e.state) == (30, DrivingState.SAFE)
        assert e.t_rx_target_ns is not None and e.t_infer_start_target_ns is not None
        assert e.t_rx_target_ns <= e.t_infer_start_target_ns
        link.send_raw(rig(link, 33, 0, 3, 2000) + rig(link, 35, 2, 3, 2000) + rig(link, 36, 0, 3, 3000))
        e = estimate(link)  # camera 1 of set 33 never came: set 36 began
        assert (e.frame_id, e.state) == (33, DrivingState.SLOW)
        sent = time.monotonic()
        link.send_raw(rig(link, 37, 1, 3, 3000))
        e = estimate(link)  # camera 2 of set 36 never comes: given up after 100 ms
        assert (e.frame_id, e.state) == (36, DrivingState.SLOW) and time.monotonic() - sent >= 0.08
        link.send_raw(rig(link, 40, 0, 2, 4000))
        for bad, offset in ((rig(link, 40, 0, 2, 4000), 69), (rig(link, 41, 1, 3, 4000), 70),
                            (rig(link, 41, 1, 2, 4001), 32)):  # camera 0 twice, another count, another sim_time
            link.send_raw(bad)
            err = next_of(link, ErrorMsg)
            assert isinstance(err, ErrorMsg) and f"byte offset {offset}" in err.message, err
        link.send_raw(rig(link, 41, 1, 2, 4000))
        assert estimate(link).frame_id == 40
        link.send_frame(frame_id=50, sim_time_ns=5000, t0_ns=link.clock.now_ns(), width=W, height=H,
                        encoding=ImageEncoding.RGB8, camera=CAM, ego_speed_mps=3.0, data=BRIGHT)
        assert (estimate(link).frame_id) == 50  # a single camera: a set of one, its own frame_id
        text = _status(link)
        assert "answers=per-set" in text and "sets=4 incomplete_sets=2" in text, text
    assert "frame set 33 without camera(s) 1: a later set began" in log.read_text()


@pytest.mark.parametrize(("index", "count", "offset"), [(1, 0, 69), (0, 1, 70), (2, 2, 69), (0, 33, 70)])
def test_c_target_refuses_bad_camera_bytes(index, count, offset, tmp_path):
    with c_link("local", tmp_path) as (link, _):
        raw = bytearray(rig(link, 9, 0, 0, 1000))
        raw[69], raw[70] = index, count
        raw[60:64] = zlib.crc32(bytes(raw[:60])).to_bytes(4, "little")
        link.send_raw(bytes(raw))
        err = next_of(link, ErrorMsg)
        assert isinstance(err, ErrorMsg) and err.code == protocol.ErrorCode.MALFORMED
        assert f"byte offset {offset}" in err.message, err.message
        link.send_raw(rig(link, 10, 0, 0, 1000))
        assert estimate(link).frame_id == 10  # the session goes on
