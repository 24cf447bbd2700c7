"""A run's checks as CI cases (``hil.harness.report.ci_outputs``): what ``--junit``
and ``--json`` write for ``hil run``. The other commands build theirs in their own
rooms (``check.ci_cases``: compare and calibrate; ``search.ci_cases``;
``study.ci_cases``; ``target-check`` in its module).

Every builder keeps the rule of ``ci_outputs``: a case fails exactly when it makes
the command's exit code non-zero.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

from hil.harness.report.ci_outputs import CiCase, CiReport, flat

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
    from hil.harness.vocab.verdict import verdict_of

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










__all__ = ["of_run", "run_figures"]
