"""One vehicle's figures in ``summary.json`` (``vehicles.<name>``), typed: what the
report, the pytest plugin, the CLI and the CI outputs read. The records of
:mod:`hil.harness.vocab.figures` (which see for the rules every record keeps).

Latencies are in ms, times on the harness clock in ns, as ``summary.json`` holds them.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from hil.harness.vocab.figures_json import Fields, field_names, optional

STAGE_KEYS = ("p50_ms", "p90_ms", "p99_ms", "max_ms", "min_ms", "mean_ms", "std_ms")


@dataclass(frozen=True)
class StageFigures:
    """Exact statistics of one stage over the applied frames (``latency_ms.<stage>``,
    ``hil.timing.stats.summarize_ns``): ``count`` and, when it is not 0, the
    percentiles, extremes, mean and standard deviation in ms (``None``: not given)."""

    count: int = 0
    p50_ms: float | None = None
    p90_ms: float | None = None
    p99_ms: float | None = None
    max_ms: float | None = None
    min_ms: float | None = None
    mean_ms: float | None = None
    std_ms: float | None = None

    @classmethod
    def from_json(cls, f: Fields) -> StageFigures:
        return cls(f.integer("count"), *(f.opt_number(k) for k in STAGE_KEYS))

    @classmethod
    def of(cls, d: Mapping[str, Any]) -> StageFigures:
        """From ``summarize_ns``'s dict (or ``latency_ms.<stage>``) at ``path``.

        Raises:
            ConfigError: a field of the wrong type, named.
        """
        return cls.from_json(Fields(d, "latency"))

    def figure(self, key: str) -> float | None:
        """The figure named ``key`` (``count``, ``p50_ms`` ... ``std_ms``)."""
        v: float | None = getattr(self, key)
        return v

    def to_json(self) -> dict[str, float | int]:
        """As ``summary.json`` holds it: ``count`` and every figure given."""
        out: dict[str, float | int] = {"count": self.count}
        out.update({k: v for k in STAGE_KEYS if (v := getattr(self, k)) is not None})
        return out


@dataclass(frozen=True)
class StageBudget:
    """A budgeted stage's per-frame figures (``budgets.<stage>``): its ``budget_ms``,
    ``frames`` measured, ``over`` the budget, their ``fraction`` and the worst (ms;
    ``None`` without frames)."""

    budget_ms: float
    frames: int = 0
    over: int = 0
    fraction: float = 0.0
    worst_ms: float | None = None

    @classmethod
    def from_json(cls, f: Fields) -> StageBudget:
        return cls(f.number("budget_ms"), f.integer("frames"), f.integer("over"), f.number("fraction"),
                   f.opt_number("worst_ms"))


@dataclass(frozen=True)
class ClockFigures:
    """The target clock at the harness instant ``ref_ns`` (``clock``): ``offset_ns``
    (target − harness) within ``uncertainty_ns``, ``skew_ppm`` ± ``skew_uncertainty_ppm``,
    the best round trip ``delay_ns``; ``None`` where the fit had no sample."""

    synced: bool = False
    offset_ns: float | None = None
    ref_ns: int | None = None
    skew_ppm: float | None = None
    skew_uncertainty_ppm: float | None = None
    uncertainty_ns: float | None = None
    delay_ns: float | None = None
    samples_used: int = 0
    events: Mapping[str, int] = field(default_factory=dict)
    rejected: Mapping[str, int] = field(default_factory=dict)

    @classmethod
    def from_json(cls, f: Fields) -> ClockFigures:
        return cls(f.flag("synced", False), f.opt_number("offset_ns"), f.opt_integer("ref_ns"),
                   f.opt_number("skew_ppm"), f.opt_number("skew_uncertainty_ppm"), f.opt_number("uncertainty_ns"),
                   f.opt_number("delay_ns"), f.integer("samples_used"), f.counts("events"), f.counts("rejected"))


@dataclass(frozen=True)
class LinkFigures:
    """The link's counters (``link``, ``hil.adapters.link.LinkStats``). ``extra``: the
    rest as written (``impairment``, ``transport``: counters one transport has)."""

    frames_sent: int = 0
    bytes_sent: int = 0
    messages_received: int = 0
    bytes_received: int = 0
    protocol_errors: int = 0
    rx_dropped: int = 0
    target_errors: int = 0
    last_error: str | None = None
    connections_refused: int = 0
    refused: tuple[str, ...] = ()
    extra: Mapping[str, Any] = field(default_factory=dict)

    @classmethod
    def from_json(cls, f: Fields) -> LinkFigures:
        return cls(frames_sent=f.integer("frames_sent"), bytes_sent=f.integer("bytes_sent"),
                   messages_received=f.integer("messages_received"), bytes_received=f.integer("bytes_received"),
                   protocol_errors=f.integer("protocol_errors"), rx_dropped=f.integer("rx_dropped"),
                   target_errors=f.integer("target_errors"), last_error=f.opt_text("last_error"),
                   connections_refused=f.integer("connections_refused"), refused=f.texts("refused"),
                   extra=f.rest(field_names(cls)))


@dataclass(frozen=True)
class TargetHello:
    """What the target said of itself (``target``: its HELLO)."""

    name: str
    clock: str
    clock_resolution_ns: int | None = None

    @classmethod
    def from_json(cls, f: Fields) -> TargetHello:
        return cls(f.text("name", "?"), f.text("clock", "?"), f.opt_integer("clock_resolution_ns"))


@dataclass(frozen=True)
class Outcome:
    """How the drive ended (``outcome``): gaps (m, ``None``: no lead), speed, collisions."""

    min_gap_m: float | None = None
    final_gap_m: float | None = None
    final_speed_mps: float | None = None
    collisions: int = 0

    @classmethod
    def from_json(cls, f: Fields) -> Outcome:
        return cls(f.opt_number("min_gap_m"), f.opt_number("final_gap_m"), f.opt_number("final_speed_mps"),
                   f.integer("collisions"))


@dataclass(frozen=True)
class RigCamera:
    """One camera of a rig (``cameras.<camera>``): frames, late frames, sets answered
    without it, and the p50 (ms) of each of its stages (``stage_p50_ms``: by stage,
    from the keys ``<stage>_p50_ms``)."""

    frames: int = 0
    late_frames: int = 0
    missing_in_sets: int = 0
    stage_p50_ms: Mapping[str, float | None] = field(default_factory=dict)

    @classmethod
    def from_json(cls, f: Fields) -> RigCamera:
        p50 = {k[: -len("_p50_ms")]: f.opt_number(k) for k in f.d if k.endswith("_p50_ms")}
        return cls(f.integer("frames"), f.integer("late_frames"), f.integer("missing_in_sets"), p50)


@dataclass(frozen=True)
class RigFigures:
    """A rig's frame sets (``rig``): sets, complete ones, desynced ones, capture skew
    and arrival spread (ms), end to end from the first and last capture (p50, ms),
    and the ``thresholds`` judged against (``skew_ms``, ``spread_ms`` ...)."""

    sets: int = 0
    complete: int = 0
    desynced: int = 0
    capture_skew_ms_max: float | None = None
    arrival_spread_ms_p50: float | None = None
    arrival_spread_ms_max: float | None = None
    e2e_from_first_capture_ms_p50: float | None = None
    e2e_from_last_capture_ms_p50: float | None = None
    thresholds: Mapping[str, float | None] = field(default_factory=dict)

    @classmethod
    def from_json(cls, f: Fields) -> RigFigures:
        return cls(sets=f.integer("sets"), complete=f.integer("complete"), desynced=f.integer("desynced"),
                   capture_skew_ms_max=f.opt_number("capture_skew_ms_max"),
                   arrival_spread_ms_p50=f.opt_number("arrival_spread_ms_p50"),
                   arrival_spread_ms_max=f.opt_number("arrival_spread_ms_max"),
                   e2e_from_first_capture_ms_p50=f.opt_number("e2e_from_first_capture_ms_p50"),
                   e2e_from_last_capture_ms_p50=f.opt_number("e2e_from_last_capture_ms_p50"),
                   thresholds=f.nums("thresholds"))


@dataclass(frozen=True)
class VehicleFigures:
    """``vehicles.<name>`` (README: ``summary.json``). Counters missing from an older
    summary read as 0, but ``frames_accounted``, which reads as ``frames_sent`` (the
    frames every one of which was settled); rates as ``None``; ``budgets`` as ``None``
    (a run before budgets were counted, unlike ``{}``: no budgeted stage); objects
    (``clock``, ``target``, ``outcome``, ``rig``) as ``None``; counts by kind as
    ``{}``. ``extra``: the sections no reader takes by key, as written
    (``streaming_ms``, ``splits_ms``, ``splits_excluded``, ...)."""

    frames_sent: int = 0
    frames_accounted: int = 0
    estimates_applied: int = 0
    dropped: int = 0
    stale: int = 0
    late_estimates: int = 0
    unknown_estimates: int = 0
    protocol_errors: int = 0
    protocol_events_unwritten: int = 0
    order_violations: int = 0
    late_frames: int = 0
    records_excluded: int = 0
    drop_rate: float | None = None
    frames_per_s: float | None = None
    estimates_per_s: float | None = None
    latency_ms: Mapping[str, StageFigures] = field(default_factory=dict)
    budgets: Mapping[str, StageBudget] | None = None
    clock: ClockFigures | None = None
    anomalies: Mapping[str, int] = field(default_factory=dict)
    anomaly_causes: Mapping[str, Mapping[str, int]] = field(default_factory=dict)
    mismatches: Mapping[str, int] = field(default_factory=dict)
    events: Mapping[str, int] = field(default_factory=dict)
    link: LinkFigures = field(default_factory=LinkFigures)
    target: TargetHello | None = None
    outcome: Outcome | None = None
    cameras: Mapping[str, RigCamera] = field(default_factory=dict)
    rig: RigFigures | None = None
    extra: Mapping[str, Any] = field(default_factory=dict)

    @classmethod
    def from_json(cls, f: Fields) -> VehicleFigures:
        sent = f.integer("frames_sent")
        budgets = f.objs("budgets") if f.d.get("budgets") is not None else None
        causes = f.objs("anomaly_causes")
        return cls(
            frames_sent=sent, frames_accounted=f.integer("frames_accounted", sent),
            estimates_applied=f.integer("estimates_applied"), dropped=f.integer("dropped"), stale=f.integer("stale"),
            late_estimates=f.integer("late_estimates"), unknown_estimates=f.integer("unknown_estimates"),
            protocol_errors=f.integer("protocol_errors"),
            protocol_events_unwritten=f.integer("protocol_events_unwritten"),
            order_violations=f.integer("order_violations"), late_frames=f.integer("late_frames"),
            records_excluded=f.integer("records_excluded"),
            drop_rate=f.opt_number("drop_rate"), frames_per_s=f.opt_number("frames_per_s"),
            estimates_per_s=f.opt_number("estimates_per_s"),
            latency_ms={k: StageFigures.from_json(s) for k, s in f.objs("latency_ms").items()},
            budgets=None if budgets is None else {k: StageBudget.from_json(b) for k, b in budgets.items()},
            clock=optional(ClockFigures, f.obj("clock")), anomalies=f.counts("anomalies"),
            anomaly_causes={side: {k: c.integer(k) for k in c.d} for side, c in causes.items()},
            mismatches=f.counts("mismatches"), events=f.counts("events"),
            link=optional(LinkFigures, f.obj("link")) or LinkFigures(), target=optional(TargetHello, f.obj("target")),
            outcome=optional(Outcome, f.obj("outcome")),
            cameras={k: RigCamera.from_json(c) for k, c in f.objs("cameras").items()},
            rig=optional(RigFigures, f.obj("rig")), extra=f.rest(field_names(cls)))


__all__ = ["ClockFigures", "LinkFigures", "Outcome", "RigCamera", "RigFigures", "StageBudget", "StageFigures",
           "TargetHello", "VehicleFigures"]
