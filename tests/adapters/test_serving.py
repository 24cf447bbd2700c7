"""The target side's frame, written once (``hil.adapters.sdk.serving``): SIGTERM ends
a target with BYE on every transport, and a harness that left first gets none."""

from __future__ import annotations

import os
import signal
import threading
import time
import uuid
from pathlib import Path

import pytest

from hil.adapters.sdk import Endpoint, serving, stop_on_sigterm
from hil.adapters.tcp.link import TcpLink
from hil.adapters.tcp.options import TcpOptions
from hil.adapters.wire import protocol
from hil.adapters.wire.messages import Bye, Inference
from hil.common.errors import TransportError
from hil.timing.clock import MonotonicClock
from tests.adapters.tcp.pair import tcp_echo
from tests.adapters.zenoh.pair import free_port


def _wait_gone(link, timeout_s: float) -> str:
    deadline = time.monotonic() + timeout_s
    while link.alive and time.monotonic() < deadline:
        time.sleep(0.01)
    return link.peer_gone_reason or ""


def test_sigterm_makes_a_tcp_target_say_bye_and_exit_cleanly(tmp_path: Path) -> None:
    address = f"127.0.0.1:{free_port()}"
    with tcp_echo(tmp_path / "t.log", listen=address) as proc:
        link = TcpLink(vehicle_id=0, clock=MonotonicClock(), options=TcpOptions(connect=address))
        try:
            link.open(hello_timeout_s=20)
            proc.send_signal(signal.SIGTERM)  # the target is blocked in its read: no frame will wake it
            reason = _wait_gone(link, 5.0)
            assert reason == "target said bye (target stopping)", reason
            assert proc.wait(timeout=10) == 0
        finally:
            link.close()


def _endpoint() -> Endpoint:
    return Endpoint(lambda frame: Inference(), target_name="t")


def test_bye_unless_the_harness_left_first() -> None:
    sent: list[bytes] = []
    ep = _endpoint()
    with serving(ep, vehicle_id=7):
        ep.start(sent.append)
    msgs = [protocol.decode(b) for b in sent]
    assert msgs[-1] == Bye(7, "target stopping") and ep.stopped

    sent.clear()
    ep, gone = _endpoint(), threading.Event()
    with serving(ep, harness_gone=gone):
        ep.start(sent.append)
        gone.set()  # end of stream: nobody to say BYE to
    assert not any(protocol.decode(b).__class__ is Bye for b in sent)

    sent.clear()
    ep = _endpoint()
    with serving(ep):
        ep.start(sent.append)
        ep.on_message(Bye(0, "harness closing"), 0)
    assert not any(protocol.decode(b).__class__ is Bye for b in sent) and ep.harness_said_bye


def test_a_bye_that_cannot_go_out_is_let_go() -> None:
    def broken(_: bytes) -> None:
        raise TransportError("gone")

    ep = _endpoint()
    with serving(ep, linger_s=5.0, harness_gone=threading.Event()):
        ep._send_raw = broken  # the link broke after HELLO
    assert ep.stopped  # and no linger: nothing was sent


def test_linger_waits_for_the_harness_to_leave() -> None:
    ep, gone = _endpoint(), threading.Event()
    threading.Timer(0.2, gone.set).start()
    t = time.monotonic()
    with serving(ep, harness_gone=gone, linger_s=5.0):
        ep.start(lambda b: None)
    assert 0.15 < time.monotonic() - t < 3.0


@pytest.mark.skipif(threading.current_thread() is not threading.main_thread(), reason="signals need the main thread")
def test_sigterm_handler_is_scoped_to_the_block() -> None:
    before = signal.getsignal(signal.SIGTERM)
    hit = threading.Event()
    with stop_on_sigterm(hit.set):
        os.kill(os.getpid(), signal.SIGTERM)
        deadline = time.monotonic() + 2
        while not hit.is_set() and time.monotonic() < deadline:
            time.sleep(0.01)  # the handler runs on the main thread, between bytecodes
    assert hit.is_set() and signal.getsignal(signal.SIGTERM) is before


@pytest.mark.skipif(threading.current_thread() is not threading.main_thread(), reason="signals need the main thread")
def test_sigterm_makes_a_can_target_say_bye() -> None:
    pytest.importorskip("can")
    pytest.importorskip("isotp")
    import can

    from hil.adapters.can.link import CanLink
    from hil.adapters.can.options import CanOptions
    from hil.adapters.can.target import serve_endpoint

    channel = f"hil-serving-{uuid.uuid4().hex}"
    bus = can.Bus(interface="virtual", channel=channel, fd=True, ignore_config=True)
    virtual = CanOptions(interface="virtual", channel=channel)
    link = CanLink(vehicle_id=0, clock=MonotonicClock(), options=virtual)
    seen: list[str] = []

    def harness() -> None:
        try:
            link.open(hello_timeout_s=10)
            os.kill(os.getpid(), signal.SIGTERM)  # to the serving (main) thread
            seen.append(_wait_gone(link, 5.0))
        finally:
            link.close()

    t = threading.Thread(target=harness, daemon=True)
    t.start()
    try:
        serve_endpoint(_endpoint(), options=virtual, bus=bus)  # returns on SIGTERM
    finally:
        t.join(timeout=10)
        bus.shutdown()
    assert seen == ["target said bye (target stopping)"]
