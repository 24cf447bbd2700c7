"""The mixed transport (adapters/mixed/link.py): frames over Zenoh, everything else over CAN.

The device runs in a thread of the test process (python-can's ``virtual`` bus works
within one process only) with its own Zenoh session listening on a free port of
127.0.0.1; the harness's ``MixedLink`` connects there and sits on the same virtual
channel. The conformance suite runs against this pair too."""

from __future__ import annotations

import contextlib
import json
import queue
import threading
import time
import uuid
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

pytest.importorskip("zenoh", reason="eclipse-zenoh is not installed (pip install eclipse-zenoh==1.10.2)")
pytest.importorskip("can", reason="python-can is not installed (pip install 'python-can>=4.6')")
pytest.importorskip("cantools", reason="cantools is not installed (pip install cantools)")
pytest.importorskip("isotp", reason="can-isotp is not installed (pip install 'can-isotp>=2.0')")

import can  # noqa: E402
import zenoh  # noqa: E402

from hil.adapters.can.options import CanOptions  # noqa: E402
from hil.adapters.link import Link, open_link  # noqa: E402
from hil.adapters.mixed.link import MixedLink  # noqa: E402
from hil.adapters.mixed.options import MixedOptions  # noqa: E402
from hil.adapters.mixed.target import serve_endpoint  # noqa: E402
from hil.adapters.sdk import TRANSPORTS, Endpoint, add_transport_args, transport_options  # noqa: E402
from hil.adapters.wire.messages import CameraInfo, Estimate, Frame, ImageEncoding, Inference  # noqa: E402
from hil.adapters.zenoh.options import ZenohOptions  # noqa: E402
from hil.adapters.zenoh.session import Keys, make_config  # noqa: E402
from hil.common.errors import ConfigError, TargetError, TransportError  # noqa: E402
from hil.timing.clock import MonotonicClock  # noqa: E402
from tests.adapters import test_conformance as conformance  # noqa: E402
from tests.adapters.can.pair import can_target, parse_echo_args  # noqa: E402
from tests.adapters.zenoh.pair import free_port  # noqa: E402

ROOT = Path(__file__).resolve().parents[3]
CAM = CameraInfo(277.0, 277.0, 160.0, 120.0, 1.3)

test_hello = conformance.test_hello
test_frame_round_trip_is_stamped = conformance.test_frame_round_trip_is_stamped
test_inference_time_is_measured_on_the_target = conformance.test_inference_time_is_measured_on_the_target
test_clock_sync_exchange = conformance.test_clock_sync_exchange
test_sequence_of_frames_all_answered = conformance.test_sequence_of_frames_all_answered
test_corrupt_message_is_counted_and_link_goes_on = conformance.test_corrupt_message_is_counted_and_link_goes_on
test_vanished_target_is_noticed_within_a_second = conformance.test_vanished_target_is_noticed_within_a_second
test_close_is_idempotent = conformance.test_close_is_idempotent


class Unpluggable:
    """A bus whose cable can be pulled: afterwards it sends nothing and hears nothing,
    without an error (a device that just went silent on CAN)."""

    def __init__(self, bus: can.BusABC) -> None:
        self.bus = bus
        self.unplugged = threading.Event()

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        if not self.unplugged.is_set():
            self.bus.send(msg, timeout=timeout)

    def recv(self, timeout: float | None = None) -> can.Message | None:
        msg = self.bus.recv(timeout=timeout)
        return None if self.unplugged.is_set() else msg

    def shutdown(self) -> None:
        self.bus.shutdown()


@contextlib.contextmanager
def mixed_target(channel: str, port: int, echo_args: list[str] = (), *, vehicle_id: int = 0,
                 unpluggable: bool = False) -> Iterator[tuple[Endpoint, Unpluggable | can.BusABC]]:
    """The echo target as a mixed device in a thread: frames from Zenoh (listening on
    127.0.0.1:``port``), everything else on virtual ``channel``. ``--exit-after-frames
    N``: the device drops off both networks on the frame after the N-th."""
    from hil.targets.echo import Echo

    a = parse_echo_args(list(echo_args))
    echo = Echo(infer_ms=a.infer_ms, throttle=a.throttle, brake=a.brake)
    raw = can.Bus(interface="virtual", channel=channel, fd=True, ignore_config=True)
    bus = Unpluggable(raw) if unpluggable else raw
    errors: list[BaseException] = []
    vanished = threading.Event()

    def infer(frame: Frame) -> Inference:
        if a.exit_after_frames is not None and echo.frames >= a.exit_after_frames:
            vanished.set()
            raw.shutdown()  # off the bus: no BYE, no heartbeats; serving ends, and with it zenoh
            ep.wait_stopped(5.0)
            return echo.result
        return echo.infer(frame)

    ep = Endpoint(infer, target_name=a.name)

    def run() -> None:
        try:
            serve_endpoint(ep, options=options(channel, listen=[f"tcp/127.0.0.1:{port}"]), vehicle_id=vehicle_id,
                           bus=bus)
        except BaseException as err:  # reported by the test thread below
            if not (isinstance(err, TransportError) and vanished.is_set()):
                errors.append(err)

    thread = threading.Thread(target=run, name=f"mixed-echo-{channel}", daemon=True)
    thread.start()
    try:
        yield ep, bus
    finally:
        thread.join(timeout=3.0)
        if thread.is_alive():
            ep.stop()
            thread.join(timeout=3.0)
        raw.shutdown()
        assert not thread.is_alive(), "the mixed echo target did not stop"
        if errors:
            raise errors[0]


def options(channel: str, **zenoh: Any) -> MixedOptions:
    """A mixed device's options: virtual CAN ``channel``, the Zenoh half's ``zenoh``."""
    return MixedOptions(zenoh=ZenohOptions(**zenoh), can=CanOptions(interface="virtual", channel=channel))


def mixed_link(channel: str, port: int, *, vehicle_id: int = 0) -> MixedLink:
    link = open_link("mixed", vehicle_id=vehicle_id, clock=MonotonicClock(),
                     options=options(channel, connect=[f"tcp/127.0.0.1:{port}"]))
    assert isinstance(link, MixedLink)
    return link


@contextlib.contextmanager
def mixed_pair(echo_args: list[str] = (), **target_options: object) -> Iterator[tuple[MixedLink, Endpoint]]:
    channel, port = f"hil-mixed-{uuid.uuid4().hex}", free_port()
    with mixed_target(channel, port, list(echo_args), **target_options) as (ep, _):
        link = mixed_link(channel, port)
        try:
            link.open(hello_timeout_s=10)
            yield link, ep
        finally:
            link.close()


@pytest.fixture
def pair():
    @contextlib.contextmanager
    def factory(echo_args=()) -> Iterator[Link]:
        with mixed_pair(echo_args) as (link, _):
            yield link
    return factory


def next_estimate(link: Link, timeout_s: float = 5.0) -> Estimate:
    deadline = time.monotonic() + timeout_s
    while (left := deadline - time.monotonic()) > 0:
        r = link.recv(timeout_s=left)
        if r is not None and isinstance(r.msg, Estimate):
            return r.msg
    raise AssertionError("no estimate in time")


def send(link: Link, frame_id: int, *, size: int = 320 * 240 * 3) -> int:
    return link.send_frame(frame_id=frame_id, sim_time_ns=0, t0_ns=link.clock.now_ns(), width=320, height=240,
                           encoding=ImageEncoding.RGB8 if size == 320 * 240 * 3 else ImageEncoding.JPEG,
                           camera=CAM, ego_speed_mps=0.0, data=bytes(size))


def wait_gone(link: Link, within_s: float) -> float:
    start = time.monotonic()
    while link.alive and time.monotonic() - start < within_s:
        link.recv(timeout_s=0.02)
    return time.monotonic() - start


# ---------------------------------------------------------------- the two paths


def test_frames_go_over_zenoh_and_estimates_come_back_over_can():
    with mixed_pair(["--throttle", "0.25"]) as (link, ep):
        for i in range(5):
            t_tx = send(link, i)  # 230 KB raw: far beyond what the CAN half could take
            est = next_estimate(link)
            assert est.frame_id == i and abs(est.control.throttle - 0.25) < 1e-4
            assert est.t_rx_target_ns <= est.t_reply_target_ns and t_tx > 0
        assert link.mixed_stats.frames_zenoh == 5 and link.stats.frames_sent == 5
        can_stats = link.can_stats
        assert can_stats is not None
        assert can_stats.isotp_sent == 0  # no frame (or anything else) went over ISO-TP
        assert can_stats.frames_received >= 5 * 2  # HIL_ESTIMATE + HIL_TARGET_TIMESTAMPS each
        assert ep.stats.frames_received == 5 and ep.stats.estimates_sent == 5


def test_clock_sync_runs_over_can():
    with mixed_pair() as (link, ep):
        before = link.can_stats.frames_sent
        samples = [link.sync_exchange(timeout_s=1.0) for _ in range(5)]
        assert all(s is not None for s in samples)
        assert link.mixed_stats.frames_zenoh == 0 and ep.stats.sync_answered == 5
        assert link.can_stats.frames_sent >= before + 5


def test_device_silent_on_can_is_noticed_within_a_second():
    channel, port = f"hil-mixed-{uuid.uuid4().hex}", free_port()
    with mixed_target(channel, port, unpluggable=True) as (ep, bus):
        link = mixed_link(channel, port)
        try:
            link.open(hello_timeout_s=10)
            bus.unplugged.set()  # its zenoh side stays up: only CAN heartbeats can tell
            took = wait_gone(link, 2.0)
            assert not link.alive and took < 1.0, (took, link.peer_gone_reason)
            assert "no CAN frame" in (link.peer_gone_reason or "")
        finally:
            link.close()
            ep.stop()


def test_device_losing_its_zenoh_side_is_noticed():
    channel, port = f"hil-mixed-{uuid.uuid4().hex}", free_port()
    keys = Keys.of("hil", 0)
    with can_target(channel, []):  # the device's CAN half: the plain CAN echo target
        session = zenoh.open(make_config(ZenohOptions(listen=[f"tcp/127.0.0.1:{port}"])))
        try:
            entities = [session.declare_subscriber(keys.h2t, lambda s: None),
                        session.liveliness().declare_token(keys.alive)]
            link = mixed_link(channel, port)
            try:
                link.open(hello_timeout_s=10)
                entities.clear()
                session.close()  # the frame path is gone; CAN still answers
                took = wait_gone(link, 2.0)
                assert not link.alive and took < 1.0
                assert "zenoh liveliness lost" in (link.peer_gone_reason or "")
            finally:
                link.close()
        finally:
            if not session.is_closed():
                session.close()


def test_open_fails_clearly_without_the_zenoh_side():
    channel, port = f"hil-mixed-{uuid.uuid4().hex}", free_port()  # nobody listens on the port
    with can_target(channel, []):
        link = mixed_link(channel, port)
        try:
            with pytest.raises(TargetError, match="zenoh token 'hil/v0/alive' did not appear"):
                link.open(hello_timeout_s=1.0)
        finally:
            link.close()


def test_two_vehicles_share_the_bus_and_keep_apart():
    channel, port0, port1 = f"hil-mixed-{uuid.uuid4().hex}", free_port(), free_port()
    with mixed_target(channel, port0, ["--throttle", "0.1"], vehicle_id=0), \
            mixed_target(channel, port1, ["--throttle", "0.9"], vehicle_id=1):
        links = [mixed_link(channel, port0, vehicle_id=0), mixed_link(channel, port1, vehicle_id=1)]
        try:
            for link in links:
                link.open(hello_timeout_s=10)
            for link in links:
                send(link, 3, size=12_000)
            got = [next_estimate(link) for link in links]
            assert [round(e.control.throttle, 3) for e in got] == [0.1, 0.9]
            assert [e.vehicle_id for e in got] == [0, 1]
        finally:
            for link in links:
                link.close()


# ---------------------------------------------------------------- options and registration


def test_options_are_checked_before_anything_opens():
    with pytest.raises(ConfigError, match="udp_multicast"):
        MixedLink(vehicle_id=0, clock=MonotonicClock(), options=MixedOptions(
            zenoh=ZenohOptions(connect=["tcp/127.0.0.1:7447"]), can=CanOptions(interface="udp_multicast", channel="x")))
    with pytest.raises(ConfigError, match="connect or listen"):
        MixedLink(vehicle_id=0, clock=MonotonicClock(), options=options("x", connect=()))
    with pytest.raises(ConfigError, match="vehicle_id=70000"):
        MixedLink(vehicle_id=70_000, clock=MonotonicClock(), options=options("x", connect=["tcp/127.0.0.1:7447"]))
    with pytest.raises(ConfigError, match="--listen"):
        serve_endpoint(Endpoint(lambda f: None, target_name="x"), options=options("x"))


def test_target_programs_take_mixed_with_both_option_sets():
    import argparse

    assert "mixed" in TRANSPORTS
    p = argparse.ArgumentParser()
    add_transport_args(p)
    a = p.parse_args(["--transport", "mixed", "--listen", "tcp/127.0.0.1:7447", "--interface", "virtual",
                      "--channel", "c", "--vehicle", "3"])
    opts = transport_options(a)
    o = opts["options"]
    assert isinstance(o, MixedOptions) and opts["vehicle_id"] == 3
    assert o.zenoh.listen == ("tcp/127.0.0.1:7447",) and o.zenoh.key_prefix == "hil"
    assert o.can.interface == "virtual" and o.can.channel == "c"


def test_sdk_serve_dispatches_mixed():
    from hil.adapters.sdk import serve
    from hil.targets.echo import Echo

    channel, port = f"hil-mixed-{uuid.uuid4().hex}", free_port()
    bus = can.Bus(interface="virtual", channel=channel, fd=True, ignore_config=True)
    result: list[object] = []
    thread = threading.Thread(target=lambda: result.append(serve(
        Echo(throttle=0.5).infer, target_name="via-serve", transport="mixed",
        options=options(channel, listen=[f"tcp/127.0.0.1:{port}"]), bus=bus)), daemon=True)
    thread.start()
    try:
        with mixed_link(channel, port) as link:
            assert link.open(hello_timeout_s=10).target_name == "via-serve"
            send(link, 1)
            assert next_estimate(link).control.throttle == pytest.approx(0.5, abs=1e-4)
        thread.join(timeout=5)  # the BYE of close() ends serve()
        assert not thread.is_alive() and result[0].estimates_sent == 1
    finally:
        bus.shutdown()


def test_run_config_with_mixed_builds_a_mixed_link(tmp_path):
    from hil.harness.config.loading import load_config
    from hil.harness.config.model import Transport
    from hil.harness.run.target_launch import make_link

    cfg = load_config(ROOT / "hil_configs/can.yaml", overrides=[
        "target.transport=mixed", "target.can.interface=virtual", "target.can.channel=bus{vehicle_id}",
        'target.zenoh.connect=["tcp/127.0.0.1:{port}"]', "target.zenoh.base_port=17000",
        "target.zenoh.key_prefix=hil/run-m"])
    assert cfg.target.transport == Transport.MIXED
    link, proc = make_link(cfg, vehicle_id=2, vehicle="ego2", clock=MonotonicClock(), out_dir=tmp_path,
                           rx=queue.Queue())
    try:
        assert proc is None and isinstance(link, MixedLink) and link.transport_name == "mixed"
        assert link.can.channel == "bus2" and link.can.interface == "virtual" and link.can.camera_over == "none"
        assert link.zenoh.connect == ["tcp/127.0.0.1:17002"] and link.keys.h2t == "hil/run-m/v2/h2t"
    finally:
        link.close()


def test_mixed_link_takes_the_zenoh_half_s_authentication(monkeypatch):
    """The Zenoh half is the Zenoh link's own (ZenohHalf): user/password reaches the
    session config, as the config's target.zenoh.auth promises for mixed too."""
    from hil.harness.config.loading import parse_config
    from hil.harness.run.link_options import zenoh_options

    monkeypatch.setenv("HIL_ZENOH_PASSWORD", "s3cret")
    cfg = parse_config({"target": {"transport": "mixed", "command": [], "zenoh": {"auth": {"user": "hil"}}}})
    zenoh_half = zenoh_options(cfg, vehicle_id=0)
    assert zenoh_half.usrpwd == {"user": "hil", "password": "s3cret"}
    link = MixedLink(vehicle_id=0, clock=MonotonicClock(),
                     options=MixedOptions(zenoh=zenoh_half, can=CanOptions(interface="virtual", channel="x")))
    assert json.loads(link.zenoh.config.get_json("transport/auth/usrpwd/user")) == "hil"


def test_whole_run_against_a_mixed_device(tmp_path):
    from hil.harness.config.loading import load_config
    from hil.harness.run.driver import execute, prepare_out_dir
    from tests.conftest import GL_BACKEND, read_mcap

    channel, port = f"hil-mixed-run-{uuid.uuid4().hex}", free_port()
    cfg = load_config(ROOT / "hil_configs/can.yaml", overrides=[
        "duration_s=2", "progress=false", "target.transport=mixed", "target.can.interface=virtual",
        f"target.can.channel={channel}", f'target.zenoh.connect=["tcp/127.0.0.1:{port}"]'])
    with mixed_target(channel, port, ["--throttle", "0.1"]):
        result = execute(cfg, out_dir=prepare_out_dir(tmp_path / "r"), gl_backend=GL_BACKEND,
                         install_signal_handlers=False)
    v = result.summary["vehicles"]["ego0"]
    assert result.summary["ended_by"] == "duration" and v["frames_sent"] == 20
    assert v["estimates_applied"] + v["dropped"] + v["stale"] == 20 and v["estimates_applied"] >= 18
    assert v["clock"]["synced"]
    recs = sorted(d["frame_id"] for _, d in read_mcap(result.mcap_path)["/ego0/pipeline"])
    assert recs == list(range(20))
