"""A run's checks as CI cases (``hil.harness.report.ci_outputs``): what ``--junit``
and ``--json`` write for ``hil run``. The other commands build theirs in their own
rooms (``check.ci_cases``: compare and calibrate; ``search.ci_cases``;
``study.ci_cases``; ``target-check`` in its module).

Every builder keeps the rule of ``ci_outputs``: a case fails exactly when it makes
the command's exit code non-zero.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from hil.harness.report.ci_outputs import CiCase, CiReport, flat
from hil.harness.vocab.figures import RunFigures

_STAGE_FIGURES = ("count", "p50_ms", "p99_ms", "max_ms", "std_ms")


def run_figures(figures: RunFigures) -> dict[str, Any]:
    """The figures of a run a CI keeps with its result: per vehicle frames, drops,
    frame rate and every stage's count, p50, p99, max and std (ms), and the realtime
    figures; keys ``ego0.end_to_end.p99_ms``, ``realtime.kept_realtime`` ..."""
    rt = figures.realtime
    out: dict[str, Any] = {
        "realtime.mode": None if rt is None else rt.mode,
        "realtime.kept_realtime": None if rt is None else rt.kept_realtime,
        "realtime.achieved_factor": None if rt is None else rt.achieved_factor,
        "realtime.late_steps": None if rt is None else rt.late_steps,
        "realtime.late_frames": None if rt is None or rt.camera is None else rt.camera.late_frames}
    for name, v in figures.vehicles.items():
        out.update({f"{name}.frames_sent": v.frames_sent, f"{name}.estimates_applied": v.estimates_applied,
                    f"{name}.dropped": v.dropped, f"{name}.drop_rate": v.drop_rate,
                    f"{name}.frames_per_s": v.frames_per_s})
        for stage, st in v.latency_ms.items():
            if st.count:
                out.update({f"{name}.{stage}.{k}": st.figure(k) for k in _STAGE_FIGURES})
    return out


def of_run(figures: RunFigures, *, run_dir: Path, exit_code: int) -> CiReport:
    """``hil run``: a ``completed`` case (failed when the run ended early or a corner
    case could not be written: exit 1), then one per verdict check, failed when it
    failed and is named by ``--fail-on`` (exit 3); a failed check not named is a
    warning: passed, with ``ok=false`` and its headline in ``system-out``."""
    name = run_dir.name if figures.name is None else figures.name
    ended = figures.ended_by
    errors = () if figures.corner_cases is None else figures.corner_cases.errors
    done = ended == "duration" and not errors
    what = ("ran its whole duration" if ended == "duration" else f"ended early: {ended}") + (
        f"; {len(errors)} corner case(s) could not be written" if errors else "")
    cases = [CiCase("completed", done, what, {"ended_by": ended, "sim_time_s": figures.sim_time_s,
                                              "wall_time_s": figures.wall_time_s,
                                              "corner_case_errors": len(errors)}, group=name)]
    v = figures.verdict
    for c in v.checks:
        props = {"measured": c.measured, "limit": c.limit, "unit": c.unit, "in_fail_on": c.name in v.fail_on,
                 **flat("details", c.details)}
        cases.append(CiCase(c.name, c.ok, c.headline, props, group=name, fails_command=c.name in v.fails_run))
    props = {"run_dir": str(run_dir), "scenario": figures.scenario, "seed": figures.seed,
             "config_hash": figures.config_hash, "fail_on": ",".join(sorted(set(v.fail_on))),
             **run_figures(figures)}
    return CiReport("run", name, cases, exit_code, props, {"verdict": v.to_json(), "run_dir": str(run_dir)},
                    time_s=figures.wall_time_s)


__all__ = ["of_run", "run_figures"]
