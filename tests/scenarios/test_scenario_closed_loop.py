"""The OpenCV baseline drives the new scenarios in one process (no transport): it
keeps its lane on the S-bend, follows and stops behind a braking lead, and the egos
of the multi-vehicle crossroads get through without touching."""

from __future__ import annotations

import pytest


@pytest.mark.slow
def test_baseline_keeps_its_lane_on_the_curved_road(make_sim, baseline_drive) -> None:
    sim = make_sim("curved_road")  # 150 m arcs of 45 deg each way at 10 m/s
    d = baseline_drive(sim, duration_s=25.0)
    assert not d.collisions
    # Half a lane is 1.85 m and the car 1.8 m wide: within 0.5 m it never touches a line.
    assert d.max_lane_offset_m["ego0"] < 0.5
    s, _ = sim.route("ego0").project(*sim.pose("ego0")[:2])
    assert float(s) > 30.0 + 200.0  # through both arcs (they end 70 + 118 + 30 + 118 m in)


@pytest.mark.slow
def test_baseline_stops_behind_a_braking_lead(make_sim, baseline_drive) -> None:
    sim = make_sim("lead_brake")
    d = baseline_drive(sim, duration_s=12.0)
    assert not d.collisions
    assert 1.0 < d.min_gap_m["ego0"] < 10.0
    assert sim.speed_mps("ego0") < 0.2 and "STOP" in d.ref_states


@pytest.mark.slow
def test_baseline_egos_share_the_crossroads_without_touching(make_sim, baseline_drive) -> None:
    sim = make_sim("multi_vehicle", {"n_vehicles": 4})
    d = baseline_drive(sim, duration_s=14.0, steps_per_frame=50)  # 10 fps
    assert not d.collisions
    assert max(d.max_lane_offset_m.values()) < 0.5
    # The crossing ego went through the junction; the main-road ones followed their lanes towards it.
    x, y, _ = sim.pose("ego3")
    assert y > 10.0 and abs(x - 1.85) < 0.5
