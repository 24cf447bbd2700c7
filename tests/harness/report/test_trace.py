"""``hil trace``: a 4-vehicle run's Perfetto trace, decoded independently of the code
that wrote it and checked slice by slice, track by track and flow by flow against the
run's ``/<vehicle>/pipeline`` records; a killed run's truncated recording; bad input.

The decoder (``tests.harness.perfetto_reader``): protobuf's generic descriptor
machinery over Perfetto's published trace schema, not the message classes that wrote
the file. The records are read with the ``mcap`` reader directly
(``tests.conftest.read_mcap``).

Injected truth: the echo targets stamp with a clock exactly 2.5 s ahead of the
harness's, so each mapped target stamp is checked against its true harness instant
within the bound the trace states.
"""

from __future__ import annotations

import json
import sys
from collections import Counter, defaultdict
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from hil.harness.cli.main import main as hil_main
from hil.harness.config.loading import parse_config
from hil.harness.record.run_folder import RecordedEvent, RunData, read_run
from hil.harness.report.timeline import RecordedClock, build_timeline
from hil.harness.report.trace import TRACE_NAME, write_trace
from hil.harness.run.driver import execute, prepare_out_dir
from hil.timing.records import FrameStatus, PipelineRecord
from hil.timing.stats import summarize_ns
from tests.conftest import GL_BACKEND, read_mcap
from tests.harness.perfetto_reader import Decoded, Slice, decode

OFFSET_NS = 2_500_000_000  # the targets' clock: harness + 2.5 s, no skew
VEHICLES = ["ego0", "ego1", "ego2", "ego3"]


# --- a 4-vehicle run -----------------------------------------------------------------

@pytest.fixture(scope="module")
def run4(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = prepare_out_dir(tmp_path_factory.mktemp("trace") / "run")
    cfg = parse_config({
        "name": "trace4", "duration_s": 2.0, "progress": False,
        "scenario": {"name": "multi_vehicle", "params": {"n_vehicles": 4}},
        "camera": {"fps": 10.0}, "engine": {"render_workers": 2},
        "target": {"command": [sys.executable, "-m", "hil.targets.echo", "--infer-ms", "3",
                               "--clock-offset-s", str(OFFSET_NS / 1e9)]},
        # a deadline every frame of ego1 misses: a timing anomaly naming frames
        "timing": {"vehicles": {"ego1": {"deadline_ms": {"end_to_end": 0.5}}}},
        "corner_cases": {"enabled": False}})
    execute(cfg, out_dir=out, gl_backend=GL_BACKEND, install_signal_handlers=False)
    return out


@pytest.fixture(scope="module")
def traced(run4: Path) -> tuple[Decoded, dict[str, list[tuple[Any, Any]]]]:
    assert hil_main(["trace", str(run4)]) == 0
    return decode(run4 / TRACE_NAME), read_mcap(run4 / "run.mcap")


def _flows_are_whole(tr: Decoded) -> None:
    """Every flow starts on one mark, ends on another: none dangles."""
    carried: Counter[int] = Counter(f for s in tr.marks for f in s.flows)
    ended: Counter[int] = Counter(f for s in tr.marks for f in s.ends)
    assert set(carried) == set(ended) and all(n == 1 for n in ended.values())


def _by_frame(slices: list[Slice]) -> dict[int, dict[str, list[Slice]]]:
    out: dict[int, dict[str, list[Slice]]] = defaultdict(lambda: defaultdict(list))
    for s in slices:
        if "frame_id" in s.args and s.track not in ("anomalies", "mismatches", "events"):
            out[s.args["frame_id"]][s.track].append(s)
    return out


def _one(group: dict[str, list[Slice]], track: str, name: str | None = None) -> Slice:
    found = [s for s in group[track] if name is None or s.name == name]
    assert len(found) == 1, (track, name, found)
    return found[0]


def _expected_tracks(r: dict[str, Any]) -> Counter[str]:
    """The (track) marks a frame's record calls for, with how many on each."""
    c: Counter[str] = Counter({"frame": 1, "capture → send": 1, "physics": 1, f"render · worker {r['render_worker']}": 1})
    if r["t0p_ns"] is not None:
        c.update({"uplink": 1, "target queue": 1, "inference": 2, "downlink": 1})
        if r["t_apply_ns"] is not None:
            c.update({"apply": 1, "physics": 1})
    return c


def test_every_slice_track_and_flow_matches_the_pipeline_records(traced: tuple[Decoded, Any]) -> None:
    tr, msgs = traced
    # One process a vehicle, and one for the run's own events where the recording has
    # any naming no vehicle (a loaded machine may put a consumer_behind there).
    run_wide = any(d.get("vehicle") is None for _m, d in msgs["/events"])
    assert sorted(tr.processes.values()) == sorted(VEHICLES + (["run (events naming no vehicle)"] if run_wide else []))
    workers = set()
    flows_seen: dict[int, tuple[str, int]] = {}
    for v in VEHICLES:
        records = [d for _m, d in msgs[f"/{v}/pipeline"]]
        assert len(records) >= 15 and all(d["status"] in ("ok", "dropped", "stale") for d in records)
        frames = _by_frame(tr.of(v))
        assert sorted(frames) == sorted(d["frame_id"] for d in records)  # no frame more, none less
        for r in records:
            g = frames[r["frame_id"]]
            assert Counter({t: len(s) for t, s in g.items()}) == _expected_tracks(r), r["frame_id"]
            workers.add(r["render_worker"])
            whole = _one(g, "frame")
            assert whole.name == f"frame {r['frame_id']}" and whole.args["status"] == r["status"]
            assert (whole.start, whole.end) == (r["t_state_ns"], r["t_apply_ns"] or r["t0p_ns"] or r["t_tx_ns"])
            for k, val in r.items():  # every stamp of the record, as recorded
                if isinstance(val, int) and k != "render_worker":
                    assert whole.args[k] == val, k
            for stage, val in r["stages_ns"].items():
                assert whole.args[f"{stage}_ns"] == val, stage
            render = _one(g, f"render · worker {r['render_worker']}")
            assert (render.start, render.end, render.args["render_worker"]) == (r["t_state_ns"], r["t0_ns"],
                                                                                 r["render_worker"])
            cap = _one(g, "capture → send")
            assert (cap.start, cap.end) == (r["t0_ns"], r["t_tx_ns"])
            assert _one(g, "physics", "camera").start == r["t_state_ns"]
            chain = [s for t, ss in g.items() if t != "frame" for s in ss]
            if r["t0p_ns"] is not None:
                _check_target_side(r, g)
            if r["t_apply_ns"] is not None:
                ap = _one(g, "apply")
                assert (ap.start, ap.end) == (r["t0p_ns"], r["t_apply_ns"])
                applied = _one(g, "physics", "control applied")
                assert (applied.start, applied.args["sim_time_apply_ns"]) == (r["t_apply_ns"], r["sim_time_apply_ns"])
            # One flow through every slice of the frame, ended by the last to start.
            ids = {i for s in chain for i in s.flows + s.ends}
            assert len(ids) == 1 and all(s.flows + s.ends == list(ids) for s in chain), r["frame_id"]
            (flow,) = ids
            assert flow not in flows_seen, "one flow id for two frames"
            flows_seen[flow] = (v, r["frame_id"])
            enders = [s for s in chain if s.ends]
            assert len(enders) == 1 and enders[0].start == max(s.start for s in chain)
    assert workers == {0, 1}  # two render workers, each vehicle on its own one's track
    _flows_are_whole(tr)


def _check_target_side(r: dict[str, Any], g: dict[str, list[Slice]]) -> None:
    """Uplink, target queue, inference, reply, downlink: mapped stamps within their
    stated bound of the truth (the target's clock is the harness's + OFFSET_NS), the
    target's own lengths as recorded, the pieces end to end."""
    up, down = _one(g, "uplink"), _one(g, "downlink")
    queue, infer, reply = _one(g, "target queue"), _one(g, "inference", "inference"), _one(g, "inference", "reply")
    assert up.start == r["t_tx_ns"] and down.end == r["t0p_ns"]
    true_rx, true_reply = r["t_rx_target_ns"] - OFFSET_NS, r["t_reply_target_ns"] - OFFSET_NS
    assert abs(up.args["uplink_ns"] - (true_rx - r["t_tx_ns"])) <= up.args["uncertainty_ns"]
    assert abs(down.args["downlink_ns"] - (r["t0p_ns"] - true_reply)) <= down.args["uncertainty_ns"]
    # A split's bound never reaches past the trip it splits: at most the distance from
    # its value to the farther end of [0, trip] (a value a little below 0, within its
    # bound, may need a bound a little wider than the trip itself).
    span = r["t0p_ns"] - r["t_tx_ns"]
    for s, value in ((up, up.args["uplink_ns"]), (down, down.args["downlink_ns"])):
        assert 0 < s.args["uncertainty_ns"] <= max(value, span - value), (s.name, value, span)
    assert up.args["t_rx_target_ns"] == r["t_rx_target_ns"]
    assert down.args["t_reply_target_ns"] == r["t_reply_target_ns"]
    # drawn where the mapping puts them: the uplink ends at the mapped t_rx (no length when negative)
    assert up.end == r["t_tx_ns"] + max(up.args["uplink_ns"], 0)
    assert (up.args.get("negative_ns", 0) < 0) == (up.args["uplink_ns"] < 0)
    assert abs(queue.start - true_rx) <= queue.args["uncertainty_ns"]
    assert down.start == min(r["t0p_ns"] - down.args["downlink_ns"], r["t0p_ns"])
    assert (down.args.get("negative_ns", 0) < 0) == (down.args["downlink_ns"] < 0)
    # the target's own stretches: recorded lengths in the arguments, drawn at the mapped rate
    assert queue.args["target_queue_ns"] == r["stages_ns"]["target_queue"]
    assert infer.args["inference_ns"] == r["stages_ns"]["inference"]
    for s, stage in ((queue, "target_queue"), (infer, "inference")):
        assert s.end is not None
        b = abs(s.args["clock_skew_ppm"]) * 1e-6  # drawn length = target length / (1 + skew), ±1 ns each end
        tol = b / (1 - b) * r["stages_ns"][stage] + 2
        assert abs((s.end - s.start) - r["stages_ns"][stage]) <= tol, stage
    assert queue.end == infer.start and infer.end == reply.start
    assert reply.end == down.start or down.args.get("negative_ns", 0) < 0


def test_the_splits_drawn_are_the_splits_the_run_reported(run4: Path, traced: tuple[Decoded, Any]) -> None:
    """Uplink and downlink of every frame, value and bound, summarised as summary.json
    summarises the run's own: the trace maps each frame with the model the run used."""
    tr, _msgs = traced
    summary = json.loads((run4 / "summary.json").read_text())
    for v in VEHICLES:
        for stage in ("uplink", "downlink"):
            drawn = [s for s in tr.of(v) if s.track == stage and s.name == stage]
            values = np.array([s.args[f"{stage}_ns"] for s in drawn])
            bounds = np.sort([s.args["uncertainty_ns"] for s in drawn])
            want = summary["vehicles"][v]["splits_ms"][stage]
            got = summarize_ns(values)
            for key in ("count", "p50_ms", "p99_ms", "min_ms", "max_ms", "mean_ms"):
                assert got[key] == want[key], (v, stage, key)
            assert round(int(bounds[len(bounds) // 2]) / 1e6, 4) == want["uncertainty_p50_ms"], (v, stage)
            assert round(int(bounds[-1]) / 1e6, 4) == want["uncertainty_max_ms"], (v, stage)
            assert int(np.count_nonzero(values < 0)) == want["negative"], (v, stage)


def test_clock_sync_exchanges_and_models_have_their_own_tracks(traced: tuple[Decoded, Any]) -> None:
    tr, msgs = traced
    for v in VEHICLES:
        sync = [s for s in tr.of(v) if s.track == "clock sync"]
        want = sorted((d["t1_ns"], d["t4_ns"], d["offset_ns"], d["delay_ns"]) for _m, d in msgs[f"/{v}/clock_sync"])
        assert sorted((s.start, s.end, s.args["offset_ns"], s.args["delay_ns"]) for s in sync) == want
        assert len(want) >= 4
        t4s = {d["t4_ns"] for _m, d in msgs[f"/{v}/clock_sync"]}
        states = [d for _m, d in msgs[f"/{v}/clock"]]
        for track, key in (("clock offset", "offset_ns"), ("clock uncertainty", "uncertainty_ns")):
            points = [(t, val) for p, tk, t, val in tr.counters if p == v and tk == track]
            assert [val for _t, val in points] == [d[key] for d in states]  # in the order written
            assert {t for t, _val in points} <= t4s  # each at its sync sample's t4


def test_events_are_instants_linked_to_their_frames(traced: tuple[Decoded, Any]) -> None:
    tr, msgs = traced
    events = [d for _m, d in msgs["/events"]]
    assert any(d["kind"] == "deadline_miss" and d["vehicle"] == "ego1" for d in events)
    got = Counter((s.process, s.track, s.name, s.start) for s in tr.marks
                  if s.track in ("anomalies", "mismatches", "events"))
    want: Counter[tuple[str, str, str, int]] = Counter()
    for d in events:
        track = "mismatches" if d["kind"].startswith("mismatch.") else (
            "anomalies" if d["kind"] in ("deadline_miss", "jitter", "dropped_frame", "stale_estimate", "out_of_order",
                                         "frame_rate_floor", "latency_spike", "clock_step", "skew_limit",
                                         "sync_lost", "causality") else "events")
        want[(d["vehicle"], track, d["kind"], d["harness_time_ns"])] += 1
    assert got == want
    frame_of = {(s.process, f): s for s in tr.marks if s.track == "frame" for f in s.flows}
    miss = next(s for s in tr.marks if s.name == "deadline_miss")
    assert miss.ends and all((miss.process, f) in frame_of for f in miss.ends)
    assert sorted(frame_of[(miss.process, f)].args["frame_id"] for f in miss.ends) == sorted(
        int(x) for x in str(miss.args["frame_ids"]).split(", "))


def test_a_killed_run_gives_a_trace_of_what_was_recorded(run4: Path, tmp_path: Path,
                                                         capsys: pytest.CaptureFixture[str]) -> None:
    killed = tmp_path / "killed"
    killed.mkdir()
    data = (run4 / "run.mcap").read_bytes()
    (killed / "run.mcap").write_bytes(data[: int(len(data) * 0.6)])  # no summary.json: killed runs have none
    assert hil_main(["trace", str(killed), "--out", str(tmp_path / "k.trace")]) == 0
    out = capsys.readouterr().out
    assert "truncated" in out and "no summary.json" in out
    salvaged = read_run(killed).pipeline
    assert 0 < sum(map(len, salvaged.values())) < sum(map(len, read_run(run4).pipeline.values()))
    tr = decode(tmp_path / "k.trace")
    _flows_are_whole(tr)  # no flow to an event or a frame the cut left out
    for v, records in salvaged.items():
        assert sorted(s.args["frame_id"] for s in tr.of(v) if s.track == "frame") == sorted(
            r["frame_id"] for r in records)


def _one_line_error(argv: list[str], capsys: pytest.CaptureFixture[str], *needles: str) -> None:
    assert hil_main(argv) == 2
    err = capsys.readouterr().err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1 and "Traceback" not in err, err
    for n in needles:
        assert n in lines[0], lines[0]


def test_bad_input_gives_one_line_and_exit_2(run4: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    _one_line_error(["trace", str(tmp_path / "nowhere")], capsys, "nowhere", "no such file")
    empty = tmp_path / "empty"
    empty.mkdir()
    _one_line_error(["trace", str(empty)], capsys, "empty", "not a run folder")
    stub = tmp_path / "stub"
    stub.mkdir()
    (stub / "run.mcap").write_bytes((run4 / "run.mcap").read_bytes()[:12])
    _one_line_error(["trace", str(stub)], capsys, "run.mcap", "truncated")
    foreign = tmp_path / "foreign"
    foreign.mkdir()
    (foreign / "run.mcap").write_text("not a recording\n")
    _one_line_error(["trace", str(foreign)], capsys, "run.mcap", "not an MCAP file")
    blocker = tmp_path / "a-file"
    blocker.write_text("")
    _one_line_error(["trace", str(run4), "--out", str(blocker / "t.trace")], capsys, "cannot write trace",
                    "Not a directory")
    _one_line_error(["trace", str(run4), "--out", str(tmp_path / "missing" / "t.trace")], capsys,
                    "cannot write trace", "No such file")
    _one_line_error(["trace", str(run4), "--out", str(tmp_path)], capsys, "is a folder")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a-file", "empty", "foreign", "stub"]  # nothing half-written


# --- without a run: the mapping around a clock step, and frames that overlap ----------

def _rec(frame_id: int, t_tx: int, t0p: int | None = None) -> PipelineRecord:
    return PipelineRecord("ego0", frame_id, 0, t_tx - 100, t_tx, FrameStatus.OK, t0p_ns=t0p)


def _state(t: int, offset: int, *, refit: bool = True) -> tuple[int, int, dict[str, Any]]:
    return t, t // 1000, {"offset_ns": offset, "ref_ns": t if refit else t - 500, "skew_ppm": 0.0, "skew_uncertainty_ppm": 0.0,
               "uncertainty_ns": 10, "delay_ns": 20, "samples_used": 3, "synced": True}


def test_recorded_clock_maps_with_the_next_model_and_not_across_a_step() -> None:
    # Refits at 1000 and 2000 (offset 5000); outliers at 3000 and 4000 keep the old
    # model; the step to offset 9000 is confirmed at 5000.
    clock = RecordedClock([_state(1000, 5000), _state(2000, 5000), _state(3000, 5000, refit=False),
                           _state(4000, 5000, refit=False), _state(5000, 9000), _state(6000, 9000)],
                          step_times_ns=[5000])
    before, why = clock.model_for(_rec(1, 1200, 1900))
    assert before is not None and before.offset_ns == 5000 and why == ""
    assert before.to_harness(1500 + 5000).value_ns == 1500
    for inside in (_rec(2, 1900, 2100), _rec(3, 2500, 2600), _rec(4, 4900, 5100)):
        assert clock.model_for(inside) == (None, "clock_step")
    after, _ = clock.model_for(_rec(5, 5100, 5200))
    assert after is not None and after.offset_ns == 9000
    last, _ = clock.model_for(_rec(6, 7000, 7100))  # after the last sample: the last model
    assert last is not None and last.ref_ns == 6000
    assert RecordedClock([]).model_for(_rec(7, 10, 20)) == (None, "no clock model recorded")


def test_recorded_clock_takes_the_model_current_when_the_analysis_took_the_frame() -> None:
    # Models at t4 = 1000, 2000, 3000 (positions 1, 2, 3 in the file).
    clock = RecordedClock([_state(1000, 5000), _state(2000, 5100), _state(3000, 5200)])
    frame = _rec(1, 1200, 1500)
    early, _ = clock.model_for(frame, position=1)  # analysed at the next sample after its t0'
    late, _ = clock.model_for(frame, position=4)   # reached the analysis after all three
    assert early is not None and early.offset_ns == 5100
    assert late is not None and late.offset_ns == 5200


def _frames_overlapping() -> Iterator[dict[str, Any]]:
    # A target busy 30 ms per frame, frames every 10 ms: their queues overlap.
    for k in range(4):
        t_tx = 1_000_000_000 + k * 10_000_000
        rx = t_tx + 100_000 + OFFSET_NS
        start = OFFSET_NS + 1_000_000_000 + 200_000 + k * 30_000_000
        rec = PipelineRecord("ego0", k, k * 10_000_000, t_tx - 300_000, t_tx, FrameStatus.OK, rx, start,
                             start + 30_000_000, start + 30_000_100, start + 30_000_100 - OFFSET_NS + 100_000,
                             start + 30_000_100 - OFFSET_NS + 300_000, 0, t_tx - 5_000_000)
        yield {**rec.to_json(), "render_worker": 0}


def test_overlapping_frames_go_to_tracks_of_the_same_name(tmp_path: Path) -> None:
    run = RunData(run_dir=tmp_path, summary=None, summary_problem=None, meta={}, mcap_present=True,
                  truncated=False, mcap_bytes=0, messages=0, pipeline={"ego0": list(_frames_overlapping())},
                  clock_states={"ego0": [_state(900_000_000, OFFSET_NS), _state(2_000_000_000, OFFSET_NS)]})
    path = tmp_path / "t.trace"
    with open(path, "wb") as f:
        stats = write_trace(build_timeline(run), f)
    tr = decode(path)  # asserts no two slices overlap on one track
    assert stats.bytes == path.stat().st_size and stats.slices == sum(m.end is not None for m in tr.marks)
    queues = [s for s in tr.marks if s.track == "target queue"]
    assert len(queues) == 4 and len({s.uuid for s in queues}) >= 2  # same name, more than one track
    for a in queues:
        for b in queues:
            if a is not b and a.uuid == b.uuid:
                assert a.end is not None and b.end is not None and (a.end <= b.start or b.end <= a.start)
    assert [s.args["target_queue_ns"] for s in sorted(queues, key=lambda s: s.args["frame_id"])] == [
        100_000 + k * 20_000_000 for k in range(4)]


def test_what_cannot_be_placed_is_drawn_whole_and_says_why(tmp_path: Path) -> None:
    t = 1_000_000_000
    dropped = PipelineRecord("ego0", 0, 0, t, t + 100, FrameStatus.DROPPED, t_state_ns=t - 50)
    no_stamps = PipelineRecord("ego0", 1, 0, t, t + 100, FrameStatus.OK, t0p_ns=t + 900, t_apply_ns=t + 950,
                               sim_time_apply_ns=5, t_state_ns=t - 50)
    # the target's t_rx maps to 1 ms before t_tx: beyond any bound (the model's is 10 ns)
    acausal = PipelineRecord("ego0", 2, 0, t, t + 100, FrameStatus.OK, t - 1_000_000 + OFFSET_NS, None, None,
                             t + 500 + OFFSET_NS, t + 900, t + 950, 5, t - 50)
    unsynced = PipelineRecord("ego1", 0, 0, t, t + 100, FrameStatus.OK, t + 200 + OFFSET_NS, None, None,
                              t + 500 + OFFSET_NS, t + 900, t + 950, 5, t - 50)
    run = RunData(run_dir=tmp_path, summary=None, summary_problem=None, meta={}, mcap_present=True,
                  truncated=False, mcap_bytes=0, messages=0,
                  pipeline={"ego0": [r.to_json() for r in (dropped, no_stamps, acausal)],
                            "ego1": [unsynced.to_json()]},
                  clock_states={"ego0": [_state(t + 1000, OFFSET_NS)]},
                  events=[RecordedEvent(t + 2000, "collision", (), "critical",
                                        {"kind": "collision", "harness_time_ns": t + 2000, "a": "npc1", "b": "npc2"}),
                          RecordedEvent(t + 3000, "mismatch.state_mismatch", ("ego0",), "critical",
                                        {"kind": "mismatch.state_mismatch", "harness_time_ns": t + 3000,
                                         "vehicle": "ego0", "frame_ids": [1, 99]})])  # frame 99 was never drawn
    tl = build_timeline(run)
    assert tl.notes == ["ego1: no clock model recorded; its target stages are drawn unmapped"]
    path = tmp_path / "t.trace"
    with open(path, "wb") as f:
        write_trace(tl, f)
    tr = decode(path)
    _flows_are_whole(tr)
    (crash,) = [s for s in tr.marks if s.name == "collision"]
    assert (crash.process, crash.track, crash.start, crash.end) == ("run (events naming no vehicle)", "events",
                                                                    t + 2000, None)
    (mismatch,) = [s for s in tr.marks if s.track == "mismatches"]
    assert mismatch.process == "ego0" and len(mismatch.ends) == 1  # a flow to frame 1 only
    frames = {(p, fid): g for p in ("ego0", "ego1") for fid, g in _by_frame(tr.of(p)).items()}
    assert mismatch.ends[0] in _one(frames[("ego0", 1)], "frame").flows
    assert sorted(frames[("ego0", 0)]) == ["capture → send", "frame", "physics", "render"]
    assert _one(frames[("ego0", 0)], "frame").args["status"] == "dropped"
    for key, why in ((("ego0", 1), "the target gave no t_rx or t_reply"),
                     (("ego0", 2), "causality: a mapped stamp is earlier than its cause beyond its bound"),
                     (("ego1", 0), "no clock model recorded")):
        whole = _one(frames[key], "uplink", "link + target")
        assert (whole.start, whole.end, whole.args["unmapped"]) == (t + 100, t + 900, why), key
        assert not {"target queue", "inference", "downlink"} & set(frames[key])
        assert _one(frames[key], "apply").end == t + 950
