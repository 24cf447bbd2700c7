"""Per-vehicle bookkeeping of a run: frames in flight, applied estimates, the
pipeline records and the live statistics shown while the run goes on."""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field

from adapters.link import Link
from timing.records import FrameStatus, PipelineRecord
from timing.stats import RateMeter, RollingWindow


@dataclass
class InFlight:
    """A frame sent and not yet answered (harness clock, ns)."""

    frame_id: int
    sim_time_ns: int
    t0_ns: int
    t_tx_ns: int
    t_state_ns: int | None = None  # the camera instant: when the physics reached sim_time_ns


@dataclass
class VehicleRun:
    name: str
    vehicle_id: int
    link: Link
    next_frame_id: int = 0
    in_flight: dict[int, InFlight] = field(default_factory=dict)
    last_applied_frame_id: int = -1
    records: list[PipelineRecord] = field(default_factory=list)
    late_estimates: int = 0
    unknown_estimates: int = 0
    protocol_faults: int = 0  # messages from the target that could not be decoded
    e2e_window: RollingWindow = field(default_factory=RollingWindow)
    fps_meter: RateMeter = field(default_factory=RateMeter)

    counts: Counter[FrameStatus] = field(default_factory=Counter)

    def add(self, rec: PipelineRecord) -> None:
        """Keep a settled frame's record (and its status count, for the live display)."""
        self.records.append(rec)
        self.counts[rec.status] += 1

    def count(self, status: FrameStatus) -> int:
        return self.counts[status]
