"""Scenarios through the harness: real runs with target processes, lockstep
determinism, latency profiles applied in sim time, real-time health, ``hil scenarios``."""

from __future__ import annotations

import hashlib
import json
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

from hil.harness.config.loading import parse_config
from hil.harness.run.driver import execute, prepare_out_dir
from tests.conftest import AHEAD_TIMEOUTS, GL_BACKEND, ahead, ahead_folder, ahead_results, read_mcap
from hil.common.errors import ConfigError

ROOT = Path(__file__).resolve().parents[2]
ECHO = [sys.executable, "-m", "hil.targets.echo"]
TARGET = {"command": [*ECHO, "--throttle", "0.2"], "estimate_timeout_s": 5.0}


def run(tmp: Path, **cfg: object):
    base: dict[str, object] = {"name": "t", "duration_s": 1.5, "progress": False, "seed": 1,
                               "scenario": {"name": "lead_brake", "params": {"brake_at_s": 0.5}}, "target": TARGET}
    base.update(cfg)
    return execute(parse_config(base), out_dir=prepare_out_dir(tmp), gl_backend=GL_BACKEND,
                   install_signal_handlers=False)


def hil(*args: str, timeout: float = 120) -> subprocess.CompletedProcess[str]:
    env = dict(os.environ, MUJOCO_GL=GL_BACKEND)
    return subprocess.run([sys.executable, "-m", "hil.harness.cli.main", *args], cwd=ROOT, env=env, capture_output=True,
                          text=True, timeout=timeout, check=False)


def truth_hash(mcap: Path) -> str:
    """sha256 over the exact bytes of every ground-truth message, in recorded order."""
    msgs = read_mcap(mcap)
    h = hashlib.sha256()
    for topic in sorted(t for t in msgs if t == "/ground_truth" or t.endswith("/truth")):
        for message, _ in msgs[topic]:
            h.update(topic.encode())
            h.update(message.data)
    return h.hexdigest()


# The lockstep runs below, ahead and beside the tests before them (tests/conftest.py):
# a lockstep run waits for every estimate and its sim side reads no clock.
CUT_IN = {"mode": "lockstep", "duration_s": 2.0, "target": {"command": [sys.executable, "-m", "hil.targets.cv_baseline"],
                                                            "estimate_timeout_s": 10.0},
          "scenario": {"name": "cut_in", "params": {"cut_in_at_s": 0.5, "lane_change_s": 1.0}}}
BRAKE = {"command": [*ECHO, "--brake", "1.0"], "estimate_timeout_s": 5.0}
LOGNORMAL = {"mode": "lockstep", "lockstep": {"latency": {"kind": "lognormal", "ms": 80, "sigma": 0.5, "max_ms": 300}}}
LOCKSTEP: dict[str, dict[str, object]] = {
    "cut_in": CUT_IN, "cut_in_again": CUT_IN, "cut_in_seed_2": {**CUT_IN, "seed": 2},
    "pedestrian": {"mode": "lockstep", "scenario": {"name": "pedestrian_occluded", "params": {"step_out_s": 0.6}}},
    "brake_200ms_late": {"mode": "lockstep", "target": BRAKE, "duration_s": 2.5,
                         "lockstep": {"latency": {"kind": "constant", "ms": 200}}},
    "brake_at_once": {"mode": "lockstep", "target": BRAKE, "duration_s": 2.5},
    "lognormal": LOGNORMAL, "lognormal_again": LOGNORMAL}


def lockstep_run(out: Path, name: str):
    cfg = dict(LOCKSTEP[name])
    return run(out, target={**cfg.pop("target", TARGET), **AHEAD_TIMEOUTS}, **cfg)


ahead(__name__, "lockstep", lockstep_run, [(ahead_folder(f"scenario-runs/{name}"), name) for name in LOCKSTEP])


@pytest.fixture(scope="module")
def lockstep() -> dict[str, Any]:
    return dict(zip(LOCKSTEP, ahead_results(__name__, "lockstep")))


# -- determinism -------------------------------------------------------------------


def test_lockstep_truth_trace_is_byte_identical_for_a_seed(lockstep) -> None:
    # The OpenCV baseline closes the loop: images -> AI -> control -> physics.
    a, b, c = lockstep["cut_in"], lockstep["cut_in_again"], lockstep["cut_in_seed_2"]
    for r in (a, b, c):
        assert r.summary["vehicles"]["ego0"]["dropped"] == 0
    assert truth_hash(a.mcap_path) == truth_hash(b.mcap_path)
    assert truth_hash(a.mcap_path) != truth_hash(c.mcap_path)  # the seed moves the cut-in
    msgs = read_mcap(a.mcap_path)
    truth = [d for _, d in msgs["/ego0/truth"]]
    assert [d["frame_id"] for d in truth] == list(range(40))
    assert any(b["entity"] == "cutter1" and b["visible_fraction"] > 0.5 for d in truth for b in d["boxes"])
    assert a.summary["scenario_realized"]["cut_in_at_s"] != c.summary["scenario_realized"]["cut_in_at_s"]


def test_ground_truth_records_initial_states_then_changes(lockstep) -> None:
    r = lockstep["pedestrian"]
    gts = [d for _, d in read_mcap(r.mcap_path)["/ground_truth"]]
    assert len(gts) == 30  # every camera tick
    assert gts[0]["initial"] and [e["name"] for e in gts[0]["entities"]] == ["ego0", "van1", "ped1"]
    assert gts[0]["entities"][1] == {"id": 1, "name": "van1", "cls": "vehicle", "x_m": gts[0]["entities"][1]["x_m"],
                                     "y_m": -5.0, "vx_mps": 0.0, "vy_mps": 0.0, "heading_rad": 0.0,
                                     "size_m": [5.0, 2.0, 2.3], "sim_time_ns": 0}
    later = [[e["name"] for e in g["entities"]] for g in gts[1:]]
    assert all(not g["initial"] for g in gts[1:])
    assert later[2] == ["ego0"] and later[-1] == ["ego0", "ped1"]  # the van never moves; the pedestrian starts
    assert all(g["egos"][0]["ref_state"] in ("SAFE", "SLOW", "STOP") for g in gts)


# -- latency profiles in lockstep ------------------------------------------------------


def _applied(r) -> dict[int, int]:
    """frame_id -> sim-time latency of application (ns) for applied frames."""
    return {d["frame_id"]: d["sim_time_apply_ns"] - d["sim_time_ns"]
            for _, d in read_mcap(r.mcap_path)["/ego0/pipeline"] if d["status"] == "ok"}


def test_constant_latency_delays_control_in_sim_time(lockstep) -> None:
    slow, quick = lockstep["brake_200ms_late"], lockstep["brake_at_once"]
    lat = _applied(slow)
    assert len(lat) == 50 - 4 and set(lat.values()) == {200_000_000}  # 4 frames were due after the end
    v = slow.summary["vehicles"]["ego0"]
    assert v["estimates_applied"] == 46 and v["frames_accounted"] == 50
    pend = [d for _, d in read_mcap(slow.mcap_path)["/ego0/pipeline"] if d["status"] == "pending"]
    assert [d["frame_id"] for d in pend] == [46, 47, 48, 49]
    assert set(_applied(quick).values()) == {0}
    # The physical consequence: 200 ms more at 10 m/s before braking.
    late, now = (r.summary["vehicles"]["ego0"]["outcome"] for r in (slow, quick))
    assert late["final_speed_mps"] < 0.1 and now["final_speed_mps"] < 0.1
    assert late["final_gap_m"] == pytest.approx(now["final_gap_m"] - 10.0 * 0.2, abs=0.2)
    assert slow.summary["latency_profile"] == {"kind": "constant", "ms": 200.0}


def test_distribution_latency_is_seeded_and_bounded(lockstep) -> None:
    a, b = _applied(lockstep["lognormal"]), _applied(lockstep["lognormal_again"])
    assert a == b
    vals = sorted(set(a.values()))
    assert len(vals) > 5 and 0 < vals[0] and vals[-1] <= 300_000_000
    assert all(v % 2_000_000 == 0 for v in vals)  # applied on the physics step grid


def test_recorded_latencies_replay_frame_by_frame(tmp_path: Path) -> None:
    # A real-time run whose target takes ~40 ms: latencies with physical consequences.
    rec = run(tmp_path / "rt", target={"command": [*ECHO, "--infer-ms", "40", "--throttle", "0.2"]})
    recorded = _applied(rec)
    assert recorded and max(recorded.values()) >= 40_000_000
    replay = run(tmp_path / "replay", mode="lockstep",
                 lockstep={"latency": {"kind": "recorded", "path": str(rec.out_dir)}})
    replayed = _applied(replay)
    assert {k: v for k, v in replayed.items() if k in recorded} == {
        k: v for k, v in recorded.items() if k in replayed}
    assert len(replayed) >= len(recorded) - 3
    with pytest.raises(ConfigError, match="lockstep.latency.path"):
        parse_config({"mode": "lockstep", "lockstep": {"latency": {"kind": "recorded",
                                                                    "path": str(tmp_path / "nope")}}})


def test_latency_profile_needs_lockstep() -> None:
    with pytest.raises(ConfigError, match="lockstep.latency.kind: got 'constant'; expected mode: lockstep"):
        parse_config({"lockstep": {"latency": {"kind": "constant"}}})


# -- real-time health ------------------------------------------------------------------


def test_summary_says_when_the_cameras_did_not_keep_real_time(tmp_path: Path) -> None:
    # An injected render delay (a documented fault): every 10th frame of the camera is
    # held 70 ms before t0, beyond the 50 ms frame tolerance (one period at 20 fps).
    # The physics is untouched, so the verdict must name the camera pipeline.
    from hil.harness.cli.main import realtime_warning

    r = run(tmp_path, duration_s=2.0, camera={"fps": 20},
            engine={"faults": {"render_delay_ms": 70, "render_delay_every": 10}})
    rt = r.summary["realtime"]
    cam = rt["camera"]
    assert rt["mode"] == "realtime" and rt["kept_realtime"] is False and "camera" in rt["lagging"]
    assert cam["tolerance_ms"] == 50.0 and cam["frames"] == 40
    assert cam["late_frames"] >= 4 and cam["worst_lag_ms"] >= 70.0, cam
    assert cam["by_vehicle"] == {"ego0": cam["late_frames"]}
    assert r.summary["vehicles"]["ego0"]["late_frames"] == cam["late_frames"]
    warning = realtime_warning(rt, sim_steps=1000)
    assert warning is not None and "camera pipeline lagged" in warning
    assert f"{cam['late_frames']} of 40 frames" in warning
    realtime = next(c for c in r.summary["verdict"]["checks"] if c["name"] == "realtime")
    assert realtime["ok"] is False and "camera frames" in realtime["headline"]
    # The render stage shows the injected delay on the held frames, and only there.
    renders = sorted(d["stages_ns"]["render"] for _, d in read_mcap(r.mcap_path)["/ego0/pipeline"]
                     if "render" in d.get("stages_ns", {}))
    assert sum(1 for x in renders if x >= 70_000_000) >= 4


def test_a_fast_pace_is_judged_on_physics_and_cameras_alone(tmp_path: Path) -> None:
    # 100x real time: the physics keeps it here (its own pace is achieved_factor); the
    # cameras cannot render 2000 frames per wall second, and the verdict says which lagged.
    r = run(tmp_path, realtime_factor=100.0, duration_s=1.0)
    rt = r.summary["realtime"]
    assert rt["requested_factor"] == 100.0 and rt["kept_realtime"] is False
    assert "camera" in rt["lagging"] and rt["camera"]["late_frames"] > 0
    assert ("physics" in rt["lagging"]) == (rt["achieved_factor"] < 95 or rt["late_steps"] > 0)
    assert rt["run_factor"] < rt["achieved_factor"]  # the whole run waited for the cameras to drain
    assert r.summary["sim_time_s"] == pytest.approx(1.0)  # it ran on, late, never silently slower


# -- the command line ----------------------------------------------------------------


def test_hil_scenarios_lists_names_params_and_ranges() -> None:
    p = hil("scenarios")
    assert p.returncode == 0, p.stderr
    for name in ("stopped_car", "pedestrian_occluded", "lead_brake", "cut_in", "curved_road", "multi_vehicle"):
        assert f"\n{name}\n" in f"\n{p.stdout}"
    assert "n_vehicles      [1, 64] (integer)  4" in p.stdout
    assert "decel_mps2       [1, 10]    6        m/s^2" in p.stdout
    j = hil("scenarios", "lead_brake", "--json")
    data = json.loads(j.stdout)
    assert list(data) == ["lead_brake"]
    assert {"name": "gap_m", "type": "number", "min": 8.0, "max": 80.0, "default": 25.0, "unit": "m",
            "help": "ego's front to the lead's rear"} in data["lead_brake"]["params"]
    bad = hil("scenarios", "nowhere")
    assert bad.returncode == 2 and "valid: curved_road, cut_in" in bad.stderr


def test_hil_run_names_bad_scenario_parameters(tmp_path: Path) -> None:
    p = hil("run", "hil_configs/demo.yaml", "--out", str(tmp_path / "r"), "--set",
            "scenario={name: multi_vehicle, params: {n_vehicles: 80}}")
    assert p.returncode == 2 and "Traceback" not in p.stderr
    assert "n_vehicles: got 80; expected an integer in [1, 64]" in p.stderr
    assert "headway_m in [12, 80] m (default 30)" in p.stderr


@pytest.mark.slow
def test_hil_run_multi_vehicle_with_four_targets(tmp_path: Path) -> None:
    out = tmp_path / "mv"
    p = hil("run", "hil_configs/demo.yaml", "--out", str(out), "--no-progress", "--set", "duration_s=2",
            "--set", "scenario.name=multi_vehicle", "--set", "scenario.params={n_vehicles: 4}",
            "--set", "camera.fps=10")
    assert p.returncode == 0, p.stdout + p.stderr
    s = json.loads((out / "summary.json").read_text())
    assert sorted(s["vehicles"]) == ["ego0", "ego1", "ego2", "ego3"]
    for name, v in s["vehicles"].items():
        assert v["frames_sent"] == 20 and v["target"]["name"] == "cv-baseline", name
        assert v["estimates_applied"] >= 10 and v["outcome"]["collisions"] == 0  # real time: a loaded machine drops some
        assert (out / f"target-{name}.log").exists()
    msgs = read_mcap(out / "run.mcap")
    for name in s["vehicles"]:
        assert len(msgs[f"/{name}/truth"]) == 20 and len(msgs[f"/{name}/camera"]) == 20
    # The main road's egos see the others: boxes of egos from other egos' cameras.
    seen = {b["entity"] for _, d in msgs["/ego0/truth"] for b in d["boxes"]}
    assert seen & {"ego1", "ego2", "ego3"}
