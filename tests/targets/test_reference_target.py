"""The reference target of ``hil calibrate``: its clock is what it says it is, it
injects exactly the faults it is told to, and its truth file says what really
happened. Driven in-process through the real SDK endpoint and wire codec."""

from __future__ import annotations

import io
import json
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path

import pytest

from hil.adapters.wire import protocol
from hil.adapters.wire.messages import CameraInfo, Control, DrivingState, Estimate, Frame, ImageEncoding
from hil.common.errors import ProtocolError
from hil.targets.reference import (Faults, InjectedClock, ReferenceEndpoint, bad_crc_bytes, bad_length_bytes)

ROOT = Path(__file__).resolve().parents[2]
CAM = CameraInfo(277.0, 277.0, 160.0, 120.0, 1.3)


def test_clock_maps_both_ways_across_a_step():
    c = InjectedClock(offset_ns=2_500_000_000, skew_ppm=300.0, base_ns=1_000_000_000)
    m = 1_000_000_000 + 10_000_000_000  # 10 s after the base: 3 ms of skew
    assert c.at(m) == m + 2_500_000_000 + 3_000_000
    c.step(20_000_000, at_mono_ns=m + 1)
    assert c.at(m) == m + 2_503_000_000  # before the step instant: unchanged
    assert c.at(m + 1) == m + 1 + 2_503_000_000 + 20_000_000
    for mono in (m - 5_000_000, m, m + 1, m + 7_000_000, m + 10**9):
        assert abs(c.to_mono(c.at(mono)) - mono) <= 1, mono
    with pytest.raises(ValueError, match="once"):
        c.step(1, at_mono_ns=m + 2)


def test_malformed_messages_fail_where_the_protocol_says():
    est = Estimate(0, 7, DrivingState.SAFE, Control(0.0, 0.0, 0.0), (), 1, 2, 3, 4)
    protocol.decode(protocol.encode(est))  # the good one decodes
    with pytest.raises(ProtocolError, match="CRC") as crc:
        protocol.decode(bad_crc_bytes(est))
    with pytest.raises(ProtocolError) as length:
        protocol.decode(bad_length_bytes(est))
    assert length.value.offset == protocol.HEADER_SIZE + 2  # n_objects


class _Wire:
    """What the endpoint sends, decoded; ``done`` frame ids as the worker finishes them."""

    def __init__(self) -> None:
        self.items: list[object] = []
        self.done: list[int] = []
        self.cv = threading.Condition()

    def send(self, data: bytes) -> None:
        try:
            item: object = protocol.decode(data)
        except ProtocolError as err:
            item = err
        with self.cv:
            self.items.append(item)

    def on_done(self, fid: int) -> None:
        with self.cv:
            self.done.append(fid)
            self.cv.notify_all()

    def wait_done(self, fid: int) -> None:
        with self.cv:
            assert self.cv.wait_for(lambda: fid in self.done, timeout=10.0), f"frame {fid} not handled"


def _frame(fid: int) -> Frame:
    return Frame(0, fid, fid * 50_000_000, time.monotonic_ns(), time.monotonic_ns(), 2, 2, ImageEncoding.RGB8,
                 CAM, 0.0, bytes(12))


def test_faults_are_injected_and_the_truth_written():
    faults = Faults(infer_ns=1_000_000, spike_ns=3_000_000, spike_frames=frozenset({2}),
                    drop_frames=frozenset({3}), reorder_frames=frozenset({5}), bad_crc_frames=frozenset({7}),
                    bad_length_frames=frozenset({8}), step_frame=9, step_ns=20_000_000)
    clock = InjectedClock(offset_ns=2_500_000_000, skew_ppm=300.0)
    truth = io.StringIO()
    wire = _Wire()
    ep = ReferenceEndpoint(clock=clock, faults=faults, truth=truth, on_done=wire.on_done)
    ep.start(wire.send)
    try:
        for fid in range(11):
            ep.on_message(_frame(fid), clock.now_ns())
            wire.wait_done(fid)
    finally:
        ep.join()
    items = wire.items[1:]  # after HELLO
    order = [x.frame_id if isinstance(x, Estimate) else "bad" for x in items]
    assert order == [0, 1, 2, 4, 6, 5, "bad", 7, "bad", 8, 9, 10]
    lines = [json.loads(s) for s in truth.getvalue().splitlines()]
    assert lines[0]["kind"] == "config" and lines[0]["skew_ppm"] == 300.0
    frames = {d["frame_id"]: d for d in lines if d["kind"] == "frame"}
    assert sorted(frames) == list(range(11))
    assert frames[3]["faults"] == ["drop"] and frames[3]["send_mono_ns"] is None
    assert frames[5]["faults"] == ["reorder"] and frames[5]["send_mono_ns"] > frames[6]["send_mono_ns"]
    assert frames[2]["send_mono_ns"] - frames[2]["infer_end_mono_ns"] >= 3_000_000
    assert [d["fault"] for d in lines if d["kind"] == "malformed"] == ["bad_crc", "bad_length"]
    step = next(d for d in lines if d["kind"] == "step")
    assert step["frame_id"] == 9 and frames[9]["faults"] == ["clock_step"]
    # Every stamp sent is the reference clock read at the instant the truth names.
    for est in (x for x in items if isinstance(x, Estimate)):
        d = frames[est.frame_id]
        assert est.t_infer_start_target_ns == clock.at(d["infer_start_mono_ns"])
        assert est.t_infer_end_target_ns == clock.at(d["infer_end_mono_ns"])
        assert est.t_reply_target_ns == clock.at(d["send_mono_ns"])
        assert abs(clock.to_mono(est.t_rx_target_ns) - d["rx_mono_ns"]) <= 1
        assert d["infer_end_mono_ns"] - d["infer_start_mono_ns"] >= 1_000_000
    # The step lies between frames 8 and 9: 9's stamps are all on the stepped clock.
    assert frames[8]["send_mono_ns"] < step["at_mono_ns"] <= frames[9]["rx_mono_ns"]


def test_reference_target_needs_no_harness_code():
    code = textwrap.dedent("""
        import sys
        BLOCKED = ("mujoco", "harness", "scenarios", "torch", "cv2", "mcap", "pydantic")
        class Block:
            def find_spec(self, name, path=None, target=None):
                if name.split(".")[0] in BLOCKED:
                    raise ImportError(f"blocked: {name}")
                return None
        sys.meta_path.insert(0, Block())
        import hil.targets.reference
        hil.targets.reference.build_parser()
        print("OK")
    """)
    p = subprocess.run([sys.executable, "-I", "-c", code], cwd=ROOT, capture_output=True, text=True,
                       env={"PYTHONPATH": str(ROOT)}, timeout=60)
    assert p.returncode == 0 and "OK" in p.stdout, p.stderr
