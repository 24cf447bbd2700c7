"""Beyond 16 vehicles a real-time run first measures what this machine renders, and
refuses in one line, naming the measured limit, what it cannot render in time;
lockstep takes any number (issue 24, start and finish scale)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from hil.common.errors import ConfigError
from hil.harness.config.loading import parse_config
from hil.harness.run import capacity
from hil.harness.run.driver import build_world
from hil.scenarios.sim import Simulation
from tests.conftest import GL_BACKEND

ROOT = Path(__file__).resolve().parents[3]


def _sim(n: int, **cfg: object) -> tuple[object, Simulation]:
    c = parse_config({"scenario": {"name": "multi_vehicle", "params": {"n_vehicles": n}}, **cfg})
    world, rules = build_world(c)
    return c, Simulation(world, rules=rules)


def test_a_real_time_run_beyond_sixteen_is_measured_and_refused_when_it_cannot_render_in_time() -> None:
    cfg, sim = _sim(20, camera={"fps": 200.0}, physics_step_s=0.001)
    with sim, pytest.raises(ConfigError) as err:
        capacity.check(cfg, sim, workers=2, cores=2)
    msg = str(err.value)
    assert msg.startswith("scenario.params.n_vehicles: 20 vehicles at 200 fps need 4000 frames/s (1 camera and "
                          "its truth each)")
    assert "measured now" in msg and "mode: lockstep" in msg and "\n" not in msg
    fits = int(msg.split("so it carries ")[1].split(" ")[0])
    assert 0 <= fits < 20


def test_what_the_machine_carries_starts_and_lockstep_is_never_refused() -> None:
    cfg, sim = _sim(17, camera={"fps": 1.0}, physics_step_s=0.001)
    with sim:
        line = capacity.check(cfg, sim, workers=2, cores=2)
    assert line is not None and line.startswith("render capacity: ") and "vehicles at 1 fps" in line
    per_worker = float(line.split(": ")[1].split(" ")[0])
    assert per_worker > 17 * capacity.HEADROOM  # what made it pass, measured
    for c, s in (_sim(64, mode="lockstep"), _sim(16, camera={"fps": 200.0}, physics_step_s=0.001)):
        with s:
            assert capacity.check(c, s, workers=2, cores=2) is None  # nothing to measure


def test_a_vehicles_frame_is_its_whole_rig_and_its_truth() -> None:
    # What a render worker draws for a vehicle at a camera instant: every camera of its
    # rig and, with truth.visible_boxes, each one's segmentation. Measured on the same
    # world: six cameras take longer than one, and truth adds to colour alone.
    cfg, sim = _sim(17, camera={"fps": 1.0, "rig": "surround6"}, physics_step_s=0.001)
    with sim:
        line = capacity.check(cfg, sim, workers=2, cores=2)
        assert line is not None and "vehicle frames/s (6 cameras and their truth)" in line
        one = capacity.measure(sim, workers=1, cores=1, cameras=1, seconds=0.3)
        six = capacity.measure(sim, workers=1, cores=1, cameras=6, seconds=0.3)
        six_truth = capacity.measure(sim, workers=1, cores=1, cameras=6, truth_px=1, seconds=0.3)
    assert six.per_worker < one.per_worker / 2 and six_truth.per_worker < six.per_worker, (one, six, six_truth)
    cfg, sim = _sim(17, camera={"fps": 1.0}, truth={"visible_boxes": False}, physics_step_s=0.001)
    with sim:
        line = capacity.check(cfg, sim, workers=2, cores=2)
    assert line is not None and "vehicle frames/s (1 camera) per render worker" in line


def test_hil_run_refuses_before_anything_starts(tmp_path: Path) -> None:
    out = tmp_path / "run"
    env = dict(os.environ, MUJOCO_GL=GL_BACKEND)
    p = subprocess.run([sys.executable, "-m", "hil.harness.cli.main", "run", "hil_configs/scale.yaml", "--no-progress",
                        "--out", str(out), "--set", "scenario.params.n_vehicles=64", "--set", "camera.fps=200",
                        "--set", "physics_step_s=0.001"], cwd=ROOT, env=env, capture_output=True, text=True,
                       timeout=120, check=False)
    assert p.returncode == 2, p.stderr
    err = p.stderr.strip().splitlines()
    assert "Traceback" not in p.stderr and "n_vehicles: 64 vehicles at 200 fps" in err[-1], p.stderr
    assert not (out / "run.mcap").exists() and not list(out.glob("target-*.log"))


def test_hil_study_takes_up_to_64_and_refuses_what_it_cannot_render(tmp_path: Path) -> None:
    env = dict(os.environ, MUJOCO_GL=GL_BACKEND)
    for argv, needle in ((["--vehicles", "65"], "1..64"),
                         (["--vehicles", "2", "64", "--fps", "200", "--set", "physics_step_s=0.001"],
                          "n_vehicles: 64 vehicles at 200 fps")):
        p = subprocess.run([sys.executable, "-m", "hil.harness.cli.main", "study", "hil_configs/study.yaml", *argv,
                            "--out", str(tmp_path / "s")], cwd=ROOT, env=env, capture_output=True, text=True,
                           timeout=120, check=False)
        assert p.returncode == 2 and needle in p.stderr and "Traceback" not in p.stderr, p.stderr
        assert not (tmp_path / "s").exists()
