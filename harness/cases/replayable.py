"""Which corner cases a lockstep replay can bring back, and which only real time shows.

``hil replay`` re-runs a case in lockstep: the same scenario, seed and parameters,
with the run's recorded per-frame latencies applied in sim time. That reproduces
what the simulation decides: the ground truth, the AI's estimates, and the
mismatches between them (``mismatch.*``: perception errors, and latency errors under
the recorded latencies), on any machine.

It cannot reproduce what only the wall clock shows. A timing anomaly (deadline miss,
latency spike, jitter, dropped frame, frame-rate floor, clock step, sync loss, ...)
depends on how long the machine, the link and the target really took; a lockstep run
waits for every estimate, so such an anomaly may or may not come back, whatever the
code. Those cases are ``real time only``: run the configuration again in real time
to see them. For the same reason a lockstep campaign records timing anomalies but
opens no case for them (``hil.harness.search.spec``).
"""

from __future__ import annotations

from enum import Enum

MISMATCH_PREFIX = "mismatch."


class Reproducibility(str, Enum):
    """Whether ``hil replay`` (lockstep) reproduces a case of a given kind."""

    REPLAY = "replay"                  # deterministic in lockstep: replay brings it back
    REAL_TIME_ONLY = "real time only"  # a wall-clock timing anomaly


def reproducibility(kind: str) -> Reproducibility:
    """How a case of ``kind`` (as stored: ``mismatch.<kind>`` or an anomaly kind) can
    be seen again."""
    return Reproducibility.REPLAY if kind.startswith(MISMATCH_PREFIX) else Reproducibility.REAL_TIME_ONLY


def why_not_replayable(kind: str) -> str:
    """One line saying why a case of ``kind`` cannot be replayed in lockstep."""
    return (f"a {kind} is a wall-clock timing anomaly: a lockstep replay waits for every estimate and cannot "
            "bring it back; run the configuration again in real time (hil run) to see it")


__all__ = ["MISMATCH_PREFIX", "Reproducibility", "reproducibility", "why_not_replayable"]
