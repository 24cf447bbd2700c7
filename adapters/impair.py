"""Link faults in real time: a user-space impairment stage inside a ``Link``.

The kernel's ``tc netem`` impairs a network interface; this machine's kernel has no
``sch_netem``, and local/CAN transports have no interface to impair. So the stage
sits inside the link itself, on both paths, for any transport:

* **uplink** (harness → target): ``Link._send_checked`` hands each encoded message to
  ``LinkImpairment.send``; the message reaches ``_send_bytes`` at its due time. The
  frame's ``t_tx`` was stamped before, so the injected delay shows in the ``uplink``
  split (``map(t_rx) − t_tx``) as it would on a slow wire.
* **downlink** (target → harness): ``Link._dispatch`` offers each decoded message to
  ``LinkImpairment.receive``; a delayed message is queued for the harness at its due
  time with ``t_rx_ns`` = the release instant (as if the wire delivered it then), so
  ``downlink`` and ``end_to_end`` measure the injected delay.

Per direction, netem's model (all optional, seeded per vehicle and direction):
``loss`` (probability a message is lost), ``duplicate`` (probability a second copy
follows, with its own delay), ``reorder`` (probability a message skips the delay and
overtakes those waiting), ``delay_ms ± jitter_ms`` (uniform), and ``rate_kbps`` (a
bandwidth cap: each message occupies the wire ``bytes·8/rate``, one after another).
In flight at most ``queue_limit`` messages per direction; more are dropped (counted,
recorded as ``overflow``).

Clock sync probes pass unimpaired unless ``sync`` is set: an asymmetric delay biases
the offset estimate by half the asymmetry (as on any real link), which would move the
injected delay out of the uplink split into the clock. HELLO, BYE and undecodable
bytes always pass. Every message through an impaired direction yields one record
(``ImpairRecord``: frame id, direction, injected delay, action) for the run's
``/<vehicle>/impairment`` channel, so analysis can tell injected latency from organic.

Raises nothing at import; ``LinkImpairment.send`` raises what ``_send_bytes`` raises
for a message that passes at once (a delayed one's send error is counted instead).
"""

from __future__ import annotations

import heapq
import threading
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from enum import Enum
from typing import Any

import numpy as np

from hil.adapters.wire import protocol
from hil.adapters.wire.messages import Bye, Estimate, Hello, MsgType, SyncRequest, SyncResponse
from hil.common.errors import ProtocolError
from hil.timing.clock import Clock


class Direction(str, Enum):
    UPLINK = "uplink"  # harness → target
    DOWNLINK = "downlink"  # target → harness


class Action(str, Enum):
    PASSED = "passed"  # through an impaired direction, nothing injected (delay 0)
    DELAYED = "delayed"
    LOST = "lost"
    DUPLICATE = "duplicate"  # the extra copy
    REORDERED = "reordered"  # skipped the delay queue
    OVERFLOW = "overflow"  # the in-flight queue was full: dropped


@dataclass(frozen=True)
class Impairment:
    """One direction's faults. Times in ms, probabilities in [0, 1], ``rate_kbps`` in
    kbit/s (0: no cap), ``queue_limit`` in messages."""

    delay_ms: float = 0.0
    jitter_ms: float = 0.0
    loss: float = 0.0
    reorder: float = 0.0
    duplicate: float = 0.0
    rate_kbps: float = 0.0
    queue_limit: int = 1000

    @property
    def active(self) -> bool:
        return bool(self.delay_ms or self.jitter_ms or self.loss or self.reorder or self.duplicate or self.rate_kbps)

    @classmethod
    def of(cls, section: Any) -> Impairment:
        """From a config section (any object with these attributes) or None."""
        if section is None:
            return cls()
        return cls(**{k: getattr(section, k) for k in cls.__dataclass_fields__})


@dataclass(frozen=True)
class ImpairRecord:
    """One message through an impaired direction. ``delay_ns``: the injected delay
    (due − in, rate cap included); ``t_out_ns``: when it was handed on (None if lost)."""

    direction: Direction
    kind: str
    frame_id: int | None
    action: Action
    delay_ns: int
    t_in_ns: int
    t_out_ns: int | None
    nbytes: int

    def to_json(self) -> dict[str, Any]:
        return {"direction": self.direction.value, "kind": self.kind, "frame_id": self.frame_id,
                "action": self.action.value, "delay_ns": self.delay_ns, "t_in_ns": self.t_in_ns,
                "t_out_ns": self.t_out_ns, "bytes": self.nbytes}


def _counts() -> dict[str, int]:
    return {"messages": 0, **{a.value: 0 for a in Action}, "send_errors": 0, "discarded": 0}


class _Lane:
    """One direction: its spec, seeded generator, wire-busy time and counters."""

    def __init__(self, spec: Impairment, rng: np.random.Generator) -> None:
        self.spec = spec
        self.rng = rng
        self.busy_until_ns = 0
        self.in_flight = 0
        self.counts = _counts()

    def draw_delay_ns(self) -> int:
        s = self.spec
        j = self.rng.uniform(-s.jitter_ms, s.jitter_ms) if s.jitter_ms else 0.0
        return max(0, int(round((s.delay_ms + j) * 1e6)))


SendFn = Callable[[bytes], None]
Sink = Callable[[ImpairRecord], None]


class LinkImpairment:
    """The impairment stage of one link: a scheduler thread releases delayed messages
    at their due time. Start with ``bind`` (``Link.set_impairment`` does); ``close()``
    is idempotent and discards what is still in flight (the link is going down).

    Records go to ``sink`` once one is set (``set_sink``); until then up to
    ``backlog`` of them wait (older ones are counted in ``records_dropped``).
    """

    def __init__(self, *, uplink: Impairment, downlink: Impairment, seed: int, vehicle_id: int,
                 clock: Clock, sync: bool = False, backlog: int = 100_000) -> None:
        self.clock = clock
        self.sync = sync
        self.seed = seed
        self._lanes = {d: _Lane(spec, np.random.default_rng([seed, vehicle_id, i]))
                       for i, (d, spec) in enumerate(((Direction.UPLINK, uplink), (Direction.DOWNLINK, downlink)))}
        self.counts: dict[str, dict[str, int]] = {d.value: lane.counts for d, lane in self._lanes.items()}
        self._heap: list[tuple[int, int, Direction, Callable[[], None]]] = []
        self._seq = 0
        self._cv = threading.Condition()
        self._send_lock = threading.Lock()
        self._send: SendFn | None = None
        self._put: Callable[[Any, Any], None] | None = None
        self._sink: Sink | None = None
        self._backlog: deque[ImpairRecord] = deque(maxlen=backlog)
        self.records_dropped = 0
        self.last_error: str | None = None  # of a delayed message's hand-off (counted in send_errors)
        self._thread: threading.Thread | None = None
        self._closed = False

    @property
    def active(self) -> bool:
        return any(lane.spec.active for lane in self._lanes.values())

    def bind(self, *, send: SendFn, put: Callable[[Any, Any], None], name: str = "impair") -> None:
        """Connect to the link's ``_send_bytes`` and ``_put(queue, received)``; start the
        scheduler thread."""
        self._send, self._put = send, put
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()

    def set_sink(self, sink: Sink) -> None:
        """Deliver records to ``sink`` (called from the scheduler and caller threads;
        must not block), the waiting backlog first."""
        with self._cv:
            self._sink = sink
            backlog, self._backlog = list(self._backlog), deque(maxlen=self._backlog.maxlen)
        for r in backlog:
            sink(r)

    # -- the two paths -------------------------------------------------------

    def send(self, buf: bytes) -> None:
        """Uplink: hand ``buf`` to the wire now or at its due time.

        Raises:
            TransportError (or what the transport raises): a message passing at once failed.
        """
        kind, frame_id = _peek(buf)
        lane = self._lanes[Direction.UPLINK]
        if not lane.spec.active or not self._impairs(kind):
            with self._send_lock:
                assert self._send is not None, "bind() first"
                self._send(buf)
            return
        self._impair(lane, Direction.UPLINK, kind, frame_id, len(buf), lambda: self._deliver_up(buf))

    def receive(self, received: Any, queue_: Any, *, nbytes: int = 0) -> bool:
        """Downlink: take ``received`` (a ``link.Received``) if its direction is
        impaired; it is put on ``queue_`` at its due time, re-stamped with the release
        instant. Returns False when the caller should queue it itself."""
        lane = self._lanes[Direction.DOWNLINK]
        msg = received.msg
        kind = _kind_of(msg)
        if not lane.spec.active or not self._impairs(kind):
            return False
        frame_id = msg.frame_id if isinstance(msg, Estimate) else getattr(msg, "seq", None)
        if not nbytes and lane.spec.rate_kbps:
            try:  # the wire size, for the bandwidth cap (only paid when a cap is set)
                nbytes = len(protocol.encode(msg))
            except (ProtocolError, TypeError, ValueError):
                nbytes = 0

        def release() -> None:
            assert self._put is not None
            self._put(queue_, type(received)(msg, self.clock.now_ns(), received.link_vehicle_id))

        self._impair(lane, Direction.DOWNLINK, kind, frame_id, nbytes, release)
        return True

    def _impairs(self, kind: str) -> bool:
        if kind in ("hello", "bye", "protocol_fault"):
            return False
        return self.sync or kind not in ("sync_request", "sync_response")

    def _deliver_up(self, buf: bytes) -> None:
        with self._send_lock:
            assert self._send is not None
            self._send(buf)

    # -- scheduling ----------------------------------------------------------

    def _impair(self, lane: _Lane, d: Direction, kind: str, frame_id: int | None, nbytes: int,
                deliver: Callable[[], None]) -> None:
        s = lane.spec
        now = self.clock.now_ns()
        lane.counts["messages"] += 1
        if s.loss and lane.rng.random() < s.loss:
            self._note(lane, ImpairRecord(d, kind, frame_id, Action.LOST, 0, now, None, nbytes))
            return
        copies = 2 if s.duplicate and lane.rng.random() < s.duplicate else 1
        for copy in range(copies):
            start = max(now, lane.busy_until_ns)
            if s.rate_kbps:
                lane.busy_until_ns = start + int(nbytes * 8 * 1e6 / s.rate_kbps)  # kbit/s → ns per byte·8
                start = lane.busy_until_ns
            reordered = copy == 0 and s.reorder and lane.rng.random() < s.reorder
            due = start if reordered else start + lane.draw_delay_ns()
            action = (Action.DUPLICATE if copy else Action.REORDERED if reordered
                      else Action.DELAYED if due > now else Action.PASSED)
            self._schedule(lane, ImpairRecord(d, kind, frame_id, action, due - now, now, None, nbytes), due, deliver)

    def _schedule(self, lane: _Lane, rec: ImpairRecord, due_ns: int, deliver: Callable[[], None]) -> None:
        with self._cv:
            if self._closed:
                return
            if lane.in_flight >= lane.spec.queue_limit:
                overflow = ImpairRecord(rec.direction, rec.kind, rec.frame_id, Action.OVERFLOW, 0, rec.t_in_ns,
                                        None, rec.nbytes)
            else:
                overflow = None
                lane.in_flight += 1
                self._seq += 1

                def fire() -> None:
                    lane.in_flight -= 1
                    try:
                        deliver()
                    except Exception as err:  # noqa: BLE001 - any transport's failure: counted, the stage goes on
                        lane.counts["send_errors"] += 1
                        self.last_error = f"{type(err).__name__}: {err}"
                    self._note(lane, ImpairRecord(rec.direction, rec.kind, rec.frame_id, rec.action, rec.delay_ns,
                                                  rec.t_in_ns, self.clock.now_ns(), rec.nbytes))

                heapq.heappush(self._heap, (due_ns, self._seq, rec.direction, fire))
                self._cv.notify()
        if overflow is not None:
            self._note(lane, overflow)

    def _note(self, lane: _Lane, rec: ImpairRecord) -> None:
        lane.counts[rec.action.value] += 1
        sink = self._sink
        if sink is not None:
            sink(rec)
            return
        with self._cv:
            if len(self._backlog) == self._backlog.maxlen:
                self.records_dropped += 1
            self._backlog.append(rec)

    def _run(self) -> None:
        while True:
            with self._cv:
                while not self._closed:
                    if self._heap:
                        wait_s = (self._heap[0][0] - self.clock.now_ns()) / 1e9
                        if wait_s <= 0:
                            break
                        self._cv.wait(timeout=wait_s)
                    else:
                        self._cv.wait()
                if self._closed:
                    return
                _, _, _, fire = heapq.heappop(self._heap)
            fire()

    def close(self) -> None:
        """Stop the scheduler; messages still in flight are discarded (counted in
        ``counts[direction]["discarded"]``). Idempotent."""
        with self._cv:
            if self._closed:
                return
            self._closed = True
            for _, _, d, _ in self._heap:
                self._lanes[d].counts["discarded"] += 1
            self._heap.clear()
            self._cv.notify_all()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout=2.0)

    def describe(self) -> dict[str, Any]:
        """The stage's settings, for the run's metadata and the study."""
        return {"seed": self.seed, "sync": self.sync,
                **{d.value: lane.spec.__dict__ for d, lane in self._lanes.items()}}


IMPAIRMENT_SCHEMA: dict[str, Any] = {
    "$schema": "https://json-schema.org/draft/2020-12/schema", "title": "hil.Impairment", "type": "object",
    "properties": {"direction": {"enum": [d.value for d in Direction]}, "kind": {"type": "string"},
                   "frame_id": {"type": ["integer", "null"]}, "action": {"enum": [a.value for a in Action]},
                   "delay_ns": {"type": "integer"}, "t_in_ns": {"type": "integer"},
                   "t_out_ns": {"type": ["integer", "null"]}, "bytes": {"type": "integer"}},
    "required": ["direction", "kind", "frame_id", "action", "delay_ns", "t_in_ns"]}


def impairment_seed(section: Any, *, run_seed: int) -> int:
    """The seed the stage of a ``target.impair`` section draws from: the section's, else the run's."""
    return int(section.seed) if section.seed is not None else run_seed


def stage_for(section: Any, *, run_seed: int, vehicle_id: int, clock: Clock) -> LinkImpairment | None:
    """The stage a ``target.impair`` config section asks for, or None when it injects
    nothing (its seed: :func:`impairment_seed`)."""
    if section is None or not getattr(section, "active", False):
        return None
    return LinkImpairment(uplink=Impairment.of(section.uplink), downlink=Impairment.of(section.downlink),
                          seed=impairment_seed(section, run_seed=run_seed), vehicle_id=vehicle_id, clock=clock,
                          sync=section.sync)


def record_on(stage: LinkImpairment | None, recorder: Any, topic: str) -> None:
    """Write the stage's records to ``topic`` of ``recorder`` (``log_time`` = when the
    message was handed on, or lost; ``publish_time`` = when it entered the stage)."""
    if stage is None:
        return
    recorder.register_json_channel(topic, "hil.Impairment", IMPAIRMENT_SCHEMA)

    def sink(r: ImpairRecord) -> None:
        recorder.write_json(topic, r.to_json(), log_time_ns=r.t_out_ns if r.t_out_ns is not None else r.t_in_ns,
                            publish_time_ns=r.t_in_ns)

    stage.set_sink(sink)


_KINDS = {MsgType.HELLO: "hello", MsgType.FRAME: "frame", MsgType.ESTIMATE: "estimate",
          MsgType.SYNC_REQUEST: "sync_request", MsgType.SYNC_RESPONSE: "sync_response",
          MsgType.HEARTBEAT: "heartbeat", MsgType.ERROR: "error", MsgType.BYE: "bye", MsgType.COMMAND: "command"}


def _peek(buf: bytes) -> tuple[str, int | None]:
    """Kind and frame id (or sequence number) of an encoded message; ``raw`` for bytes
    that are not one (``send_raw``)."""
    try:
        h = protocol.decode_header(buf)
    except ProtocolError:
        return "raw", None
    return _KINDS.get(h.type, "raw"), h.frame_id


def _kind_of(msg: Any) -> str:
    if isinstance(msg, Hello):
        return "hello"
    if isinstance(msg, Bye):
        return "bye"
    if isinstance(msg, SyncResponse):
        return "sync_response"
    if isinstance(msg, SyncRequest):
        return "sync_request"
    if isinstance(msg, Estimate):
        return "estimate"
    name = type(msg).__name__
    return "protocol_fault" if name == "ProtocolFault" else name.lower()


__all__ = ["IMPAIRMENT_SCHEMA", "Action", "Direction", "ImpairRecord", "Impairment", "LinkImpairment", "record_on",
           "stage_for"]
