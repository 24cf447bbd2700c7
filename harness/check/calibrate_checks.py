"""The checks of ``hil calibrate``: every figure a run reports against the truth that
the reference target (``targets/reference.py``) injected and wrote down.

Inputs: the truth file (JSON lines), the run's ``summary.json`` and the topics of its
``run.mcap`` (``/<vehicle>/pipeline``, ``/<vehicle>/clock``, ``/events``). Output:
``Check`` rows (figure, reported, truth, error, bound, pass); the anomalies are
judged in ``hil.harness.check.calibrate_faults``. All times are integer ns unless named _ms.

A summary percentile is checked against an interval, not a point: the reported
splits are over a subset of the frames (the harness may leave some out), each
within its stated uncertainty ``U``. If ``k`` of the ``N`` true values are left out,
the reported q-th percentile lies between the percentile of the ``N − k`` smallest
and of the ``N − k`` largest true values, widened by ``U``: a sure bound whatever
frames were left out.
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from hil.common.errors import ConfigError

RESOLUTION_NS = 1  # the reference clock's resolution
ROUNDING_MS = 1e-4  # summary.json rounds milliseconds to 4 decimals
QUANTILES = (("min", 0.0), ("p50", 50.0), ("p90", 90.0), ("p99", 99.0), ("max", 100.0))
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


@dataclass
class RunData:
    """What the harness reported for one vehicle: its summary and MCAP topics."""

    summary: dict[str, Any]
    pipeline: list[dict[str, Any]]
    clock: list[dict[str, Any]]
    events: list[dict[str, Any]]
    sync: list[dict[str, Any]] = field(default_factory=list)  # /<vehicle>/clock_sync: every exchange
    sync_max_delay_ns: int = 50_000_000  # the run's timing.sync.max_delay_ms: slower exchanges are rejected


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
        true_ns = truth.offset_at(int(ref)) if ref is not None else None
        err_ns = None if true_ns is None else int(clk["offset_ns"]) - true_ns
        b = int(clk.get("uncertainty_ns") or 0) + 1 + RESOLUTION_NS
        out.append(Check("clock offset, summary", clk["offset_ns"] / 1e6, None if true_ns is None else true_ns / 1e6,
                         None if err_ns is None else err_ns / 1e6, b / 1e6, err_ns is not None and abs(err_ns) <= b,
                         "ms", note))
    skew, su = clk.get("skew_ppm"), clk.get("skew_uncertainty_ppm")
    if skew is not None and su is not None:
        err_ppm = float(skew) - truth.skew_ppm
        out.append(Check("clock skew, summary", float(skew), truth.skew_ppm, err_ppm, float(su) + 0.001,
                         abs(err_ppm) <= float(su) + 0.001, "ppm"))
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
