"""A run as a timeline: every frame's stages, the clock-sync exchanges and the events,
placed on per-vehicle tracks (what ``hil trace`` draws; :mod:`hil.harness.report.trace`
writes it as a Perfetto trace).

Each frame of ``/<vehicle>/pipeline`` becomes, where its record has the stamps:

* ``physics``: instants ``camera`` at ``t_state`` (the physics reached the frame's
  sim time) and ``control applied`` at ``t_apply``;
* ``render · worker N``: ``[t_state, t0]`` (waiting for and rendering in render worker
  N, from the record's ``render_worker``);
* ``capture → send``: ``[t0, t_tx]`` (encode and hand-off);
* ``uplink`` ``[t_tx, t_rx]``, ``target queue`` ``[t_rx, t_infer_start]``,
  ``inference`` ``[t_infer_start, t_infer_end]`` then ``reply`` ``[t_infer_end, t_reply]``,
  ``downlink`` ``[t_reply, t0']``: target stamps mapped onto the harness clock with the
  model the run recorded on ``/<vehicle>/clock`` (:class:`RecordedClock`), each slice
  carrying its bound (``uncertainty_ns``);
* ``apply``: ``[t0', t_apply]``;
* ``frame``: the whole trip, with every stamp and stage of the record as arguments;

all linked by one flow. ``clock sync`` holds each 4-timestamp exchange ``[t1, t4]``,
``clock offset`` / ``clock uncertainty`` the model after each; ``anomalies``,
``mismatches`` and ``events`` every ``/events`` message as an instant, linked by a flow
to each frame it names. A slice that would end before it starts (a mapped stamp
earlier than its cause, within its bound) is drawn with no length at its harness-clock
end (``t_tx`` for the uplink, ``t0'`` for the downlink) and says so in its
``negative_ns`` argument. Times: harness clock (``time.monotonic_ns``), ns.
"""

from __future__ import annotations

import math
from bisect import bisect_right
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

from hil.harness.record.run_folder import RunData, pipeline_record
from hil.timing.anomaly import AnomalyKind
from hil.timing.pipeline import causality_violations, split_stages
from hil.timing.records import PipelineRecord
from hil.timing.sync import SyncState

# Tracks of a vehicle, in display order; the render track's name adds its worker.
TRACKS = ("frame", "physics", "render", "capture → send", "uplink", "target queue", "inference", "downlink",
          "apply", "clock sync", "clock offset", "clock uncertainty", "anomalies", "mismatches", "events")
COUNTER_TRACKS = ("clock offset", "clock uncertainty")
_ANOMALY_KINDS = frozenset(k.value for k in AnomalyKind)
Arg = int | float | str | bool


@dataclass(frozen=True)
class Mark:
    """One slice (``end_ns`` set) or instant (``end_ns`` None) on ``track`` of
    ``vehicle`` (None: the whole run). ``flows``: flow ids it continues; ``ends_flows``:
    those it ends."""

    vehicle: str | None
    track: str
    name: str
    start_ns: int
    end_ns: int | None
    args: Mapping[str, Arg]
    flows: tuple[int, ...] = ()
    ends_flows: tuple[int, ...] = ()


@dataclass(frozen=True)
class CounterPoint:
    vehicle: str
    track: str
    t_ns: int
    value: int


@dataclass
class Timeline:
    """Everything to draw. ``frames``: pipeline records drawn per vehicle; ``notes``:
    what could not be drawn as recorded, for the person who runs ``hil trace``."""

    vehicles: list[str]
    marks: list[Mark] = field(default_factory=list)
    counters: list[CounterPoint] = field(default_factory=list)
    frames: dict[str, int] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)


def track_rank(track: str) -> int:
    """Display position of a track among its vehicle's (``render · worker N`` as ``render``)."""
    base = "render" if track.startswith("render") else track
    return TRACKS.index(base) if base in TRACKS else len(TRACKS)


class RecordedClock:
    """One vehicle's target-clock models as the run wrote them on ``/<vehicle>/clock``
    (one after each sync sample: ``(t4, position in the file, message)``), mapping
    with :class:`SyncState` itself.

    A frame is mapped with the model the run's timing analysis mapped it with: the
    one current when the analysis took the frame, which is when a sync sample newer
    than its ``t0'`` is in — the model of the first such sample, or, when the frame
    reached the analysis after that (``position``: its record's place in the file,
    which the analysis wrote in its own order), the last model written before it.
    Around a clock step (``step_times_ns``: when each was detected) the mapping is
    unknowable from the last refit before it to its detection: a frame in flight then
    gets no model (``"clock_step"``), as in the run's splits.
    """

    def __init__(self, states: Sequence[tuple[int, int, Mapping[str, Any]]],
                 step_times_ns: Sequence[int] = ()) -> None:
        good = [(t, i, s) for t, i, d in states if (s := _state(d)) is not None]
        self._t = [t for t, _, _ in good]
        self._pos = [i for _, i, _ in good]
        self._models = [s for _, _, s in good]
        refits = [t for t, _, s in good if s.ref_ns == t]  # a refit stamps the model with its sample's t4
        self._steps = []
        for d_ns in sorted(step_times_ns):
            k = bisect_right(refits, d_ns - 1) - 1
            self._steps.append((refits[k] if k >= 0 else 0, d_ns))

    def __len__(self) -> int:
        return len(self._models)

    def model_for(self, rec: PipelineRecord, position: int = -1) -> tuple[SyncState | None, str]:
        """The model that maps ``rec``'s target stamps, or None and why not."""
        if not self._models:
            return None, "no clock model recorded"
        lo, hi = rec.t_tx_ns, rec.t0p_ns or rec.t_tx_ns
        for since_ns, detected_ns in self._steps:
            if since_ns <= hi and lo <= detected_ns:
                return None, "clock_step"
        first_after = bisect_right(self._t, hi)
        last_before = bisect_right(self._pos, position) - 1
        return self._models[min(max(first_after, last_before), len(self._models) - 1)], ""


def _state(d: Mapping[str, Any]) -> SyncState | None:
    try:
        st = SyncState(offset_ns=int(d["offset_ns"]), ref_ns=int(d["ref_ns"]), skew_ppm=float(d["skew_ppm"]),
                       skew_uncertainty_ppm=float(d["skew_uncertainty_ppm"]),
                       uncertainty_ns=int(d["uncertainty_ns"]), delay_ns=d.get("delay_ns"),
                       samples_used=int(d.get("samples_used", 1)), synced=bool(d.get("synced", True)))
    except (KeyError, TypeError, ValueError):
        return None
    finite = all(math.isfinite(x) for x in (st.skew_ppm, st.skew_uncertainty_ppm))
    return st if st.samples_used > 0 and finite else None


def build_timeline(run: RunData) -> Timeline:
    """Everything ``run`` recorded, as marks on tracks (see the module docstring)."""
    tl = Timeline(vehicles=list(run.vehicles))
    known = set(tl.vehicles)
    frame_flows: dict[tuple[str, int], list[int]] = {}  # the flows from a frame to the events naming it
    drawn_frames = {(v, d.get("frame_id")) for v, recs in run.pipeline.items() for d in recs}
    next_flow = 1
    for ev in run.events:
        args = _event_args(ev.data)
        track = ("mismatches" if ev.kind.startswith("mismatch.") else
                 "anomalies" if ev.kind in _ANOMALY_KINDS else "events")
        t = ev.data.get("harness_time_ns")
        t_ns = t if isinstance(t, int) and not isinstance(t, bool) and t > 0 else ev.t_ns
        frames = [f for f in ev.data.get("frame_ids") or () if isinstance(f, int)]
        concerned: list[str | None] = [v for v in ev.vehicles if v in known]
        for v in concerned or [None]:
            linked = [f for f in frames if (v, f) in drawn_frames]
            flows = list(range(next_flow, next_flow + len(linked)))
            for f, flow in zip(linked, flows):
                frame_flows.setdefault((str(v), f), []).append(flow)
            next_flow += len(flows)
            tl.marks.append(Mark(v, track, ev.kind, t_ns, None, args, ends_flows=tuple(flows)))
    steps: dict[str, list[int]] = {}
    for m in tl.marks:
        if m.track == "anomalies" and m.name == AnomalyKind.CLOCK_STEP.value and m.vehicle is not None:
            steps.setdefault(m.vehicle, []).append(m.start_ns)
    for v in tl.vehicles:
        clock = RecordedClock(run.clock_states.get(v, []), steps.get(v, ()))
        drawn = 0
        positions = run.pipeline_positions.get(v, [])
        for k, d in enumerate(run.pipeline.get(v, [])):
            rec = pipeline_record(d)
            if rec is None:
                continue
            worker = d.get("render_worker")
            model = clock.model_for(rec, positions[k] if k < len(positions) else -1)
            marks = _frame_marks(rec, model, worker if isinstance(worker, int) else None, next_flow,
                                 frame_flows.get((v, rec.frame_id), []))
            tl.marks += marks
            next_flow += 1
            drawn += 1
        tl.frames[v] = drawn
        _clock_marks(tl, v, run)
        if drawn and not len(clock):
            tl.notes.append(f"{v}: no clock model recorded; its target stages are drawn unmapped")
    return tl


def _event_args(data: Mapping[str, Any]) -> dict[str, Arg]:
    out: dict[str, Arg] = {}
    for k, val in data.items():
        if isinstance(val, (bool, int, float, str)) and not (isinstance(val, float) and not math.isfinite(val)):
            out[k] = val
        elif isinstance(val, (list, tuple)) and all(isinstance(x, (int, str)) for x in val):
            out[k] = ", ".join(str(x) for x in val)
    return out


def _clock_marks(tl: Timeline, v: str, run: RunData) -> None:
    for d in run.sync_exchanges.get(v, []):
        t1, t4 = d.get("t1_ns"), d.get("t4_ns")
        if isinstance(t1, int) and isinstance(t4, int) and 0 < t1 <= t4:
            tl.marks.append(Mark(v, "clock sync", "clock sync", t1, t4, _event_args(d)))
    for t, _pos, d in run.clock_states.get(v, []):
        for track, key in (("clock offset", "offset_ns"), ("clock uncertainty", "uncertainty_ns")):
            val = d.get(key)
            if isinstance(val, int) and not isinstance(val, bool):
                tl.counters.append(CounterPoint(v, track, t, val))


def _frame_marks(rec: PipelineRecord, model: tuple[SyncState | None, str], worker: int | None, flow: int,
                 event_flows: Sequence[int]) -> list[Mark]:
    """The marks of one frame, the frame slice last; every other mark carries ``flow``."""
    v, base = rec.vehicle, {"frame_id": rec.frame_id}
    out: list[Mark] = []

    def add(track: str, name: str, start: int, end: int | None, **args: Arg) -> None:
        a: dict[str, Arg] = {**base, **args}
        if end is not None and end < start:
            a["negative_ns"] = end - start  # drawn with no length; the value is in the arguments
            end = start
        out.append(Mark(v, track, name, start, end, a, (flow,)))

    if rec.t_state_ns is not None:
        add("physics", "camera", rec.t_state_ns, None, sim_time_ns=rec.sim_time_ns)
        render = "render" if worker is None else f"render · worker {worker}"
        extra: dict[str, Arg] = {} if worker is None else {"render_worker": worker}
        add(render, "render", rec.t_state_ns, rec.t0_ns, render_ns=rec.t0_ns - rec.t_state_ns, **extra)
    add("capture → send", "capture → send", rec.t0_ns, rec.t_tx_ns, capture_to_send_ns=rec.t_tx_ns - rec.t0_ns)
    if rec.t0p_ns is not None:
        _target_marks(rec, model, add)
        if rec.t_apply_ns is not None:
            add("apply", "apply", rec.t0p_ns, rec.t_apply_ns, apply_delay_ns=rec.t_apply_ns - rec.t0p_ns)
            add("physics", "control applied", rec.t_apply_ns, None,
                **({} if rec.sim_time_apply_ns is None else {"sim_time_apply_ns": rec.sim_time_apply_ns}))
    last = max(range(len(out)), key=lambda i: (out[i].start_ns, i))
    out[last] = replace(out[last], flows=(), ends_flows=(flow,))
    stamps = {k: val for k, val in rec.to_json().items() if isinstance(val, int) and k != "frame_id"}
    stages = {f"{k}_ns": val for k, val in rec.stages_ns().items()}
    start = rec.t_state_ns if rec.t_state_ns is not None else rec.t0_ns
    end = max(t for t in (start, rec.t_tx_ns, rec.t0p_ns, rec.t_apply_ns) if t is not None)
    out.append(Mark(v, "frame", f"frame {rec.frame_id}", start, end,
                    {**base, "status": rec.status.value, **stamps, **stages}, tuple(event_flows)))
    return out


def _target_marks(rec: PipelineRecord, mapping: tuple[SyncState | None, str], add: Callable[..., None]) -> None:
    """Uplink, target queue, inference, reply and downlink of a frame whose estimate
    came back, mapped onto the harness clock; one unmapped slice when they cannot be."""
    assert rec.t0p_ns is not None
    stages = rec.stages_ns()
    target = {f"{k}_ns": stages[k] for k in ("target_queue", "inference", "target_total", "transport") if k in stages}
    if rec.t_rx_target_ns is None or rec.t_reply_target_ns is None:
        add("uplink", "link + target", rec.t_tx_ns, rec.t0p_ns, unmapped="the target gave no t_rx or t_reply",
            **target)
        return
    model, why = mapping
    if model is not None and causality_violations(rec, model):
        model, why = None, "causality: a mapped stamp is earlier than its cause beyond its bound"
    if model is None:
        add("uplink", "link + target", rec.t_tx_ns, rec.t0p_ns, unmapped=why, **target)
        return
    splits = split_stages(rec, model)
    up, down = splits["uplink"], splits["downlink"]
    clock_args: dict[str, Arg] = {"clock_offset_ns": model.offset_ns, "clock_ref_ns": model.ref_ns,
                                  "clock_skew_ppm": model.skew_ppm}

    def mapped(t_target: int | None) -> tuple[int, int] | None:
        if t_target is None:
            return None
        m = model.to_harness(t_target)
        return m.value_ns, m.uncertainty_ns

    rx, reply = mapped(rec.t_rx_target_ns), mapped(rec.t_reply_target_ns)
    start, end = mapped(rec.t_infer_start_target_ns), mapped(rec.t_infer_end_target_ns)
    assert rx is not None and reply is not None
    add("uplink", "uplink", rec.t_tx_ns, rx[0], uplink_ns=up.value_ns, uncertainty_ns=up.uncertainty_ns,
        t_rx_target_ns=rec.t_rx_target_ns, **clock_args)
    # The target's own stretches: lengths on its clock in the arguments (exact), drawn
    # between the mapped stamps, each with the larger bound of its two ends.
    last = rx
    if start is not None:
        add("target queue", "target queue", rx[0], start[0], target_queue_ns=stages["target_queue"],
            uncertainty_ns=max(rx[1], start[1]), **clock_args)
        last = start
        if end is not None:
            add("inference", "inference", start[0], end[0], inference_ns=stages["inference"],
                uncertainty_ns=max(start[1], end[1]), **clock_args)
            last = end
    name = "reply" if last is not rx else "target (no inference stamps)"
    add("inference", name, last[0], reply[0], uncertainty_ns=max(last[1], reply[1]), **clock_args)
    # A negative downlink is drawn with no length at t0' (exact), not at the mapped t_reply.
    neg: dict[str, Arg] = {"negative_ns": rec.t0p_ns - reply[0]} if reply[0] > rec.t0p_ns else {}
    add("downlink", "downlink", min(reply[0], rec.t0p_ns), rec.t0p_ns, downlink_ns=down.value_ns,
        uncertainty_ns=down.uncertainty_ns, t_reply_target_ns=rec.t_reply_target_ns, **neg, **clock_args)
