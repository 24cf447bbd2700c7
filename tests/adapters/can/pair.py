"""CAN pair for the conformance suite: the echo target runs in a thread of the test
process on a python-can ``virtual`` bus (in-process only) with a channel name unique
to the test, and a ``CanLink`` on the same channel.

``--exit-after-frames N`` would make ``Echo`` call ``os._exit`` and take the test
process with it; here the target instead drops off the bus abruptly on the frame after
the N-th (its bus is shut down: no BYE, no more heartbeats), like a crashed device.
"""

from __future__ import annotations

import argparse
import contextlib
import threading
import uuid
from collections.abc import Iterator
from pathlib import Path

from hil.adapters.can.options import CanOptions
from hil.adapters.link import Link
from hil.common.errors import TransportError
from hil.timing.clock import MonotonicClock

try:
    import can
    import cantools  # noqa: F401
    import isotp  # noqa: F401
except ImportError:
    SKIP_REASON: str | None = ("python-can, cantools and can-isotp are needed "
                               "(pip install 'python-can>=4.6' cantools 'can-isotp>=2.0')")
else:
    SKIP_REASON = None


def parse_echo_args(args: list[str]) -> argparse.Namespace:
    """The options of ``python -m hil.targets.echo`` that shape the target (transport
    options are the pair's business)."""
    p = argparse.ArgumentParser(prog="echo (CAN pair)")
    p.add_argument("--infer-ms", type=float, default=0.0)
    p.add_argument("--throttle", type=float, default=0.0)
    p.add_argument("--brake", type=float, default=0.0)
    p.add_argument("--name", default="echo")
    p.add_argument("--exit-after-frames", type=int, default=None)
    return p.parse_args(args)


@contextlib.contextmanager
def can_target(channel: str, echo_args: list[str], *, vehicle_id: int = 0) -> Iterator[threading.Thread]:
    """The echo target serving ``vehicle_id`` on virtual ``channel`` in a thread; on exit
    it is stopped (if the harness did not say BYE) and joined, and its bus shut down.
    An exception in the target thread is raised here."""
    from hil.adapters.can.target import serve_endpoint
    from hil.adapters.sdk import Endpoint
    from hil.adapters.wire.messages import Frame, Inference
    from hil.targets.echo import Echo

    a = parse_echo_args(echo_args)
    echo = Echo(infer_ms=a.infer_ms, throttle=a.throttle, brake=a.brake)
    bus = can.Bus(interface="virtual", channel=channel, fd=True, ignore_config=True)
    errors: list[BaseException] = []
    vanished = threading.Event()

    def infer(frame: Frame) -> Inference:
        if a.exit_after_frames is not None and echo.frames >= a.exit_after_frames:
            vanished.set()
            bus.shutdown()  # the device drops off the bus: no BYE, no more heartbeats
            ep.wait_stopped(5.0)
            return echo.result
        return echo.infer(frame)

    ep = Endpoint(infer, target_name=a.name)

    def run() -> None:
        try:
            serve_endpoint(ep, options=CanOptions(interface="virtual", channel=channel), vehicle_id=vehicle_id, bus=bus)
        except BaseException as err:  # reported by the test thread below
            if not (isinstance(err, TransportError) and vanished.is_set()):  # leaving was the point
                errors.append(err)

    thread = threading.Thread(target=run, name=f"can-echo-{channel}", daemon=True)
    thread.start()
    try:
        yield thread
    finally:
        thread.join(timeout=3.0)
        if thread.is_alive():
            ep.stop()
            thread.join(timeout=3.0)
        bus.shutdown()
        assert not thread.is_alive(), "the CAN echo target did not stop"
        if errors:
            raise errors[0]


@contextlib.contextmanager
def can_pair(tmp_path: Path, echo_args: list[str]) -> Iterator[Link]:
    from hil.adapters.link import open_link

    del tmp_path  # nothing to log: the target runs in this process
    channel = f"hil-test-{uuid.uuid4().hex}"
    with can_target(channel, echo_args):
        link = open_link("can", options=CanOptions(interface="virtual", channel=channel), vehicle_id=0,
                         clock=MonotonicClock())
        try:
            link.open(hello_timeout_s=10)
            yield link
        finally:
            link.close()


PAIR_FACTORY = can_pair
