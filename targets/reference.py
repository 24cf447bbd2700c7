"""The reference target: injects known timing truth and writes it down, so the harness
can be checked against it (``hil calibrate``).

It runs on the same machine as the harness and reads the harness's clock
(``CLOCK_MONOTONIC``), but stamps on a clock of its own::

    target(m) = m + offset_ns + round((m - base_ns) * skew_ppm * 1e-6) [+ step_ns once stepped]

with ``m`` the monotonic reading and ``base_ns`` the reading at start. It injects,
each at the frames given on the command line: a fixed inference time (a spin of
exactly ``--infer-ms`` of monotonic time), latency spikes (extra time between the
end of inference and the reply), dropped frames (never answered), reorders (the
estimates of frames R and R+1 sent as R+1 then R), a clock step (``+step_ms`` just
before a frame's receipt is processed, so no frame straddles it) and malformed
messages (an extra copy of a frame's estimate with a bad payload CRC, or with an
object count that disagrees with the payload length), each sent before the good
estimate of that frame.

For every frame it writes one JSON line to ``--truth``: the true instants on
``CLOCK_MONOTONIC`` (receipt, inference start and end, the instant the reply was
handed to the transport), the stamps it sent, and the faults injected. Frames that
the SDK skipped (a newer frame came while inference ran) are written too: they are
true drops. Line kinds: ``config``, ``frame``, ``skipped``, ``step``, ``malformed``.

    python -m hil.targets.reference --truth truth.jsonl --clock-offset-s 2.5 --clock-skew-ppm 300 \\
        --infer-ms 20 --spike-frames 55 --drop-frames 65 --reorder-frames 75 --step-frame 100

Needs only the target SDK (adapters): no harness or simulator code.
"""

from __future__ import annotations

import argparse
import json
import struct
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import IO, Any

from hil.adapters.sdk import Endpoint
from hil.adapters.wire import protocol
from hil.adapters.wire.messages import Control, DrivingState, Estimate, Frame, Inference, Message
from hil.common.errors import ProtocolError, TransportError

TRUTH_VERSION = 1


class InjectedClock:
    """The target's clock: the host's monotonic clock with a known offset, skew and
    optional forward step. All values integer ns; thread-safe (the step is set once)."""

    def __init__(self, *, offset_ns: int, skew_ppm: float, base_ns: int | None = None) -> None:
        self.offset_ns = offset_ns
        self.skew_ppm = skew_ppm
        self.base_ns = time.monotonic_ns() if base_ns is None else base_ns
        self.step_ns = 0
        self.step_at_mono_ns: int | None = None

    def at(self, mono_ns: int) -> int:
        """The target clock's reading at host monotonic instant ``mono_ns``."""
        t = mono_ns + self.offset_ns + round((mono_ns - self.base_ns) * self.skew_ppm * 1e-6)
        if self.step_at_mono_ns is not None and mono_ns >= self.step_at_mono_ns:
            t += self.step_ns
        return t

    def now_ns(self) -> int:
        return self.at(time.monotonic_ns())

    def step(self, step_ns: int, *, at_mono_ns: int) -> None:
        """Step the clock forward by ``step_ns`` from ``at_mono_ns`` on.

        Raises:
            ValueError: a second step, or a step that is not forwards.
        """
        if self.step_at_mono_ns is not None or step_ns <= 0:
            raise ValueError("the reference clock steps once, forwards")
        self.step_ns, self.step_at_mono_ns = step_ns, at_mono_ns

    def to_mono(self, t_target_ns: int) -> int:
        """The monotonic instant at which the clock read ``t_target_ns`` (±1 ns)."""
        # Readings before the step stay below at(step) - step_ns; those after reach at(step).
        stepped = (self.step_at_mono_ns is not None
                   and t_target_ns >= self.at(self.step_at_mono_ns) - self.step_ns)
        t = t_target_ns - (self.step_ns if stepped else 0)
        return self.base_ns + round((t - self.offset_ns - self.base_ns) / (1.0 + self.skew_ppm * 1e-6))


@dataclass(frozen=True, kw_only=True)
class Faults:
    """Where faults are injected (frame ids) and how big they are."""

    infer_ns: int = 20_000_000
    spike_ns: int = 25_000_000
    spike_frames: frozenset[int] = frozenset()
    drop_frames: frozenset[int] = frozenset()
    reorder_frames: frozenset[int] = frozenset()
    bad_crc_frames: frozenset[int] = frozenset()
    bad_length_frames: frozenset[int] = frozenset()
    step_frame: int | None = None
    step_ns: int = 20_000_000

    def to_json(self) -> dict[str, Any]:
        return {k: sorted(v) if isinstance(v, frozenset) else v for k, v in self.__dict__.items()}


def bad_crc_bytes(est: Estimate) -> bytes:
    """``est`` encoded with a payload CRC, then one payload byte flipped: a good header
    with a bad payload (PROTOCOL.md §8), so a stream receiver skips exactly it."""
    buf = bytearray(protocol.encode(est, payload_crc=True))
    buf[protocol.HEADER_SIZE + 4] ^= 0xFF  # inside steering_rad
    return bytes(buf)


def bad_length_bytes(est: Estimate) -> bytes:
    """``est`` (no objects) encoded with ``n_objects`` = 1: the payload's own length
    field disagrees with ``payload_len`` (a good header, a bad payload)."""
    if est.objects:
        raise ValueError("bad_length_bytes needs an estimate without objects")
    buf = bytearray(protocol.encode(est))
    struct.pack_into("<H", buf, protocol.HEADER_SIZE + 2, 1)
    return bytes(buf)


@dataclass
class _Held:
    est: Estimate
    line: dict[str, Any]


@dataclass
class _Log:
    """The truth file: one JSON line per event, flushed at once (a target may be
    ended by a signal at the end of the run)."""

    f: IO[str] | None
    lock: threading.Lock = field(default_factory=threading.Lock)

    def write(self, line: dict[str, Any]) -> None:
        if self.f is None:
            return
        with self.lock:
            self.f.write(json.dumps(line, separators=(",", ":")) + "\n")
            self.f.flush()


class ReferenceEndpoint(Endpoint):
    """An SDK endpoint that injects ``faults`` and logs the truth of every frame."""

    def __init__(self, *, clock: InjectedClock, faults: Faults, truth: IO[str] | None,
                 target_name: str = "reference", on_done: Callable[[int], None] | None = None) -> None:
        """``on_done(frame_id)`` is called on the worker once a frame is fully handled
        (answered, dropped or held back for a reorder)."""
        super().__init__(self._infer, target_name=target_name, clock=clock)
        self.on_done = on_done
        self.iclock = clock
        self.faults = faults
        self.log = _Log(truth)
        self._held: _Held | None = None
        self.log.write({"kind": "config", "version": TRUTH_VERSION, "offset_ns": clock.offset_ns,
                        "skew_ppm": clock.skew_ppm, "base_ns": clock.base_ns, "faults": faults.to_json()})

    @staticmethod
    def _infer(frame: Frame) -> Inference:  # pragma: no cover - _work does the inference itself
        del frame
        return Inference(DrivingState.SAFE, Control(0.0, 0.0, 0.0))

    def on_message(self, item: Message | ProtocolError, t_rx: int) -> None:
        if isinstance(item, Frame):
            with self._cv:
                skipped = self._pending[0].frame_id if self._pending is not None else None
            if skipped is not None:
                self.log.write({"kind": "skipped", "frame_id": skipped})
        super().on_message(item, t_rx)

    def _spin_until(self, end_mono_ns: int) -> int:
        while (now := time.monotonic_ns()) < end_mono_ns:
            pass
        return now

    def _work(self) -> None:
        while True:
            if (item := self._next_frame()) is None:
                return
            frame, t_rx = item
            fid = frame.frame_id
            try:
                self._handle(frame, t_rx)
            except (OSError, TransportError):
                return
            if self.on_done is not None:
                self.on_done(fid)

    def _handle(self, frame: Frame, t_rx: int) -> None:
        f, c = self.faults, self.iclock
        fid = frame.frame_id
        faults: list[str] = []
        if f.step_frame is not None and fid >= f.step_frame and c.step_at_mono_ns is None:
            # Stepped between frames, so no frame mixes the two clocks: this frame's
            # receipt, stamped before the step, is restamped now on the stepped clock.
            at = time.monotonic_ns()
            c.step(f.step_ns, at_mono_ns=at)
            t_rx = c.at(at)
            self.log.write({"kind": "step", "frame_id": fid, "at_mono_ns": at, "step_ns": f.step_ns})
            faults.append("clock_step")
        rx_mono = c.to_mono(t_rx)
        start = time.monotonic_ns()
        end = self._spin_until(start + f.infer_ns)
        line: dict[str, Any] = {"kind": "frame", "frame_id": fid, "rx_mono_ns": rx_mono,
                                "infer_start_mono_ns": start, "infer_end_mono_ns": end,
                                "t_rx_target_ns": t_rx}
        est = Estimate(frame.vehicle_id, fid, DrivingState.SAFE, Control(0.0, 0.0, 0.0), (),
                       t_rx, c.at(start), c.at(end), 0)
        if fid in f.spike_frames:
            faults.append("spike")
            self._spin_until(end + f.spike_ns)
        if fid in f.drop_frames:
            faults.append("drop")
            line.update(faults=faults, send_mono_ns=None)
            self.log.write(line)
            return
        self._malformed(est, fid)
        if fid in f.reorder_frames and self._held is None:
            faults.append("reorder")
            line["faults"] = faults
            self._held = _Held(est, line)
            return
        line["faults"] = faults
        self._reply(est, line)
        if self._held is not None:
            held, self._held = self._held, None
            self._reply(held.est, held.line)

    def _malformed(self, est: Estimate, fid: int) -> None:
        for kind, make, frames in (("bad_crc", bad_crc_bytes, self.faults.bad_crc_frames),
                                   ("bad_length", bad_length_bytes, self.faults.bad_length_frames)):
            if fid in frames:
                raw = make(replace(est, t_reply_target_ns=self.iclock.now_ns()))
                with self._send_lock:
                    assert self._send_raw is not None
                    self._send_raw(raw)
                self.log.write({"kind": "malformed", "frame_id": fid, "fault": kind})

    def _reply(self, est: Estimate, line: dict[str, Any]) -> None:
        """Stamp ``t_reply`` now, send, and log the frame's truth."""
        send = time.monotonic_ns()
        self.send(replace(est, t_reply_target_ns=self.iclock.at(send)))
        self.stats.estimates_sent += 1
        line["send_mono_ns"] = send
        line["inference_ns"] = line["infer_end_mono_ns"] - line["infer_start_mono_ns"]
        line["turnaround_ns"] = send - line["rx_mono_ns"]
        self.log.write(line)


def _frames(text: str) -> frozenset[int]:
    try:
        ids = frozenset(int(x) for x in text.split(",") if x.strip())
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated frame ids, got {text!r}") from None
    if any(i < 0 for i in ids):
        raise argparse.ArgumentTypeError(f"frame ids are ≥ 0; got {text!r}")
    return ids


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m hil.targets.reference",
                                description=" ".join(__doc__.split("\n\n")[0].split()))  # the first paragraph
    p.add_argument("--truth", type=Path, default=None, help="write the injected truth here (JSON lines)")
    p.add_argument("--name", default="reference")
    p.add_argument("--clock-offset-s", type=float, default=2.5, help="target clock ahead of the host's (s)")
    p.add_argument("--clock-skew-ppm", type=float, default=300.0, help="target clock running fast (ppm)")
    p.add_argument("--infer-ms", type=float, default=20.0, help="inference: a spin of this long (ms)")
    p.add_argument("--spike-ms", type=float, default=25.0, help="extra delay before the reply of a spike (ms)")
    p.add_argument("--spike-frames", type=_frames, default=frozenset(), help="frames with a spike, e.g. 55,120")
    p.add_argument("--drop-frames", type=_frames, default=frozenset(), help="frames never answered")
    p.add_argument("--reorder-frames", type=_frames, default=frozenset(),
                   help="frames R whose estimate is sent after frame R+1's")
    p.add_argument("--bad-crc-frames", type=_frames, default=frozenset(),
                   help="frames preceded by a copy of their estimate with a bad payload CRC")
    p.add_argument("--bad-length-frames", type=_frames, default=frozenset(),
                   help="frames preceded by a copy of their estimate whose object count disagrees with its length")
    p.add_argument("--step-frame", type=int, default=None, help="step the clock just before this frame")
    p.add_argument("--step-ms", type=float, default=20.0, help="size of the clock step (ms, forwards)")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    from hil.adapters.sdk import add_transport_args, transport_options

    p = build_parser()
    add_transport_args(p)
    a = p.parse_args(argv)
    if a.infer_ms < 0 or a.spike_ms < 0 or a.step_ms <= 0:
        p.error("--infer-ms and --spike-ms must be ≥ 0 and --step-ms > 0")
    faults = Faults(infer_ns=int(a.infer_ms * 1e6), spike_ns=int(a.spike_ms * 1e6), spike_frames=a.spike_frames,
                    drop_frames=a.drop_frames, reorder_frames=a.reorder_frames, bad_crc_frames=a.bad_crc_frames,
                    bad_length_frames=a.bad_length_frames, step_frame=a.step_frame, step_ns=int(a.step_ms * 1e6))
    clock = InjectedClock(offset_ns=int(a.clock_offset_s * 1e9), skew_ppm=a.clock_skew_ppm)
    truth = open(a.truth, "w", encoding="utf-8") if a.truth is not None else None  # noqa: SIM115
    try:
        ep = ReferenceEndpoint(clock=clock, faults=faults, truth=truth, target_name=a.name)
        serve_endpoint(ep, a.transport, transport_options(a))
    finally:
        if truth is not None:
            truth.close()
    return 0


def serve_endpoint(ep: Endpoint, transport: str, options: dict[str, object]) -> None:
    """Serve ``ep`` over ``transport`` (``local`` or ``zenoh``) until BYE.

    Raises:
        TransportError: another transport, or it cannot be used.
    """
    from hil.adapters import transports

    if transport not in ("local", "zenoh"):
        raise TransportError(f"the reference target serves local or zenoh, not {transport!r}")
    transports.serve_function(transport)(ep, **options)  # local: options is empty


if __name__ == "__main__":
    raise SystemExit(main())
