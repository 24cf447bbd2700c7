"""``hil compare`` and ``hil calibrate`` as CI cases (what ``--junit`` and ``--json`` write).

Every builder keeps the rule of ``hil.harness.report.ci_outputs``: a case fails exactly
when it makes the command's exit code non-zero."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict
from pathlib import Path
from typing import TYPE_CHECKING

from hil.harness.report.ci_outputs import CiCase, CiReport, flat

if TYPE_CHECKING:
    from hil.harness.check.calibrate import Calibration
    from hil.harness.check.gate import Check as CompareCheck


def of_compare(checks: Sequence[CompareCheck], *, baseline: str, run: str, exit_code: int,
               notes: Sequence[str] = ()) -> CiReport:
    """``hil compare``: one case per check (vehicle, stage, metric), failed when it
    fails the gate; an ``over, not significant`` one passes with its reason."""
    from hil.harness.check.gate_render import change, name_of, row_text

    cases = []
    for c in checks:
        props = {"vehicle": c.vehicle, "stage": c.stage, "metric": c.metric, "baseline": c.baseline, "run": c.run,
                 "limit": c.limit, "change": change(c), "verdict": c.verdict.value, "method": c.method.value,
                 "ci_lo": c.ci[0] if c.ci else None, "ci_hi": c.ci[1] if c.ci else None, "p_worse": c.p_worse,
                 "p_worse_needed": c.need, "reason": c.reason, "note": c.note}
        text = f"{row_text(c)}: {c.verdict.value}"
        cases.append(CiCase(name_of(c), not c.verdict.fails, text, props, group=c.vehicle,
                            output=f"{row_text(c, p_worse=False)}: {c.reason}" if c.reason else ""))
    return CiReport("compare", f"{run} against {baseline}", cases, exit_code,
                    {"baseline": baseline, "run": run, "notes": list(notes)})


def of_calibrate(cal: Calibration, *, out: Path, exit_code: int) -> CiReport:
    """``hil calibrate``: the run, each figure against its truth and bound, each
    injected fault (flagged exactly once) and each anomaly not injected (a false
    alarm fails)."""
    from hil.harness.check.calibrate_faults import Cause

    cases = [CiCase("run", cal.run_ok, cal.run_note or "ran its whole duration", {"transport": cal.transport},
                    group="run")]
    for c in cal.checks:
        d = asdict(c)
        cases.append(CiCase(c.figure, c.ok, f"{c.figure}: reported {c.reported}, truth {c.truth}, error {c.error}, "
                            f"bound {c.bound} {c.unit}" + (f" ({c.note})" if c.note else ""), d, group="figures"))
    for f in cal.faults:
        at = "" if f.frame_id is None else f" at frame {f.frame_id}"
        text = f"{f.fault}{at}: flagged by {', '.join(f.flagged_by) or 'nothing'}" + (f" ({f.note})" if f.note else "")
        cases.append(CiCase(f.fault + at, f.ok, text, asdict(f), group="faults"))
    for o in cal.others:
        cases.append(CiCase(f"{o.kind} {o.label}", o.cause is not Cause.FALSE, str(o),
                            {"kind": o.kind, "frame_ids": list(o.frame_ids), "cause": o.cause.value},
                            group="other_anomalies"))
    return CiReport("calibrate", cal.transport, cases, exit_code, {"folder": str(out), **flat("overhead", cal.overhead)})


__all__ = ["of_calibrate", "of_compare"]
