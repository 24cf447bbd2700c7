"""``hil study`` as CI cases (what ``--junit`` and ``--json`` write).

Every builder keeps the rule of ``hil.harness.report.ci_outputs``: a case fails exactly
when it makes the command's exit code non-zero."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

from hil.harness.report.ci_outputs import CiCase, CiReport

if TYPE_CHECKING:
    from hil.harness.study.study import PointResult


def of_study(results: Sequence[PointResult], *, out: Path, exit_code: int, wall_s: float) -> CiReport:
    """``hil study``: one case per point, failed when it failed or was skipped (both exit 1)."""
    cases = []
    for r in results:
        m = r.metrics
        text = (f"{m.get('fps_per_vehicle_min')} fps per vehicle (min), e2e p50 {m.get('e2e_p50_ms')} ms, real "
                f"time {'kept' if m.get('kept_realtime') else 'NOT kept'}" if r.status == "ok"
                else f"{r.status}: {r.reason}")
        props = {"status": r.status, "placement": r.point.placement.value, "vehicles": r.point.vehicles,
                 "fps": r.point.fps, "run_dir": r.run_dir, "wall_s": round(r.wall_s, 2), **m}
        cases.append(CiCase(r.point.name, r.status == "ok", text, props, group=r.point.placement.value))
    return CiReport("study", out.name, cases, exit_code, {"folder": str(out)}, time_s=wall_s)


__all__ = ["of_study"]
