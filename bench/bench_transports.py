"""Transport benchmark: a 320x240 frame's round trip through each transport, next to
the raw floors measured in the same run.

Run: ``.venv/bin/python bench/bench_transports.py`` (about a minute; ``--rounds`` and
``--block`` change the sample count). Prints markdown tables. Not part of the test
suite.

What is timed: from ``Link.send_frame`` to the ESTIMATE coming out of ``Link.recv``
in the calling thread, to ``hil.targets.echo``'s logic (answers at once), for a raw RGB8
image (230 400 bytes, a 230 504-byte FRAME message) and a JPEG (q85, ~12 KB):

* local (child process; frames through the shared-memory ring where negotiated, and
  with ``shm=False`` for comparison), zenoh and tcp (target process on 127.0.0.1; tcp also
  to the C reference target of targets/c, built here when ``cc`` is present), can
  (python-can ``virtual`` bus, target in a thread of this process: it has no bit
  timing, and in-process only; JPEG only), mixed (frames over zenoh, the rest over the
  virtual CAN bus; device in a thread of this process).

Raw floors, two processes each, the same message bytes out and an 80-byte answer
back (an ESTIMATE's size), timed the same way:

* a TCP loopback connection (``TCP_NODELAY``), the same loop as the socketpair;
* zenoh put/subscribe ping-pong (callback subscribers, explicit tcp/127.0.0.1, no
  scouting, Zenoh's shared memory at its default, as the transport uses it);
* a Unix socketpair (``sendall`` / ``recv_into`` the known length);
* shared memory + pipe: the bytes written into a memfd, the length through a pipe,
  the child copies them out and answers through another pipe;
* the hand-off floor: a 32-byte message over a socketpair where each side hands it
  to a second thread, as the Link (reader thread -> caller) and the SDK (reader ->
  inference worker) do; no protocol work at all.

Samples are taken in interleaved blocks (every path a block in turn) so that the
machine's drift hits all of them alike; still, on the 2-CPU development machine p50s
move by ±30 % between runs (the raw shared-memory floor from 10 to 45 µs, as the two
processes land on one CPU or two): compare within one run. Also: estimates per second a CanLink receives
over the virtual bus, next to the bus's raw frames per second.
"""

from __future__ import annotations

import argparse
import contextlib
import mmap
import os
import queue
import socket
import subprocess
import sys
import threading
import time
import uuid
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from hil.adapters.link import Link, open_link  # noqa: E402
from hil.adapters.tcp.options import TcpOptions  # noqa: E402
from hil.adapters.wire import protocol  # noqa: E402
from hil.adapters.wire.messages import CameraInfo, Control, DrivingState, Estimate, Frame, ImageEncoding  # noqa: E402
from hil.timing.clock import MonotonicClock  # noqa: E402

CAM = CameraInfo(277.0, 277.0, 160.0, 120.0, 1.3)
REPLY = bytes(80)
ZKEY_PING, ZKEY_PONG = "bench/raw/ping", "bench/raw/pong"
RoundTrip = Callable[[], int]  # one round trip, returns ns


# ---------------------------------------------------------------- children of the raw floors


def child_main(kind: str, args: list[str]) -> None:
    if kind == "shm":
        mem_fd, r_fd, w_fd = map(int, args)
        mm = mmap.mmap(mem_fd, os.fstat(mem_fd).st_size)
        while len(head := os.read(r_fd, 8)) == 8:
            n = int.from_bytes(head, "little")
            bytes(mm[:n])  # copy out, as a target keeps the frame
            os.write(w_fd, REPLY)
    elif kind == "sock":
        sock = socket.socket(fileno=int(args[0]))
        buf = bytearray(1 << 20)
        view = memoryview(buf)
        while (head := sock.recv(8)) and len(head) == 8:
            n, got = int.from_bytes(head, "little"), 0
            while got < n:
                k = sock.recv_into(view[got:n])
                if not k:
                    return
                got += k
            sock.sendall(REPLY)
    elif kind == "tcp":  # the socketpair floor's loop, on a TCP loopback connection
        tsock = socket.create_connection(("127.0.0.1", int(args[0])))
        tsock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        child_main("sock", [str(tsock.fileno())])
    elif kind == "handoff":
        sock = socket.socket(fileno=int(args[0]))
        cv, box = threading.Condition(), []

        def worker() -> None:
            while True:
                with cv:
                    cv.wait_for(lambda: box)
                    item = box.pop()
                if item is None:
                    return
                sock.sendall(REPLY)

        t = threading.Thread(target=worker)
        t.start()
        while data := sock.recv(1 << 16):
            with cv:
                box.append(data)
                cv.notify()
        with cv:
            box.append(None)
            cv.notify()
        t.join()
    elif kind == "zenoh":
        import zenoh

        from hil.adapters.zenoh.options import ZenohOptions
        from hil.adapters.zenoh.session import make_config
        session = zenoh.open(make_config(ZenohOptions(listen=[str(args[0])])))
        pub = session.declare_publisher(ZKEY_PONG, congestion_control=zenoh.CongestionControl.BLOCK)
        # Zenoh undeclares an entity when its Python object is dropped: keep it.
        entities = [session.declare_subscriber(ZKEY_PING, lambda s: (s.payload.to_bytes(), pub.put(REPLY)))]
        sys.stdin.read()  # until the parent closes our stdin
        entities.clear()
        session.close()


def spawn_child(kind: str, *args: int | str, pass_fds: tuple[int, ...] = (), stdin: int | None = None
                ) -> subprocess.Popen[bytes]:
    return subprocess.Popen([sys.executable, __file__, "--child", kind, *map(str, args)], pass_fds=pass_fds,
                            stdin=stdin, cwd=ROOT)


def end(proc: subprocess.Popen[bytes]) -> None:
    """End a child of ours by PID: it normally leaves on EOF."""
    try:
        proc.wait(timeout=5)
    except subprocess.TimeoutExpired:
        proc.terminate()
        try:
            proc.wait(timeout=5)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


# ---------------------------------------------------------------- floors (parent side)


@contextlib.contextmanager
def raw_shm(payload: bytes) -> Iterator[RoundTrip]:
    mem_fd = os.memfd_create("bench-raw", 0)
    os.ftruncate(mem_fd, len(payload))
    mm = mmap.mmap(mem_fd, len(payload))
    to_r, to_w = os.pipe()
    back_r, back_w = os.pipe()
    proc = spawn_child("shm", mem_fd, to_r, back_w, pass_fds=(mem_fd, to_r, back_w))
    for fd in (mem_fd, to_r, back_w):
        os.close(fd)
    head = len(payload).to_bytes(8, "little")

    def once() -> int:
        t = time.perf_counter_ns()
        mm[:len(payload)] = payload
        os.write(to_w, head)
        os.read(back_r, len(REPLY))
        return time.perf_counter_ns() - t
    try:
        yield once
    finally:
        os.close(to_w)
        end(proc)
        os.close(back_r)
        mm.close()


@contextlib.contextmanager
def raw_socketpair(payload: bytes) -> Iterator[RoundTrip]:
    ours, theirs = socket.socketpair()
    for s in (ours, theirs):
        s.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 4 << 20)
        s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4 << 20)
    proc = spawn_child("sock", theirs.fileno(), pass_fds=(theirs.fileno(),))
    theirs.close()
    msg = len(payload).to_bytes(8, "little") + payload

    def once() -> int:
        t = time.perf_counter_ns()
        ours.sendall(msg)
        got = 0
        while got < len(REPLY):
            got += len(ours.recv(len(REPLY) - got))
        return time.perf_counter_ns() - t
    try:
        yield once
    finally:
        ours.shutdown(socket.SHUT_RDWR)
        ours.close()
        end(proc)


@contextlib.contextmanager
def raw_tcp(payload: bytes) -> Iterator[RoundTrip]:
    """The socketpair floor over a TCP loopback connection (TCP_NODELAY both ends)."""
    with socket.create_server(("127.0.0.1", 0)) as server:
        proc = spawn_child("tcp", server.getsockname()[1])
        ours, _ = server.accept()
    ours.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    msg = len(payload).to_bytes(8, "little") + payload

    def once() -> int:
        t = time.perf_counter_ns()
        ours.sendall(msg)
        got = 0
        while got < len(REPLY):
            got += len(ours.recv(len(REPLY) - got))
        return time.perf_counter_ns() - t
    try:
        yield once
    finally:
        ours.shutdown(socket.SHUT_RDWR)
        ours.close()
        end(proc)


@contextlib.contextmanager
def raw_handoff() -> Iterator[RoundTrip]:
    ours, theirs = socket.socketpair()
    proc = spawn_child("handoff", theirs.fileno(), pass_fds=(theirs.fileno(),))
    theirs.close()
    got: queue.SimpleQueue[bytes] = queue.SimpleQueue()

    def reader() -> None:
        with contextlib.suppress(OSError):
            while data := ours.recv(1 << 16):
                got.put(data)
    thread = threading.Thread(target=reader, daemon=True)
    thread.start()
    notice = bytes(32)

    def once() -> int:
        t = time.perf_counter_ns()
        ours.sendall(notice)
        got.get(timeout=5)
        return time.perf_counter_ns() - t
    try:
        yield once
    finally:
        ours.shutdown(socket.SHUT_RDWR)
        end(proc)
        thread.join(timeout=2)
        ours.close()


@contextlib.contextmanager
def raw_zenoh(payload: bytes) -> Iterator[RoundTrip]:
    import zenoh

    from hil.adapters.zenoh.options import ZenohOptions
    from hil.adapters.zenoh.session import make_config
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    proc = spawn_child("zenoh", endpoint, stdin=subprocess.PIPE)
    session = zenoh.open(make_config(ZenohOptions(connect=[endpoint])))
    got: queue.SimpleQueue[bytes] = queue.SimpleQueue()
    entities = [session.declare_subscriber(ZKEY_PONG, lambda s: got.put(s.payload.to_bytes()))]
    pub = session.declare_publisher(ZKEY_PING, congestion_control=zenoh.CongestionControl.BLOCK)

    def once() -> int:
        t = time.perf_counter_ns()
        pub.put(payload)
        got.get(timeout=5)
        return time.perf_counter_ns() - t
    try:
        deadline = time.monotonic() + 20
        while True:  # until the child's subscriber is reached
            pub.put(b"hello")
            with contextlib.suppress(queue.Empty):
                got.get(timeout=0.1)
                break
            if time.monotonic() > deadline:
                raise RuntimeError("raw zenoh child did not answer")
        yield once
    finally:
        entities.clear()
        session.close()
        assert proc.stdin is not None
        proc.stdin.close()
        end(proc)


# ---------------------------------------------------------------- transports


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def link_round_trip(link: Link, payload: bytes, encoding: ImageEncoding) -> RoundTrip:
    frame_id = iter(range(1, 1 << 62))

    def once() -> int:
        t = time.perf_counter_ns()
        fid = next(frame_id)
        link.send_frame(frame_id=fid, sim_time_ns=0, t0_ns=link.clock.now_ns(), width=320, height=240,
                        encoding=encoding, camera=CAM, ego_speed_mps=0.0, data=payload)
        while True:
            r = link.recv(timeout_s=5.0)
            if r is None:
                raise RuntimeError(f"{link.transport_name}: no estimate for frame {fid} in 5 s")
            if isinstance(r.msg, Estimate) and r.msg.frame_id == fid:
                return time.perf_counter_ns() - t
    return once


class Handled:
    """Round trips to the instant the link's reader hands the estimate on
    (``Link.deliver_to``), which is where a run handles it (the control goes to the
    physics from that thread): no wake-up of another thread is counted."""

    def __init__(self, link: Link) -> None:
        self.link = link
        self._frame_id = iter(range(1, 1 << 62))
        self._got: dict[int, int] = {}
        self._done = threading.Event()
        link.deliver_to(self._handle)

    def _handle(self, r: Any) -> None:
        if isinstance(r.msg, Estimate):
            self._got[r.msg.frame_id] = time.perf_counter_ns()
            self._done.set()

    def round_trip(self, payload: bytes, encoding: ImageEncoding) -> RoundTrip:
        link = self.link

        def once() -> int:
            self._done.clear()
            t = time.perf_counter_ns()
            fid = next(self._frame_id)
            link.send_frame(frame_id=fid, sim_time_ns=0, t0_ns=link.clock.now_ns(), width=320, height=240,
                            encoding=encoding, camera=CAM, ego_speed_mps=0.0, data=payload)
            while fid not in self._got:
                if not self._done.wait(5.0):
                    raise RuntimeError(f"{link.transport_name}: no estimate for frame {fid} in 5 s")
                self._done.clear()
            return self._got.pop(fid) - t
        return once


@contextlib.contextmanager
def opened(link: Link) -> Iterator[Link]:
    try:
        link.open(hello_timeout_s=30)
        yield link
    finally:
        link.close()


@contextlib.contextmanager
def local_link(**options: Any) -> Iterator[Link]:
    from hil.adapters.local.options import LocalOptions

    with opened(open_link("local", command=[sys.executable, "-m", "hil.targets.echo"], vehicle_id=0,
                          clock=MonotonicClock(), options=LocalOptions(**options))) as link:
        yield link


@contextlib.contextmanager
def zenoh_link() -> Iterator[Link]:
    port = free_port()
    proc = subprocess.Popen([sys.executable, "-m", "hil.targets.echo", "--transport", "zenoh", "--listen",
                             f"tcp/127.0.0.1:{port}"], cwd=ROOT, stdin=subprocess.DEVNULL)
    try:
        from hil.adapters.zenoh.options import ZenohOptions

        with opened(open_link("zenoh", vehicle_id=0, clock=MonotonicClock(),
                              options=ZenohOptions(connect=[f"tcp/127.0.0.1:{port}"]))) as link:
            yield link
    finally:
        end(proc)


@contextlib.contextmanager
def tcp_link() -> Iterator[Link]:
    address = f"127.0.0.1:{free_port()}"
    proc = subprocess.Popen([sys.executable, "-m", "hil.targets.echo", "--transport", "tcp", "--listen", address],
                            cwd=ROOT, stdin=subprocess.DEVNULL)
    try:
        with opened(open_link("tcp", vehicle_id=0, clock=MonotonicClock(),
                              options=TcpOptions(connect=address))) as link:
            yield link
    finally:
        end(proc)


def c_target() -> Path | None:
    """The C reference target (targets/c), built into a temporary folder with the
    system compiler; None where there is no ``cc``/``make`` or the build fails."""
    import shutil
    import tempfile

    if shutil.which("cc") is None or shutil.which("make") is None:
        return None
    out = Path(tempfile.mkdtemp(prefix="bench-c-target-"))
    proc = subprocess.run(["make", "-s", "-C", str(ROOT / "targets" / "c"), f"BUILD={out}"], capture_output=True)
    return out / "hil_target" if proc.returncode == 0 else None


@contextlib.contextmanager
def tcp_c_link(exe: Path) -> Iterator[Link]:
    address = f"127.0.0.1:{free_port()}"
    proc = subprocess.Popen([str(exe), "--transport", "tcp", "--listen", address], stdin=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    try:
        with opened(open_link("tcp", vehicle_id=0, clock=MonotonicClock(),
                              options=TcpOptions(connect=address))) as link:
            yield link
    finally:
        end(proc)


@contextlib.contextmanager
def device_thread(serve: Callable[..., None], options: Any, channel: str) -> Iterator[object]:
    """``hil.targets.echo`` served by ``serve`` (CAN or mixed, with ``options``) on
    virtual bus ``channel``, in a thread."""
    import can

    from hil.adapters.sdk import Endpoint
    from hil.targets.echo import Echo

    bus = can.Bus(interface="virtual", channel=channel, fd=True, ignore_config=True)
    ep = Endpoint(Echo().infer, target_name="echo")
    thread = threading.Thread(target=serve, args=(ep,), kwargs={"options": options, "bus": bus}, daemon=True)
    thread.start()
    try:
        yield ep
    finally:
        thread.join(timeout=3)
        ep.stop()
        thread.join(timeout=3)
        bus.shutdown()


@contextlib.contextmanager
def can_link() -> Iterator[Link]:
    from hil.adapters.can.options import CanOptions
    from hil.adapters.can.target import serve_endpoint
    channel = f"bench-{uuid.uuid4().hex}"
    bus = CanOptions(interface="virtual", channel=channel)
    with device_thread(serve_endpoint, bus, channel), \
            opened(open_link("can", vehicle_id=0, clock=MonotonicClock(), options=bus)) as link:
        yield link


@contextlib.contextmanager
def mixed_link() -> Iterator[Link]:
    from hil.adapters.can.options import CanOptions
    from hil.adapters.mixed.options import MixedOptions
    from hil.adapters.mixed.target import serve_endpoint
    from hil.adapters.zenoh.options import ZenohOptions
    channel, port = f"bench-{uuid.uuid4().hex}", free_port()
    bus, endpoint = CanOptions(interface="virtual", channel=channel), f"tcp/127.0.0.1:{port}"
    with device_thread(serve_endpoint, MixedOptions(zenoh=ZenohOptions(listen=[endpoint]), can=bus), channel), \
            opened(open_link("mixed", vehicle_id=0, clock=MonotonicClock(),
                             options=MixedOptions(zenoh=ZenohOptions(connect=[endpoint]), can=bus))) as link:
        yield link


# ---------------------------------------------------------------- measuring


@dataclass
class Timed:
    name: str
    once: RoundTrip
    samples: list[int] = field(default_factory=list)

    def pct(self, q: float) -> float:
        return float(np.percentile(np.array(self.samples) / 1e3, q))


def measure(paths: list[Timed], *, warmup: int, rounds: int, block: int) -> None:
    for p in paths:
        for _ in range(warmup):
            p.once()
    for _ in range(rounds):
        for p in paths:
            p.samples += [p.once() for _ in range(block)]


def can_rates(n: int = 3000) -> tuple[float, float]:
    """(estimates/s a CanLink receives, raw virtual-bus CAN FD frames/s between two threads)."""
    import can

    from hil.adapters.can.options import CanOptions
    from hil.adapters.can.target import serve_endpoint
    channel = f"bench-{uuid.uuid4().hex}"
    bus = CanOptions(interface="virtual", channel=channel)
    with device_thread(serve_endpoint, bus, channel) as ep, \
            opened(open_link("can", vehicle_id=0, clock=MonotonicClock(), options=bus)) as link:
        est = [Estimate(0, i, DrivingState.SAFE, Control(0.0, 0.1, 0.0), (), 1, 2, 3, 4) for i in range(n)]
        sender = threading.Thread(target=lambda: [ep.send(e) for e in est])  # type: ignore[attr-defined]
        got = 0
        t = time.perf_counter()
        sender.start()
        while got < n and (r := link.recv(timeout_s=5.0)) is not None:
            got += isinstance(r.msg, Estimate)
        est_rate = got / (time.perf_counter() - t)
        sender.join()
    a = can.Bus(interface="virtual", channel=channel + "-raw", fd=True, ignore_config=True)
    b = can.Bus(interface="virtual", channel=channel + "-raw", fd=True, ignore_config=True)
    msg = can.Message(arbitration_id=0x10300000, data=bytes(64), is_extended_id=True, is_fd=True)
    m = 20_000
    sender = threading.Thread(target=lambda: [a.send(msg) for _ in range(m)])
    t = time.perf_counter()
    sender.start()
    received = sum(1 for _ in range(m) if b.recv(timeout=5.0) is not None)
    raw_rate = received / (time.perf_counter() - t)
    sender.join()
    a.shutdown()
    b.shutdown()
    return est_rate, raw_rate


def protocol_cpu_us(raw_img: bytes, n: int = 2000) -> float:
    """Median µs of the protocol work of one local round trip through the ring, in one
    thread with no I/O: build and encode the FRAME, write its slot, decode the notice,
    read and decode the slot, encode the ESTIMATE and stream-decode it."""
    from hil.adapters.local.shm import NOTICES, ShmReader, ShmRing
    from hil.adapters.wire.stream import StreamDecoder

    est = Estimate(0, 1, DrivingState.SAFE, Control(0.0, 0.1, 0.0), (), 1, 2, 3, 4)
    times = []
    with ShmRing() as ring:
        reader = ShmReader(os.dup(ring.fd))
        notices, answers = StreamDecoder(NOTICES), StreamDecoder()
        for i in range(n):
            t = time.perf_counter_ns()
            frame = Frame(0, i, 0, 0, 0, 320, 240, ImageEncoding.RGB8, CAM, 0.0, raw_img)
            (notice,) = notices.feed(ring.put(protocol.encode(frame)))
            reader.read(notice)  # type: ignore[arg-type]
            answers.feed(protocol.encode(est))
            times.append(time.perf_counter_ns() - t)
        reader.close()
    return float(np.median(times)) / 1e3


def jpeg_320x240() -> bytes:
    import cv2

    rng = np.random.default_rng(0)
    y, x = np.mgrid[0:240, 0:320]
    img = np.stack([x * 255 / 320, y * 255 / 240, (x + y) * 255 / 560], axis=-1) + rng.normal(0, 6, (240, 320, 3))
    ok, buf = cv2.imencode(".jpg", np.clip(img, 0, 255).astype(np.uint8), [cv2.IMWRITE_JPEG_QUALITY, 85])
    assert ok
    return buf.tobytes()


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--rounds", type=int, default=20, help="interleaved rounds (default 20)")
    p.add_argument("--block", type=int, default=40, help="round trips per path per round (default 40)")
    p.add_argument("--warmup", type=int, default=50, help="round trips per path before timing (default 50)")
    p.add_argument("--child", nargs="+", help=argparse.SUPPRESS)
    a = p.parse_args(argv)
    if a.child:
        child_main(a.child[0], a.child[1:])
        return 0
    raw_img = np.random.default_rng(1).integers(0, 256, 320 * 240 * 3, dtype=np.uint8).tobytes()
    jpeg = jpeg_320x240()
    msg = {enc: protocol.encode(Frame(0, 1, 0, 0, 0, 320, 240, enc, CAM, 0.0, data))
           for enc, data in ((ImageEncoding.RGB8, raw_img), (ImageEncoding.JPEG, jpeg))}
    cols = ((ImageEncoding.RGB8, raw_img, "raw RGB8"), (ImageEncoding.JPEG, jpeg, "JPEG"))
    started = time.perf_counter()
    rows: dict[str, dict[ImageEncoding, Timed]] = {}
    with contextlib.ExitStack() as stack:
        def add(name: str, enc: ImageEncoding, once: RoundTrip) -> None:
            rows.setdefault(name, {})[enc] = Timed(name, once)

        for enc, data, _ in cols:
            add("raw: zenoh put/subscribe", enc, stack.enter_context(raw_zenoh(msg[enc])))
            add("raw: Unix socketpair", enc, stack.enter_context(raw_socketpair(msg[enc])))
            add("raw: TCP loopback", enc, stack.enter_context(raw_tcp(msg[enc])))
            add("raw: shared memory + pipe", enc, stack.enter_context(raw_shm(msg[enc])))
        handoff = stack.enter_context(raw_handoff())
        add("raw: hand-off floor (32 B, 2 thread hand-offs)", ImageEncoding.RGB8, handoff)
        local = stack.enter_context(local_link())
        handled = Handled(stack.enter_context(local_link()))
        local_inline = stack.enter_context(local_link(shm=False))
        zlink = stack.enter_context(zenoh_link())
        tlink = stack.enter_context(tcp_link())
        c_exe = c_target()
        tclink = stack.enter_context(tcp_c_link(c_exe)) if c_exe is not None else None
        clink = stack.enter_context(can_link())
        mlink = stack.enter_context(mixed_link())
        for enc, data, _ in cols:
            add("local (default)", enc, link_round_trip(local, data, enc))
            add("local, handled on the reader's thread (a run's path)", enc, handled.round_trip(data, enc))
            add("local, inline (shm=False)", enc, link_round_trip(local_inline, data, enc))
            add("zenoh", enc, link_round_trip(zlink, data, enc))
            add("tcp (kernel receive stamps)", enc, link_round_trip(tlink, data, enc))
            if tclink is not None:
                add("tcp to the C reference target", enc, link_round_trip(tclink, data, enc))
            add("mixed (zenoh + virtual CAN, device in-process)", enc, link_round_trip(mlink, data, enc))
        add("can (virtual bus, device in-process)", ImageEncoding.JPEG,
            link_round_trip(clink, jpeg, ImageEncoding.JPEG))
        paths = [pth for r in rows.values() for pth in r.values()]
        slow = [pth for pth in paths if pth.name.startswith("can")]
        measure([pth for pth in paths if pth not in slow], warmup=a.warmup, rounds=a.rounds, block=a.block)
        measure(slow, warmup=10, rounds=a.rounds, block=max(a.block * 4 // 5, 20))
        local_stats = local.local_stats  # type: ignore[attr-defined]
    est_rate, raw_rate = can_rates()
    cpu_us = protocol_cpu_us(raw_img)

    n = {len(pth.samples) for pth in paths}
    print("## Round trip of one 320x240 frame to a target that answers at once (µs, p50 / p99)\n")
    print(f"{os.cpu_count()} CPUs; {min(n)}–{max(n)} round trips per cell after warm-up, interleaved. "
          f"Messages: raw {len(msg[ImageEncoding.RGB8])} B, JPEG {len(msg[ImageEncoding.JPEG])} B; "
          f"80-byte answer in the raw floors.\n")
    print("| path | " + " | ".join(f"{label} p50 | p99" for *_, label in cols) + " |")
    print("| --- |" + " ---: | ---: |" * len(cols))
    for name, r in rows.items():
        cells = [f"{r[enc].pct(50):.0f} | {r[enc].pct(99):.0f}" if enc in r else "– | –" for enc, *_ in cols]
        print(f"| {name} | " + " | ".join(cells) + " |")

    def ratio(num: str, den: str, enc: ImageEncoding) -> str:
        if num not in rows or enc not in rows[num] or enc not in rows[den]:
            return "–"
        return f"{rows[num][enc].pct(50) / rows[den][enc].pct(50):.2f}"

    checks = [
        ("zenoh / raw zenoh", "zenoh", "raw: zenoh put/subscribe", 1.25),
        ("tcp / raw TCP loopback", "tcp (kernel receive stamps)", "raw: TCP loopback", 1.5),
        ("tcp to the C target / raw TCP loopback", "tcp to the C reference target", "raw: TCP loopback", 1.5),
        ("local / raw shared memory + pipe", "local (default)", "raw: shared memory + pipe", 2.0),
        ("local handled on the reader's thread / raw shared memory + pipe",
         "local, handled on the reader's thread (a run's path)", "raw: shared memory + pipe", 2.0),
        ("local / raw Unix socketpair", "local (default)", "raw: Unix socketpair", None),
        ("local (default) / local inline", "local (default)", "local, inline (shm=False)", None),
        ("mixed / raw zenoh", "mixed (zenoh + virtual CAN, device in-process)", "raw: zenoh put/subscribe", None),
    ]
    print("\n## Ratios of p50s\n")
    print("| ratio | " + " | ".join(label for *_, label in cols) + " | goal |")
    print("| --- |" + " ---: |" * len(cols) + " --- |")
    for label, num, den, goal in checks:
        vals = [ratio(num, den, enc) for enc, *_ in cols]
        verdict = "–"
        measured = [float(v) for v in vals if v != "–"]
        if goal is not None and not measured:  # nothing to judge is not a goal met
            verdict = f"≤ {goal:g}: not measured"
        elif goal is not None:
            met = all(v <= goal for v in measured)
            verdict = f"≤ {goal:g}: " + ("met" if met else "**not met on this machine**")
        print(f"| {label} | " + " | ".join(vals) + f" | {verdict} |")
    floor = rows["raw: hand-off floor (32 B, 2 thread hand-offs)"][ImageEncoding.RGB8].pct(50)
    shm_floor = rows["raw: shared memory + pipe"][ImageEncoding.RGB8].pct(50)
    local_p50 = rows["local (default)"][ImageEncoding.RGB8].pct(50)
    print(f"\nWhere the local round trip of a raw frame goes (p50, µs): {local_p50:.0f} in all = hand-off "
          f"floor {floor:.0f} (a bare 32-byte round trip through the same four threads: the Link's reader "
          f"and the caller here, the SDK's reader and its inference worker in the target; the raw floors "
          f"have two) + protocol work {cpu_us:.0f} (encode, validate and decode the FRAME and the ESTIMATE, "
          f"write and read the slot; one thread, no I/O) + {local_p50 - floor - cpu_us:.0f} of scheduling "
          f"those threads on {os.cpu_count()} CPUs. The raw shared-memory round trip is {shm_floor:.0f}: "
          f"2x of it ({2 * shm_floor:.0f}) is out of reach for a Python Link and SDK on this machine "
          f"whatever the transport does; the ring's gain shows against the inline row.")
    print(f"\nLocal (default) sent {local_stats.frames_shm} frames through the ring and "
          f"{local_stats.frames_inline} inline; "
          f"{local_stats.overwritten_unread} slots overwritten unread.")
    print("\n## Virtual CAN bus (python-can `virtual`, one process)\n")
    print("| what | per second |")
    print("| --- | ---: |")
    print(f"| ESTIMATEs received by a CanLink (2 CAN FD frames each, no objects) | {est_rate:,.0f} |")
    print(f"| raw: 64-byte CAN FD frames between two threads (the floor) | {raw_rate:,.0f} |")
    print(f"| ratio: CAN frames of estimates / raw frames | {2 * est_rate / raw_rate:.2f} |")
    print(f"\n{time.perf_counter() - started:.0f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
