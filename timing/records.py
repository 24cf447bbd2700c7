"""Per-frame pipeline records.

One ``PipelineRecord`` holds every timestamp of one frame's trip (see the timing
table in DESIGN.md) and derives the stage durations that need no clock sync:

* ``render``          = t0 − t_state (harness clock): from the camera's exposure
  instant (the simulation reaching the frame's sim time) to the image being ready
* ``capture_to_send`` = t_tx − t0 (harness clock)
* ``end_to_end``      = t0' − t0 (harness clock)
* ``to_apply``        = t_apply − t0 (harness clock)
* ``apply_delay``     = t_apply − t0' (harness clock)
* ``target_total``    = t_reply − t_rx (target clock; needs only its rate)
* ``target_queue``    = t_infer_start − t_rx (target clock)
* ``inference``       = t_infer_end − t_infer_start (target clock)
* ``transport``       = (t0' − t_tx) − (t_reply − t_rx): uplink + downlink together,
  exact without sync because each clock's offset cancels within its own difference.

Splitting ``transport`` into uplink and downlink needs the target clock mapped onto
the harness clock (``hil.timing.sync``). All values are integer nanoseconds.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum


class FrameStatus(str, Enum):
    """What became of a frame."""

    OK = "ok"            # an estimate arrived in time and its control was applied
    DROPPED = "dropped"  # no estimate within the timeout
    STALE = "stale"      # an estimate arrived after a newer one had been applied
    PENDING = "pending"  # still waiting (only while the run goes on)


STAGES: tuple[str, ...] = (
    "render", "capture_to_send", "transport", "target_queue", "inference", "target_total",
    "apply_delay", "end_to_end", "to_apply",
)


@dataclass(frozen=True)
class PipelineRecord:
    """Every timestamp of one frame. ``*_target_ns`` fields are on the target's clock,
    the others on the harness clock; ``None`` where the stage never happened."""

    vehicle: str
    frame_id: int
    sim_time_ns: int
    t0_ns: int
    t_tx_ns: int
    status: FrameStatus
    t_rx_target_ns: int | None = None
    t_infer_start_target_ns: int | None = None
    t_infer_end_target_ns: int | None = None
    t_reply_target_ns: int | None = None
    t0p_ns: int | None = None
    t_apply_ns: int | None = None
    sim_time_apply_ns: int | None = None
    t_state_ns: int | None = None
    # How much earlier than t0' the estimate's last byte may have arrived (the reader
    # found it already waiting, hil.adapters.wire.receipt): the truth is in [t0' - this, t0'].
    t0p_uncertainty_ns: int = 0
    # The camera of the vehicle's rig the frame came from (None: a rig of one camera,
    # and the record has no such key); its frame set is ``frame_id - camera``.
    camera: int | None = None

    def stages_ns(self) -> dict[str, int]:
        """Stage durations (ns) that this record can give, keyed by ``STAGES`` names."""
        out: dict[str, int] = {"capture_to_send": self.t_tx_ns - self.t0_ns}
        if self.t_state_ns is not None:
            out["render"] = self.t0_ns - self.t_state_ns
        if self.t0p_ns is not None:
            out["end_to_end"] = self.t0p_ns - self.t0_ns
        if self.t_apply_ns is not None:
            out["to_apply"] = self.t_apply_ns - self.t0_ns
            if self.t0p_ns is not None:
                out["apply_delay"] = self.t_apply_ns - self.t0p_ns
        rx, start, end, reply = (self.t_rx_target_ns, self.t_infer_start_target_ns,
                                 self.t_infer_end_target_ns, self.t_reply_target_ns)
        if rx is not None and reply is not None:
            out["target_total"] = reply - rx
            if self.t0p_ns is not None:
                out["transport"] = (self.t0p_ns - self.t_tx_ns) - (reply - rx)
        if rx is not None and start is not None:
            out["target_queue"] = start - rx
        if start is not None and end is not None:
            out["inference"] = end - start
        return out

    def order_violations(self) -> list[str]:
        """Names of timestamp pairs that are out of order within one clock (each
        should be empty for a sane target; cross-clock order needs sync)."""
        return [f"{nb} < {na}" for na, nb, _ in self._backwards()]

    def backwards_ns(self) -> int:
        """The largest step backwards between consecutive timestamps of one clock (0:
        none): how far out of order ``order_violations`` are."""
        return max((by for _, _, by in self._backwards()), default=0)

    def _backwards(self) -> list[tuple[str, str, int]]:
        """(earlier name, later name, ns the later one is before the earlier) of each
        out-of-order pair within one clock."""
        bad = []
        chain_h = [("t_state", self.t_state_ns), ("t0", self.t0_ns), ("t_tx", self.t_tx_ns), ("t0'", self.t0p_ns),
                   ("t_apply", self.t_apply_ns)]
        chain_t = [("t_rx", self.t_rx_target_ns), ("t_infer_start", self.t_infer_start_target_ns),
                   ("t_infer_end", self.t_infer_end_target_ns), ("t_reply", self.t_reply_target_ns)]
        for chain in (chain_h, chain_t):
            present = [(n, v) for n, v in chain if v is not None]
            for (na, va), (nb, vb) in zip(present, present[1:]):
                if vb < va:
                    bad.append((na, nb, va - vb))
        return bad

    def to_json(self) -> dict[str, object]:
        """A JSON-able dict: every timestamp plus the stage durations in ns."""
        d: dict[str, object] = {k: v for k, v in self.__dict__.items() if k != "camera" or v is not None}
        d["status"] = self.status.value
        d["stages_ns"] = self.stages_ns()
        return d
