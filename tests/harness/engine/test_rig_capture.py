"""A rig's trigger table: which cameras of which egos capture at each step of the
camera period (hil.harness.engine.physics.capture_table)."""

from __future__ import annotations

from hil.harness.engine.physics import capture_table


def test_one_camera_per_ego_is_mask_one_at_its_phase() -> None:
    assert capture_table(50, (0, 25)) == {0: ((0,), (1,)), 25: ((1,), (1,))}


def test_a_rig_on_one_trigger_line_captures_every_camera_at_once() -> None:
    assert capture_table(50, (0, 10), (0, 0, 0)) == {0: ((0,), (0b111,)), 10: ((1,), (0b111,))}


def test_trigger_offsets_put_each_camera_at_its_own_step_wrapping_the_period() -> None:
    table = capture_table(50, (0, 45), (0, 0, 5))
    assert table == {0: ((0, 1), (0b011, 0b100)), 5: ((0,), (0b100,)), 45: ((1,), (0b011,))}


def test_a_dropped_camera_never_triggers() -> None:
    assert capture_table(50, (0,), (0, 0, 5), dropped=0b010) == {0: ((0,), (0b001,)), 5: ((0,), (0b100,))}
