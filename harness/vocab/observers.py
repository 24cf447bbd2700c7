"""Run observers: what the sim loop tells the analysis that watches it.

The loop calls every observer in order at these points; an observer never blocks
and never raises for data it dislikes (it records an event instead). Timing
analysis (clock sync, anomalies) and the corner-case detector are observers, so
the loop stays about stepping, sending and applying.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Protocol

from hil.adapters.wire.messages import Estimate
from hil.scenarios.ground_truth import CameraTruth, GroundTruth
from hil.timing.records import PipelineRecord
from hil.timing.sync import SyncSample


class RunObserver(Protocol):
    def on_truth(self, gt: GroundTruth, *, t_ns: int) -> None:
        """Ground truth taken at a camera tick (``t_ns`` harness clock)."""

    def on_record(self, vehicle: str, rec: PipelineRecord, estimate: Estimate | None) -> None:
        """A frame is settled: answered (with its estimate), stale, or dropped."""

    def on_sync(self, vehicle: str, sample: SyncSample) -> None:
        """A clock-sync sample arrived for ``vehicle``'s target."""

    def on_tick(self, *, now_ns: int, sim_time_ns: int) -> None:
        """Called after every physics step (keep it cheap)."""


class TruthObserver(RunObserver, Protocol):
    """Optional extra hooks, for observers that judge estimates against truth."""

    def on_camera_truth(self, vehicle: str, frame_id: int, truth: CameraTruth, *, cameras: int = 1) -> None:
        """What one of ``vehicle``'s cameras showed in the frame (or fused frame set)
        that the estimate carrying ``frame_id`` answers, at its capture; that answer is
        judged on ``cameras`` such truths, one per camera of its set."""

    def on_apply(self, vehicle: str, frame_id: int, truth_now: Callable[[], GroundTruth]) -> None:
        """Frame ``frame_id``'s control was just applied; ``truth_now()`` gives the
        world at this instant (call it only when needed: it costs); where it takes the
        keyword ``egos=``, it narrows the route truth to those egos."""
