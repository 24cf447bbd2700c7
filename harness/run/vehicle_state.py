"""Per-vehicle bookkeeping of a run: the settled pipeline records' statistics and
the live ones shown while the run goes on (frames in flight and controls being
applied are the loop's frame ledger, ``hil.harness.run.ledger``)."""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field
from typing import NamedTuple

from hil.adapters.link import Link
from hil.timing.anomaly import is_sane
from hil.timing.records import STAGES, FrameStatus, PipelineRecord
from hil.timing.stats import RateMeter, RollingWindow, SpillColumn


@dataclass
class InFlight:
    """A frame sent and not yet answered (harness clock, ns)."""

    frame_id: int
    sim_time_ns: int
    t0_ns: int
    t_tx_ns: int
    t_state_ns: int | None = None  # the camera instant: when the physics reached sim_time_ns
    t0p_uncertainty_ns: int = 0  # the answer's receipt stamp is known to [t0' - this, t0'] (hil.adapters.wire.receipt)
    camera: int | None = None  # the camera of the vehicle's rig (None: a rig of one camera)


# capture -> send (t0 -> t_tx) in the harness's hands, part by part: ``encode`` in the
# render worker (t0 -> encoded and in its slot), ``hand_off`` to the shard (the worker's
# pipe, the pump thread's wake, the message's decoding), ``queue`` (waiting for the
# shard: other frames being sent), ``send`` (the link's work until t_tx).
SEND_PARTS = ("encode", "hand_off", "queue", "send")


PROGRESS_NS = 250_000_000  # progress rows (every vehicle's percentiles), at most this often


class ProgressRow(NamedTuple):
    """One vehicle's line of the live display (plain values: a shard in another
    process sends them)."""

    name: str
    frames: int
    fps: float
    e2e_p50_ms: float | None
    e2e_p99_ms: float | None
    dropped: int
    anomalies: int | None


@dataclass
class VehicleRun:
    name: str
    vehicle_id: int
    link: Link
    next_frame_id: int = 0
    # Exact statistics in bounded memory: one int64 per stage per applied, sane frame
    # (about 80 bytes a frame), not the records themselves (the MCAP has those),
    # spilled to disk in blocks (``SpillColumn``): memory stays flat however long the run.
    stage_values: dict[str, SpillColumn] = field(default_factory=lambda: {s: SpillColumn() for s in STAGES})
    frames_settled: int = 0
    order_violations: int = 0
    late_estimates: int = 0
    unknown_estimates: int = 0
    protocol_faults: int = 0  # messages from the target that could not be decoded
    # The camera pipeline's real time: frames handed to the link more than the frame
    # late tolerance after their camera instant (t_tx - t_state), and the worst lag.
    late_frames: int = 0
    worst_frame_lag_ns: int = 0
    send_parts: dict[str, SpillColumn] = field(default_factory=lambda: {p: SpillColumn() for p in SEND_PARTS})
    e2e_window: RollingWindow = field(default_factory=RollingWindow)
    fps_meter: RateMeter = field(default_factory=RateMeter)

    counts: Counter[FrameStatus] = field(default_factory=Counter)

    def add(self, rec: PipelineRecord) -> None:
        """Count a settled frame and keep its stage durations (applied frames whose
        stamps are sane; absurd ones are flagged as causality anomalies instead)."""
        self.frames_settled += 1
        self.counts[rec.status] += 1
        if rec.status != FrameStatus.OK:
            return
        if rec.order_violations():
            self.order_violations += 1
        if is_sane(rec)[0]:
            for name, v in rec.stages_ns().items():
                self.stage_values[name].append(v)

    def frame_out(self, lag_ns: int, *, tolerance_ns: int, parts: tuple[int, int, int, int]) -> None:
        """A frame left for its target ``lag_ns`` after its camera instant; ``parts``:
        its capture -> send in ``SEND_PARTS``' order (ns)."""
        if lag_ns > tolerance_ns:
            self.late_frames += 1
        if lag_ns > self.worst_frame_lag_ns:
            self.worst_frame_lag_ns = lag_ns
        for col, ns in zip(self.send_parts.values(), parts):
            col.append(ns)

    def count(self, status: FrameStatus) -> int:
        return self.counts[status]

    def progress_row(self, now_ns: int, anomalies: int | None = None) -> ProgressRow:
        return ProgressRow(self.name, self.next_frame_id, self.fps_meter.rate_hz(now_ns),
                           self.e2e_window.percentile_ms(50), self.e2e_window.percentile_ms(99),
                           self.count(FrameStatus.DROPPED), anomalies)
