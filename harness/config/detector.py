"""The ``detector:`` and ``corner_cases:`` sections of a run config.

::

    detector: {pos_tol_m: 1.5, pos_tol_rel: 0.1, max_range_m: 50, min_frames: 3}
    corner_cases:
      history_s: 10          # kept before each trigger
      after_s: 2             # and after it (sim time); triggers this close join one case
      windows: 16            # case windows cut out of run.mcap after the run (the rest refer to it)
      on_anomalies: [deadline_miss, sync_lost, clock_step]   # besides every mismatch
"""

from __future__ import annotations

from pydantic import BaseModel, Field, field_validator

from hil.harness.config.types import MODEL_CONFIG, Float, Int
from hil.timing.anomaly import AnomalyKind

ANOMALY_KINDS = tuple(k.value.lower() for k in AnomalyKind)


class DetectorSettings(BaseModel):
    """Tolerances of the corner-case detector (m, frames, m/s^2; see
    harness/cases/detector.py and late_reaction.py for ``near_miss_m`` and
    ``avoid_decel_mps2``): the config section and what the detector takes, one model."""

    model_config = MODEL_CONFIG

    enabled: bool = True
    pos_tol_m: Float = Field(1.5, gt=0, le=100)
    pos_tol_rel: Float = Field(0.1, ge=0, le=1)
    ghost_gate_m: Float = Field(4.0, gt=0, le=100)
    max_range_m: Float = Field(50.0, gt=0, le=1000)
    min_visible_px: Int = Field(40, ge=1, le=1_000_000)
    min_visible_fraction: Float = Field(0.25, ge=0, le=1)
    min_frames: Int = Field(3, ge=1, le=1000)
    clear_frames: Int = Field(5, ge=1, le=1000)
    near_miss_m: Float = Field(1.0, ge=0, le=100)        # late reaction: a gap under this is a near miss
    avoid_decel_mps2: Float = Field(4.0, gt=0, le=20)    # late reaction: "could still stop" at this decel


class CornerCaseSettings(BaseModel):
    model_config = MODEL_CONFIG

    enabled: bool = True
    history_s: Float = Field(10.0, gt=0, le=600)
    after_s: Float = Field(2.0, ge=0, le=600)
    windows: Int = Field(16, ge=0, le=1000)
    on_anomalies: list[str] = Field(default_factory=lambda: ["deadline_miss", "sync_lost", "clock_step"])

    @field_validator("on_anomalies")
    @classmethod
    def _known(cls, kinds: list[str]) -> list[str]:
        for k in kinds:
            if k not in ANOMALY_KINDS:
                raise ValueError(f"anomaly kinds, one of {', '.join(ANOMALY_KINDS)} (not {k!r})")
        return kinds
