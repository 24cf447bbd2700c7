"""The target SDK: serve an AI's ``infer(frame) -> Inference`` over a transport.

An AI developer writes one function and calls ``serve``::

    from hil.adapters.sdk import serve
    from hil.adapters.wire.messages import Inference, Control, DrivingState

    def infer(frame):
        return Inference(DrivingState.SAFE, Control(throttle=0.2))

    serve(infer, target_name="my-ai")

The SDK says HELLO, stamps ``t_rx``, ``t_infer_start``, ``t_infer_end`` and
``t_reply`` on the target's own clock, answers clock-sync requests at once (from
the reader, never queued behind inference) and sends one ESTIMATE per processed
frame. When frames arrive faster than ``infer`` runs, only the newest waiting frame
is processed; the skipped ones are counted (``SdkStats.frames_skipped``) and the
harness sees them as dropped. A target of a camera rig answers every camera
(``cameras="each"``) or one ESTIMATE per frame set (``infer_set``, a fusing stack):
``hil.adapters.frame_sets``.

Needs only numpy and the chosen transport: no simulator, torch or harness code.
"""

from __future__ import annotations

import signal
import socket
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import NoReturn, TypeVar, cast

import numpy as np

from hil.adapters import transports
from hil.adapters.frame_sets import (SET_TIMEOUT_S, CameraMode, FrameSet, RigQueue, SetInferFn, camera_mode,
                                     on_camera)
from hil.adapters.wire import protocol
from hil.adapters.wire.messages import (Auth, AuthStep, Bye, ClockId, Command, ErrorMsg, Estimate, Frame, Hello,
                                        ImageEncoding, Inference, Message, SyncRequest, SyncResponse)
from hil.adapters.wire.receipt import StreamReader
from hil.adapters.wire.stream import StreamDecoder
from hil.common.errors import ConfigError, ProtocolError, TransportError
from hil.timing.clock import Clock, MonotonicClock

R = TypeVar("R")
InferFn = Callable[[Frame], Inference]
CommandFn = Callable[[str], str]  # a COMMAND's text -> the reply's text


@dataclass
class SdkStats:
    frames_received: int = 0
    frames_skipped: int = 0
    estimates_sent: int = 0
    sync_answered: int = 0
    protocol_errors: int = 0
    infer_errors: int = 0
    commands: int = 0
    sets_incomplete: int = 0  # frame sets handed to infer_set with a camera missing


def decode_image(frame: Frame) -> np.ndarray:
    """The frame's pixels as an HxWx3 uint8 array in BGR order (OpenCV's).

    Raw RGB8/BGR8 need only numpy; JPEG needs OpenCV (``opencv-python-headless``).

    Raises:
        ProtocolError: the image bytes cannot be decoded (offset 0 of the image).
    """
    img: np.ndarray | None
    if frame.encoding in (ImageEncoding.RGB8, ImageEncoding.BGR8):
        img = np.frombuffer(frame.data, np.uint8).reshape(frame.height, frame.width, 3)
        return img[:, :, ::-1] if frame.encoding == ImageEncoding.RGB8 else img
    try:
        import cv2
    except ImportError as err:  # pragma: no cover - depends on the device's install
        raise ImportError("JPEG frames need OpenCV: pip install opencv-python-headless") from err
    img = cv2.imdecode(np.frombuffer(frame.data, np.uint8), cv2.IMREAD_COLOR)
    if img is None or img.shape[:2] != (frame.height, frame.width):
        raise ProtocolError("JPEG image does not decode to the frame's size", offset=0)
    return img


class Endpoint:
    """Target side of one session, independent of the transport: a transport feeds it
    received bytes (``on_bytes`` for streams, ``on_message_bytes`` for message
    transports) and gives it a ``send`` function; the endpoint answers clock-sync
    requests at once and runs ``infer`` on a worker thread, newest frame first.
    """

    def __init__(self, infer: InferFn | None, *, target_name: str, clock: Clock | None = None,
                 clock_id: ClockId = ClockId.MONOTONIC, clock_resolution_ns: int = 1,
                 on_command: CommandFn | None = None, token: bytes | None = None,
                 cameras: CameraMode | str | None = None, infer_set: SetInferFn | None = None,
                 set_timeout_s: float = SET_TIMEOUT_S) -> None:
        """``on_command``: handles COMMAND texts (announced in HELLO as
        ``protocol.CAP_COMMANDS``); called on the reader thread, so it must be quick
        and thread-safe; its return value is the reply's text. ``token``: the shared
        secret this target proves when challenged (announced as ``protocol.CAP_AUTH``,
        PROTOCOL.md 4.8; ``hil.adapters.wire.auth``). ``cameras``: ``"each"`` answers
        every camera of a rig (``CAP_CAMERAS``); ``infer_set`` (``cameras="set"``) is
        called once per frame set instead of ``infer``, a set incomplete
        ``set_timeout_s`` after its first frame given up (``hil.adapters.frame_sets``).

        Raises:
            ConfigError: ``cameras`` without the function it calls.
        """
        self.cameras = camera_mode(infer, cameras, infer_set)
        self.infer = infer
        self.infer_set = infer_set
        self.set_timeout_s = set_timeout_s
        self._rig = RigQueue(self.cameras, timeout_s=set_timeout_s) if self.cameras is not CameraMode.ONE else None
        self.on_command = on_command
        self.clock = clock or MonotonicClock()
        self.stats = SdkStats()
        self.target_name = target_name
        self.clock_id = clock_id
        self.clock_resolution_ns = clock_resolution_ns
        self.token = token
        self._send_raw: Callable[[bytes], None] | None = None
        self._send_lock = threading.Lock()
        self._cv = threading.Condition()
        self._pending: tuple[Frame, int] | None = None
        self._stopped = threading.Event()
        self.harness_said_bye = False  # the session ended by the harness's BYE
        self.bye_reason = ""  # the reason it gave
        self._vehicle_id = 0
        self._decoder: StreamDecoder[NoReturn] = StreamDecoder()
        self._worker: threading.Thread | None = None

    # -- lifecycle -------------------------------------------------------------

    def start(self, send: Callable[[bytes], None]) -> None:
        """Attach the transport's ``send`` (one encoded message per call), start the
        inference worker and say HELLO."""
        self._send_raw = send
        self._worker = threading.Thread(target=self._work, name="infer", daemon=True)
        self._worker.start()
        self.send(self.hello())

    def hello(self) -> Hello:
        """This endpoint's HELLO (capabilities: ``CAP_COMMANDS`` with ``on_command``,
        ``CAP_AUTH`` with a token)."""
        caps = (protocol.CAP_COMMANDS if self.on_command is not None else 0) | (
            protocol.CAP_AUTH if self.token else 0) | self.cameras.capabilities
        return Hello(self.target_name, protocol.VERSION, self.clock_id, self.clock_resolution_ns, caps)

    @property
    def vehicle_id(self) -> int:
        """The vehicle of the frames served (0 before the first)."""
        return self._vehicle_id

    @property
    def stopped(self) -> bool:
        """True once the harness said BYE (or ``stop()`` was called)."""
        return self._stopped.is_set()

    def wait_stopped(self, timeout_s: float | None = None) -> bool:
        return self._stopped.wait(timeout_s)

    def stop(self) -> None:
        with self._cv:
            self._stopped.set()
            self._cv.notify()

    def join(self, timeout_s: float = 5.0) -> None:
        self.stop()
        if self._worker is not None and self._worker is not threading.current_thread():
            self._worker.join(timeout=timeout_s)

    # -- transport side ----------------------------------------------------------

    def send(self, msg: Message) -> None:
        if self._send_raw is None:
            raise TransportError("endpoint not started")
        buf = protocol.encode(msg)
        with self._send_lock:
            self._send_raw(buf)

    def send_stamped(self, make: Callable[[int], Message]) -> None:
        """Send ``make(now)``, reading the clock after taking the write lock: a stamp
        of the hand-off to the transport (``t3``, ``t_reply``) must not include the
        wait for another writer's message (PROTOCOL.md section 3)."""
        if self._send_raw is None:
            raise TransportError("endpoint not started")
        with self._send_lock:
            self._send_raw(protocol.encode(make(self.clock.now_ns())))

    def on_bytes(self, data: bytes | bytearray | memoryview, t_rx: int) -> None:
        """Stream transports: bytes as they arrive, stamped at arrival (target clock)."""
        for item in self._decoder.feed(data):
            self.on_message(item, t_rx)

    def on_message_bytes(self, data: bytes, t_rx: int) -> None:
        """Message transports: one whole message, stamped at arrival (target clock)."""
        try:
            item: Message | ProtocolError = protocol.decode(data)
        except ProtocolError as err:
            item = err
        self.on_message(item, t_rx)

    def on_message(self, item: Message | ProtocolError, t_rx: int) -> None:
        """Handle one decoded message; returns quickly (never waits for inference)."""
        if isinstance(item, ProtocolError):
            self.stats.protocol_errors += 1
            # PROTOCOL.md section 9: a version this target does not speak gets
            # UNSUPPORTED_VERSION (decode_header's only failure at offset 4 that says so).
            version = item.offset == 4 and "unsupported protocol version" in str(item)
            code = protocol.ErrorCode.UNSUPPORTED_VERSION if version else protocol.ErrorCode.MALFORMED
            self.send(ErrorMsg(self._vehicle_id, code, str(item)[:1000]))
            return
        if isinstance(item, SyncRequest):
            self._vehicle_id = item.vehicle_id
            self.send_stamped(lambda t3: SyncResponse(item.vehicle_id, item.seq, item.t1_ns, t_rx, t3))
            self.stats.sync_answered += 1
        elif isinstance(item, Frame):
            self._vehicle_id = item.vehicle_id
            self.stats.frames_received += 1
            error = None
            with self._cv:
                if self._rig is not None:
                    skipped, error = self._rig.put(item, t_rx, time.monotonic())
                    self.stats.frames_skipped += skipped
                else:
                    if self._pending is not None:
                        self.stats.frames_skipped += 1
                    self._pending = (item, t_rx)
                self._cv.notify()
            if error is not None:  # a frame that contradicts its set: dropped, reported
                self.on_message(error, t_rx)
        elif isinstance(item, Command):
            self._on_command(item)
        elif isinstance(item, Auth):
            self._on_auth(item)
        elif isinstance(item, Bye):
            self.harness_said_bye = True
            self.bye_reason = item.reason
            self.stop()

    def _on_auth(self, a: Auth) -> None:
        """Answer a CHALLENGE with the proof of the token (the harness learns that this
        is the target it started or was told to reach); the challenge's vehicle id is
        the vehicle this target serves."""
        if a.step != AuthStep.CHALLENGE or not self.token:
            why = "this target holds no token" if not self.token else "a target sends the PROOF, never receives it"
            self.send(ErrorMsg(a.vehicle_id, protocol.ErrorCode.UNEXPECTED, f"AUTH {a.step.name}: {why}"))
            return
        from hil.adapters.wire.auth import proof

        self._vehicle_id = a.vehicle_id
        self.send(Auth(a.vehicle_id, AuthStep.PROOF, proof(self.token, a.data, a.vehicle_id)))

    def _on_command(self, cmd: Command) -> None:
        """Run the handler and reply with a COMMAND of the same ``seq``."""
        self.stats.commands += 1
        if self.on_command is None:
            reply = "error: this target accepts no commands"
        else:
            try:
                reply = str(self.on_command(cmd.text))
            except Exception as err:  # the AI's bug must not kill the session
                reply = f"error: {type(err).__name__}: {err}"
        raw = reply.encode("utf-8")[:protocol.MAX_COMMAND_LEN]
        self.send(Command(cmd.vehicle_id, cmd.seq, raw.decode("utf-8", "ignore"), self.clock.now_ns()))

    # -- inference worker --------------------------------------------------------

    def _next_frame(self) -> tuple[Frame, int] | None:
        """Wait for the newest pending frame (and its receipt time); None once stopped."""
        with self._cv:
            while self._pending is None and not self._stopped.is_set():
                self._cv.wait()
            if self._stopped.is_set():
                return None
            assert self._pending is not None
            item, self._pending = self._pending, None
            return item

    def _next_rig(self) -> tuple[Frame, int] | FrameSet | None:
        """A multi-camera target's next frame or frame set; None once stopped."""
        assert self._rig is not None
        with self._cv:
            while not self._stopped.is_set():
                now = time.monotonic()
                if (item := self._rig.take(now)) is not None:
                    if isinstance(item, FrameSet) and item.missing:
                        self.stats.sets_incomplete += 1
                    return item
                self._cv.wait(self._rig.wait_s(now))
            return None

    def _work(self) -> None:
        while (item := self._next_frame() if self._rig is None else self._next_rig()) is not None:
            if isinstance(item, FrameSet):
                fs, infer_set = item, self.infer_set
                assert infer_set is not None  # camera_mode: SET comes with infer_set
                ok = self._answer(lambda: infer_set(fs), fs.vehicle_id, fs.set_id, fs.t_rx_ns)
            else:
                (frame, t_rx), infer = item, self.infer
                assert infer is not None  # camera_mode: ONE and EACH come with infer
                ok = self._answer(lambda: on_camera(infer(frame), frame), frame.vehicle_id, frame.frame_id, t_rx)
            if not ok:
                return

    def _answer(self, run: Callable[[], Inference], vehicle_id: int, frame_id: int, t_rx: int) -> bool:
        """Run the AI and send its ESTIMATE for ``frame_id`` (a frame's, or a set's id);
        False once the transport is gone."""
        t_start = self.clock.now_ns()
        try:
            result = run()
        except Exception as err:  # the AI's bug must not kill the session
            self.stats.infer_errors += 1
            self.send(ErrorMsg(vehicle_id, protocol.ErrorCode.TARGET_FAILURE,
                               f"infer failed: {type(err).__name__}: {err}"[:1000]))
            return True
        t_end = self.clock.now_ns()
        try:
            self.send_stamped(lambda t_reply: Estimate(vehicle_id, frame_id, result.state, result.control,
                                                       tuple(result.objects), t_rx, t_start, t_end, t_reply))
        except (OSError, TransportError):
            return False
        self.stats.estimates_sent += 1
        return True


CAPABILITY_NAMES = ((0x0000_0001, "SHM_FRAMES"),  # hil.adapters.local.shm.SHM_FRAMES (local transport only)
                    (protocol.CAP_COMMANDS, "COMMANDS"), (protocol.CAP_AUTH, "AUTH"),
                    (protocol.CAP_CAMERAS, "CAMERAS"), (protocol.CAP_FRAME_SETS, "FRAME_SETS"))


def announce_line(ep: Endpoint, *, transport: str, where: str, access: str, keep_serving: bool,
                  keys: str | None = None) -> str:
    """The one line a target prints when it starts serving: what a person who started
    it by hand needs to know to point a harness at it."""
    h = ep.hello()
    caps = [name for bit, name in CAPABILITY_NAMES if h.capabilities & bit]
    return (f"{h.target_name}: {transport} target {where}" + (f", keys {keys}" if keys else "")
            + f", clock {getattr(h.clock_id, 'name', h.clock_id)} ({h.clock_resolution_ns} ns), protocol "
            f"v{h.protocol_version}, capabilities: {', '.join(caps) or 'none'}, access: {access}; "
            + ("serving run after run until Ctrl-C/SIGTERM" if keep_serving else "serving one run"))


def session_line(ep: Endpoint, n: int, peer: str, ended: str) -> str:
    """The one line a target prints when a session ends."""
    st = ep.stats
    vehicle = f", vehicle {ep.vehicle_id}" if st.frames_received or st.sync_answered else ""
    return (f"{ep.target_name}: session {n} with {peer}{vehicle}: {st.frames_received} frames, "
            f"{st.estimates_sent} estimates, {st.sync_answered} clock syncs, {st.protocol_errors} bad messages; "
            f"ended: {ended}")


def add_stats(base: Endpoint, done: Endpoint) -> None:
    """Add the counters of a finished session's endpoint into ``base``'s (the totals
    ``serve`` returns); nothing when they are the same endpoint."""
    if done is not base:
        for name, value in vars(done.stats).items():
            if isinstance(value, int) and isinstance(getattr(base.stats, name, None), int):
                setattr(base.stats, name, getattr(base.stats, name) + value)


def fresh_endpoint(base: Endpoint, done: Endpoint) -> Endpoint:
    """The endpoint for the next harness of a target serving run after run: same AI,
    clock, command handler and token (``done``'s counters added into ``base``'s)."""
    add_stats(base, done)
    return Endpoint(base.infer, target_name=base.target_name, clock=base.clock, clock_id=base.clock_id,
                    clock_resolution_ns=base.clock_resolution_ns, on_command=base.on_command, token=base.token,
                    cameras=base.cameras, infer_set=base.infer_set, set_timeout_s=base.set_timeout_s)


@contextmanager
def stop_on_sigterm(on_term: Callable[[], None]) -> Iterator[None]:
    """While the block runs on the main thread, SIGTERM calls ``on_term`` instead of
    ending the process; the old handler comes back after. Elsewhere: nothing (signals
    are the main thread's)."""
    old = None
    if threading.current_thread() is threading.main_thread():
        old = signal.signal(signal.SIGTERM, lambda *_: on_term())
    try:
        yield
    finally:
        if old is not None:
            signal.signal(signal.SIGTERM, old)


@contextmanager
def serving(ep: Endpoint, *, vehicle_id: int | None = None, harness_gone: threading.Event | None = None,
            linger_s: float = 0.0, on_term: Callable[[], None] | None = None) -> Iterator[None]:
    """What every transport's target side does around its own serve loop, once.

    While the block runs, SIGTERM stops ``ep`` and calls ``on_term`` (to wake a loop
    blocked in a read, or to stop serving further runs): ``stop_on_sigterm``. On
    leaving, however the block ends: unless the harness said BYE or is gone
    (``harness_gone`` set), the target says BYE, then waits up to ``linger_s`` for
    ``harness_gone`` (a transport whose liveliness news can overtake the BYE, Zenoh's,
    lingers so the harness reads a BYE, not a crash); the inference worker is joined.
    A BYE that cannot be sent any more is let go. ``vehicle_id``: the BYE's (default:
    the vehicle of the frames served).
    """
    def term() -> None:
        ep.stop()
        if on_term is not None:
            on_term()

    try:
        with stop_on_sigterm(term):
            yield
    finally:
        try:
            if not (ep.harness_said_bye or (harness_gone is not None and harness_gone.is_set())):
                try:
                    ep.send(Bye(ep.vehicle_id if vehicle_id is None else vehicle_id, "target stopping"))
                except (TransportError, OSError):
                    pass
                else:
                    if harness_gone is not None and linger_s > 0:
                        harness_gone.wait(linger_s)
        finally:
            ep.join()


def serve_stream(ep: Endpoint, reader: StreamReader[R], *, send: Callable[[bytes], None],
                 deliver: Callable[[Message | ProtocolError | R, int], None] | None = None,
                 quit_: threading.Event | None = None) -> str:
    """A stream transport's target loop (tcp, local) inside ``serving``: the next
    message from ``reader`` (one message per read, each stamped with its own arrival,
    ``hil.adapters.wire.receipt``), handed to ``deliver(item, t_rx)`` (default
    ``ep.on_message``), until BYE, end of stream or a broken socket (the harness has
    left: no BYE back), or SIGTERM, which shuts the socket's reading side to end the
    blocked read and leaves its writing side open for our BYE (and sets ``quit_``: no
    further sessions). A ``quit_`` already set when the session begins (a SIGTERM
    that came as the harness connected) stops it at once: HELLO, then BYE. The caller
    closes the socket. Returns how the session ended."""
    gone = threading.Event()
    sock = reader.sock
    ended = "stopped (SIGTERM)"

    def wake() -> None:
        try:
            sock.shutdown(socket.SHUT_RD)
        except OSError:
            pass
        if quit_ is not None:
            quit_.set()

    give = deliver if deliver is not None else cast(Callable[[Message | ProtocolError | R, int], None], ep.on_message)
    with serving(ep, harness_gone=gone, on_term=wake):
        if quit_ is not None and quit_.is_set():  # before ``wake`` was in place
            ep.stop()
        ep.start(send)
        while not ep.stopped:
            try:
                r = reader.next()
            except OSError as err:
                gone.set()
                ended = f"the connection failed: {err.strerror or err}"
                break
            if r is None:
                if not ep.stopped:  # not our own SIGTERM's shutdown
                    gone.set()
                    ended = "the harness closed the connection"
                break
            for item in r.items:
                give(item, r.t_rx_ns)
    return said_bye(ep) or ended


def said_bye(ep: Endpoint) -> str:
    """How a session the harness ended ended, with its reason; '' if it did not."""
    if not ep.harness_said_bye:
        return ""
    return "the harness said BYE" + (f" ({ep.bye_reason})" if ep.bye_reason else "")


# The command line of target programs (--transport and its options, one-line
# errors): hil.adapters.sdk_args, here for the programs that import them from the SDK.
from hil.adapters.sdk_args import TRANSPORTS as TRANSPORTS  # noqa: E402
from hil.adapters.sdk_args import TargetArgumentParser as TargetArgumentParser  # noqa: E402
from hil.adapters.sdk_args import add_transport_args as add_transport_args  # noqa: E402
from hil.adapters.sdk_args import run_target as run_target  # noqa: E402
from hil.adapters.sdk_args import transport_options as transport_options  # noqa: E402


def serve(infer: InferFn | None = None, *, target_name: str, transport: str | transports.Transport = "local",
          clock: Clock | None = None, clock_id: ClockId = ClockId.MONOTONIC, clock_resolution_ns: int = 1,
          on_command: CommandFn | None = None, cameras: CameraMode | str | None = None,
          infer_set: SetInferFn | None = None, set_timeout_s: float = SET_TIMEOUT_S,
          **transport_options: object) -> SdkStats:
    """Serve ``infer`` until the harness says BYE or the connection ends.

    Args:
        infer: the AI; called with each frame, returns an ``Inference``.
        target_name: reported in HELLO (at most 64 bytes of UTF-8).
        transport: one of ``TRANSPORTS``; ``"local"`` is a child of the harness.
        clock: the clock to stamp with (default: this host's monotonic clock).
        on_command: optional handler of COMMAND messages (text in, reply text out),
            for control software that takes commands during a run (model swaps).
        cameras, infer_set, set_timeout_s: a camera rig's target (``Endpoint``):
            ``cameras="each"`` answers every camera with ``infer``; ``infer_set``
            answers once per frame set (``hil.adapters.frame_sets.FrameSet``).
        transport_options: passed to the transport's ``serve_endpoint`` (its package's
            ``target`` module): ``options``, its options model (e.g. a ``ZenohOptions``,
            ``hil.adapters.zenoh.options``), and ``vehicle_id``, ``keep_serving``;
            ``transport_options(args)`` makes them from the command line.

    Returns:
        Counters of what was served.

    Raises:
        TransportError: unknown transport, or it cannot be used (for example
            ``HIL_LOCAL_FD`` is not set because the program was not started by the
            harness).
        ConfigError: ``cameras`` without the function it calls.
    """
    ep = Endpoint(infer, target_name=target_name, clock=clock, clock_id=clock_id,
                  clock_resolution_ns=clock_resolution_ns, on_command=on_command, cameras=cameras,
                  infer_set=infer_set, set_timeout_s=set_timeout_s)
    kind = transports.transport_of(transport)
    if kind is transports.Transport.LOCAL and transport_options:
        raise TransportError(f"the local transport takes no options; got {sorted(transport_options)}")
    # The transport's serve_endpoint, from the table in hil.adapters.transports (local: the
    # socket in HIL_LOCAL_FD plus the shared-memory frame ring of HIL_LOCAL_SHM).
    transports.serve_function(kind)(ep, **transport_options)
    return ep.stats
