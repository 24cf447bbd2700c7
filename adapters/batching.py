"""A shared target's dynamic batching: one AI serves many vehicles' sessions.

Each vehicle has its own session (``BatchedEndpoint``: its own HELLO, clock-sync
answers, COMMANDs and BYE, over its own socket or Zenoh keys), but frames go to one
``BatchScheduler``, which runs ``infer_batch(frames)`` on a worker thread:

* **window**: a batch starts when the first waiting frame has waited ``window_ns``
  (default 2 ms), or at once when it is full: ``max_batch`` frames, or one frame
  from every open session (no session can add a second: see fairness);
* **fairness**: one waiting frame per vehicle; a newer frame replaces the waiting
  one (counted in that session's ``SdkStats.frames_skipped``; the harness sees it as
  dropped), as the single-vehicle SDK does; when more vehicles wait than a batch
  takes, the ones waiting longest go first, so no vehicle starves;
* **timestamps**: each frame keeps its own ``t_rx`` (arrival); ``t_infer_start`` and
  ``t_infer_end`` are its batch's, so the harness's ``target_queue`` stage
  (``t_infer_start - t_rx``) shows its queueing, window included; ``t_reply`` is
  stamped as its estimate leaves.

``BatchLog`` records every frame's batch (CSV: batch number, batch size, vehicle,
frame, the target's three stamps, and the batch's parts when the AI reports them:
``batch_parts``, e.g. the CNN's ``decode_ns,nets_ns,post_ns``, each measured inside
``t_infer_start``..``t_infer_end``), the run folder's ``target-shared-batches.csv``
when the harness started the target (``HIL_BATCH_LOG``).

Needs only the standard library and the SDK (no numpy, no torch).
"""

from __future__ import annotations

import os
import sys
import threading
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO

from hil.adapters import transports
from hil.adapters.sdk import CommandFn, Endpoint
from hil.adapters.wire import protocol
from hil.adapters.wire.messages import ErrorMsg, Estimate, Frame, Inference, Message
from hil.common.errors import ConfigError, ProtocolError, TransportError
from hil.timing.clock import Clock, MonotonicClock

BatchInferFn = Callable[[Sequence[Frame]], Sequence[Inference]]
# The parts of the batch ``infer_batch`` last ran, in ns, in the order the log's header names them.
BatchPartsFn = Callable[[], Sequence[int]]
ENV_BATCH_LOG = "HIL_BATCH_LOG"
ENV_CTL = "HIL_LOCAL_CTL"  # a shared local target's control socket (hil.adapters.local.shared_link)
DEFAULT_WINDOW_NS = 2_000_000
DEFAULT_MAX_BATCH = 16
BATCH_LOG_HEADER = "batch,batch_size,vehicle_id,frame_id,t_rx_ns,t_infer_start_ns,t_infer_end_ns\n"


class BatchLog:
    """Per-frame batch records, one CSV line per frame, written per batch (flushed, so
    a target ended by SIGTERM leaves what it served). ``parts``: names of the batch's
    parts (columns ``<name>_ns`` after the stamps, the same on every row of a batch)."""

    def __init__(self, path: str | os.PathLike[str], *, parts: Sequence[str] = ()) -> None:
        """Raises: OSError: the file cannot be created. ValueError: a part name that
        is not a plain identifier."""
        bad = [p for p in parts if not p.isidentifier()]
        if bad:
            raise ValueError(f"batch log parts {bad}: expected plain names such as 'decode'")
        self.path = Path(path)
        self.parts = tuple(parts)
        self._f: IO[str] | None = open(self.path, "w", encoding="ascii")  # noqa: SIM115 (closed in close())
        self._f.write(BATCH_LOG_HEADER.rstrip("\n") + "".join(f",{p}_ns" for p in self.parts) + "\n")

    def write(self, batch: int, rows: Sequence[tuple[int, int, int]], t_start_ns: int, t_end_ns: int,
              parts_ns: Sequence[int] = ()) -> None:
        """``rows``: (vehicle_id, frame_id, t_rx_ns) of each frame of batch ``batch``;
        ``parts_ns``: the batch's part durations, one per name in ``parts`` (empty
        cells when the AI reported none)."""
        f = self._f
        if f is None:
            return
        n = len(rows)
        tail = "".join(f",{int(v)}" for v in parts_ns) if len(parts_ns) == len(self.parts) else "," * len(self.parts)
        f.write("".join(f"{batch},{n},{v},{fid},{t_rx},{t_start_ns},{t_end_ns}{tail}\n" for v, fid, t_rx in rows))
        f.flush()

    def close(self) -> None:
        f, self._f = self._f, None
        if f is not None:
            f.close()


@dataclass
class BatchStats:
    """What the scheduler did: batches run, their sizes, frames replaced while waiting."""

    batches: int = 0
    frames: int = 0
    replaced: int = 0
    infer_errors: int = 0
    sizes: Counter[int] = field(default_factory=Counter)

    def line(self) -> str:
        sizes = " ".join(f"{k}:{v}" for k, v in sorted(self.sizes.items()))
        mean = self.frames / self.batches if self.batches else 0.0
        return (f"batches={self.batches} frames={self.frames} mean_batch={mean:.2f} replaced={self.replaced} "
                f"infer_errors={self.infer_errors} batch_sizes={{{sizes}}}")


class BatchScheduler:
    """Collects frames from sessions and runs ``infer_batch`` on them in batches.

    Args:
        infer_batch: frames in, one ``Inference`` per frame out (same order).
        window_ns: longest a frame waits for others before its batch starts (>= 0).
        max_batch: most frames per batch (>= 1).
        log: per-frame batch records (optional).
        batch_parts: the parts of the batch ``infer_batch`` last ran (ns, in the
            order of ``log.parts``), read right after each batch on the worker thread.

    Raises:
        ValueError: a window below 0 or ``max_batch`` below 1.
    """

    def __init__(self, infer_batch: BatchInferFn, *, clock: Clock | None = None, window_ns: int = DEFAULT_WINDOW_NS,
                 max_batch: int = DEFAULT_MAX_BATCH, log: BatchLog | None = None,
                 batch_parts: BatchPartsFn | None = None) -> None:
        if window_ns < 0:
            raise ValueError(f"batch window {window_ns} ns: expected >= 0")
        if max_batch < 1:
            raise ValueError(f"max batch {max_batch}: expected >= 1")
        self.infer_batch = infer_batch
        self.clock = clock or MonotonicClock()
        self.window_ns = window_ns
        self.max_batch = max_batch
        self.log = log
        self.batch_parts = batch_parts
        self.stats = BatchStats()
        self._cv = threading.Condition()
        # session -> (frame, t_rx); dict order is arrival order of the waiting frame
        self._pending: dict[BatchedEndpoint, tuple[Frame, int]] = {}
        self._sessions: set[BatchedEndpoint] = set()
        self._stopped = False
        self._worker: threading.Thread | None = None

    def start(self) -> None:
        self._worker = threading.Thread(target=self._work, name="batch-infer", daemon=True)
        self._worker.start()

    def stop(self, timeout_s: float = 5.0) -> None:
        with self._cv:
            self._stopped = True
            self._cv.notify_all()
        if self._worker is not None and self._worker is not threading.current_thread():
            self._worker.join(timeout=timeout_s)
        if self.log is not None:
            self.log.close()

    # -- sessions ------------------------------------------------------------------

    def attach(self, session: BatchedEndpoint) -> None:
        with self._cv:
            self._sessions.add(session)

    def detach(self, session: BatchedEndpoint) -> None:
        """The session ended: its waiting frame is dropped, batches stop waiting for it."""
        with self._cv:
            self._sessions.discard(session)
            self._pending.pop(session, None)
            self._cv.notify_all()

    def submit(self, session: BatchedEndpoint, frame: Frame, t_rx: int) -> None:
        """Queue ``frame`` (arrived at ``t_rx``, target clock); replaces the session's
        waiting frame, if any. Never waits for inference."""
        with self._cv:
            if self._stopped:
                return
            old = self._pending.pop(session, None)
            if old is not None:
                session.stats.frames_skipped += 1
                self.stats.replaced += 1
            self._pending[session] = (frame, t_rx)  # moves to the end: it is now the newest
            self._cv.notify_all()

    # -- worker --------------------------------------------------------------------

    def _take(self) -> list[tuple[BatchedEndpoint, Frame, int]] | None:
        """The next batch, after the window; None once stopped."""
        with self._cv:
            while True:
                while not self._pending and not self._stopped:
                    self._cv.wait()
                if self._stopped:
                    return None
                first_rx = min(t for _, t in self._pending.values())
                deadline = first_rx + self.window_ns
                full = min(self.max_batch, max(1, len(self._sessions)))
                while len(self._pending) < full and not self._stopped:
                    left_ns = deadline - self.clock.now_ns()
                    if left_ns <= 0:
                        break
                    self._cv.wait(left_ns / 1e9)
                    full = min(self.max_batch, max(1, len(self._sessions)))
                if self._stopped:
                    return None
                if not self._pending:  # its sessions ended while waiting
                    continue
                # Longest-waiting first (arrival order of the waiting frames).
                chosen = sorted(self._pending.items(), key=lambda kv: kv[1][1])[: self.max_batch]
                for s, _ in chosen:
                    del self._pending[s]
                return [(s, f, t) for s, (f, t) in chosen]

    def _work(self) -> None:
        while True:
            batch = self._take()
            if batch is None:
                return
            frames = [f for _, f, _ in batch]
            t_start = self.clock.now_ns()
            try:
                results = list(self.infer_batch(frames))
                if len(results) != len(frames):
                    raise ValueError(f"infer_batch returned {len(results)} results for {len(frames)} frames")
            except Exception as err:  # the AI's bug must not kill the service
                self.stats.infer_errors += 1
                for s, f, _ in batch:
                    s.stats.infer_errors += 1
                    s.send_quietly(ErrorMsg(f.vehicle_id, protocol.ErrorCode.TARGET_FAILURE,
                                            f"infer failed: {type(err).__name__}: {err}"[:1000]))
                continue
            t_end = self.clock.now_ns()
            parts: Sequence[int] = ()
            if self.batch_parts is not None:
                try:
                    parts = self.batch_parts()
                except Exception:  # noqa: BLE001 - the log loses its parts, the service goes on
                    parts = ()
            st = self.stats
            st.batches += 1
            st.frames += len(batch)
            st.sizes[len(batch)] += 1
            for (s, f, t_rx), r in zip(batch, results):
                est = Estimate(f.vehicle_id, f.frame_id, r.state, r.control, tuple(r.objects), t_rx, t_start, t_end,
                               self.clock.now_ns())
                try:
                    sent = s.send_quietly(est)
                except ProtocolError as err:  # an output the wire cannot carry: this frame fails, not the service
                    s.stats.infer_errors += 1
                    s.send_quietly(ErrorMsg(f.vehicle_id, protocol.ErrorCode.TARGET_FAILURE,
                                            f"infer output not encodable: {err}"[:1000]))
                    continue
                if sent:
                    s.stats.estimates_sent += 1
            if self.log is not None:
                self.log.write(st.batches, [(f.vehicle_id, f.frame_id, t) for _, f, t in batch], t_start, t_end,
                               parts)


def _no_single_infer(frame: Frame) -> Inference:  # pragma: no cover - never called
    raise RuntimeError("a batched session's frames go to its scheduler")


class BatchedEndpoint(Endpoint):
    """One vehicle's session of a shared target: the SDK's ``Endpoint`` (HELLO, clock
    sync, COMMANDs, BYE, protocol errors) whose frames go to ``scheduler``."""

    def __init__(self, scheduler: BatchScheduler, *, target_name: str, clock_id: object = None,
                 clock_resolution_ns: int = 1, on_command: CommandFn | None = None) -> None:
        kw = {} if clock_id is None else {"clock_id": clock_id}
        super().__init__(_no_single_infer, target_name=target_name, clock=scheduler.clock,
                         clock_resolution_ns=clock_resolution_ns, on_command=on_command, **kw)  # type: ignore[arg-type]
        self.scheduler = scheduler

    def start(self, send: Callable[[bytes], None]) -> None:
        """Attach ``send``, join the scheduler and say HELLO (no worker of its own)."""
        self._send_raw = send
        self.scheduler.attach(self)
        self.send(self.hello())

    def on_message(self, item: Message | Exception, t_rx: int) -> None:
        if isinstance(item, Frame):
            self._vehicle_id = item.vehicle_id
            self.stats.frames_received += 1
            self.scheduler.submit(self, item, t_rx)
            return
        super().on_message(item, t_rx)  # type: ignore[arg-type]

    def stop(self) -> None:
        super().stop()
        self.scheduler.detach(self)

    def join(self, timeout_s: float = 5.0) -> None:
        self.stop()

    def send_quietly(self, msg: Message) -> bool:
        """Send; False (nothing raised) when the session's transport is gone."""
        try:
            self.send(msg)
        except (OSError, TransportError):
            return False
        return True


def open_batch_log(path: str | None, *, parts: Sequence[str] = ()) -> BatchLog | None:
    """The batch log at ``path``, else at ``HIL_BATCH_LOG``, else none; a path that
    cannot be written is reported on stderr and skipped (serving matters more)."""
    where = path or os.environ.get(ENV_BATCH_LOG) or None
    if where is None:
        return None
    try:
        return BatchLog(where, parts=parts)
    except OSError as err:
        print(f"batch log {where}: {err}; batch sizes are only counted", file=sys.stderr, flush=True)
        return None


def started_shared() -> bool:
    """True in a target the harness started as a shared local target (``HIL_LOCAL_CTL``
    is set): it must serve many vehicles even without ``--shared``."""
    return os.environ.get(ENV_CTL, "").isdigit()


def parse_vehicles(text: str) -> list[int]:
    """``--vehicles``: a count N (vehicles 0..N-1) or a comma-separated list of ids.

    Raises:
        ValueError: neither (named in the message).
    """
    parts = [p.strip() for p in text.split(",") if p.strip()]
    if not parts or not all(p.isdigit() for p in parts):
        raise ValueError(f"--vehicles {text!r}: expected a count (4) or vehicle ids (0,2,3)")
    if len(parts) == 1 and "," not in text:
        n = int(parts[0])
        if not 1 <= n <= 256:
            raise ValueError(f"--vehicles {text!r}: expected 1..256 vehicles")
        return list(range(n))
    return sorted({int(p) for p in parts})


def serve_batched(infer_batch: BatchInferFn, *, target_name: str, transport: str = "local",
                  on_command: CommandFn | None = None, window_ns: int = DEFAULT_WINDOW_NS,
                  max_batch: int = DEFAULT_MAX_BATCH, vehicles: Sequence[int] = (), batch_log: str | None = None,
                  batch_parts: tuple[Sequence[str], BatchPartsFn] | None = None,
                  announce: Callable[[str], None] | None = None, **transport_options: object) -> BatchStats:
    """Serve ``infer_batch`` to many vehicles from this one process (a shared target).

    ``transport``: ``local`` (started by the harness with ``target.shared: true``:
    vehicles arrive over ``HIL_LOCAL_CTL``, ``hil.adapters.local.shared_link``) or ``zenoh``
    (one session, the keys of each of ``vehicles``, ``hil.adapters.zenoh.shared_target``).
    ``announce`` gets one line when serving ends (default: stderr): the batch counts.
    ``batch_parts``: (part names, a function giving the last batch's parts in ns):
    the batch log gets a ``<name>_ns`` column per part.

    Raises:
        TransportError: another transport, or the transport cannot be used.
        ConfigError: bad Zenoh options. ValueError: bad window or batch size.
    """
    names, parts_fn = batch_parts if batch_parts is not None else ((), None)
    scheduler = BatchScheduler(infer_batch, window_ns=window_ns, max_batch=max_batch,
                               log=open_batch_log(batch_log, parts=names), batch_parts=parts_fn)

    def make_endpoint() -> BatchedEndpoint:
        return BatchedEndpoint(scheduler, target_name=target_name, on_command=on_command)

    try:
        # The transport's serve_shared, from the table in hil.adapters.transports.
        kind = transports.transport_of(transport)
        serve_shared = transports.shared_serve_function(kind)
        if kind is transports.Transport.LOCAL:
            if transport_options:
                raise TransportError(f"the local transport takes no options; got {sorted(transport_options)}")
            serve_shared(scheduler, make_endpoint)
        else:
            options = {k: v for k, v in transport_options.items() if k != "vehicle_id"}  # it serves ``vehicles``
            serve_shared(scheduler, make_endpoint, vehicles=list(vehicles), **options)
    finally:
        scheduler.stop()
        (announce or (lambda text: print(text, file=sys.stderr, flush=True)))(
            f"{target_name}: shared target: {scheduler.stats.line()}")
    return scheduler.stats


__all__ = ["BATCH_LOG_HEADER", "ConfigError", "BatchInferFn", "BatchLog", "BatchPartsFn", "BatchScheduler", "BatchStats", "BatchedEndpoint",
           "ENV_BATCH_LOG", "ENV_CTL", "open_batch_log", "started_shared", "parse_vehicles", "serve_batched"]
