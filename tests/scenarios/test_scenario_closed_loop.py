"""The OpenCV baseline drives the new scenarios in one process (no transport): it
keeps its lane on the S-bend, follows and stops behind a braking lead, and the egos
of the multi-vehicle crossroads get through without touching."""

from __future__ import annotations

from typing import Any

import pytest
from conftest import Drive, build, drive_with_baseline  # tests/scenarios/conftest.py

from tests.conftest import ahead, ahead_results


def closed_loop(name: str, params: dict[str, float] | None, duration_s: float,
                steps_per_frame: int) -> tuple[Drive, dict[str, tuple[tuple[float, float, float], float, float]]]:
    """The baseline's drive and, after it, each ego's pose, speed and distance along its
    route (a module-level function: lockstep in one process and reading no clock, it
    runs ahead in a child process, beside the tests before these)."""
    from hil.scenarios.sim import Simulation

    with Simulation(build(name, params)) as sim:
        d = drive_with_baseline(sim, duration_s=duration_s, steps_per_frame=steps_per_frame)
        after = {}
        for e in sim.egos:
            x, y, yaw = sim.pose(e)
            after[e] = ((float(x), float(y), float(yaw)), float(sim.speed_mps(e)),
                        float(sim.route(e).project(x, y)[0]))
    return d, after


ahead(__name__, "curved_road", closed_loop, [("curved_road", None, 25.0, 25)])  # 150 m arcs of 45 deg each way
ahead(__name__, "lead_brake", closed_loop, [("lead_brake", None, 12.0, 25)])
ahead(__name__, "crossroads", closed_loop, [("multi_vehicle", {"n_vehicles": 4}, 14.0, 50)])  # 10 fps


@pytest.fixture(scope="module")
def curved_road() -> Any:
    return ahead_results(__name__, "curved_road")[0]


@pytest.fixture(scope="module")
def lead_brake() -> Any:
    return ahead_results(__name__, "lead_brake")[0]


@pytest.fixture(scope="module")
def crossroads() -> Any:
    return ahead_results(__name__, "crossroads")[0]


@pytest.mark.slow
def test_baseline_keeps_its_lane_on_the_curved_road(curved_road) -> None:
    d, after = curved_road
    assert not d.collisions
    # Half a lane is 1.85 m and the car 1.8 m wide: within 0.5 m it never touches a line.
    assert d.max_lane_offset_m["ego0"] < 0.5
    assert after["ego0"][2] > 30.0 + 200.0  # through both arcs (they end 70 + 118 + 30 + 118 m in)


@pytest.mark.slow
def test_baseline_stops_behind_a_braking_lead(lead_brake) -> None:
    d, after = lead_brake
    assert not d.collisions
    assert 1.0 < d.min_gap_m["ego0"] < 10.0
    assert after["ego0"][1] < 0.2 and "STOP" in d.ref_states


@pytest.mark.slow
def test_baseline_egos_share_the_crossroads_without_touching(crossroads) -> None:
    d, after = crossroads
    assert not d.collisions
    assert max(d.max_lane_offset_m.values()) < 0.5
    # The crossing ego went through the junction; the main-road ones followed their lanes towards it.
    (x, y, _), _, _ = after["ego3"]
    assert y > 10.0 and abs(x - 1.85) < 0.5
