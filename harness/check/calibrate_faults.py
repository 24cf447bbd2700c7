"""The anomaly half of ``hil calibrate``: each injected fault must be flagged exactly
once, and each anomaly that was not injected is judged against the truth: real (and
where the time went: the target, the link or the harness's own delays) or a false
alarm (the truth shows nothing there, or it was flagged twice). Inputs as in
``hil.harness.check.calibrate_checks``; all times integer ns.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from enum import Enum
from typing import Any

from hil.harness.check.calibrate_checks import RunData, Truth
from hil.timing.anomaly import AnomalyKind


TIMING_KINDS = frozenset(k.value for k in AnomalyKind)
# An anomaly kind a fault of each sort may be flagged as (either, exactly once).
FAULT_KINDS: Mapping[str, tuple[str, ...]] = {
    "spike": ("latency_spike", "deadline_miss"), "drop": ("dropped_frame",),
    "reorder": ("out_of_order", "stale_estimate"), "clock_step": ("clock_step",),
    "malformed": ("protocol_error",)}


@dataclass(frozen=True)
class FaultCheck:
    """One injected fault: which anomalies flagged it (kind@frames); ok when exactly one."""

    fault: str
    frame_id: int | None
    flagged_by: tuple[str, ...]
    ok: bool
    note: str = ""


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


def _frames_of(ev: Mapping[str, Any]) -> set[int]:
    return set(ev.get("frame_ids") or [])


PROTOCOL_KIND = "protocol_error"


def kind_table(faults: Iterable[FaultCheck], others: Iterable[Other]) -> dict[str, dict[str, int]]:
    """Per anomaly kind: faults injected, flags where injected, real flags elsewhere
    (by cause) and false alarms. Every kind of ``AnomalyKind`` is listed."""
    table = {k: {"injected": 0, "flagged_where_injected": 0, "real_elsewhere": 0, "false_alarms": 0}
             for k in sorted(TIMING_KINDS) + [PROTOCOL_KIND]}
    for f in faults:
        base = f.fault.split(" ")[0]
        kinds = FAULT_KINDS.get(base, (PROTOCOL_KIND,))
        got = [lab.split("@")[0] for lab in f.flagged_by]
        kind = next((k for k in got if k in table), kinds[0])
        table[kind]["injected"] += 1
        table[kind]["flagged_where_injected"] += len(got)
    for o in others:
        row = table.setdefault(o.kind, {"injected": 0, "flagged_where_injected": 0, "real_elsewhere": 0,
                                        "false_alarms": 0})
        row["false_alarms" if o.cause is Cause.FALSE else "real_elsewhere"] += 1
    return table


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


def _rate_truth(e: Mapping[str, Any], truth: Truth, recs: Mapping[int, Mapping[str, Any]]) -> tuple[str, Cause]:
    """A rate below the floor is the target's if it sent too few in the window; the
    harness's if it sent enough but fewer reached the harness in it (the detector
    counts arrivals, ``t0'``: replies held up on this side, on a starved host)."""
    end, hz = int(e["harness_time_ns"]), float(e.get("threshold") or 0.0)
    window_s = 2.0  # the detector's default window
    start = end - window_s * 1e9
    sent = sum(1 for tl in truth.frames.values()
               if tl.get("send_mono_ns") is not None and start < tl["send_mono_ns"] <= end)
    text = f"the target sent {sent} estimates in the {window_s:g} s before (floor {hz:g}/s)"
    if sent < hz * window_s:
        return text, Cause.TARGET
    got = sum(1 for r in recs.values() if r.get("t0p_ns") is not None and start < r["t0p_ns"] <= end)
    if got < hz * window_s:
        return f"{text}; {got} arrived in it: held up between the target and the harness", Cause.HARNESS
    return text, Cause.FALSE


def _sync_truth(e: Mapping[str, Any], sync: Sequence[Mapping[str, Any]], max_delay_ns: int) -> tuple[str, Cause]:
    """No good clock-sync sample for the event's gap: real if every exchange that came
    back in it spent more than ``max_delay_ns`` outside the target (``delay_ns``: the
    round trip less the target's own turnaround), which is what the sync rejects:
    held up between the target and the harness. An exchange in the gap within the
    limit, or none at all (the truth keeps no sync lines), shows nothing."""
    end = int(e["harness_time_ns"])
    gap_ns = float(e.get("measured") or 0.0) * 1e9
    back = [s for s in sync if not s.get("warmup") and end - gap_ns < int(s["t4_ns"]) <= end]
    if not back:
        return "the truth shows nothing here (no exchange came back in the gap)", Cause.FALSE
    outside = sorted(int(s["delay_ns"]) for s in back)
    text = (f"{len(back)} exchanges came back in the {gap_ns / 1e9:.1f} s gap, {outside[0] / 1e6:.1f}-"
            f"{outside[-1] / 1e6:.1f} ms outside the target (limit {max_delay_ns / 1e6:g} ms)")
    if outside[0] > max_delay_ns:
        return f"{text}: held up between the target and the harness", Cause.HARNESS
    return f"{text}: the sync had exchanges within its limit there", Cause.FALSE


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
            text, cause = _rate_truth(e, truth, recs)
        elif kind == "sync_lost" and e.get("harness_time_ns") is not None:
            text, cause = _sync_truth(e, run.sync, run.sync_max_delay_ns)
        seen.add((kind, tuple(fids)))
        out.append(Other(_label(e), kind, tuple(fids), cause, text))
    return out
