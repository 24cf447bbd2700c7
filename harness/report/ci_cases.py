"""Each command's checks as CI cases (``hil.harness.report.ci_outputs``): what
``--junit`` and ``--json`` write for ``hil run``, ``compare``, ``search``, ``study``
and ``calibrate`` (``target-check`` builds its own rows in its module).

Every builder keeps the rule of ``ci_outputs``: a case fails exactly when it makes
the command's exit code non-zero.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import asdict
from pathlib import Path
from typing import TYPE_CHECKING, Any

from hil.harness.report.ci_outputs import CiCase, CiReport, flat

if TYPE_CHECKING:
    from hil.harness.check.calibrate import Calibration
    from hil.harness.report.compare import Check as CompareCheck
    from hil.harness.search.campaign import Outcome
    from hil.harness.study.study import PointResult

_STAGE_FIGURES = ("count", "p50_ms", "p99_ms", "max_ms", "std_ms")


def run_figures(summary: Mapping[str, Any]) -> dict[str, Any]:
    """The figures of a run a CI keeps with its result: per vehicle frames, drops,
    frame rate and every stage's count, p50, p99, max and std (ms), and the realtime
    figures; keys ``ego0.end_to_end.p99_ms``, ``realtime.kept_realtime`` ..."""
    out: dict[str, Any] = {}
    rt = summary.get("realtime") or {}
    for k in ("mode", "kept_realtime", "achieved_factor", "late_steps"):
        out[f"realtime.{k}"] = rt.get(k)
    out["realtime.late_frames"] = (rt.get("camera") or {}).get("late_frames")
    for name, v in (summary.get("vehicles") or {}).items():
        for k in ("frames_sent", "estimates_applied", "dropped", "drop_rate", "frames_per_s"):
            out[f"{name}.{k}"] = v.get(k)
        for stage, st in (v.get("latency_ms") or {}).items():
            if isinstance(st, Mapping) and st.get("count"):
                out.update({f"{name}.{stage}.{k}": st.get(k) for k in _STAGE_FIGURES})
    return out


def of_run(summary: Mapping[str, Any], *, run_dir: Path, exit_code: int) -> CiReport:
    """``hil run``: a ``completed`` case (failed when the run ended early or a corner
    case could not be written: exit 1), then one per verdict check, failed when it
    failed and is named by ``--fail-on`` (exit 3); a failed check not named is a
    warning: passed, with ``ok=false`` and its headline in ``system-out``."""
    from hil.harness.analysis.verdict import verdict_of

    name = str(summary.get("name", run_dir.name))
    ended = summary.get("ended_by")
    errors = (summary.get("corner_cases") or {}).get("errors") or []
    done = ended == "duration" and not errors
    what = ("ran its whole duration" if ended == "duration" else f"ended early: {ended}") + (
        f"; {len(errors)} corner case(s) could not be written" if errors else "")
    cases = [CiCase("completed", done, what, {"ended_by": ended, "sim_time_s": summary.get("sim_time_s"),
                                              "wall_time_s": summary.get("wall_time_s"),
                                              "corner_case_errors": len(errors)}, group=name)]
    v = verdict_of(summary)
    fails = set(v.get("fails_run") or [])
    fail_on = set(v.get("fail_on") or [])
    for c in v["checks"]:
        props = {"measured": c.get("measured"), "limit": c.get("limit"), "unit": c.get("unit"),
                 "in_fail_on": c["name"] in fail_on, **flat("details", c.get("details") or {})}
        cases.append(CiCase(c["name"], bool(c["ok"]), str(c["headline"]), props, group=name,
                            fails_command=c["name"] in fails))
    props = {"run_dir": str(run_dir), "scenario": summary.get("scenario"), "seed": summary.get("seed"),
             "config_hash": summary.get("config_hash"), "fail_on": ",".join(sorted(fail_on)),
             **run_figures(summary)}
    return CiReport("run", name, cases, exit_code, props, {"verdict": v, "run_dir": str(run_dir)},
                    time_s=summary.get("wall_time_s"))


def of_compare(checks: Sequence[CompareCheck], *, baseline: str, run: str, exit_code: int,
               notes: Sequence[str] = ()) -> CiReport:
    """``hil compare``: one case per check (vehicle, stage, metric), failed when it
    fails the gate; an ``over, not significant`` one passes with its reason."""
    from hil.harness.report.compare_render import change, name_of, row_text

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


__all__ = ["of_calibrate", "of_compare", "of_run", "of_search", "of_study", "run_figures"]
