"""Corner cases refer to the run's data (issue 11 item 3, issue 19 point 3): triggers
noted during the run (nothing else kept), grouped in sim time with one cause each,
windows cut out of the finished run.mcap afterwards, bounded."""

from __future__ import annotations

import json
import sqlite3
import gc
import types
from pathlib import Path

import numpy as np
import pytest

from hil.harness.vocab.events import Event, EventBus
from hil.harness.cases.casebook import CaseRecorder, Trigger, group_cases, read_cases
from hil.harness.cases.windows import write_case_windows
from hil.harness.record.channels import register_all
from hil.harness.record.recorder import Recorder
from tests.conftest import read_mcap
from hil.common.errors import ConfigError

MS = 1_000_000
META = {"name": "r", "scenario": "stopped_car", "seed": 3, "config_hash": "h", "scenario_params": {"gap_m": 20.0}}
JPEG = b"\xff\xd8" + bytes(20_000) + b"\xff\xd9"


def mismatch(vehicle: str, kind: str, cause: str, sim_ms: int, severity: str = "warning") -> dict:
    return {"kind": f"mismatch.{kind}", "mismatch": kind, "cause": cause, "vehicle": vehicle,
            "sim_time_ns": sim_ms * MS, "severity": severity, "detail": f"{kind} {cause} at {sim_ms}",
            "entity": None}


def fake_run(run_dir: Path, *, seconds: float, events: dict[int, list[dict]], wall_per_tick_ns: int = 50 * MS,
             max_triggers: int = 4096) -> CaseRecorder:
    """A run of two vehicles at 20 fps: ground truth, camera JPEGs, events at given
    ticks; harness time runs ``wall_per_tick_ns`` per 50 ms of sim time."""
    with Recorder(run_dir / "run.mcap") as rec:
        cases = CaseRecorder(rec, run_dir, run_meta=META, history_s=1.0, after_s=2.0, trigger_kinds={"sync_lost"},
                             max_triggers=max_triggers)
        register_all(cases, ["ego0", "ego1"])
        bus = EventBus.recording_to(cases)  # as a run wires it: recorded, then the cases
        bus.subscribe(cases.on_event)
        for tick in range(int(seconds * 20)):
            sim, t = tick * 50 * MS, 1_000 * MS + tick * wall_per_tick_ns
            ents = [{"id": 0, "name": "ego0", "x_m": tick * 0.5}, {"id": 1, "name": "ego1", "x_m": 100 + tick * 0.5}]
            if tick == 0:
                ents.append({"id": 2, "name": "car1", "x_m": 40.0})  # static: never recorded again
            cases.write_json("/ground_truth", {"sim_time_ns": sim, "initial": tick == 0, "entities": ents,
                                               "egos": [], "collisions": []}, log_time_ns=t, publish_time_ns=t)
            for v in ("ego0", "ego1"):
                cases.write_image(f"/{v}/camera", JPEG + tick.to_bytes(4, "big"), fmt="jpeg",
                                  frame_id=f"{v}/camera", log_time_ns=t + 1, publish_time_ns=t + 1)
            for ev in events.get(tick, ()):
                bus.publish(Event.from_json({**ev, "harness_time_ns": t + 2}))
        cases.close()
    return cases


def test_cases_group_in_sim_time_one_cause_each(tmp_path: Path):
    events = {
        # One lasting latency mismatch: reported, escalated 1.5 s later: one case.
        20: [mismatch("ego0", "state_mismatch", "latency", 1000)],
        50: [mismatch("ego0", "state_mismatch", "latency", 2500, "critical")],
        # A perception mismatch of the same kind meanwhile: its own case.
        52: [mismatch("ego0", "state_mismatch", "perception", 2600, "critical")],
        # The same vehicle and kind 5 s later: another case.
        150: [mismatch("ego0", "state_mismatch", "latency", 7500)],
        # Another vehicle at the same time: another case.
        21: [mismatch("ego1", "state_mismatch", "latency", 1050)],
        # A timing anomaly without sim time: takes the latest ground truth's.
        60: [{"kind": "sync_lost", "vehicle": "ego1", "sim_time_ns": None, "severity": "warning"}],
        61: [{"kind": "clock_step", "vehicle": "ego1"}],  # not a trigger
    }
    cases = fake_run(tmp_path, seconds=9, events=events)
    assert cases.errors == [] and cases.cases_written == 5
    rows, bad = read_cases(tmp_path)
    assert bad == []
    got = [(r["id"], r["vehicle"], r["kind"], r["cause"], r["severity"], r["events"], r["sim_time_ns"] // MS)
           for r in sorted(rows, key=lambda r: r["id"])]
    assert got == [(1, "ego0", "mismatch.state_mismatch", "latency", "critical", 2, 1000),
                   (2, "ego1", "mismatch.state_mismatch", "latency", "warning", 1, 1050),
                   (3, "ego0", "mismatch.state_mismatch", "perception", "critical", 1, 2600),
                   (4, "ego0", "mismatch.state_mismatch", "latency", "warning", 1, 7500),
                   (5, "ego1", "sync_lost", None, "warning", 1, 3000)]  # timing cases after mismatch cases
    first = rows[0]
    assert "2 events over 1.50 s of sim time" in first["summary"]
    assert first["event"]["severity"] == "critical"  # the case shows its most severe event
    assert (first["window_start_ns"], first["window_end_ns"]) == (0, 4500 * MS)
    assert first["mcap_path"] == "run.mcap"


def test_grouping_does_not_depend_on_machine_speed_or_order():
    ts = [Trigger("ego0", "mismatch.x", "latency", s * MS, h, "warning", {"detail": str(s)})
          for s, h in ((100, 5), (1900, 9), (4000, 1), (4100, 2))]
    a = group_cases(ts, join_ns=2000 * MS)
    # Harness times scrambled (another machine), triggers in another order: same cases.
    ts2 = [Trigger(t.vehicle, t.kind, t.cause, t.sim_time_ns, 10**12 - t.harness_time_ns, t.severity, t.event)
           for t in reversed(ts)]
    b = group_cases(ts2, join_ns=2000 * MS)
    assert [[t.sim_time_ns for t in c.triggers] for c in a] == [[t.sim_time_ns for t in c.triggers] for c in b] \
        == [[100 * MS, 1900 * MS], [4000 * MS, 4100 * MS]]


def held_bytes(obj: object, *, skip: object) -> int:
    """Bytes of the binary payloads (bytes, arrays) reachable from ``obj``, not
    looking into ``skip`` (the run's own Recorder)."""
    seen, todo, total = {id(skip)}, [obj], 0
    while todo:
        o = todo.pop()
        if id(o) in seen or isinstance(o, (type, types.ModuleType, types.FunctionType)):
            continue
        seen.add(id(o))
        if isinstance(o, (bytes, bytearray, memoryview)):
            total += len(o)
        elif isinstance(o, np.ndarray):
            total += o.nbytes
        else:
            todo.extend(gc.get_referents(o))
    return total


def test_nothing_is_kept_during_the_run_but_the_triggers(tmp_path: Path):
    # 30 s of two cameras (1,200 JPEGs of 20 kB) with a mismatch every second: the
    # case recorder holds no image, whatever the run length.
    events = {t: [mismatch("ego0", "missed_object", "perception", t * 50)] for t in range(0, 600, 20)}
    cases = fake_run(tmp_path, seconds=30, events=events)
    assert held_bytes(cases, skip=cases.rec) < len(JPEG)
    assert cases.cases_written == 1  # one lasting mismatch (a trigger every 1 s, joined within 2 s)
    # Triggers beyond the bound are counted and reported, never held.
    (tmp_path / "b").mkdir()
    cases = fake_run(tmp_path / "b", seconds=2, max_triggers=10,
                     events={t: [mismatch("ego0", "ghost_object", "perception", t * 50)] for t in range(40)})
    assert cases.triggers_dropped == 30 and "30 corner-case triggers" in cases.errors[0]


def test_windows_are_cut_from_the_finished_run(tmp_path: Path):
    events = {60: [mismatch("ego0", "state_mismatch", "latency", 3000)],
              120: [mismatch("ego1", "state_mismatch", "perception", 6000)]}
    fake_run(tmp_path, seconds=9, events=events)
    run_size = (tmp_path / "run.mcap").stat().st_size
    assert write_case_windows(tmp_path, limit=1) == []  # only the first case
    rows = {r["id"]: r for r in read_cases(tmp_path)[0]}
    assert rows[1]["mcap_path"] == "corner_cases/case-0001.mcap" and rows[2]["mcap_path"] == "run.mcap"
    window = read_mcap(tmp_path / rows[1]["mcap_path"])
    # Sim 2.0-5.0 s (1 s before, 2 s after): 61 ticks; only ego0's camera.
    sims = [d["sim_time_ns"] for _, d in window["/ground_truth"]]
    assert (min(sims), max(sims), len(sims)) == (2000 * MS, 5000 * MS, 61)
    assert len(window["/ego0/camera"]) == 61 and "/ego1/camera" not in window
    assert rows[1]["messages"] == sum(len(v) for v in window.values())
    # The window stands alone: its first ground truth holds every entity, the static car too.
    first = window["/ground_truth"][0][1]
    assert first["initial"] is True and {e["name"] for e in first["entities"]} == {"ego0", "ego1", "car1"}
    assert [d["kind"] for _, d in window["/events"]] == ["mismatch.state_mismatch"]
    assert (tmp_path / rows[1]["mcap_path"]).stat().st_size < run_size / 4
    # On demand, by id; an unknown id is a clear error.
    assert write_case_windows(tmp_path, case_ids=[2]) == []
    assert read_mcap(tmp_path / "corner_cases/case-0002.mcap")["/ego1/camera"]
    with pytest.raises(ConfigError, match="no corner case 7"):
        write_case_windows(tmp_path, case_ids=[7])


def test_rows_hold_what_replay_needs(tmp_path: Path):
    fake_run(tmp_path, seconds=3, events={10: [mismatch("ego0", "collision_while_safe", "perception", 500,
                                                        "critical")]})
    row = sqlite3.connect(tmp_path / "corner_cases.sqlite").execute(
        "SELECT run, scenario, seed, params, config_hash, vehicle, kind, sim_time_ns, event FROM cases").fetchone()
    assert row[:3] == ("r", "stopped_car", 3) and json.loads(row[3]) == {"gap_m": 20.0}
    assert row[4:8] == ("h", "ego0", "mismatch.collision_while_safe", 500 * MS)
    assert json.loads(row[8])["cause"] == "perception"


def test_hil_cases_shows_and_cuts_windows(tmp_path: Path):
    from tests.harness.cases.test_corner_cases import hil

    fake_run(tmp_path, seconds=4, events={30: [mismatch("ego1", "missed_object", "perception", 1500)]})
    p = hil("cases", str(tmp_path))
    assert p.returncode == 0 and "run.mcap @ 0.50-3.50 s" in p.stdout, p.stdout + p.stderr
    p = hil("cases", str(tmp_path), "--window", "1")
    assert p.returncode == 0 and "case-0001.mcap" in p.stdout, p.stdout + p.stderr
    assert read_mcap(tmp_path / "corner_cases/case-0001.mcap")["/ego1/camera"]
    p = hil("cases", str(tmp_path), "--window", "9")
    assert p.returncode == 2 and "no corner case 9" in p.stderr and "Traceback" not in p.stderr


def test_a_late_written_event_is_in_its_own_window(tmp_path: Path):
    # Events reach /events once the timing analysis of their frames is done: here
    # 3 s (60 ticks) after their sim time, past the window's end.
    fake_run(tmp_path, seconds=8, events={100: [mismatch("ego0", "state_mismatch", "latency", 2000)]})
    assert write_case_windows(tmp_path) == []
    window = read_mcap(tmp_path / "corner_cases/case-0001.mcap")
    assert [d["sim_time_ns"] for _, d in window["/events"]] == [2000 * MS]
    assert max(d["sim_time_ns"] for _, d in window["/ground_truth"]) == 4000 * MS


def test_a_window_keeps_the_run_metadata(tmp_path: Path):
    from mcap.reader import make_reader

    fake_run(tmp_path, seconds=3, events={20: [mismatch("ego0", "ghost_object", "perception", 1000)]})
    write_case_windows(tmp_path)
    with open(tmp_path / "corner_cases/case-0001.mcap", "rb") as f:
        meta = {m.name: dict(m.metadata) for m in make_reader(f).iter_metadata()}
    assert meta["case"] == {"id": "1", "vehicle": "ego0", "window_start_ns": "0", "window_end_ns": str(3000 * MS)}
    with open(tmp_path / "run.mcap", "rb") as f:
        assert {m.name for m in make_reader(f).iter_metadata()} <= set(meta)


def test_hil_cases_of_a_run_without_cases_lists_none(tmp_path: Path):
    # A clean run writes no corner_cases.sqlite; `hil cases` said "error: ... no
    # corner_cases.sqlite", exit 2, for it (README walkthrough): now it lists none, exit 0.
    from tests.harness.cases.test_corner_cases import hil

    fake_run(tmp_path, seconds=1, events={})
    assert not (tmp_path / "corner_cases.sqlite").exists()  # as a real run without cases
    p = hil("cases", str(tmp_path))
    assert p.returncode == 0 and "0 corner cases" in p.stdout, p.stdout + p.stderr
    p = hil("cases", str(tmp_path), "--window", "1")  # nothing to cut: still a mistake
    assert p.returncode == 2 and "no corner_cases.sqlite" in p.stderr and "Traceback" not in p.stderr
