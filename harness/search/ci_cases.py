"""``hil search`` as CI cases (what ``--junit`` and ``--json`` write).

Every builder keeps the rule of ``hil.harness.report.ci_outputs``: a case fails exactly
when it makes the command's exit code non-zero."""

from __future__ import annotations

from typing import TYPE_CHECKING

from hil.harness.report.ci_outputs import CiCase, CiReport, flat

if TYPE_CHECKING:
    from hil.harness.search.campaign import Outcome


def of_search(oc: Outcome, *, exit_code: int) -> CiReport:
    """``hil search``: a ``complete`` case (every episode of the shard ran to its
    duration: exit 0), then one per episode run by this call, failed when it did not."""
    s = oc.summary
    name = str((s.get("campaign") or {}).get("name", oc.out_dir.name))
    ok_now = sum(1 for r in oc.ran if r.status == "ok")
    what = (f"{ok_now + oc.already_done} of {oc.planned} episodes of shard {oc.shard} ran to their duration"
            + (" (stopped)" if oc.stopped else ""))
    cases = [CiCase("complete", oc.complete, what, {"planned": oc.planned, "already_done": oc.already_done,
                                                    "ran": len(oc.ran), "stopped": oc.stopped}, group=name)]
    for r in oc.ran:
        props = {"status": r.status, "ended_by": r.ended_by, "error": r.error, "sim_s": r.sim_s, "wall_s": r.wall_s,
                 "virtual_km": r.virtual_km, "corner_cases": len(r.cases), "anomalies": r.anomalies,
                 "collisions": r.collisions, "min_gap_m": r.min_gap_m, "score": r.score, "dir": r.dir,
                 **flat("params", r.params)}
        text = (f"{r.sim_s:.1f} s simulated, {len(r.cases)} corner cases, score {r.score:g}" if r.status == "ok"
                else f"{r.status}: {r.error or r.ended_by}")
        cases.append(CiCase(f"e{r.index:05d}", r.status == "ok", text, props, group=name))
    cases_total = (s.get("cases") or {}).get("total")
    return CiReport("search", name, cases, exit_code,
                    {"folder": str(oc.out_dir), "shard": str(oc.shard), "corner_cases": cases_total,
                     "virtual_km": s.get("virtual_km")}, {"summary": s}, time_s=oc.wall_s)


__all__ = ["of_search"]
