"""The ``timing:`` section of a run config: clock sync and anomaly thresholds.

::

    timing:
      sync: {interval_s: 1.0, burst: 4}        # a burst of 4 exchanges every second
      thresholds: {deadline_ms: {end_to_end: 100}, frame_rate_floor_hz: 10}
      vehicles:                                 # per-vehicle overrides of thresholds
        ego0: {deadline_ms: {end_to_end: 50}}

Unset thresholds keep ``hil.timing.anomaly.Thresholds``' documented defaults.
"""

from __future__ import annotations

import dataclasses

from pydantic import BaseModel, Field, field_validator

from hil.harness.config.types import MODEL_CONFIG, Float, Int
from hil.timing.anomaly import Thresholds
from hil.timing.pipeline import CROSS_CLOCK_STAGES
from hil.timing.records import STAGES
from hil.timing.sync import SyncConfig


_SYNC = SyncConfig()  # the one home of the clock-sync defaults (hil.timing.sync)


class SyncSettings(BaseModel):
    """Clock-sync exchanges: ``burst`` 4-timestamp exchanges every ``interval_s``;
    samples with a round trip over ``max_delay_ms`` are rejected; an offset jump over
    ``step_threshold_ms`` is a clock step; no good sample for ``lost_after_s`` is sync
    lost; skew beyond ``skew_limit_ppm`` is flagged. The estimator's own settings
    default to ``hil.timing.sync.SyncConfig``'s (one home per default)."""

    model_config = MODEL_CONFIG

    interval_s: Float = Field(1.0, gt=0, le=60)
    burst: Int = Field(4, ge=1, le=64)
    window_s: Float = Field(_SYNC.window_s, gt=0, le=3600)
    max_delay_ms: Float = Field(_SYNC.max_delay_ns / 1e6, gt=0, le=10_000)
    step_threshold_ms: Float = Field(_SYNC.step_threshold_ns / 1e6, gt=0, le=10_000)
    lost_after_s: Float = Field(_SYNC.lost_after_s, gt=0, le=3600)
    skew_limit_ppm: Float = Field(_SYNC.skew_limit_ppm, gt=0, le=100_000)

    def to_sync_config(self) -> SyncConfig:
        return SyncConfig(window_s=self.window_s, max_delay_ns=int(self.max_delay_ms * 1e6),
                          step_threshold_ns=int(self.step_threshold_ms * 1e6),
                          lost_after_s=self.lost_after_s, skew_limit_ppm=self.skew_limit_ppm)


DEADLINE_STAGES = (*STAGES, *CROSS_CLOCK_STAGES)  # what the timing observer measures per frame


class ThresholdsConfig(BaseModel):
    """Anomaly thresholds; each unset field keeps its default (see
    ``hil.timing.anomaly.Thresholds``). ``deadline_ms`` maps a stage name (end_to_end,
    to_apply, inference, uplink, ...) to its deadline."""

    model_config = MODEL_CONFIG

    deadline_ms: dict[str, Float] | None = None
    jitter_ms: Float | None = Field(None, gt=0)
    jitter_window: Int | None = Field(None, ge=5, le=10_000)
    frame_rate_floor_hz: Float | None = Field(None, ge=0, le=1000)
    frame_rate_window_s: Float | None = Field(None, gt=0, le=600)
    spike_k: Float | None = Field(None, gt=0, le=1000)
    spike_floor_ms: Float | None = Field(None, ge=0, le=60_000)
    spike_window: Int | None = Field(None, ge=10, le=100_000)

    @field_validator("deadline_ms")
    @classmethod
    def _known_stages(cls, deadlines: dict[str, float] | None) -> dict[str, float] | None:
        # A typo'd stage was never measured, so its budget silently judged nothing.
        for stage in deadlines or {}:
            if stage not in DEADLINE_STAGES:
                raise ValueError(f"stage names, one of {', '.join(DEADLINE_STAGES)} (not {stage!r})")
        return deadlines

    def apply(self, base: Thresholds) -> Thresholds:
        changes = {k: v for k, v in self.model_dump().items() if v is not None}
        if "deadline_ms" in changes:
            changes["deadline_ms"] = {**base.deadline_ms, **changes["deadline_ms"]}
        return dataclasses.replace(base, **changes)


class RigSettings(BaseModel):
    """A camera rig's anomalies (``hil.timing.rig``): ``rig_desync`` when a frame set's
    capture skew is over ``skew_ms`` (default 1 ms: a shared trigger line gives 0) or
    its arrival spread (its frames' hand-offs to the link) over ``spread_ms`` (default:
    one camera period); ``camera_late`` when a camera's end-to-end is over its set's
    median by more than ``late_ms`` in ``late_sets`` sets running."""

    model_config = MODEL_CONFIG

    skew_ms: Float = Field(1.0, ge=0, le=60_000)
    spread_ms: Float | None = Field(None, ge=0, le=60_000)
    late_ms: Float = Field(20.0, ge=0, le=60_000)
    late_sets: Int = Field(5, ge=1, le=100_000)


class TimingConfig(BaseModel):
    model_config = MODEL_CONFIG

    sync: SyncSettings = Field(default_factory=SyncSettings)
    thresholds: ThresholdsConfig = Field(default_factory=ThresholdsConfig)
    vehicles: dict[str, ThresholdsConfig] = Field(default_factory=dict)
    rig: RigSettings = Field(default_factory=RigSettings)

    def thresholds_for(self, vehicle: str) -> Thresholds:
        """The run's thresholds with ``vehicle``'s overrides applied."""
        t = self.thresholds.apply(Thresholds())
        override = self.vehicles.get(vehicle)
        return override.apply(t) if override is not None else t
