"""The CAN transport: DBC mapping, ISO-TP on python-can's in-process ``virtual`` bus,
bus capacity math, option checks, and socketcan ``vcan0`` where it exists. Never
``udp_multicast`` (it would send off this machine)."""

from __future__ import annotations

import contextlib
import queue
import threading
import time
import uuid
from collections.abc import Callable, Iterator
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("can", reason="python-can is not installed (pip install 'python-can>=4.6')")
pytest.importorskip("cantools", reason="cantools is not installed (pip install cantools)")
pytest.importorskip("isotp", reason="can-isotp is not installed (pip install 'can-isotp>=2.0')")

import can  # noqa: E402

from hil.adapters.can.capacity import (bus_capacity, classic_frame_time_s, fd_frame_time_s,  # noqa: E402
                                       isotp_frame_lengths)
from hil.adapters.can.dbc import DBC_PATH, MAX_DBC_OBJECTS, HilCan, Role, load_database  # noqa: E402
from hil.adapters.can.link import CanLink  # noqa: E402
from hil.adapters.can.options import CanOptions  # noqa: E402
from hil.adapters.can.target import serve_endpoint  # noqa: E402
from hil.adapters.link import open_link  # noqa: E402
from hil.adapters.sdk import Endpoint  # noqa: E402
from hil.adapters.wire import protocol  # noqa: E402
from hil.adapters.wire.messages import (Bye, CameraInfo, ClockId, Control, DetectedObject, DrivingState,  # noqa: E402
                                        ErrorMsg, Estimate, Frame, Heartbeat, Hello, ImageEncoding, Inference,
                                        ObjectClass, SyncRequest, SyncResponse)
from hil.common.errors import ConfigError, ProtocolError, TargetError  # noqa: E402
from hil.timing.clock import MonotonicClock  # noqa: E402

CAM = CameraInfo(277.0, 277.0, 160.0, 120.0, 1.3)
OBJ = DetectedObject(ObjectClass.PEDESTRIAN, 0.75, (10.5, 20.0, 30.25, 80.0), (12.5, -1.25, 0.0))


def channel() -> str:
    return f"hil-test-{uuid.uuid4().hex}"


def virtual(chan: str) -> CanOptions:
    """A python-can ``virtual`` bus (in this process only) on channel ``chan``."""
    return CanOptions(interface="virtual", channel=chan)


# ---------------------------------------------------------------- DBC


def test_dbc_ships_next_to_the_module_and_every_frame_round_trips():
    db = load_database()
    assert DBC_PATH.parent == Path(__file__).resolve().parents[3] / "adapters" / "can"
    assert len(db.messages) == 16
    for m in db.messages:
        assert m.is_extended_frame and m.is_fd, m.name
        assert m.frame_id & 0xFFFF == 0, f"{m.name}: hil.dbc lists vehicle 0"
        values = {}
        for i, s in enumerate(m.signals):
            if s.is_float:
                values[s.name] = 1.5 + i
            else:
                values[s.name] = s.maximum if i % 2 else s.minimum
        assert m.decode(m.encode(values), decode_choices=False) == pytest.approx(values), m.name


def test_can_id_layout_carries_priority_message_and_vehicle():
    c = HilCan(role=Role.TARGET, vehicle_id=0x1234)
    assert c.can_id("HIL_ESTIMATE") == 0 << 26 | 0x001 << 16 | 0x1234
    assert c.can_id("HIL_SYNC_RESPONSE") == 1 << 26 | 0x011 << 16 | 0x1234
    assert c.isotp_tx_data == 6 << 26 | 0x042 << 16 | 0x1234  # target sends DOWN data
    assert c.isotp_rx_data == 6 << 26 | 0x040 << 16 | 0x1234
    order = [c.can_id(n) for n in ("HIL_ESTIMATE", "HIL_SYNC_RESPONSE", "HIL_TARGET_TIMESTAMPS",
                                   "HIL_HEARTBEAT_TARGET", "HIL_HELLO", "HIL_ISOTP_DOWN_FC", "HIL_ISOTP_DOWN_DATA")]
    assert order == sorted(order), "control wins arbitration over everything, camera data loses"


ROUND_TRIPS = [
    (Role.TARGET, Estimate(7, 42, DrivingState.SLOW, Control(-0.123456, 0.25, 1.0), (OBJ, OBJ), 1, 2, 3, 2**63 - 1)),
    (Role.TARGET, Estimate(7, 2**32 - 1, DrivingState.STOP, Control(), (), -(2**63), 0, 5, 6)),
    (Role.HARNESS, SyncRequest(7, 3, 1_000_000_000)),
    (Role.TARGET, SyncResponse(7, 3, 1_000_000_000, 1_700_000_000_123_456_789, 1_700_000_000_123_456_999)),
    (Role.HARNESS, Heartbeat(7, 5)),
    (Role.TARGET, Heartbeat(7, 6)),
    (Role.TARGET, Hello("échø-ai", 1, ClockId.PTP, 8, 0)),
    (Role.TARGET, ErrorMsg(7, protocol.ErrorCode.MALFORMED, "bad magic")),
    (Role.HARNESS, ErrorMsg(7, 0x8001, "")),
    (Role.HARNESS, Bye(7, "harness closing")),
    (Role.TARGET, Bye(7, "")),
]


@pytest.mark.parametrize("role,msg", ROUND_TRIPS, ids=lambda v: type(v).__name__ if not isinstance(v, Role) else v.value)
def test_messages_round_trip_through_dbc_frames(role, msg):
    sender = HilCan(role=role, vehicle_id=7)
    receiver = HilCan(role=Role.HARNESS if role is Role.TARGET else Role.TARGET, vehicle_id=7)
    frames = sender.encode(msg)
    assert frames is not None
    got = [item for f in frames for item in receiver.decode(f.arbitration_id, f.data)]
    assert got == [msg]


def test_control_is_quantized_to_the_signal_resolution():
    t, h = HilCan(role=Role.TARGET, vehicle_id=0), HilCan(role=Role.HARNESS, vehicle_id=0)
    e = Estimate(0, 1, DrivingState.SAFE, Control(0.1234567, 0.33333, 0.00004), (), 1, 2, 3, 4)
    (got,) = [m for f in t.encode(e) for m in h.decode(f.arbitration_id, f.data)]
    assert got.control.steering_rad == pytest.approx(0.123457, abs=1e-12)
    assert got.control.throttle == pytest.approx(0.3333, abs=1e-12)
    assert got.control.brake == 0.0


@pytest.mark.parametrize("msg", [
    Estimate(0, 1, DrivingState.SAFE, Control(), (OBJ,) * (MAX_DBC_OBJECTS + 1), 1, 2, 3, 4),
    Estimate(0, 2**32, DrivingState.SAFE, Control(), (), 1, 2, 3, 4),
    Estimate(0, 1, DrivingState.SAFE, Control(steering_rad=3000.0), (), 1, 2, 3, 4),
    Estimate(9, 1, DrivingState.SAFE, Control(), (), 1, 2, 3, 4),  # another vehicle's id
    Hello("n" * 53, 1, ClockId.MONOTONIC, 1),
    ErrorMsg(0, 1, "x" * 61),
    SyncRequest(0, 1, 1),  # the target never sends one
    Estimate(0, 1, DrivingState.SAFE, Control(), (replace(OBJ, camera=2),), 1, 2, 3, 4),  # no signal for it
], ids=["9-objects", "64-bit-frame-id", "steering-range", "vehicle-id", "long-name", "long-text", "direction",
        "object-camera"])
def test_what_dbc_frames_cannot_carry_goes_over_isotp(msg):
    assert HilCan(role=Role.TARGET, vehicle_id=0).encode(msg) is None


def test_bad_frames_decode_to_protocol_errors_with_offsets():
    h = HilCan(role=Role.HARNESS, vehicle_id=0)
    (frame, stamps) = HilCan(role=Role.TARGET, vehicle_id=0).encode(
        Estimate(0, 1, DrivingState.SAFE, Control(), (), 1, 2, 3, 4))
    bad_state = bytearray(frame.data)
    bad_state[4] = 3
    (err,) = h.decode(frame.arbitration_id, bytes(bad_state))
    assert isinstance(err, ProtocolError) and err.offset == 4 and "State" in str(err)
    (short,) = h.decode(stamps.arbitration_id, stamps.data[:40])
    assert isinstance(short, ProtocolError) and "40 data bytes, expected 48" in str(short)
    reserved = bytearray(stamps.data)
    reserved[44] = 1  # padding after TReply
    (err,) = h.decode(stamps.arbitration_id, bytes(reserved))
    assert isinstance(err, ProtocolError) and err.offset == 44 and "reserved" in str(err)
    (bye,) = HilCan(role=Role.TARGET, vehicle_id=0).encode(Bye(0, "ok"))
    junk = bytearray(bye.data)
    junk[10] = ord("x")  # after the 2-byte reason
    (err,) = h.decode(bye.arbitration_id, bytes(junk))
    assert isinstance(err, ProtocolError) and err.offset == 10 and "must be 0" in str(err)


# ---------------------------------------------------------------- virtual bus


@contextlib.contextmanager
def target(chan: str, infer: Callable[[Frame], Inference], *, name: str = "t", vehicle_id: int = 0) -> Iterator[Endpoint]:
    """An SDK endpoint served on virtual ``chan`` in a thread until the harness says BYE."""
    ep = Endpoint(infer, target_name=name)
    bus = can.Bus(interface="virtual", channel=chan, fd=True, ignore_config=True)
    errors: list[BaseException] = []

    def run() -> None:
        try:
            serve_endpoint(ep, options=virtual(chan), vehicle_id=vehicle_id, bus=bus)
        except BaseException as err:
            errors.append(err)

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    try:
        yield ep
    finally:
        thread.join(timeout=3.0)
        if thread.is_alive():
            ep.stop()
            thread.join(timeout=3.0)
        bus.shutdown()
        assert not thread.is_alive() and not errors, errors


def jpeg_320x240() -> bytes:
    cv2 = pytest.importorskip("cv2")
    rng = np.random.default_rng(0)
    y, x = np.mgrid[0:240, 0:320]
    img = np.stack([x * 255 / 320, y * 255 / 240, (x + y) * 255 / 560], axis=-1) + rng.normal(0, 6, (240, 320, 3))
    ok, buf = cv2.imencode(".jpg", np.clip(img, 0, 255).astype(np.uint8), [cv2.IMWRITE_JPEG_QUALITY, 85])
    assert ok
    return buf.tobytes()


def test_jpeg_frame_crosses_isotp_intact_and_the_estimate_comes_back():
    jpeg = jpeg_320x240()
    assert 10_000 < len(jpeg) < 15_000
    got: queue.Queue[Frame] = queue.Queue()

    def infer(frame: Frame) -> Inference:
        got.put(frame)
        return Inference(DrivingState.STOP, Control(brake=0.5), (OBJ,) * 3)

    chan = channel()
    with target(chan, infer), CanLink(vehicle_id=0, clock=MonotonicClock(), options=virtual(chan)) as link:
        link.open(hello_timeout_s=5)
        t_tx = link.send_frame(frame_id=9, sim_time_ns=1, t0_ns=link.clock.now_ns(), width=320, height=240,
                               encoding=ImageEncoding.JPEG, camera=CAM, ego_speed_mps=3.0, data=jpeg)
        frame = got.get(timeout=5)
        assert frame.data == jpeg and frame.frame_id == 9 and frame.t_tx_ns == t_tx
        r = link.recv(timeout_s=5)
        while r is not None and not isinstance(r.msg, Estimate):
            r = link.recv(timeout_s=5)
        assert r is not None and r.msg.objects == (OBJ,) * 3 and r.msg.control.brake == 0.5
        stats = link.can_stats
        assert stats is not None and stats.isotp_sent == 1 and stats.isotp_errors == 0
        assert link.stats.protocol_errors == 0


def test_large_estimate_and_long_hello_travel_over_isotp():
    many = tuple(DetectedObject(ObjectClass.VEHICLE, 0.5, (i, i, i + 1.0, i + 2.0), (i, 0.0, 0.0)) for i in range(40))
    chan = channel()
    name = "a-target-name-longer-than-the-52-bytes-a-hello-frame-carries"
    infer = lambda frame: Inference(DrivingState.SAFE, Control(), many)  # noqa: E731
    with target(chan, infer, name=name), CanLink(vehicle_id=0, clock=MonotonicClock(), options=virtual(chan)) as link:
        assert link.open(hello_timeout_s=5).target_name == name
        link.send_frame(frame_id=1, sim_time_ns=0, t0_ns=0, width=2, height=2, encoding=ImageEncoding.RGB8,
                        camera=CAM, ego_speed_mps=0.0, data=bytes(12))
        r = link.recv(timeout_s=5)
        while r is not None and not isinstance(r.msg, Estimate):
            r = link.recv(timeout_s=5)
        assert r is not None and r.msg.objects == many


def test_vehicles_share_a_bus_without_hearing_each_other():
    chan = channel()
    idle = lambda frame: Inference(DrivingState.SAFE, Control())  # noqa: E731
    with target(chan, idle, name="one", vehicle_id=1), target(chan, idle, name="two", vehicle_id=2):
        with CanLink(vehicle_id=2, clock=MonotonicClock(), options=virtual(chan)) as two, \
                CanLink(vehicle_id=1, clock=MonotonicClock(), options=virtual(chan)) as one:
            assert two.open(hello_timeout_s=5).target_name == "two"
            assert one.open(hello_timeout_s=5).target_name == "one"
            assert one.sync_exchange(timeout_s=2) is not None and two.sync_exchange(timeout_s=2) is not None


def test_a_newer_camera_frame_replaces_the_one_waiting():
    chan = channel()  # no target: the first frame waits for flow control that never comes
    link = CanLink(vehicle_id=0, clock=MonotonicClock(), options=virtual(chan))
    with pytest.raises(TargetError, match="did not say hello"):
        link.open(hello_timeout_s=0.05)
    try:
        for i in range(3):
            link.send_frame(frame_id=i, sim_time_ns=0, t0_ns=0, width=64, height=64, encoding=ImageEncoding.RGB8,
                            camera=CAM, ego_speed_mps=0.0, data=bytes(64 * 64 * 3))
        assert link.frames_superseded >= 1
        assert link.stats.frames_sent == 3
    finally:
        link.close()


# ---------------------------------------------------------------- options


def test_udp_multicast_is_refused_everywhere():
    udp = CanOptions(interface="udp_multicast", channel="x")
    for make in (lambda: CanLink(vehicle_id=0, clock=MonotonicClock(), options=udp),
                 lambda: open_link("can", vehicle_id=0, clock=MonotonicClock(), options=udp),
                 lambda: serve_endpoint(Endpoint(lambda f: None, target_name="t"), options=udp)):
        with pytest.raises(ConfigError, match="udp_multicast.*off this machine"):
            make()


def test_bad_options_name_the_value():
    clock = MonotonicClock()
    with pytest.raises(ConfigError, match="unknown CAN interface 'nope'; valid: .*virtual"):
        CanLink(vehicle_id=0, clock=clock, options=CanOptions(interface="nope"))
    with pytest.raises(ConfigError, match="vehicle_id=70000"):
        CanLink(vehicle_id=70000, clock=clock, options=CanOptions(interface="virtual"))
    with pytest.raises(ConfigError, match="fd=False"):
        CanLink(vehicle_id=0, clock=clock, options=CanOptions(interface="virtual", fd=False))
    with pytest.raises(ConfigError, match="camera_over='udp'"):
        CanLink(vehicle_id=0, clock=clock, options=CanOptions(interface="virtual", camera_over="udp"))


VCAN0 = Path("/sys/class/net/vcan0")


@pytest.mark.skipif(not VCAN0.exists(), reason="no vcan0 here (sudo modprobe vcan && sudo ip link add dev vcan0 "
                                               "type vcan && sudo ip link set vcan0 mtu 72 up)")
def test_socketcan_vcan0_round_trip():
    ep = Endpoint(lambda frame: Inference(DrivingState.SAFE, Control(throttle=0.5)), target_name="vcan")
    vcan0 = CanOptions(interface="socketcan", channel="vcan0")
    thread = threading.Thread(target=serve_endpoint, args=(ep,), kwargs={"options": vcan0, "vehicle_id": 4242},
                              daemon=True)
    thread.start()
    try:
        with CanLink(vehicle_id=4242, clock=MonotonicClock(), options=vcan0) as link:
            assert link.open(hello_timeout_s=5).target_name == "vcan"
            link.send_frame(frame_id=1, sim_time_ns=0, t0_ns=0, width=64, height=64, encoding=ImageEncoding.RGB8,
                            camera=CAM, ego_speed_mps=0.0, data=bytes(64 * 64 * 3))
            r = link.recv(timeout_s=5)
            while r is not None and not isinstance(r.msg, Estimate):
                r = link.recv(timeout_s=5)
            assert r is not None and r.msg.control.throttle == 0.5
    finally:
        thread.join(timeout=3)
        if thread.is_alive():
            ep.stop()
            thread.join(timeout=3)


# ---------------------------------------------------------------- capacity


def test_frame_times_match_a_hand_count():
    # 64-byte CAN FD frame, 29-bit id, worst-case stuffing, 500k/2M:
    # nominal: 36 arbitration bits + 8 stuff + 13 tail = 57 bits = 114 µs;
    # data: 517 (ESI, DLC, 512) + 130 stuff + 32 (stuff count, CRC-21, 7 fixed) = 679 bits = 339.5 µs.
    assert fd_frame_time_s(64, bitrate=500_000, data_bitrate=2_000_000) == pytest.approx(453.5e-6)
    assert fd_frame_time_s(3, bitrate=500_000, data_bitrate=2_000_000) == pytest.approx(146e-6)
    assert classic_frame_time_s(8, bitrate=500_000) == pytest.approx(320e-6)  # the textbook 160 bits
    assert fd_frame_time_s(64, bitrate=500_000, data_bitrate=2_000_000, stuffing="typical") < 453.5e-6


def test_capacity_of_a_hand_computed_case():
    # 3990-byte JPEG + 104 bytes of header and metadata = 4094 bytes: an ISO-TP first frame
    # (62 bytes) and 64 consecutive frames of 63, all 64-byte frames, plus a 3-byte flow control.
    assert isotp_frame_lengths(4094, fd=True) == [64] * 65 + [3]
    r = bus_capacity(bitrate=500_000, data_bitrate=2_000_000, fd=True, frame_bytes=3990, fps=10,
                     sync_hz=0, heartbeat_hz=0)
    camera = 65 * 453.5e-6 + 146e-6
    estimate = 211e-6 + 373.5e-6  # HIL_ESTIMATE (16 B) + HIL_TARGET_TIMESTAMPS (48 B)
    assert r.can_frames_per_camera_frame == 66
    assert r.camera_frame_time_s == pytest.approx(camera)
    assert r.estimate_time_s == pytest.approx(estimate)
    assert r.max_fps == pytest.approx(1 / (camera + estimate))  # 33.1 fps
    assert r.load == pytest.approx(10 * (camera + estimate))
    r.check()


def test_check_says_what_to_change_when_fps_is_too_high():
    r = bus_capacity(bitrate=500_000, data_bitrate=2_000_000, fd=True, frame_bytes=12_000, fps=20)
    assert 10 < r.max_fps < 12 and r.load > 1
    with pytest.raises(ConfigError) as info:
        r.check()
    text = str(info.value)
    assert text.startswith("camera.fps=20 needs 1.9 Mbit/s but the bus carries 1.1 Mbit/s at bitrate 500k/2M")
    assert "lower fps to \u2264 11.2" in text and "jpeg_quality" in text and "zenoh (mixed target)" in text
    assert bus_capacity(bitrate=500_000, data_bitrate=0, fd=False, frame_bytes=12_000, fps=1).max_fps < 2
    assert bus_capacity(bitrate=500_000, data_bitrate=2_000_000, fd=True, frame_bytes=12_000, fps=20,
                        camera_over="none").load < 0.05


def test_a_late_reader_keeps_each_frames_interface_arrival():
    """A CAN message's receipt stamp is its (last) frame's interface time, not when a
    held-up reader got to it: an estimate sent while the harness's reader thread waits
    50 ms for the interpreter lock is stamped at its sending (virtual bus: the
    interface time is the send), not 50 ms later."""
    import sys

    from hil.adapters.can.link import CanLink
    from hil.adapters.wire import protocol
    from hil.adapters.wire.messages import Hello, SyncResponse

    channel = f"late-reader-{uuid.uuid4().hex}"
    device = can.Bus(interface="virtual", channel=channel, fd=True, ignore_config=True)
    clock = MonotonicClock()
    link = CanLink(vehicle_id=0, clock=clock, options=virtual(channel))
    try:
        from hil.adapters.can.dbc import HilCan, Role

        codec = HilCan(role=Role.TARGET, vehicle_id=0)

        def say(msg: object) -> None:
            for f in codec.encode(msg) or []:
                device.send(can.Message(arbitration_id=f.arbitration_id, data=f.data, is_extended_id=True,
                                        is_fd=True, bitrate_switch=True))

        opener = threading.Thread(target=lambda: link.open(hello_timeout_s=5))
        opener.start()
        say(Hello("dev", protocol.VERSION, ClockId.MONOTONIC, 1))
        opener.join(5)
        link.sync_samples()
        old = sys.getswitchinterval()
        sys.setswitchinterval(1.0)  # the reader waits for the interpreter lock while this thread spins
        try:
            before = clock.now_ns()
            say(SyncResponse(0, 7, 1, 2, 3))
            after = clock.now_ns()
            end = time.monotonic_ns() + 50_000_000
            while time.monotonic_ns() < end:
                pass
        finally:
            sys.setswitchinterval(old)
        r = link._sync_rx.get(timeout=5)  # noqa: SLF001 - the SYNC_RESPONSE with its receipt stamp
        assert r.msg.seq == 7
        assert before - 200_000 <= r.t_rx_ns <= after + 2_000_000, (r.t_rx_ns - before) / 1e6
        assert link.can_stats.interface_stamps >= 1  # type: ignore[attr-defined]
    finally:
        link.close()
        device.shutdown()
