"""Clock synchronisation: map a target's clock onto the harness clock (NTP/PTP style).

Each exchange gives four integer-nanosecond timestamps: ``t1`` harness send, ``t2``
target receive, ``t3`` target send, ``t4`` harness receive. From them::

    offset θ = ((t2 − t1) + (t3 − t4)) / 2     (target minus harness)
    delay  δ = (t4 − t1) − (t3 − t2)           (round trip without the target's turnaround)

Whatever the path asymmetry, the true offset at the exchange lies within ``θ ± δ/2``
(plus a few ns for clock resolution and the skew during the exchange): that half
round trip is the sample's *error bound* ``e``.

Pipeline: reject absurd samples (counted by reason) → NTP clock filter (the
minimum-delay sample of the last ``filter_size``) → weighted least-squares line
``offset(t) = a + b·(t − t_ref)`` over the filtered samples of the last ``window_s``
(weights ``1/e²``, so low-delay samples dominate).

Uncertainty is a hard bound if the offset is linear over the window: the fitted
value at ``t`` is ``Σ L_i(t)·θ_i`` with ``Σ L_i = 1``, so its error is at most
``Σ |L_i(t)|·e_i ≤ U0 + G·|t − t_ref|`` where ``U0 = Σ w_i e_i / W`` and
``G = Σ w_i |x_i| e_i / S``; ``G`` also bounds the skew error, so each sample's own
interval ``θ_i ± e_i`` carried to ``t`` at rate ``b ± G`` holds the truth too. The
reported offset is the line's value clipped into the intersection of all those
intervals, and its uncertainty the distance to the farther edge: about half the
best recent round trip plus ``G`` × the time since it. Until the fit bounds
the newest sample tighter than the prior does (few samples, short span), the rate
comes from the prior: 0 ± ``max_skew_ppm``, or after a clock step the pre-step rate
± ``max_skew_ppm`` (a step rarely changes the rate, but a restart may).
Residuals beyond their bounds (the offset is not linear: wander, small steps) widen
the bound; samples beyond ``step_k`` × it are outliers, and ``step_confirm``
consistent outliers restart the fit (a ``CLOCK_STEP`` if the jump is at least
``step_threshold_ns``).

Big values (offsets of 1e18 ns between a monotonic and a realtime clock) stay Python
ints; only residuals relative to an integer epoch go through float64.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, fields, replace
from enum import Enum

import numpy as np

from hil.common.errors import ConfigError, HilError


class NotSyncedError(HilError):
    """A mapping was asked for before any good clock sample arrived."""


@dataclass(frozen=True, kw_only=True)
class SyncConfig:
    """Clock-sync settings (all keyword-only).

    Attributes:
        window_s: sliding window of the skew fit, seconds of harness time.
        filter_size: NTP clock filter length (minimum delay of the last N samples).
        max_delay_ns: samples with a larger round-trip delay are rejected.
        step_threshold_ns: smallest offset jump reported as ``CLOCK_STEP``. A jump is
            only considered at all if it exceeds ``step_k`` × the hard error bound.
        step_k: safety factor on the hard error bound for step detection.
        step_confirm: consecutive mutually consistent outliers that confirm a step
            (one wild sample is rejected, not taken for a step).
        lost_after_s: seconds without a good sample before ``SYNC_LOST``.
        min_samples_for_skew: filtered samples needed before the skew is fitted.
        skew_limit_ppm: ``SKEW_LIMIT`` once the skew is provably beyond this.
        max_skew_ppm: prior bound on |skew| used until the fit knows better.
        resolution_ns: target clock resolution, added to every sample's error bound.
        max_points: cap on filtered samples kept in the window (bounded memory).
    """

    window_s: float = 30.0
    filter_size: int = 8
    max_delay_ns: int = 50_000_000
    step_threshold_ns: int = 1_000_000
    step_k: float = 2.0
    step_confirm: int = 2
    lost_after_s: float = 3.0
    min_samples_for_skew: int = 4
    skew_limit_ppm: float = 1000.0
    max_skew_ppm: float = 2000.0
    resolution_ns: int = 1
    max_points: int = 1024

    def __post_init__(self) -> None:
        for f in fields(self):
            v = getattr(self, f.name)
            if not isinstance(v, (int, float)) or isinstance(v, bool) or not v > 0:
                raise ConfigError(f"SyncConfig.{f.name} must be a positive number; got {v!r}")
        if self.filter_size != int(self.filter_size) or self.step_confirm != int(self.step_confirm):
            raise ConfigError("SyncConfig.filter_size and step_confirm must be whole numbers")
        if self.max_skew_ppm >= 1e5:
            raise ConfigError(f"SyncConfig.max_skew_ppm must be below 1e5; got {self.max_skew_ppm}")


@dataclass(frozen=True)
class SyncSample:
    """One 4-timestamp exchange, integer ns (``t2``/``t3`` on the target clock);
    ``seq`` is the exchange's sequence number on the wire."""

    t1_ns: int
    t2_target_ns: int
    t3_target_ns: int
    t4_ns: int
    seq: int = 0

    @property
    def offset_ns(self) -> float:
        """θ = ((t2 − t1) + (t3 − t4)) / 2, target minus harness."""
        return ((self.t2_target_ns - self.t1_ns) + (self.t3_target_ns - self.t4_ns)) / 2

    @property
    def delay_ns(self) -> int:
        """δ = (t4 − t1) − (t3 − t2)."""
        return (self.t4_ns - self.t1_ns) - (self.t3_target_ns - self.t2_target_ns)


class SyncEventKind(str, Enum):
    CLOCK_STEP = "clock_step"
    SYNC_LOST = "sync_lost"
    SYNC_REGAINED = "sync_regained"
    SKEW_LIMIT = "skew_limit"
    SAMPLE_REJECTED = "sample_rejected"


@dataclass(frozen=True)
class SyncEvent:
    """Something the sync noticed. ``measured``/``threshold`` are in ``unit``
    (ms for a step, s for lost/regained, ppm for skew, "" for a rejection)."""

    kind: SyncEventKind
    harness_time_ns: int
    measured: float = 0.0
    threshold: float = 0.0
    unit: str = ""
    detail: str = ""
    old_offset_ns: int | None = None
    new_offset_ns: int | None = None
    since_ns: int | None = None  # CLOCK_STEP: last good sample before it (harness ns)


@dataclass(frozen=True)
class Mapped:
    """A timestamp mapped onto another clock, with its error bound (both ns)."""

    value_ns: int
    uncertainty_ns: int


@dataclass(frozen=True, kw_only=True)
class SyncState:
    """A frozen snapshot of the sync model; it maps timestamps by itself.

    ``offset(t) = offset_ns + skew_ppm·1e-6·(t − ref_ns)`` (target − harness, ns) with
    error at most ``uncertainty_ns + skew_uncertainty_ppm·1e-6·|t − ref_ns|`` (+1 ns).
    ``ref_ns`` is the harness time of the latest fit update, so ``offset_ns`` and
    ``uncertainty_ns`` are current values. ``delay_ns`` is the best round trip of the
    last ``filter_size`` samples; ``samples_used`` the filtered samples in the fit.
    ``samples_used == 0`` means no model yet (mapping raises ``NotSyncedError``).
    """

    offset_ns: int = 0
    ref_ns: int = 0
    skew_ppm: float = 0.0
    skew_uncertainty_ppm: float = 0.0
    uncertainty_ns: int = 0
    delay_ns: int | None = None
    samples_used: int = 0
    synced: bool = False
    skew_fitted: bool = False
    last_sample_ns: int | None = None

    def _need_model(self) -> None:
        if self.samples_used == 0:
            raise NotSyncedError("no clock-sync sample accepted yet: run the sync warm-up first")

    def offset_at(self, t_harness_ns: int) -> int:
        """Model offset (target − harness, ns) at a harness time. Raises NotSyncedError."""
        self._need_model()
        return self.offset_ns + round(self.skew_ppm * 1e-6 * (t_harness_ns - self.ref_ns))

    def uncertainty_at(self, t_harness_ns: int) -> int:
        """Bound on the offset error (ns) at a harness time. Raises NotSyncedError."""
        self._need_model()
        grow = self.skew_uncertainty_ppm * 1e-6 * abs(t_harness_ns - self.ref_ns)
        return math.ceil(self.uncertainty_ns + grow) + 1

    def to_target(self, t_harness_ns: int) -> Mapped:
        """Harness timestamp → target clock (ns ± ns). Raises NotSyncedError."""
        return Mapped(t_harness_ns + self.offset_at(t_harness_ns), self.uncertainty_at(t_harness_ns))

    def to_harness(self, t_target_ns: int) -> Mapped:
        """Target timestamp → harness clock (ns ± ns), inverting the affine model.
        Raises NotSyncedError."""
        self._need_model()
        b = self.skew_ppm * 1e-6
        t = self.ref_ns + round((t_target_ns - self.ref_ns - self.offset_ns) / (1.0 + b))
        rate = min(abs(b) + self.skew_uncertainty_ppm * 1e-6, 0.5)
        return Mapped(t, math.ceil(self.uncertainty_at(t) / (1.0 - rate)) + 1)

    def to_json(self) -> dict[str, object]:
        return dict(self.__dict__)


@dataclass(frozen=True)
class _Point:
    """An accepted sample: harness mid time, offset (doubled, exact ints) and floats
    relative to the fit epoch."""

    seq: int
    t4_ns: int
    mid2: int      # t1 + t4
    theta2: int    # 2θ
    delay_ns: int
    err_ns: float  # hard bound on |θ − true offset at mid|
    x: float       # mid − epoch_t (ns)
    y: float       # θ − epoch_offset (ns)


class ClockSync:
    """Streaming clock-sync estimator for one target. Not thread-safe: feed it from
    one thread. Timestamps are integer ns; nothing here reads a clock."""

    def __init__(self, config: SyncConfig | None = None) -> None:
        self.config = config or SyncConfig()
        c = self.config
        self._register: deque[_Point] = deque(maxlen=int(c.filter_size))
        self._fit: deque[_Point] = deque()
        self._pending: list[_Point] = []
        self._epoch_t: int | None = None  # the fit's integer origin (harness ns) ...
        self._epoch_o = 0                 # ... and offset there (ns)
        self._seq, self._last_fit_seq, self._prior_b = 0, -1, 0.0
        self._state = SyncState()
        self._last_good_ns: int | None = None
        self._lost = self._skew_flagged = False
        self.rejected: dict[str, int] = {}  # rejected samples by reason
        self.steps = self.resyncs = 0       # reported clock steps; silent restarts

    def add(self, sample: SyncSample) -> list[SyncEvent]:
        """Feed one exchange; returns the events it caused (possibly none).

        Absurd samples (a timestamp ≤ 0, receive before send on either clock, a
        negative or too long round trip) are rejected with a ``SAMPLE_REJECTED``
        event and counted in ``rejected`` by reason; they never raise.
        """
        reason = self._why_bad(sample)
        if reason is not None:
            return self._reject(reason, sample.t4_ns if isinstance(sample.t4_ns, int) else 0)
        p = self._point(sample)
        events: list[SyncEvent] = []
        st = self._state
        if st.samples_used:
            mid = p.mid2 // 2
            dev = abs(p.theta2 - 2 * st.offset_at(mid)) / 2
            if dev > self.config.step_k * (st.uncertainty_at(mid) + p.err_ns):
                return self._outlier(p)
        if self._pending:
            self._count("outlier", len(self._pending))
            self._pending.clear()
        self._accept(p, events)
        return events

    def check(self, now_harness_ns: int) -> list[SyncEvent]:
        """Call periodically: emits ``SYNC_LOST`` once when no good sample came for
        ``lost_after_s``."""
        if self._state.samples_used == 0 or self._lost or self._last_good_ns is None:
            return []
        gap_ns = now_harness_ns - self._last_good_ns
        if gap_ns <= self.config.lost_after_s * 1e9:
            return []
        self._lost = True
        self._state = replace(self._state, synced=False)
        return [SyncEvent(SyncEventKind.SYNC_LOST, now_harness_ns, gap_ns / 1e9,
                          self.config.lost_after_s, "s", "no good clock-sync sample")]

    def state(self) -> SyncState:
        """The current model as a frozen, self-mapping snapshot."""
        return self._state

    @property
    def unconfirmed(self) -> int:
        """Samples inconsistent with the model that wait for the next ones to tell a
        wild sample from a clock step (0 when none): while any wait, the model may
        not hold after the last accepted sample."""
        return len(self._pending)

    def to_harness(self, t_target_ns: int) -> Mapped:
        """Map a target timestamp onto the harness clock. Raises NotSyncedError."""
        return self._state.to_harness(t_target_ns)

    def to_target(self, t_harness_ns: int) -> Mapped:
        """Map a harness timestamp onto the target clock. Raises NotSyncedError."""
        return self._state.to_target(t_harness_ns)

    def _why_bad(self, s: SyncSample) -> str | None:
        ts = (s.t1_ns, s.t2_target_ns, s.t3_target_ns, s.t4_ns)
        if not all(isinstance(t, int) and not isinstance(t, bool) for t in ts):
            return "non-integer timestamp"
        if min(ts) <= 0:
            return "zero or negative timestamp"
        if s.t4_ns < s.t1_ns:
            return "harness receive before send (t4 < t1)"
        if s.t3_target_ns < s.t2_target_ns:
            return "target send before receive (t3 < t2)"
        slack = self.config.max_skew_ppm * 1e-6 * (s.t3_target_ns - s.t2_target_ns)
        if s.delay_ns < -(slack + 2 * self.config.resolution_ns):
            return "negative round-trip delay"
        if s.delay_ns > self.config.max_delay_ns:
            return "delay above max_delay_ns"
        return None

    def _reject(self, reason: str, t4_ns: int) -> list[SyncEvent]:
        self._count(reason)
        events = [SyncEvent(SyncEventKind.SAMPLE_REJECTED, t4_ns, detail=reason)]
        return events + self.check(t4_ns) if t4_ns > 0 else events

    def _count(self, reason: str, n: int = 1) -> None:
        self.rejected[reason] = self.rejected.get(reason, 0) + n

    def _point(self, s: SyncSample) -> _Point:
        c, delay = self.config, max(s.delay_ns, 0)
        bmax = c.max_skew_ppm * 1e-6  # the rate may move θ during the turnaround
        err = (delay + bmax * (s.t3_target_ns - s.t2_target_ns)) / 2 * (1 + bmax) + c.resolution_ns + 1
        theta2 = (s.t2_target_ns - s.t1_ns) + (s.t3_target_ns - s.t4_ns)
        self._seq += 1
        return self._rebase(_Point(self._seq, s.t4_ns, s.t1_ns + s.t4_ns, theta2, delay, err, 0.0, 0.0))

    def _outlier(self, p: _Point) -> list[SyncEvent]:
        """A sample inconsistent with the model: a wild sample or the first sign of a
        clock step. ``step_confirm`` mutually consistent ones make a step."""
        if self._pending and not self._agree(self._pending[-1], p):
            self._count("outlier", len(self._pending))
            self._pending.clear()
        self._pending.append(p)
        if len(self._pending) < self.config.step_confirm:
            return []
        return self._step()

    def _agree(self, a: _Point, b: _Point) -> bool:
        st = self._state
        dx = abs(b.mid2 - a.mid2) / 2
        drift = st.skew_ppm * 1e-6 * (b.mid2 - a.mid2) / 2
        bound = a.err_ns + b.err_ns + st.skew_uncertainty_ppm * 1e-6 * dx
        return abs((b.theta2 - a.theta2) / 2 - drift) <= self.config.step_k * bound

    def _step(self) -> list[SyncEvent]:
        """Confirmed step: restart the filter and fit from the post-step samples,
        keeping the pre-step skew as the prior so the fit re-converges at once."""
        pending, st = self._pending, self._state
        last = pending[-1]
        old = st.offset_at(last.mid2 // 2)
        new = last.theta2 // 2
        events: list[SyncEvent] = []
        if abs(new - old) >= self.config.step_threshold_ns:
            self.steps += 1
            events.append(SyncEvent(
                SyncEventKind.CLOCK_STEP, last.t4_ns, abs(new - old) / 1e6,
                self.config.step_threshold_ns / 1e6, "ms",
                f"target clock stepped by {(new - old) / 1e6:+.3f} ms", old, new,
                self._last_good_ns))
        else:
            self.resyncs += 1
        # A step rarely changes the rate: keep it as the prior's value (not its bound,
        # which stays ± max_skew_ppm in case the target restarted at another rate).
        self._prior_b = st.skew_ppm * 1e-6 if st.skew_fitted else 0.0
        self._register.clear()
        self._fit.clear()
        self._pending, self._epoch_t, self._last_fit_seq, self._state = [], None, -1, SyncState()
        for q in pending:
            self._accept(self._rebase(q), events)
        return events

    def _rebase(self, q: _Point) -> _Point:
        """``q`` with x, y relative to the fit epoch (set by the first point)."""
        if self._epoch_t is None:
            self._epoch_t, self._epoch_o = q.mid2 // 2, q.theta2 // 2
        return replace(q, x=(q.mid2 - 2 * self._epoch_t) / 2, y=(q.theta2 - 2 * self._epoch_o) / 2)

    def _accept(self, p: _Point, events: list[SyncEvent]) -> None:
        if self._lost:
            self._lost = False
            gap = (p.t4_ns - (self._last_good_ns or p.t4_ns)) / 1e9
            events.append(SyncEvent(SyncEventKind.SYNC_REGAINED, p.t4_ns, gap,
                                    self.config.lost_after_s, "s", f"after {gap:.3f} s"))
        self._last_good_ns = p.t4_ns
        self._register.append(p)
        best = min(self._register, key=lambda q: (q.delay_ns, -q.seq))
        if best.seq > self._last_fit_seq:
            self._last_fit_seq = best.seq
            self._fit.append(best)
            horizon = best.x - self.config.window_s * 1e9
            while self._fit[0].x < horizon or len(self._fit) > self.config.max_points:
                self._fit.popleft()
            self._refit(p.t4_ns, events)
        else:
            self._state = replace(self._state, synced=True, last_sample_ns=p.t4_ns,
                                  delay_ns=min(q.delay_ns for q in self._register))

    def _refit(self, now_ns: int, events: list[SyncEvent]) -> None:
        c = self.config
        pts = self._fit
        x = np.fromiter((q.x for q in pts), np.float64, len(pts))
        y = np.fromiter((q.y for q in pts), np.float64, len(pts))
        e = np.fromiter((q.err_ns for q in pts), np.float64, len(pts))
        w = 1.0 / (e * e)
        sw = w.sum()
        xm, ym = float(w @ x) / sw, float(w @ y) / sw
        xc = x - xm
        s = float(w @ (xc * xc))
        u0 = float(w @ e) / sw
        # Prior rate (b0 ± g0) or fitted rate (b ± G): whichever bounds the newest
        # sample's time tighter.
        d = abs(float(xc[-1]))  # the newest point (points are kept in time order)
        fitted, b, g = False, self._prior_b, c.max_skew_ppm * 1e-6
        u_ref = u0 + g * float(w @ np.abs(xc)) / sw
        if len(pts) >= c.min_samples_for_skew and s > 0:
            g_fit = float(w @ (np.abs(xc) * e)) / s
            if g_fit * d < u_ref - u0 + g * d:
                fitted, g, u_ref = True, g_fit, u0
                b = float(w @ (xc * (y - ym))) / s
        excess = float((np.abs(y - (ym + b * xc)) - e - (u_ref + g * np.abs(xc))).max())
        u_ref += max(0.0, excess)  # not linear over the window (wander): widen the bound
        # At now, the truth lies in the line's interval and in every sample's own
        # interval carried forward at rate b ± g: report the intersection. Later or
        # earlier t only widens by g·|t − now| (triangle inequality), so the snapshot
        # form offset_ns ± (uncertainty_ns + g·|t − ref_ns|) stays a hard bound.
        assert self._epoch_t is not None
        now_rel = now_ns - self._epoch_t
        line_c, line_h = ym + b * (now_rel - xm), u_ref + g * abs(now_rel - xm)
        c_i, h_i = y + b * (now_rel - x), e + g * np.abs(now_rel - x)
        lo = max(float((c_i - h_i).max()), line_c - line_h)
        hi = min(float((c_i + h_i).min()), line_c + line_h)
        if lo <= hi:
            val = min(max(line_c, lo), hi)
            u_now = max(val - lo, hi - val)
        else:  # inconsistent with a line: keep the line, widened by the gap
            val, u_now = line_c, line_h + (lo - hi)
        self._state = SyncState(
            offset_ns=self._epoch_o + round(val), ref_ns=now_ns, skew_ppm=b * 1e6,
            skew_uncertainty_ppm=g * 1e6, uncertainty_ns=math.ceil(u_now) + 1,
            delay_ns=min(q.delay_ns for q in self._register), samples_used=len(pts),
            synced=not self._lost, skew_fitted=fitted, last_sample_ns=now_ns)
        if fitted:
            lim = c.skew_limit_ppm * 1e-6
            if not self._skew_flagged and abs(b) - g > lim:
                self._skew_flagged = True
                events.append(SyncEvent(SyncEventKind.SKEW_LIMIT, now_ns, b * 1e6, c.skew_limit_ppm,
                                        "ppm", f"target clock rate {b * 1e6:+.1f} ± {g * 1e6:.1f} ppm"))
            elif self._skew_flagged and abs(b) + g < lim:
                self._skew_flagged = False
