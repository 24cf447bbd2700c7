"""``summary.json``'s ``spill``: whether the exact per-frame columns of a run reached
their spill file (``hil.timing.stats.SpillColumn``, ``$TMPDIR``). A block that could
not be written (a full ``$TMPDIR``) is kept in memory instead: the figures stay exact,
but memory grows with the run, and the summary names where."""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

from hil.timing.stats import SpillColumn


def spill_summary(vehicles: Iterable[Any], timing: Any) -> dict[str, Any]:
    """``{"failures": N, "columns": {"ego0/latency/end_to_end": n, ...}, "error": first}``
    over every vehicle's stage columns (``VehicleRun.stage_values``, ``send_parts``) and the timing
    observer's split columns (``TimingObserver.v[name].splits``); ``failures`` 0 and
    nothing else when every block was spilled."""
    columns: dict[str, SpillColumn] = {}
    for v in vehicles:
        columns.update({f"{v.name}/latency/{stage}": col for stage, col in v.stage_values.items()})
        columns.update({f"{v.name}/capture_to_send/{part}": col for part, col in v.send_parts.items()})
    for name, vt in getattr(timing, "v", {}).items():
        for split, cols in vt.splits.items():
            for part, col in zip(("frame", "value", "uncertainty"), cols.columns):
                columns[f"{name}/splits/{split}/{part}"] = col
    failed = {k: c.spill_failures for k, c in columns.items() if c.spill_failures}
    out: dict[str, Any] = {"failures": sum(failed.values())}
    if failed:
        out["columns"] = failed
        out["error"] = next(c.spill_error for c in columns.values() if c.spill_error)
        out["note"] = ("blocks of per-frame values that could not be written to the spill file ($TMPDIR) were kept "
                       "in memory: the figures are exact, but memory grew with the run")
    return out
