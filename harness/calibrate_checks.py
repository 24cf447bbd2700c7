"""The checks of ``hil calibrate``: every figure a run reports against the truth that
the reference target (``targets/reference.py``) injected and wrote down.

Inputs: the truth file (JSON lines), the run's ``summary.json`` and the topics of its
``run.mcap`` (``/<vehicle>/pipeline``, ``/<vehicle>/clock``, ``/events``). Output:
``Check`` rows (figure, reported, truth, error, bound, pass) and ``FaultCheck`` rows
(each injected fault: flagged exactly once?), plus notes on anomalies that were not
injected, each judged against the truth. All times are integer ns unless named _ms.

A summary percentile is checked against an interval, not a point: the reported
splits are over a subset of the frames (the harness may leave some out), each
within its stated uncertainty ``U``. If ``k`` of the ``N`` true values are left out,
the reported q-th percentile lies between the percentile of the ``N − k`` smallest
and of the ``N − k`` largest true values, widened by ``U``: a sure bound whatever
frames were left out.
"""

from __future__ import annotations

import json
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from enum import Enum
from typing import Any

import numpy as np

from timing.anomaly import AnomalyKind
from timing.errors import ConfigError

RESOLUTION_NS = 1  # the reference clock's resolution
ROUNDING_MS = 1e-4  # summary.json rounds milliseconds to 4 decimals
QUANTILES = (("min", 0.0), ("p50", 50.0), ("p90", 90.0), ("p99", 99.0), ("max", 100.0))
TIMING_KINDS = frozenset(k.value for k in AnomalyKind)
# An anomaly kind a fault of each sort may be flagged as (either, exactly once).
FAULT_KINDS: Mapping[str, tuple[str, ...]] = {
    "spike": ("latency_spike", "deadline_miss"), "drop": ("dropped_frame",),
    "reorder": ("out_of_order", "stale_estimate"), "clock_step": ("clock_step",),
    "malformed": ("protocol_error",)}


@dataclass
class Truth:
    """What the reference target injected. ``frames``: frame id → its truth line."""

    offset_ns: int
    skew_ppm: float
    base_ns: int
    faults: dict[str, Any]
    frames: dict[int, dict[str, Any]] = field(default_factory=dict)
    skipped: set[int] = field(default_factory=set)
    step_at_mono_ns: int | None = None
    step_ns: int = 0
    malformed: list[dict[str, Any]] = field(default_factory=list)

    def offset_at(self, mono_ns: int) -> int:
        """True offset (target − harness, ns) at a harness monotonic instant."""
        off = self.offset_ns + round((mono_ns - self.base_ns) * self.skew_ppm * 1e-6)
        if self.step_at_mono_ns is not None and mono_ns >= self.step_at_mono_ns:
            off += self.step_ns
        return off


def load_truth(path: Path) -> Truth:
    """Read the reference target's truth file.

    Raises:
        ConfigError: missing, empty or malformed (names the line).
    """
    try:
        lines = path.read_text(encoding="utf-8").splitlines()
    except OSError as err:
        raise ConfigError(f"truth file {path}: {err.strerror or err}") from err
    truth: Truth | None = None
    for n, text in enumerate(lines, 1):
        try:
            d = json.loads(text)
            kind = d["kind"]
            if kind == "config":
                truth = Truth(int(d["offset_ns"]), float(d["skew_ppm"]), int(d["base_ns"]), dict(d["faults"]))
                continue
            if truth is None:
                raise ValueError("the first line must be the config line")
            if kind == "frame":
                truth.frames[int(d["frame_id"])] = d
            elif kind == "skipped":
                truth.skipped.add(int(d["frame_id"]))
            elif kind == "step":
                truth.step_at_mono_ns, truth.step_ns = int(d["at_mono_ns"]), int(d["step_ns"])
            elif kind == "malformed":
                truth.malformed.append(d)
            else:
                raise ValueError(f"unknown line kind {kind!r}")
        except (ValueError, KeyError, TypeError) as err:
            raise ConfigError(f"truth file {path}, line {n}: {err}") from err
    if truth is None:
        raise ConfigError(f"truth file {path}: no config line (did the reference target start?)")
    return truth


@dataclass(frozen=True)
class Check:
    """One figure: the reported value, the truth, the error and its bound (``unit``)."""

    figure: str
    reported: float | None
    truth: float | None
    error: float | None
    bound: float | None
    ok: bool
    unit: str
    note: str = ""


@dataclass(frozen=True)
class FaultCheck:
    """One injected fault: which anomalies flagged it (kind@frames); ok when exactly one."""

    fault: str
    frame_id: int | None
    flagged_by: tuple[str, ...]
    ok: bool
    note: str = ""


def _pct(sorted_ms: np.ndarray, q: float) -> float:
    return float(np.percentile(sorted_ms, q)) if sorted_ms.size else float("nan")


def quantile_checks(name: str, reported: Mapping[str, Any], true_ns: Sequence[int], *,
                    bound_ms: float) -> list[Check]:
    """Each reported quantile against the interval the truth allows (module doc)."""
    n = int(reported.get("count", 0) or 0)
    x = np.sort(np.asarray(true_ns, dtype=np.float64) / 1e6)
    if n == 0:
        return [Check(f"{name}", None, None, None, None, x.size == 0, "ms",
                      "nothing reported" + (f" for {x.size} true values" if x.size else ""))]
    k = x.size - n
    if k < 0:
        return [Check(f"{name} count", float(n), float(x.size), float(-k), 0.0, False, "frames",
                      "more values reported than frames answered")]
    out = []
    for label, q in QUANTILES:
        rep = reported.get(f"{label}_ms")
        if rep is None:
            continue
        lo, hi = _pct(x[:n], q), _pct(x[k:], q)
        b = bound_ms + ROUNDING_MS
        err = 0.0 if lo <= rep <= hi else (rep - hi if rep > hi else rep - lo)
        truth = (lo + hi) / 2
        note = f"truth {lo:.4f}..{hi:.4f} over {x.size} frames, {k} left out" if k else ""
        out.append(Check(f"{name} {label}", float(rep), truth, err, b, abs(err) <= b, "ms", note))
    return out


def per_frame_check(name: str, errors_ns: Sequence[int], bounds_ns: Sequence[int],
                    reported_ns: Sequence[int], truth_ns: Sequence[int]) -> Check:
    """The worst frame (largest error relative to its bound) of a per-frame figure."""
    if not errors_ns:
        return Check(name, None, None, None, None, False, "ms", "no frames to check")
    ratio = [abs(e) / max(b, 1) for e, b in zip(errors_ns, bounds_ns)]
    i = int(np.argmax(ratio))
    bad = sum(1 for r in ratio if r > 1)
    note = f"{len(errors_ns)} frames" + (f", {bad} outside their bound" if bad else ", all inside")
    return Check(name, reported_ns[i] / 1e6, truth_ns[i] / 1e6, errors_ns[i] / 1e6, bounds_ns[i] / 1e6,
                 bad == 0, "ms", f"worst frame; {note}")


class Cause(str, Enum):
    """Where the truth puts an anomaly that was not injected."""

    TARGET = "target"    # the target really was late or skipped a frame
    LINK = "link"        # the frame or reply really took long on the way
    HARNESS = "harness"  # the harness's own delay (render to send, receipt stamping)
    UNKNOWN = "unknown"  # real, over many frames (jitter)
    FALSE = "false"      # the truth shows nothing there: a false alarm


@dataclass(frozen=True)
class Other:
    """An anomaly that was not injected, judged against the truth."""

    label: str
    kind: str
    frame_ids: tuple[int, ...]
    cause: Cause
    text: str

    def __str__(self) -> str:
        verdict = "FALSE ALARM" if self.cause is Cause.FALSE else f"real ({self.cause.value})"
        return f"{self.label}: {verdict}: {self.text}"


@dataclass
class RunData:
    """What the harness reported for one vehicle: its summary and MCAP topics."""

    summary: dict[str, Any]
    pipeline: list[dict[str, Any]]
    clock: list[dict[str, Any]]
    events: list[dict[str, Any]]


def clock_checks(truth: Truth, run: RunData) -> list[Check]:
    """Offset (every clock state and the summary) and skew against the truth."""
    out: list[Check] = []
    errs, bounds, reps, trues = [], [], [], []
    for st in run.clock:
        if not st.get("samples_used"):
            continue
        t = truth.offset_at(int(st["ref_ns"]))
        errs.append(int(st["offset_ns"]) - t)
        bounds.append(int(st["uncertainty_ns"]) + 1 + RESOLUTION_NS)
        reps.append(int(st["offset_ns"]))
        trues.append(t)
    c = per_frame_check("clock offset, each state", errs, bounds, reps, trues)
    out.append(Check(c.figure, c.reported, c.truth, c.error, c.bound, c.ok, c.unit,
                     c.note.replace("frames", "clock states").replace("worst frame", "worst state")))
    clk = run.summary.get("clock") or {}
    if clk.get("offset_ns") is not None:
        ref = clk.get("ref_ns")
        note = ""
        if ref is None and run.clock:
            ref, note = run.clock[-1]["ref_ns"], "summary gives no instant: taken at the last clock state's"
        t = truth.offset_at(int(ref)) if ref is not None else None
        err = None if t is None else int(clk["offset_ns"]) - t
        b = int(clk.get("uncertainty_ns") or 0) + 1 + RESOLUTION_NS
        out.append(Check("clock offset, summary", clk["offset_ns"] / 1e6, None if t is None else t / 1e6,
                         None if err is None else err / 1e6, b / 1e6, err is not None and abs(err) <= b, "ms", note))
    skew, su = clk.get("skew_ppm"), clk.get("skew_uncertainty_ppm")
    if skew is not None and su is not None:
        err = float(skew) - truth.skew_ppm
        out.append(Check("clock skew, summary", float(skew), truth.skew_ppm, err, float(su) + 0.001,
                         abs(err) <= float(su) + 0.001, "ppm"))
    bad = [s for s in run.clock if s.get("samples_used")
           and abs(float(s["skew_ppm"]) - truth.skew_ppm) > float(s["skew_uncertainty_ppm"]) + 0.001]
    out.append(Check("clock skew, each state", None, truth.skew_ppm, None, None, not bad, "ppm",
                     f"{len(bad)} of {len(run.clock)} states outside their bound" if bad else
                     f"{len(run.clock)} states, all inside"))
    return out


def _answered(truth: Truth, run: RunData) -> list[tuple[dict[str, Any], dict[str, Any]]]:
    """(pipeline record, truth line) of every frame answered in time and applied."""
    out = []
    for rec in run.pipeline:
        tl = truth.frames.get(int(rec["frame_id"]))
        if rec.get("status") == "ok" and tl is not None and tl.get("send_mono_ns") is not None \
                and rec.get("t0p_ns") is not None and rec.get("t_infer_end_target_ns") is not None:
            out.append((rec, tl))
    return out


def duration_checks(truth: Truth, run: RunData) -> list[Check]:
    """Target-side durations (inference, transport) per frame and in the summary; the
    split of the transport (uplink, downlink) in the summary; receipt lag per frame."""
    clk = run.summary.get("clock") or {}
    rate_ppm = abs(float(clk.get("skew_ppm") or 0.0)) + float(clk.get("skew_uncertainty_ppm") or 0.0)
    pairs = _answered(truth, run)
    inf_rep, inf_true, tr_rep, tr_true, up, down, lag = [], [], [], [], [], [], []
    inf_b, tr_b = [], []
    for rec, tl in pairs:
        d_true = tl["infer_end_mono_ns"] - tl["infer_start_mono_ns"]
        inf_rep.append(rec["t_infer_end_target_ns"] - rec["t_infer_start_target_ns"])
        inf_true.append(d_true)
        # Target durations are reported on the target's clock, not rate-corrected:
        # the harness's own skew (± its uncertainty) bounds that error.
        inf_b.append(2 * RESOLUTION_NS + round(rate_ppm * 1e-6 * d_true))
        turn_true = tl["send_mono_ns"] - tl["rx_mono_ns"]
        tr_rep.append((rec["t0p_ns"] - rec["t_tx_ns"]) - (rec["t_reply_target_ns"] - rec["t_rx_target_ns"]))
        tr_true.append((rec["t0p_ns"] - rec["t_tx_ns"]) - turn_true)
        tr_b.append(2 * RESOLUTION_NS + round(rate_ppm * 1e-6 * turn_true))
        up.append(tl["rx_mono_ns"] - rec["t_tx_ns"])
        down.append(rec["t0p_ns"] - tl["send_mono_ns"])
        lag.append(rec["t0p_ns"] - tl["send_mono_ns"])
    out = [per_frame_check("inference, each frame", [r - t for r, t in zip(inf_rep, inf_true)], inf_b,
                           inf_rep, inf_true),
           per_frame_check("transport (round trip − turnaround), each frame",
                           [r - t for r, t in zip(tr_rep, tr_true)], tr_b, tr_rep, tr_true)]
    lat = run.summary.get("latency_ms") or {}
    if "inference" in lat:
        out += quantile_checks("inference, summary", lat["inference"], inf_true,
                               bound_ms=max(inf_b, default=0) / 1e6)
    splits = run.summary.get("splits_ms") or {}
    for name, vals in (("uplink", up), ("downlink", down)):
        rep = splits.get(name) or {}
        out += quantile_checks(f"{name} split", rep, vals, bound_ms=float(rep.get("uncertainty_max_ms") or 0.0))
    neg = [v for v in lag if v < 0]
    spread = (f"p50 {np.percentile(lag, 50) / 1e6:.3f}, p99 {np.percentile(lag, 99) / 1e6:.3f}, "
              f"max {max(lag) / 1e6:.3f} ms" if lag else "no frames")
    out.append(Check("receipt lag t0' − true send, each frame (min)", min(lag, default=0) / 1e6, 0.0,
                     min(min(lag, default=0), 0) / 1e6, 0.0, bool(lag) and not neg, "ms",
                     f"t0' must not precede the true send: {len(neg)} frames do; {spread}" if neg else spread))
    return out


def overhead(truth: Truth, run: RunData, *, clock_sync_samples: int, wall_s: float) -> dict[str, Any]:
    """The harness's own cost of measuring: how late it stamps a receipt (t0' − true
    send), how long from render to hand-off (t_tx − t0) and how much sync traffic."""
    pairs = _answered(truth, run)
    lag = [rec["t0p_ns"] - tl["send_mono_ns"] for rec, tl in pairs]
    up = [tl["rx_mono_ns"] - rec["t_tx_ns"] for rec, tl in pairs]
    c2s = [rec["t_tx_ns"] - rec["t0_ns"] for rec in run.pipeline]

    def q(v: Sequence[int]) -> dict[str, float | None]:
        if not v:
            return {"p50_ms": None, "p99_ms": None, "max_ms": None}
        return {"p50_ms": round(float(np.percentile(v, 50)) / 1e6, 4),
                "p99_ms": round(float(np.percentile(v, 99)) / 1e6, 4), "max_ms": round(max(v) / 1e6, 4)}

    clk = run.summary.get("clock") or {}
    return {"receipt_lag": q(lag), "true_uplink": q(up), "capture_to_send": q(c2s),
            "sync_exchanges": clock_sync_samples,
            "sync_exchanges_per_s": round(clock_sync_samples / wall_s, 2) if wall_s > 0 else None,
            "best_sync_round_trip_ms": None if clk.get("delay_ns") is None else round(clk["delay_ns"] / 1e6, 4)}


def _frames_of(ev: Mapping[str, Any]) -> set[int]:
    ids = set(ev.get("frame_ids") or [])
    if ev.get("frame_id") is not None:
        ids.add(int(ev["frame_id"]))
    return ids


def _is_protocol(ev: Mapping[str, Any]) -> bool:
    kind = str(ev.get("kind", ""))
    return "protocol" in kind or "malformed" in kind


def _label(ev: Mapping[str, Any]) -> str:
    fr = sorted(_frames_of(ev))
    return f"{ev['kind']}@{','.join(map(str, fr))}" if fr else str(ev["kind"])


def fault_checks(truth: Truth, run: RunData) -> tuple[list[FaultCheck], list[Other]]:
    """Each injected fault flagged exactly once; each other timing anomaly or protocol
    error judged against the truth. Returns (fault rows, the other anomalies)."""
    events = [e for e in run.events if e.get("kind") in TIMING_KINDS or _is_protocol(e)]
    used: set[int] = set()
    rows: list[FaultCheck] = []

    def claim(fault: str, fid: int | None, match: Iterable[int]) -> None:
        hits = list(match)
        used.update(hits)
        rows.append(FaultCheck(fault, fid, tuple(_label(events[i]) for i in hits), len(hits) == 1,
                               "" if len(hits) == 1 else "missed" if not hits else "flagged more than once"))

    f = truth.faults
    for fault, frames, window in (("spike", f.get("spike_frames", []), (0,)),
                                  ("drop", f.get("drop_frames", []), (0,)),
                                  ("reorder", f.get("reorder_frames", []), (0, 1))):
        for fid in frames:
            want = {fid + d for d in window}
            claim(fault, fid, (i for i, e in enumerate(events)
                               if e["kind"] in FAULT_KINDS[fault] and _frames_of(e) & want))
    if truth.step_at_mono_ns is not None:
        claim("clock_step", f.get("step_frame"), (i for i, e in enumerate(events) if e["kind"] == "clock_step"))
        step = next((e for e in events if e["kind"] == "clock_step"), None)
        if step is not None and step.get("measured") is not None:
            rows[-1] = FaultCheck(rows[-1].fault, rows[-1].frame_id, rows[-1].flagged_by, rows[-1].ok,
                                  (rows[-1].note + " " if rows[-1].note else "")
                                  + f"measured {step['measured']:+.3f} ms, injected {truth.step_ns / 1e6:+.3f} ms")
    proto = [i for i, e in enumerate(events) if _is_protocol(e)]
    counted = int((run.summary.get("link") or {}).get("protocol_errors", 0))
    for j, m in enumerate(truth.malformed):
        hit = [proto[j]] if j < len(proto) else []
        used.update(hit)
        note = "" if hit else f"not in /events (link counted {counted} protocol errors)"
        rows.append(FaultCheck(f"malformed ({m['fault']})", int(m["frame_id"]),
                               tuple(_label(events[i]) for i in hit), bool(hit), note))
    if len(proto) > len(truth.malformed):
        used.update(proto)
        rows.append(FaultCheck("malformed", None, tuple(_label(events[i]) for i in proto), False,
                               f"{len(proto)} protocol-error events for {len(truth.malformed)} malformed messages"))
    return rows, _others(truth, run, [e for i, e in enumerate(events) if i not in used])


def _true_stage_ns(stage: str, tl: Mapping[str, Any], rec: Mapping[str, Any]) -> int | None:
    """A stage's true duration for one frame: harness-clock stages are exact (the truth
    is on the same clock), target-side and cross-clock ones come from the truth."""
    if tl.get("send_mono_ns") is None or rec.get("t0p_ns") is None:
        return None
    true = {"uplink": tl["rx_mono_ns"] - rec["t_tx_ns"], "downlink": rec["t0p_ns"] - tl["send_mono_ns"],
            "inference": tl["infer_end_mono_ns"] - tl["infer_start_mono_ns"],
            "target_total": tl["send_mono_ns"] - tl["rx_mono_ns"],
            "transport": (rec["t0p_ns"] - rec["t_tx_ns"]) - (tl["send_mono_ns"] - tl["rx_mono_ns"])}
    if stage in true:
        return int(true[stage])
    v = (rec.get("stages_ns") or {}).get(stage)
    return None if v is None else int(v)


def _latency_truth(e: Mapping[str, Any], tl: Mapping[str, Any], rec: Mapping[str, Any],
                   nominal_ns: int) -> tuple[str, Cause]:
    """Whether a spike or deadline miss that was not injected really happened (the
    stage's true value at or above the limit the detector applied) and where most of
    the time went: capture → send or receipt lag (the harness), uplink (the link),
    target beyond its inference (the target)."""
    stage = str(e.get("stage") or "end_to_end")
    true = _true_stage_ns(stage, tl, rec)
    limit = e.get("threshold")
    if true is None or limit is None:
        return "the truth has no value for this frame", Cause.FALSE
    parts = {"capture→send": rec["t_tx_ns"] - rec["t0_ns"], "uplink": tl["rx_mono_ns"] - rec["t_tx_ns"],
             "target beyond its inference": tl["send_mono_ns"] - tl["rx_mono_ns"] - nominal_ns,
             "receipt lag": rec["t0p_ns"] - tl["send_mono_ns"]}
    top = max(parts, key=lambda k: parts[k])
    where = ", ".join(f"{k} {v / 1e6:.1f}" for k, v in parts.items())
    if true / 1e6 >= float(limit) - 1e-3:
        cause = {"uplink": Cause.LINK, "target beyond its inference": Cause.TARGET}.get(top, Cause.HARNESS)
        return f"true {stage} {true / 1e6:.3f} ms ≥ limit {float(limit):.3f} ms; {where} ms; most in {top}", cause
    return f"true {stage} {true / 1e6:.3f} ms < limit {float(limit):.3f} ms; {where} ms", Cause.FALSE


def _dropped_truth(fid: int, truth: Truth, recs: Mapping[int, Mapping[str, Any]]) -> tuple[str, Cause]:
    tl = truth.frames.get(fid)
    if fid in truth.skipped:
        return "the target skipped it (a newer frame came during inference)", Cause.TARGET
    if tl is None:
        return "the target never received it", Cause.LINK
    if tl.get("send_mono_ns") is None:
        return "never answered", Cause.TARGET
    if fid in recs and recs[fid].get("t0p_ns") is None:
        return "answered, but not received within the timeout", Cause.HARNESS
    return "the truth shows it answered in time", Cause.FALSE


def _rate_truth(e: Mapping[str, Any], truth: Truth) -> tuple[str, Cause]:
    end, hz = int(e["harness_time_ns"]), float(e.get("threshold") or 0.0)
    window_s = 2.0  # the detector's default window
    sent = sum(1 for tl in truth.frames.values()
               if tl.get("send_mono_ns") is not None and end - window_s * 1e9 < tl["send_mono_ns"] <= end)
    text = f"the target sent {sent} estimates in the {window_s:g} s before (floor {hz:g}/s)"
    return text, Cause.TARGET if sent < hz * window_s else Cause.FALSE


def _others(truth: Truth, run: RunData, events: list[dict[str, Any]]) -> list[Other]:
    """Anomalies that were not injected: real (the truth shows it, and where the time
    went) or false alarms (the truth shows nothing there, or flagged twice)."""
    out: list[Other] = []
    recs = {int(r["frame_id"]): r for r in run.pipeline}
    nominal = int(truth.faults.get("infer_ns", 0))
    seen: set[tuple[str, tuple[int, ...]]] = set()
    for e in events:
        kind, fids = e["kind"], sorted(_frames_of(e))
        text, cause = "the truth shows nothing here", Cause.FALSE
        if fids and (kind, tuple(fids)) in seen:
            text = "flagged again (one event per frame and kind)"
        elif kind == "dropped_frame" and fids:
            text, cause = _dropped_truth(fids[0], truth, recs)
        elif kind in ("latency_spike", "deadline_miss") and fids and fids[0] in truth.frames and fids[0] in recs:
            text, cause = _latency_truth(e, truth.frames[fids[0]], recs[fids[0]], nominal)
        elif kind == "jitter":
            text, cause = "end-to-end varied over the window (not injected)", Cause.UNKNOWN
        elif kind == "frame_rate_floor" and e.get("harness_time_ns") is not None:
            text, cause = _rate_truth(e, truth)
        seen.add((kind, tuple(fids)))
        out.append(Other(_label(e), kind, tuple(fids), cause, text))
    return out
