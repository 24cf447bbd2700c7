"""The words an event is shown in (report tables, the case pages, the timeline)."""

from __future__ import annotations

from hil.harness.record.event_text import value_vs_threshold


def test_a_value_against_its_threshold_reads_as_a_sentence_would() -> None:
    # A dropped frame read "1 frames > 0 frames".
    assert value_vs_threshold({"measured": 1.0, "threshold": 0.0, "unit": "frames"}) == "1 frame > 0 frames"
    assert value_vs_threshold({"measured": 3.0, "threshold": 0.0, "unit": "frames"}) == "3 frames > 0 frames"
    assert value_vs_threshold({"measured": 1.0, "threshold": 0.5, "unit": "ms"}) == "1 ms > 0.5 ms"
    assert value_vs_threshold({"measured": 61.2, "threshold": 50.0, "unit": "ms"}) == "61.2 ms > 50 ms"
    assert value_vs_threshold({"measured": None, "threshold": 0.0, "unit": "ms"}) == "–"
