"""Timing anomaly detectors (one ``AnomalyDetector`` per vehicle).

Discrete events are flagged once each: a dropped frame, a stale or out-of-order
estimate, an insane record (``CAUSALITY``), a clock step. Conditions are flagged
once per *episode*, on entering it, and re-armed only after recovery:

* deadline miss, per stage — re-armed by one frame within the deadline;
* latency spike against a rolling median + k·MAD baseline — re-armed by one
  non-spike frame; a frame that also misses its deadline is reported only as the
  deadline miss, and a late reply flagged out of order is not also a spike;
* jitter (robust std of end-to-end over a window) — re-armed below
  ``jitter_rearm`` × limit;
* frame-rate floor (``on_tick``) — re-armed at ``frame_rate_rearm`` × floor. The
  rate counts estimates by their own receipt time ``t0'`` over windows that are
  complete: a window is judged only once every estimate in it can have been
  handed over (``complete_until_ns``), so analysis that waits for a newer clock
  sample never reads as a missing frame rate;
* mapped-timestamp causality (bad sync) — re-armed by a consistent record.

So a single injected spike is flagged exactly once and a clean run flags nothing.

A camera rig's records (``PipelineRecord.camera`` set) are judged camera by camera:
every per-frame baseline and episode above (order, deadline, spike, jitter,
causality) is the camera's own, so cameras that differ steadily (a wider image, a
slower camera) never read as jitter or spikes of one stream; the frame-rate floor
counts frame sets answered (``frame_id - camera``), one per trigger of the rig as
one estimate per frame is for a single camera.
Records that fail ``is_sane`` are flagged and kept out of every baseline. The
detector expects records in completion order (the order estimates arrived or
timed out). Durations are integer ns in, milliseconds in the anomalies.
"""

from __future__ import annotations

import math
from bisect import bisect_right, insort
from collections import deque
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field, replace
from enum import Enum
from types import MappingProxyType
from typing import NamedTuple

from hil.common.errors import ConfigError
from hil.timing.pipeline import Mapper, Split, Violation, causality_violations, split_stages
from hil.timing.records import FrameStatus, PipelineRecord
from hil.timing.sync import SyncEvent, SyncEventKind


class AnomalyKind(str, Enum):
    DEADLINE_MISS = "deadline_miss"
    JITTER = "jitter"
    DROPPED_FRAME = "dropped_frame"
    STALE_ESTIMATE = "stale_estimate"
    OUT_OF_ORDER = "out_of_order"
    FRAME_RATE_FLOOR = "frame_rate_floor"
    LATENCY_SPIKE = "latency_spike"
    CLOCK_STEP = "clock_step"
    SKEW_LIMIT = "skew_limit"
    SYNC_LOST = "sync_lost"
    CAUSALITY = "causality"
    # a camera rig's frame sets (hil.timing.rig)
    RIG_DESYNC = "rig_desync"
    CAMERA_MISSING = "camera_missing"
    CAMERA_LATE = "camera_late"


class Severity(str, Enum):
    INFO = "info"
    WARNING = "warning"
    CRITICAL = "critical"


SEVERITY: Mapping[AnomalyKind, Severity] = MappingProxyType({
    k: Severity.CRITICAL if k in (AnomalyKind.DEADLINE_MISS, AnomalyKind.FRAME_RATE_FLOOR)
    else Severity.WARNING for k in AnomalyKind})

FRAME_RATE_STEP_NS = 100_000_000  # the frame-rate windows are judged every 100 ms (the floor's period at 10 Hz)
_MIN_STEP_NS = 10_000_000          # and never more often than every 10 ms (a floor over 100 Hz: its period's multiple)
MAX_JUDGED_WINDOWS = 100_000       # per on_tick call; older ones are skipped (bounded work)
MAX_ARRIVALS = 1 << 16             # receipt times kept without a tick

_SYNC_KINDS: Mapping[SyncEventKind, AnomalyKind] = MappingProxyType({
    SyncEventKind.CLOCK_STEP: AnomalyKind.CLOCK_STEP,
    SyncEventKind.SKEW_LIMIT: AnomalyKind.SKEW_LIMIT,
    SyncEventKind.SYNC_LOST: AnomalyKind.SYNC_LOST})


@dataclass(frozen=True)
class Anomaly:
    """One timing anomaly. ``measured``/``threshold`` are in ``unit`` (ms, Hz, ppm,
    s or frames); ``sim_time_ns`` is ``None`` where no frame is involved."""

    kind: AnomalyKind
    vehicle: str
    frame_ids: tuple[int, ...]
    sim_time_ns: int | None
    harness_time_ns: int
    measured: float
    threshold: float
    unit: str
    severity: Severity
    stage: str | None = None
    detail: str = ""
    cause: str | None = None  # a latency anomaly's side: "harness", "link" or "target" (CAUSE_SIDES)

    def to_json(self) -> dict[str, object]:
        d: dict[str, object] = dict(self.__dict__)
        d["kind"], d["severity"], d["frame_ids"] = self.kind.value, self.severity.value, list(self.frame_ids)
        return d


class _Where(NamedTuple):
    """Which frames, and when, an anomaly is about."""

    frame_ids: tuple[int, ...]
    sim_time_ns: int | None
    harness_time_ns: int


# Which side of the bench each stage's time is spent on. A latency anomaly on a
# composite stage (end_to_end = capture_to_send + transport + target_total; to_apply
# adds apply_delay) is blamed on the side whose part rose most over its own recent
# median, so an instrument's hiccup is never read as the AI's lateness.
CAUSE_SIDES: Mapping[str, str] = MappingProxyType({
    "render": "harness", "capture_to_send": "harness", "apply_delay": "harness",
    "transport": "link", "uplink": "link", "downlink": "link",
    "target_queue": "target", "inference": "target", "target_total": "target"})
_PARTS: Mapping[str, tuple[str, ...]] = MappingProxyType({
    "end_to_end": ("capture_to_send", "transport", "target_total"),
    "to_apply": ("capture_to_send", "transport", "target_total", "apply_delay")})
_PART_WINDOW = 100  # recent values of each part kept for its median


def _middle(s: list[float] | list[int]) -> float:
    """The median of the sorted ``s`` (not empty), as numpy gives it: the middle value, or
    the mean of the middle two."""
    h = len(s) // 2
    return float(s[h]) if len(s) % 2 else (s[h - 1] + s[h]) / 2


def median_mad(values: Iterable[int]) -> tuple[float, float]:
    """(median, median absolute deviation) of ``values`` (not empty): the values of
    ``np.median``, by sorting. A window of 50-100 values costs ~8 µs this way against ~23
    through numpy (whose first median of floats imports ``numpy.ma``, ~10-80 ms, in the
    middle of a run), once or twice per record."""
    s = sorted(values)
    med = _middle(s)
    return med, _middle(sorted([abs(x - med) for x in s]))


def _default_deadlines() -> dict[str, float]:
    return {"end_to_end": 100.0}


@dataclass(frozen=True, kw_only=True)
class Thresholds:
    """Detector limits. Defaults are set so a clean run flags nothing.

    Attributes:
        deadline_ms: per-stage deadline in ms (any ``STAGES`` name, or ``uplink`` /
            ``downlink``, judged on value − uncertainty). Default end-to-end 100 ms:
            the budget of one frame at the paper's 10 fps floor.
        jitter_ms: limit on the robust std (1.4826 × MAD) of end-to-end over
            ``jitter_window`` frames (default 10 ms over 50 frames: a tenth of the
            frame budget; robust, so one spike reads as a spike, not as jitter).
        jitter_rearm: the jitter episode ends below this fraction of the limit.
        frame_rate_floor_hz: estimates per second over ``frame_rate_window_s``
            (default 10 Hz over 2 s, the paper's floor), counted by receipt time
            ``t0'`` over complete windows (see ``on_tick``); re-armed at
            ``frame_rate_rearm`` × floor.
        spike_k, spike_floor_ms, spike_window, spike_min_baseline, spike_stages: a
            spike is a value above median + max(k × 1.4826 × MAD, floor) of the last
            ``spike_window`` values of that stage (default k 10 robust σ (≈ 15 raw
            MADs), floor 5 ms, 100 frames, judged after 50; end-to-end only).
            Measured on simulated 60-s runs at 20 fps with lognormal latency (σ 0.3,
            p99 ≈ 2 × p50): k 8 flagged ~1 run in 10, k 10 none of 40; fewer than 50
            baseline frames under-estimate the MAD. The floor keeps a 1-ms baseline
            from tripping on noise.
        max_plausible_ms: a sync-free stage longer than this is an absurd record
            (default 60 s, the histogram range).
        max_skew_ppm, clock_tolerance_ns: slack when checking that the target's
            own duration fits inside the harness round trip.
        order_memory: recent frames remembered for order checks.
    """

    deadline_ms: Mapping[str, float] = field(default_factory=_default_deadlines)
    jitter_ms: float = 10.0
    jitter_window: int = 50
    jitter_rearm: float = 0.8
    frame_rate_floor_hz: float = 10.0
    frame_rate_window_s: float = 2.0
    frame_rate_rearm: float = 1.1
    spike_k: float = 10.0
    spike_floor_ms: float = 5.0
    spike_window: int = 100
    spike_min_baseline: int = 50
    spike_stages: tuple[str, ...] = ("end_to_end",)
    max_plausible_ms: float = 60_000.0
    max_skew_ppm: float = 2000.0
    clock_tolerance_ns: int = 1_000
    order_memory: int = 64

    def __post_init__(self) -> None:
        for name in ("jitter_ms", "jitter_window", "jitter_rearm", "frame_rate_window_s",
                     "frame_rate_rearm", "spike_k", "spike_window", "spike_min_baseline",
                     "max_plausible_ms", "order_memory"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not v > 0:
                raise ConfigError(f"Thresholds.{name} must be a positive number; got {v!r}")
        for name in ("frame_rate_floor_hz", "spike_floor_ms", "max_skew_ppm", "clock_tolerance_ns"):
            if not getattr(self, name) >= 0:
                raise ConfigError(f"Thresholds.{name} must be ≥ 0; got {getattr(self, name)!r}")
        for stage, ms in self.deadline_ms.items():
            if not isinstance(ms, (int, float)) or not ms > 0:
                raise ConfigError(f"Thresholds.deadline_ms[{stage!r}] must be a positive number "
                                  f"of milliseconds; got {ms!r}")


_DEFAULTS = Thresholds()  # frozen: is_sane without thresholds (once per record) builds none


def is_sane(rec: PipelineRecord, thresholds: Thresholds | None = None) -> tuple[bool, str]:
    """Whether a record's timestamps are physically possible, and if not why.

    Absurd: a timestamp ≤ 0, negative sim time, either clock's chain going
    backwards, a sync-free stage beyond ``max_plausible_ms`` (far future), a target
    turnaround longer than the harness round trip, an OK frame without ``t0'``.
    Never raises.
    """
    t = thresholds or _DEFAULTS
    stamps = {"t0": rec.t0_ns, "t_tx": rec.t_tx_ns, "t_rx": rec.t_rx_target_ns,
              "t_infer_start": rec.t_infer_start_target_ns, "t_infer_end": rec.t_infer_end_target_ns,
              "t_reply": rec.t_reply_target_ns, "t0'": rec.t0p_ns, "t_apply": rec.t_apply_ns}
    for name, v in stamps.items():
        if v is not None and v <= 0:
            return False, f"{name} is zero or negative ({v})"
    if rec.sim_time_ns < 0:
        return False, f"negative sim time ({rec.sim_time_ns})"
    if rec.sim_time_apply_ns is not None and rec.sim_time_apply_ns < rec.sim_time_ns:
        return False, "control applied at a sim time before the frame's"
    bad = rec.order_violations()
    if bad:
        return False, f"timestamps go backwards: {', '.join(bad)} (by up to {rec.backwards_ns() / 1e6:.3f} ms)"
    if rec.status is FrameStatus.OK and rec.t0p_ns is None:
        return False, "OK frame without t0'"
    stages = rec.stages_ns()
    limit = t.max_plausible_ms * 1e6
    for name, v in stages.items():
        if name != "transport" and v > limit:
            return False, (f"{name} of {v / 1e6:.1f} ms is beyond {t.max_plausible_ms:.0f} ms "
                           "(far-future stamp)")
    if "transport" in stages:
        slack = t.clock_tolerance_ns + t.max_skew_ppm * 1e-6 * stages["target_total"]
        if stages["transport"] < -slack:
            return False, "target turnaround longer than the harness round trip"
    return True, ""


@dataclass
class _Seen:
    """A recent estimate: when it arrived and whether it was already flagged."""

    t0p_ns: int
    flagged: bool


class _Stream:
    """The per-frame baselines and episodes of one camera (or of the one camera)."""

    def __init__(self, t: Thresholds) -> None:
        self.e2e: deque[int] = deque(maxlen=t.jitter_window)
        self.base: dict[str, deque[int]] = {s: deque(maxlen=t.spike_window) for s in t.spike_stages}
        self.in_spike: dict[str, bool] = {}
        self.in_miss: dict[str, bool] = {}
        self.in_jitter = self.in_causal = False
        self.recent: dict[int, _Seen] = {}
        self.max_frame: int | None = None
        self.parts: dict[str, deque[int]] = {p: deque(maxlen=_PART_WINDOW) for p in (*_PARTS["to_apply"], *_PARTS)}


def _judging_step_ns(floor_hz: float) -> int:
    """How often the frame-rate windows are judged: the floor's period (100 ms at the
    default 10 Hz), or the smallest multiple of it of at least ``_MIN_STEP_NS``;
    ``FRAME_RATE_STEP_NS`` without a floor."""
    if floor_hz <= 0:
        return FRAME_RATE_STEP_NS
    period = round(1e9 / floor_hz)
    return period * max(1, -(-_MIN_STEP_NS // period))


class AnomalyDetector:
    """Flags timing anomalies of one vehicle's records, sync events and ticks.
    ``counts`` tallies the anomalies by kind; ``excluded`` the insane records."""

    def __init__(self, vehicle: str, thresholds: Thresholds | None = None) -> None:
        self.vehicle = vehicle
        self.thresholds = t = thresholds or Thresholds()
        self.counts: dict[AnomalyKind, int] = {}
        self.excluded = 0
        self._in_floor = False
        self._arrivals: list[int] = []  # t0' of estimates not yet out of every window, sorted
        self._start_ns: int | None = None
        self._next_judge_ns: int | None = None
        self._answered = False  # an estimate arrived (the frame-rate windows start with the first)
        self._judged = False  # a frame-rate window was judged
        self._step_ns = _judging_step_ns(t.frame_rate_floor_hz)
        self._streams: dict[int | None, _Stream] = {}  # by camera of a rig (None: one camera)
        self._s = self._stream(None)  # the stream of the record being judged
        self._sets: dict[int, None] = {}  # a rig's recent frame sets with an arrival (insertion order)

    def _stream(self, camera: int | None) -> _Stream:
        s = self._streams.get(camera)
        if s is None:
            s = self._streams[camera] = _Stream(self.thresholds)
        return s

    def _arrived(self, rec: PipelineRecord) -> bool:
        """Whether ``rec``'s ``t0'`` counts for the frame rate: every estimate of one
        camera, the first of each frame set of a rig."""
        if rec.camera is None:
            return True
        set_id = rec.frame_id - rec.camera
        if set_id in self._sets:
            return False
        self._sets[set_id] = None
        while len(self._sets) > self.thresholds.order_memory:
            del self._sets[next(iter(self._sets))]
        return True

    def _make(self, kind: AnomalyKind, where: _Where, *, measured: float, threshold: float,
              unit: str, stage: str | None = None, detail: str = "") -> Anomaly:
        self.counts[kind] = self.counts.get(kind, 0) + 1
        return Anomaly(kind, self.vehicle, where.frame_ids, where.sim_time_ns, where.harness_time_ns,
                       measured, threshold, unit, SEVERITY[kind], stage, detail)

    def on_record(self, rec: PipelineRecord, *, splits: Mapping[str, Split] | None = None,
                  mapper: Mapper | None = None) -> list[Anomaly]:
        """Check one completed record. ``splits`` (from ``split_stages``) adds
        cross-clock deadlines; ``mapper`` (a ``ClockSync`` or ``SyncState``) also adds
        mapped-timestamp causality checks and computes ``splits`` if not given.
        Never raises for bad timestamps: an insane record gives one ``CAUSALITY``
        anomaly and is left out of every baseline (counted in ``excluded``)."""
        ok, why = is_sane(rec, self.thresholds)
        at = rec.t0p_ns if rec.t0p_ns is not None else rec.t_tx_ns
        self._s = self._stream(rec.camera)
        if rec.t0p_ns is not None and rec.t0p_ns > 0 and self._arrived(rec):
            insort(self._arrivals, rec.t0p_ns)  # it arrived, whatever its target stamps say
            if len(self._arrivals) > MAX_ARRIVALS:  # never ticked: keep memory bounded
                del self._arrivals[:MAX_ARRIVALS // 2]
            if not self._answered and not self._judged:
                # The stream's first estimate: windows start with it, not with the ticks
                # (or the capture) before it, whose silence no window at its rate holds.
                self._start_ns, self._next_judge_ns = rec.t0p_ns, None
            self._answered = True
        mk = _Where((rec.frame_id,), rec.sim_time_ns, at)
        if not ok:
            self.excluded += 1
            back = rec.backwards_ns()  # (timestamps out of order: by how much; else the why says it)
            return [self._make(AnomalyKind.CAUSALITY, mk, measured=back / 1e6, threshold=0.0, unit="ms" if back else "",
                               detail=why)]
        if self._start_ns is None:
            self._start_ns = rec.t0_ns
        if rec.status is FrameStatus.DROPPED:
            return [self._make(AnomalyKind.DROPPED_FRAME, mk, measured=1.0, threshold=0.0,
                               unit="frames", detail="no estimate within the timeout")]
        if rec.t0p_ns is None:
            return []
        out = self._order(rec)
        late = bool(out)
        if rec.status is not FrameStatus.OK:
            return out
        if mapper is not None:
            splits = splits if splits is not None else split_stages(rec, mapper)
            out += self._causality(causality_violations(rec, mapper), mk)
        values = dict(splits) if splits is not None else {}
        for name, v in rec.stages_ns().items():
            values.setdefault(name, Split(v, 0))
        n = len(out)
        missed = self._deadlines(values, mk, out)
        self._spikes(values, mk, out, skip=missed, late=late)
        self._jitter(values.get("end_to_end"), mk, out)
        out[n:] = [self._blame(a, values) for a in out[n:]]
        for part, q in self._s.parts.items():
            if part in values:
                q.append(values[part].value_ns)
        return out

    def _blame(self, a: Anomaly, values: Mapping[str, Split]) -> Anomaly:
        """A latency anomaly with its side (``CAUSE_SIDES``) and, for a composite
        stage, the part that rose most over its recent median named in the detail.
        Without the target's stamps only the harness's own parts are known: the
        harness is blamed when they account for at least half of the stage's rise,
        else the side is left unknown (link and target cannot be told apart)."""
        stage = a.stage or ""
        if stage in CAUSE_SIDES:
            return replace(a, cause=CAUSE_SIDES[stage])
        if a.kind is AnomalyKind.JITTER or stage not in _PARTS or stage not in values:
            return a
        parts = [p for p in _PARTS[stage] if p in values]
        rises = {p: values[p].value_ns - self._median(p) for p in [*parts, stage]}
        if len(parts) == len(_PARTS[stage]):
            part = max(parts, key=lambda p: rises[p])
        else:
            part = max((p for p in parts if CAUSE_SIDES[p] == "harness"), key=lambda p: rises[p], default="")
            if not part or rises[part] < 0.5 * rises[stage]:
                return a
        side = CAUSE_SIDES[part]
        # On a vehicle's first frames a part has no recent values: its rise is its value.
        rise = (f"{rises[part] / 1e6:+.3f} ms over its recent median" if self._s.parts[part]
                else "the largest part (no earlier frame to compare with)")
        why = (f"{'caused by the harness' if side == 'harness' else 'on the ' + side + ' side'}: {part} "
               f"{values[part].value_ns / 1e6:.3f} ms, {rise}")
        return replace(a, cause=side, detail=f"{a.detail}; {why}" if a.detail else why)

    def _median(self, part: str) -> int:
        q = self._s.parts[part]
        return int(_middle(sorted(q))) if q else 0

    def on_sync_events(self, events: Iterable[SyncEvent], *,
                       sim_time_ns: int | None = None) -> list[Anomaly]:
        """Clock step, skew limit and sync lost become anomalies (one per event);
        regained and rejected-sample events are not anomalies."""
        out = []
        for ev in events:
            kind = _SYNC_KINDS.get(ev.kind)
            if kind is not None:
                out.append(self._make(kind, _Where((), sim_time_ns, ev.harness_time_ns),
                                      measured=ev.measured, threshold=ev.threshold, unit=ev.unit,
                                      detail=ev.detail))
        return out

    def on_tick(self, now_ns: int, sim_time_ns: int | None = None, *,
                complete_until_ns: int | None = None) -> list[Anomaly]:
        """Periodic check (harness time ns): the estimate rate below the floor,
        flagged once per episode.

        Windows of ``frame_rate_window_s`` are judged one a step (the floor's
        period, ``_judging_step_ns``), each counting the estimates whose ``t0'``
        lies in it, and only once the window is complete: it ends at or before
        ``complete_until_ns`` (default ``now_ns``: the caller hands every estimate
        over as it arrives), so every estimate in it has been seen. Each window
        ends midway between the arrivals it counts (their mean phase within a
        step, plus half a step; ``_window_end``): an estimate stream at the floor's
        own rate holds exactly floor x window estimates in every window however its
        latency jitters (within half a period), where an edge among the arrivals
        counted one short. The first window starts at the first estimate's ``t0'``
        (seen before any window was judged), else the first record's ``t0`` or the
        first tick. An anomaly's ``harness_time_ns`` is the end of the window
        that fell below the floor; ``sim_time_ns`` is the caller's (when judged)."""
        t = self.thresholds
        step = self._step_ns
        if self._start_ns is None:
            self._start_ns = now_ns
        window_ns = int(t.frame_rate_window_s * 1e9)
        if self._next_judge_ns is None:
            self._next_judge_ns = self._start_ns + window_ns
        end_ns = now_ns if complete_until_ns is None else min(complete_until_ns, now_ns)
        if end_ns - self._next_judge_ns > MAX_JUDGED_WINDOWS * step:  # a huge jump
            skip = (end_ns - self._next_judge_ns) // step - MAX_JUDGED_WINDOWS
            self._next_judge_ns += skip * step
        out: list[Anomaly] = []
        while self._next_judge_ns <= end_ns:
            e = self._window_end(self._next_judge_ns, window_ns)
            self._next_judge_ns += step  # (the next end lies after this slot: the ends only increase)
            self._judged = True
            n = bisect_right(self._arrivals, e) - bisect_right(self._arrivals, e - window_ns)
            rate = n / t.frame_rate_window_s
            if self._in_floor:
                self._in_floor = rate < t.frame_rate_floor_hz * t.frame_rate_rearm
            elif rate < t.frame_rate_floor_hz:
                self._in_floor = True
                out.append(self._make(AnomalyKind.FRAME_RATE_FLOOR, _Where((), sim_time_ns, e),
                                      measured=rate, threshold=t.frame_rate_floor_hz, unit="Hz",
                                      detail=f"{n} estimates received in the {t.frame_rate_window_s} s "
                                             "before this instant"))
        # Kept: every arrival a later window can count (it ends at most a step before its slot).
        del self._arrivals[:bisect_right(self._arrivals, self._next_judge_ns - window_ns - step)]
        return out

    def _window_end(self, slot_ns: int, window_ns: int) -> int:
        """Where the window judged at ``slot_ns`` ends: the last instant at or before
        it that lies half a step from the mean phase (within a step) of the arrivals
        in the window ending at the slot; the slot itself where it holds none. At
        the floor's rate the arrivals keep one phase, so the window's two edges fall
        midway between them."""
        step = self._step_ns
        lo, hi = bisect_right(self._arrivals, slot_ns - window_ns), bisect_right(self._arrivals, slot_ns)
        if lo == hi:
            return slot_ns
        c = s = 0.0
        k = 2 * math.pi / step
        for a in self._arrivals[lo:hi]:
            angle = (a % step) * k
            c += math.cos(angle)
            s += math.sin(angle)
        mid = (round(math.atan2(s, c) / k) + step // 2) % step  # midway between the arrivals' phase
        return slot_ns - (slot_ns - mid) % step

    # --- pieces -------------------------------------------------------------------

    def _order(self, rec: PipelineRecord) -> list[Anomaly]:
        """Stale, duplicate and out-of-order estimates, each frame flagged once."""
        assert rec.t0p_ns is not None
        t0p, fid, out = rec.t0p_ns, rec.frame_id, []
        st = self._s
        newest = st.max_frame
        unit = "frames"
        if rec.status is FrameStatus.STALE:
            behind = float(max((newest or fid) - fid, 0))
            out.append(self._make(AnomalyKind.STALE_ESTIMATE, _Where((fid,), rec.sim_time_ns, t0p),
                                  measured=behind, threshold=0.0, unit=unit,
                                  detail="estimate arrived after a newer one was applied"))
        elif fid in st.recent:
            out.append(self._make(AnomalyKind.OUT_OF_ORDER, _Where((fid,), rec.sim_time_ns, t0p),
                                  measured=0.0, threshold=0.0, unit=unit, detail="duplicate estimate"))
        elif newest is not None and fid < newest:
            out.append(self._make(AnomalyKind.OUT_OF_ORDER, _Where((fid, newest), rec.sim_time_ns, t0p),
                                  measured=float(newest - fid), threshold=0.0, unit=unit,
                                  detail=f"arrived after frame {newest}'s estimate"))
        else:  # records handed over in frame order: did this one overtake older ones?
            for f, entry in st.recent.items():
                if f < fid and not entry.flagged and entry.t0p_ns > t0p:
                    entry.flagged = True
                    out.append(self._make(
                        AnomalyKind.OUT_OF_ORDER, _Where((f, fid), rec.sim_time_ns, t0p),
                        measured=float(fid - f), threshold=0.0, unit=unit,
                        detail=f"overtaken by frame {fid}'s estimate"))
        st.recent[fid] = _Seen(t0p, bool(out))
        while len(st.recent) > self.thresholds.order_memory:
            del st.recent[next(iter(st.recent))]
        st.max_frame = fid if newest is None else max(newest, fid)
        return out

    def _causality(self, violations: list[Violation], mk: _Where) -> list[Anomaly]:
        was, self._s.in_causal = self._s.in_causal, bool(violations)
        if not violations or was:
            return []
        v = max(violations, key=lambda x: x.by_ns - x.uncertainty_ns)
        return [self._make(AnomalyKind.CAUSALITY, mk, measured=v.by_ns / 1e6,
                           threshold=v.uncertainty_ns / 1e6, unit="ms", stage=v.name,
                           detail="mapped target timestamp earlier than its cause "
                                  "(clock step or bad sync?)")]

    def _deadlines(self, values: Mapping[str, Split], mk: _Where, out: list[Anomaly]) -> set[str]:
        missed = set()
        for stage, limit_ms in self.thresholds.deadline_ms.items():
            sp = values.get(stage)
            if sp is None:
                continue
            lo_ms = (sp.value_ns - sp.uncertainty_ns) / 1e6
            miss = lo_ms > limit_ms
            if miss:
                missed.add(stage)
                if not self._s.in_miss.get(stage, False):
                    out.append(self._make(AnomalyKind.DEADLINE_MISS, mk, measured=lo_ms,
                                          threshold=limit_ms, unit="ms", stage=stage))
            self._s.in_miss[stage] = miss
        return missed

    def _spikes(self, values: Mapping[str, Split], mk: _Where, out: list[Anomaly], *,
                skip: set[str], late: bool) -> None:
        t = self.thresholds
        for stage, base in self._s.base.items():
            sp = values.get(stage)
            if sp is None:
                continue
            v = sp.value_ns - sp.uncertainty_ns
            spike = False
            if len(base) >= t.spike_min_baseline:
                med, mad = median_mad(base)
                limit = med + max(t.spike_k * 1.4826 * mad, t.spike_floor_ms * 1e6)
                spike = v > limit
                if spike and not self._s.in_spike.get(stage, False) and stage not in skip and not late:
                    out.append(self._make(
                        AnomalyKind.LATENCY_SPIKE, mk, measured=v / 1e6, threshold=limit / 1e6,
                        unit="ms", stage=stage,
                        detail=f"baseline median {med / 1e6:.3f} ms, MAD {mad / 1e6:.3f} ms"))
            self._s.in_spike[stage] = spike
            base.append(sp.value_ns)

    def _jitter(self, e2e: Split | None, mk: _Where, out: list[Anomaly]) -> None:
        t = self.thresholds
        if e2e is None:
            return
        st = self._s
        st.e2e.append(e2e.value_ns)
        if len(st.e2e) < t.jitter_window:
            return
        jitter_ms = 1.4826 * median_mad(st.e2e)[1] / 1e6
        if st.in_jitter:
            st.in_jitter = jitter_ms >= t.jitter_ms * t.jitter_rearm
        elif jitter_ms > t.jitter_ms:
            st.in_jitter = True
            out.append(self._make(AnomalyKind.JITTER, mk, measured=jitter_ms, threshold=t.jitter_ms,
                                  unit="ms", stage="end_to_end",
                                  detail=f"robust std over the last {t.jitter_window} frames"))
