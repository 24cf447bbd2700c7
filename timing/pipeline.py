"""Stage splits across clock domains.

``PipelineRecord.stages_ns()`` gives every stage that needs no clock sync
(end-to-end, inference, the whole transport, …); those are exact and are returned
here with uncertainty 0, whatever the sync state. Only the two cross-clock stages
need the target clock mapped onto the harness clock:

* ``uplink``   = map(t_rx) − t_tx
* ``downlink`` = t0' − map(t_reply)

each with its error bound. Where the receipt stamp ``t0'`` itself is known only to a
span (``PipelineRecord.t0p_uncertainty_ns``: the estimate waited in the socket), the
stages that use it carry that span as their bound too. The value is the signed mapped difference, never
clamped: a split of −0.05 ± 0.2 ms is reported as such (clamping it to 0 would
hide the mapping error it shows and bias every statistic). Both truths lie in
``[0, t0' − t_tx]``, so the bound is the farthest point of that range that lies
within the mapping's own bound; it is never wider than the mapping's. A mapped
timestamp earlier than its cause by more than its uncertainty is a causality
violation (``causality_violations``) and its split keeps the mapping's bound.
All values are integer nanoseconds.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple, Protocol

from hil.timing.records import PipelineRecord
from hil.timing.sync import Mapped, SyncState

CROSS_CLOCK_STAGES: tuple[str, ...] = ("uplink", "downlink")
T0P_STAGES = frozenset({"end_to_end", "apply_delay", "transport"})  # sync-free stages that end or start at t0'


class Mapper(Protocol):
    """Anything that maps a target timestamp onto the harness clock
    (``ClockSync``, ``SyncState``)."""

    def to_harness(self, t_target_ns: int) -> Mapped:
        ...


@dataclass(frozen=True)
class Split:
    """A stage duration and its error bound, both ns (bound 0: exact, one clock)."""

    value_ns: int
    uncertainty_ns: int

    def to_json(self) -> dict[str, int]:
        return {"value_ns": self.value_ns, "uncertainty_ns": self.uncertainty_ns}


class Violation(NamedTuple):
    """A mapped timestamp earlier than its cause: ``name`` says which pair,
    ``by_ns`` how much earlier, ``uncertainty_ns`` the bound it exceeded."""

    name: str
    by_ns: int
    uncertainty_ns: int


def _usable(mapper: Mapper | None) -> bool:
    if mapper is None:
        return False
    if isinstance(mapper, SyncState):
        return mapper.samples_used > 0
    state = getattr(mapper, "state", None)
    if callable(state):
        s = state()
        return not isinstance(s, SyncState) or s.samples_used > 0
    return True


def _mapped_ends(rec: PipelineRecord, mapper: Mapper | None) -> tuple[Mapped, Mapped] | None:
    if (rec.t_rx_target_ns is None or rec.t_reply_target_ns is None or rec.t0p_ns is None
            or not _usable(mapper)):
        return None
    assert mapper is not None
    return mapper.to_harness(rec.t_rx_target_ns), mapper.to_harness(rec.t_reply_target_ns)


def split_stages(rec: PipelineRecord, sync: Mapper | None) -> dict[str, Split]:
    """Every stage of ``rec`` as a ``Split``.

    Sync-free stages come from ``rec.stages_ns()`` unchanged, uncertainty 0 (those
    using ``t0'``: its own ``t0p_uncertainty_ns``).
    ``uplink``/``downlink`` are added when the record has ``t_rx``, ``t_reply`` and
    ``t0'`` and ``sync`` has a model (a ``SyncState`` with ``samples_used == 0`` or
    ``None`` gives no cross-clock split: a split is never reported without its
    uncertainty). Never raises for a record with missing stamps.
    """
    rx_u = rec.t0p_uncertainty_ns  # t0' itself is known to [t0' - rx_u, t0']
    out = {name: Split(v, rx_u if name in T0P_STAGES else 0) for name, v in rec.stages_ns().items()}
    ends = _mapped_ends(rec, sync)
    if ends is None:
        return out
    rx, reply = ends
    assert rec.t0p_ns is not None
    span = max(rec.t0p_ns - rec.t_tx_ns, 0)
    for name, raw, u in (("uplink", rx.value_ns - rec.t_tx_ns, rx.uncertainty_ns),
                         ("downlink", rec.t0p_ns - reply.value_ns, reply.uncertainty_ns + rx_u)):
        out[name] = Split(raw, _bound(raw, u, span))
    return out


def _bound(value_ns: int, uncertainty_ns: int, span_ns: int) -> int:
    """Error bound (ns) of a signed split ``value_ns ± uncertainty_ns`` whose truth
    also lies in ``[0, span_ns]``: the distance to the farthest point of both
    ranges' intersection, or the mapping's bound if they do not meet."""
    lo, hi = max(value_ns - uncertainty_ns, 0), min(value_ns + uncertainty_ns, span_ns)
    if lo > hi:
        return uncertainty_ns
    return max(value_ns - lo, hi - value_ns)


def causality_violations(rec: PipelineRecord, mapper: Mapper | None) -> list[Violation]:
    """Cross-clock order checks: mapped ``t_rx`` before ``t_tx``, or ``t0'`` before
    mapped ``t_reply``, by more than the mapping uncertainty. Empty when the record
    lacks the stamps or ``mapper`` has no model."""
    ends = _mapped_ends(rec, mapper)
    if ends is None:
        return []
    rx, reply = ends
    assert rec.t0p_ns is not None
    out = []
    if rec.t_tx_ns - rx.value_ns > rx.uncertainty_ns:
        out.append(Violation("t_rx < t_tx", rec.t_tx_ns - rx.value_ns, rx.uncertainty_ns))
    if reply.value_ns - rec.t0p_ns > reply.uncertainty_ns:
        out.append(Violation("t0' < t_reply", reply.value_ns - rec.t0p_ns, reply.uncertainty_ns))
    return out
