"""The physics never waits for a consumer (issue 24): a run process that stops
reading the physics's ring loses world states and answers, counted and flagged by
name, while the physics keeps its pace."""

from __future__ import annotations

import os
import sys
from pathlib import Path

from hil.harness.config.loading import parse_config
from hil.harness.run.driver import execute, prepare_out_dir
from tests.conftest import GL_BACKEND, read_mcap


def test_a_stuck_run_process_loses_records_and_is_named_while_physics_keeps_pace(tmp_path: Path) -> None:
    cfg = parse_config({
        "name": "stall", "duration_s": 3.0, "progress": False, "seed": 1,
        "scenario": {"name": "lead_brake", "params": {"brake_at_s": 2.0}},
        "target": {"command": [sys.executable, "-m", "hil.targets.echo", "--throttle", "0.2"],
                   "estimate_timeout_s": 5.0},
        # 1 KiB holds about half a second of this world's states and answers; the run
        # process stops reading for 2.5 s, half a second in.
        "engine": {"ring_kib": 1, "faults": {"stall_run_ms": 2500}},
    })
    r = execute(cfg, out_dir=prepare_out_dir(tmp_path / "run"), gl_backend=GL_BACKEND, install_signal_handlers=False)
    rt = r.summary["realtime"]
    lost = rt["behind"].get("run", 0)
    assert lost > 10, rt["behind"]
    assert set(rt["behind"]) == {"run"}  # the render workers kept up
    assert "consumers" in rt["lagging"] and not rt["kept_realtime"]
    # The physics did not wait for its consumer: it kept its pace over the stall.
    assert rt["achieved_factor"] > 0.95, rt
    assert r.summary["sim_time_s"] >= 2.99
    # The camera truths of the instants whose world states were lost never meet them:
    # the end of the run does not wait the 5 s estimate timeout for them (it did).
    assert r.summary["wall_time_s"] < 3.0 + 5.0, r.summary["wall_time_s"]
    events = [d for _, d in read_mcap(r.mcap_path)["/events"] if d["kind"] == "consumer_behind"]
    assert events and events[-1]["consumer"] == "run" and events[-1]["measured"] == lost
    assert r.summary["events"]["run"]["consumer_behind"] == len(events)
    check = next(c for c in r.summary["verdict"]["checks"] if c["name"] == "realtime")
    assert not check["ok"] and f"run {lost}" in check["headline"], check
    # Every frame is still accounted for: answers whose confirmation was lost are
    # recorded as applied, without t_apply.
    v = r.summary["vehicles"]["ego0"]
    assert v["estimates_applied"] + v["dropped"] + v["stale"] == v["frames_sent"]


def test_stuck_shard_processes_lose_records_and_the_run_still_ends_on_time(tmp_path: Path) -> None:
    # The same stuck consumer in each shard process: their rings lose world states too,
    # and the end of the run does not wait for the camera truths of those instants.
    cfg = parse_config({
        "name": "stall-shards", "duration_s": 3.0, "progress": False, "seed": 1,
        "scenario": {"name": "multi_vehicle", "params": {"n_vehicles": 2}},
        "target": {"command": [sys.executable, "-m", "hil.targets.echo"], "estimate_timeout_s": 5.0},
        "truth": {"visible_boxes": True},
        "engine": {"ring_kib": 1, "shards": 2, "faults": {"stall_run_ms": 2500}},
    })
    r = execute(cfg, out_dir=prepare_out_dir(tmp_path / "run"), gl_backend=GL_BACKEND, install_signal_handlers=False)
    rt = r.summary["realtime"]
    assert rt["shards"] == 2
    assert {"shard-0", "shard-1"} <= set(rt["behind"]), rt["behind"]
    assert rt["achieved_factor"] > 0.95, rt
    assert r.summary["wall_time_s"] < 3.0 + 5.0, r.summary["wall_time_s"]
    for v in r.summary["vehicles"].values():
        assert v["estimates_applied"] + v["dropped"] + v["stale"] == v["frames_sent"]


def test_physics_on_a_core_of_its_own_spins_between_steps_and_applies_controls_at_once(tmp_path: Path) -> None:
    # engine.physics_cpu: the last core here; the physics spins instead of sleeping
    # (never woken late), yet takes each control as it comes, not at its next step.
    core = max(os.sched_getaffinity(0))
    cfg = parse_config({
        "name": "spin", "duration_s": 2.0, "progress": False, "seed": 1, "physics_step_s": 0.005,
        "scenario": {"name": "lead_brake", "params": {"brake_at_s": 1.0}},
        "target": {"command": [sys.executable, "-m", "hil.targets.echo", "--throttle", "0.2"]},
        "engine": {"physics_cpu": core},
    })
    r = execute(cfg, out_dir=prepare_out_dir(tmp_path / "run"), gl_backend=GL_BACKEND, install_signal_handlers=False)
    rt = r.summary["realtime"]
    assert f"on core {core}, spinning between steps" in rt["physics_scheduling"], rt["physics_scheduling"]
    assert rt["achieved_factor"] > 0.95, rt
    # A 5 ms step: a control held to the next step would wait 2.5 ms on the mean.
    apply = r.summary["vehicles"]["ego0"]["latency_ms"]["apply_delay"]
    assert apply["count"] > 20 and apply["p50_ms"] < 1.0, apply
