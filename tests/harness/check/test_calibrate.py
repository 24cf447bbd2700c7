"""``hil calibrate`` and the verdicts built on the reference target's injected truth.

The fast tests check the judging itself on hand-made truth (sound quantile bounds,
missed and double-flagged faults, false alarms). The slow ones run the real harness
in real time against ``hil.targets.reference``: every injected fault flagged exactly
once, no anomaly the truth does not show, every figure inside its stated bound;
and a clean 60 s run that raises no anomaly at all."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from hil.harness.check.calibrate import TRUTH_FILE, Calibration, calibrate, calibration_config
from hil.harness.check.calibrate_checks import RunData, Truth, load_truth, quantile_checks
from hil.harness.check.calibrate_faults import Cause, fault_checks, kind_table
from hil.harness.config.loading import load_config
from hil.harness.config.model import Transport
from tests.conftest import GL_BACKEND, ahead_folder, ahead_results, beside, read_mcap
from hil.common.errors import ConfigError

ROOT = Path(__file__).resolve().parents[3]
CONFIG = ROOT / "hil_configs" / "calibrate.yaml"
TIMING_KINDS = ("deadline_miss", "jitter", "dropped_frame", "stale_estimate", "out_of_order", "frame_rate_floor",
                "latency_spike", "clock_step", "skew_limit", "sync_lost", "causality")


# --- judging, on hand-made truth -------------------------------------------------


def _reported(values_ms: list[float]) -> dict[str, float]:
    import numpy as np

    return {"count": len(values_ms), "min_ms": min(values_ms), "max_ms": max(values_ms),
            **{f"p{q}_ms": float(np.percentile(values_ms, q)) for q in (50, 90, 99)}}


def test_quantile_bound_holds_whatever_frames_were_left_out():
    true_ns = [1_000_000 * (i + 1) for i in range(100)]  # 1..100 ms
    # Every frame reported, each 0.4 ms high: inside a stated 0.5 ms, outside 0.3 ms.
    high = _reported([v / 1e6 + 0.4 for v in true_ns])
    assert all(c.ok for c in quantile_checks("x", high, true_ns, bound_ms=0.5))
    assert not all(c.ok for c in quantile_checks("x", high, true_ns, bound_ms=0.3))
    # Two frames left out (the largest): exact values pass with no slack at all,
    # whichever two they were; 3 ms high fails a 0.5 ms bound.
    assert all(c.ok for c in quantile_checks("x", _reported([v / 1e6 for v in true_ns[:98]]), true_ns,
                                             bound_ms=0.0))
    assert all(c.ok for c in quantile_checks("x", _reported([v / 1e6 for v in true_ns[2:]]), true_ns,
                                             bound_ms=0.0))
    assert not all(c.ok for c in quantile_checks("x", _reported([v / 1e6 + 3 for v in true_ns[:98]]), true_ns,
                                                 bound_ms=0.5))
    # More values than frames answered cannot be right.
    assert not quantile_checks("x", {**high, "count": 101}, true_ns, bound_ms=1.0)[0].ok


def _truth(**faults) -> Truth:
    t = Truth(offset_ns=0, skew_ppm=0.0, base_ns=0, faults=faults)
    for fid in range(10):
        t.frames[fid] = {"frame_id": fid, "rx_mono_ns": 1_000 + fid * 50_000_000, "infer_start_mono_ns": 0,
                         "infer_end_mono_ns": 0, "send_mono_ns": 2_000 + fid * 50_000_000}
    return t


def _run(events, pipeline=(), sync=(), **summary) -> RunData:
    return RunData({"link": {"protocol_errors": 0}, **summary}, list(pipeline), [], events, list(sync))


def _received(truth: Truth, lag_ns: int = 100_000) -> list[dict]:
    """Pipeline records of every frame ``truth`` answered, each reply taken off the link
    ``lag_ns`` after the target sent it."""
    return [{"frame_id": fid, "t0p_ns": tl["send_mono_ns"] + lag_ns} for fid, tl in truth.frames.items()
            if tl["send_mono_ns"] is not None]


def test_fault_flagged_twice_or_never_fails():
    truth = _truth(drop_frames=[3], spike_frames=[5])
    truth.frames[3]["send_mono_ns"] = None
    twice = [{"kind": "dropped_frame", "frame_ids": [3]}, {"kind": "dropped_frame", "frame_ids": [3]},
             {"kind": "latency_spike", "frame_ids": [5]}]
    rows, others = fault_checks(truth, _run(twice))
    assert [(r.fault, r.ok) for r in rows] == [("spike", True), ("drop", False)]
    assert rows[1].note == "flagged more than once"
    table = kind_table(rows, others)
    assert table["dropped_frame"] == {"injected": 1, "flagged_where_injected": 2, "real_elsewhere": 0,
                                      "false_alarms": 0}
    assert table["latency_spike"]["flagged_where_injected"] == 1 and table["sync_lost"]["injected"] == 0
    rows, _ = fault_checks(truth, _run(twice[1:2]))
    assert [(r.fault, r.ok, r.note) for r in rows] == [("spike", False, "missed"), ("drop", True, "")]


def test_anomaly_the_truth_does_not_show_is_a_false_alarm():
    truth = _truth()
    # Frame 4 was answered within 2 µs of its send, every frame was sent: neither a
    # drop nor a rate below 10/s happened.
    events = [{"kind": "dropped_frame", "frame_ids": [4]},
              {"kind": "frame_rate_floor", "frame_ids": [], "harness_time_ns": 10 * 50_000_000, "threshold": 2.0}]
    _, others = fault_checks(truth, _run(events, pipeline=_received(truth)))
    assert [o.cause for o in others] == [Cause.FALSE, Cause.FALSE], others
    # A drop the target really made (it skipped the frame) is explained.
    truth.skipped.add(4)
    _, others = fault_checks(truth, _run(events[:1] * 2))
    assert [o.cause for o in others] == [Cause.TARGET, Cause.FALSE] and "skipped" in others[0].text
    assert "flagged again" in others[1].text


def test_a_rate_the_target_kept_but_the_harness_received_late_is_the_harnesss():
    # The target sent all 10 replies in the 2 s window ending at 0.5 s, one every 50 ms;
    # on a starved host the harness took each off the link 0.4 s later: 2 arrived in the
    # window (floor 2/s: 4 wanted). Real, and on this side of the target, not a false alarm.
    truth = _truth()
    floor = {"kind": "frame_rate_floor", "frame_ids": [], "harness_time_ns": 10 * 50_000_000, "threshold": 2.0}
    _, others = fault_checks(truth, _run([floor], pipeline=_received(truth, lag_ns=400_000_000)))
    assert [o.cause for o in others] == [Cause.HARNESS], others
    assert "10 estimates" in others[0].text and "2 arrived" in others[0].text
    # Sent too few is the target's, whatever arrived.
    for fid in range(2, 10):
        truth.frames[fid]["send_mono_ns"] = None
    _, others = fault_checks(truth, _run([floor], pipeline=_received(truth)))
    assert [o.cause for o in others] == [Cause.TARGET], others


def _exchange(t4_ns: int, outside_ns: int, turnaround_ns: int = 20_000) -> dict:
    t1 = t4_ns - outside_ns - turnaround_ns
    return {"seq": 0, "t1_ns": t1, "t2_target_ns": 7_000, "t3_target_ns": 7_000 + turnaround_ns, "t4_ns": t4_ns,
            "offset_ns": 0, "delay_ns": outside_ns, "warmup": False}


def test_sync_lost_is_real_where_every_exchange_in_the_gap_was_too_slow_outside_the_target():
    lost = {"kind": "sync_lost", "frame_ids": [], "harness_time_ns": 10_000_000_000, "measured": 3.5,
            "threshold": 3.0}
    slow = [_exchange(7_000_000_000 + k * 1_000_000_000, 80_000_000) for k in range(3)]  # 80 ms > 50 ms
    _, others = fault_checks(_truth(), _run([lost], sync=slow))
    assert [o.cause for o in others] == [Cause.HARNESS], others
    assert "3 exchanges" in others[0].text and "80.0-80.0 ms outside the target (limit 50 ms)" in others[0].text
    # One within the limit in the gap, or none back at all: the truth shows nothing.
    fast = slow[:2] + [_exchange(9_000_000_000, 1_000_000)]
    for sync in (fast, [], [_exchange(6_000_000_000, 80_000_000)]):  # the last one before the gap
        _, others = fault_checks(_truth(), _run([lost], sync=sync))
        assert [o.cause for o in others] == [Cause.FALSE], (sync, others)


def test_malformed_message_must_reach_the_events(tmp_path):
    truth = _truth()
    truth.malformed.append({"kind": "malformed", "frame_id": 2, "fault": "bad_crc"})
    rows, _ = fault_checks(truth, _run([], link={"protocol_errors": 1}))
    assert not rows[0].ok and "not in /events" in rows[0].note
    rows, _ = fault_checks(truth, _run([{"kind": "protocol_error", "detail": "payload CRC (byte 56)"}]))
    assert rows[0].ok


def test_truth_file_errors_name_the_line(tmp_path):
    p = tmp_path / TRUTH_FILE
    p.write_text('{"kind":"config","offset_ns":1,"skew_ppm":0,"base_ns":0,"faults":{}}\n{"kind":"frame"}\n')
    with pytest.raises(ConfigError, match=r"line 2"):
        load_truth(p)
    with pytest.raises(ConfigError, match="truth file"):
        load_truth(tmp_path / "missing.jsonl")


def test_only_the_reference_target_is_calibrated(tmp_path):
    demo = load_config(ROOT / "hil_configs" / "demo.yaml")
    with pytest.raises(ConfigError, match="hil.targets.reference"):
        calibration_config(demo, truth_path=tmp_path / TRUTH_FILE)
    cfg = calibration_config(load_config(CONFIG), truth_path=tmp_path / TRUTH_FILE, transport=Transport.ZENOH)
    assert cfg.target.transport == Transport.ZENOH and str(tmp_path / TRUTH_FILE) in cfg.target.args
    args = " ".join(cfg.target.args)
    assert "--transport zenoh --listen tcp/127.0.0.1:{port}" in args  # where the harness connects
    assert cfg.target.zenoh.connect == ["tcp/127.0.0.1:{port}"]
    # A harness that listens: the reference target connects to it, at the configured endpoint.
    listening = load_config(CONFIG, overrides=["target.transport=zenoh", "target.zenoh.connect=[]",
                                               'target.zenoh.listen=["tcp/127.0.0.1:7999"]'])
    args = " ".join(calibration_config(listening, truth_path=tmp_path / TRUTH_FILE).target.args)
    assert "--connect tcp/127.0.0.1:7999" in args and "--listen" not in args


@pytest.mark.parametrize("argv, says", [
    (["calibrate", "/no/such.yaml"], "config file not found"),
    (["calibrate", str(ROOT / "hil_configs" / "demo.yaml")], "hil.targets.reference"),
    (["calibrate", "--transport", "can"], "invalid choice"),
])
def test_bad_input_exits_2_with_one_line(tmp_path, argv, says):
    out = tmp_path / "out"
    p = subprocess.run([sys.executable, "-m", "hil.harness.cli.main", *argv, "--out", str(out)], cwd=ROOT,
                       capture_output=True, text=True, timeout=120)
    assert p.returncode == 2, p.stderr
    assert says in p.stderr and len(p.stderr.strip().splitlines()) == 1 and "Traceback" not in p.stderr
    assert not out.exists()  # nothing made for a bad input


# --- real runs against the reference target ----------------------------------------


def _calibrate(tmp_path: Path, *overrides: str, transport: Transport | None = None) -> Calibration:
    cfg = load_config(CONFIG, overrides=list(overrides))
    return calibrate(cfg, out_dir=tmp_path / "cal", gl_backend=GL_BACKEND, transport=transport)


def _timing_events(out: Path) -> list[dict]:
    return [d for _, d in read_mcap(out / "run.mcap")["/events"] if d["kind"] in TIMING_KINDS]


@pytest.fixture(scope="module")
def faults_run(tmp_path_factory) -> tuple[Calibration, Path]:
    tmp = tmp_path_factory.mktemp("calibrate_local")
    return _calibrate(tmp), tmp / "cal"


# The clean run only has to raise no false alarm, and it judges every anomaly against
# the reference target's truth (a delay the machine causes is explained): it runs beside
# the other tests (tests.conftest.beside), on the machine as they leave it. The runs with
# injected faults stay here: a loaded machine widens the spike detector's baseline past
# the injected spike (seen at 20 fps, where the spike had to stay under 40 ms: the
# zenoh run's spike at frame 55 missed; at 12.5 fps it is 65 ms).
CLEAN = ("duration_s=60", 'target.args=["--infer-ms", "20"]', "timing={}")
beside(__name__, "clean_run", _calibrate, ahead_folder("calibrate-clean"), *CLEAN)


@pytest.fixture(scope="module")
def clean_run() -> tuple[Calibration, Path]:
    (cal,) = ahead_results(__name__, "clean_run")
    return cal, ahead_folder("calibrate-clean") / "cal"


@pytest.mark.slow
def test_every_injected_timing_fault_is_flagged_once_where_injected(faults_run):
    cal, out = faults_run
    timing = [f for f in cal.faults if not f.fault.startswith("malformed")]
    assert {f.fault for f in timing} == {"spike", "drop", "reorder", "clock_step"}
    assert all(f.ok for f in timing), [(f.fault, f.flagged_by, f.note) for f in timing]
    events = _timing_events(out)
    by_kind = {k: [e for e in events if e["kind"] == k] for k in TIMING_KINDS}
    assert [e.get("frame_ids") or [e.get("frame_id")] for e in by_kind["dropped_frame"]
            if 12 in (e.get("frame_ids") or [e.get("frame_id")])] == [[12]]
    assert len(by_kind["clock_step"]) == 1
    # Never where not injected: whatever else was flagged, the truth shows it really
    # happened (a frame the target skipped, a latency really over the limit).
    assert cal.others_explained, [str(o) for o in cal.others]
    for kind in ("causality", "skew_limit", "sync_lost", "frame_rate_floor", "out_of_order", "jitter"):
        assert not by_kind[kind], (kind, by_kind[kind])


@pytest.mark.slow
def test_every_reported_figure_lies_inside_its_stated_bound(faults_run):
    cal, out = faults_run
    bad = [c for c in cal.checks if not c.ok]
    assert not bad, bad
    saved = json.loads((out / "calibration.json").read_text())
    assert saved["checks"] and saved["overhead"]["receipt_lag"]["p50_ms"] is not None


@pytest.mark.slow
def test_each_malformed_message_is_one_event(faults_run):
    cal, _ = faults_run
    malformed = [f for f in cal.faults if f.fault.startswith("malformed")]
    assert len(malformed) == 2 and all(f.ok for f in malformed), malformed


@pytest.mark.slow
def test_calibrate_over_zenoh_loopback(tmp_path):
    cal = _calibrate(tmp_path, transport=Transport.ZENOH)
    assert cal.transport == "zenoh" and cal.run_ok
    assert all(c.ok for c in cal.checks), [c for c in cal.checks if not c.ok]
    assert all(f.ok for f in cal.faults), cal.faults
    assert cal.others_explained, [str(o) for o in cal.others]


@pytest.mark.slow
def test_clean_run_raises_no_anomaly_at_default_thresholds(clean_run):
    # 60 s, no fault injected, default thresholds and sync. The reference target's
    # truth says whether it delivered a clean run: where this shared machine preempted
    # the target itself (a frame skipped, a reply late beyond its inference), the
    # anomalies the truth puts on the target are real and allowed, and so are those it
    # puts on the link or on the harness's own stages (counted in the calibration's
    # overhead as anomalies_from_harness_delays): how often the harness itself is late
    # is a real-time figure for bench/ (a timed pass/fail flakes on a shared 2-core
    # machine), not a verdict. None may be a false alarm.
    cal, out = clean_run
    summary = json.loads((out / "summary.json").read_text())["vehicles"]["ego0"]
    assert all(c.ok for c in cal.checks), [c for c in cal.checks if not c.ok]
    false = [str(o) for o in cal.others if o.cause is Cause.FALSE]
    assert not false, false
    if not cal.others:
        assert summary["anomalies"] == {} and _timing_events(out) == []
