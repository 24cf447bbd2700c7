"""Per-frame columns that could not be spilled (a full or missing ``$TMPDIR``) are
named in ``summary.json`` (``spill``), not only counted on the column (issue 26, item 8)."""

from __future__ import annotations

from pathlib import Path

from hil.harness.run.spill import spill_summary
from hil.harness.run.vehicle_state import VehicleRun
from hil.timing.stats import SpillColumn, SpillFile


def test_spill_failures_are_named(tmp_path: Path):
    ok, broken = SpillFile(str(tmp_path)), SpillFile(str(tmp_path / "gone"))  # no such folder: mkstemp fails
    v = VehicleRun("ego0", 0, link=None)  # type: ignore[arg-type]  # no link is needed to hold columns
    v.stage_values = {"end_to_end": SpillColumn(block=4, spill=broken), "inference": SpillColumn(block=4, spill=ok)}
    for i in range(10):  # two full blocks each
        for col in v.stage_values.values():
            col.append(i)
    s = spill_summary([v], timing=None)
    assert s["failures"] == 2 and s["columns"] == {"ego0/latency/end_to_end": 2}
    assert "No such file or directory" in s["error"] and "memory" in s["note"]
    assert v.stage_values["end_to_end"].to_numpy().tolist() == list(range(10))  # exact all the same
    assert spill_summary([VehicleRun("ego1", 1, link=None)], timing=None) == {"failures": 0}  # type: ignore[arg-type]
    ok.close()
