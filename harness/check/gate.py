"""``hil compare BASELINE RUN``: the latency regression gate.

Compares two runs (each argument a run folder or its ``summary.json``) and exits 1
when RUN is worse than BASELINE, 0 otherwise, 2 on bad input (missing, truncated or
foreign file; bad tolerances).

Two runs of one build never give the same figures, so the gate compares the
distributions of their **per-frame samples** (``/<vehicle>/pipeline`` in each
``run.mcap``, see ``hil.harness.check.gate_samples``) and asks, for every vehicle and stage
of the baseline and each of ``p1`` (the floor), ``p50``, ``p99`` and ``std``
(jitter), plus each vehicle's drop rate, how sure it is that the figure grew by more
than its allowance ``max(rel × baseline, abs)`` (``hil.harness.check.gate_tolerances``):
a circular block bootstrap of both runs' frames gives the standard error of the
change, the run-to-run noise (what one pair cannot show: the machine's load changing
between the runs) is added to it, and ``P(worse)`` is the probability that the true
growth exceeds the allowance (``hil.timing.gate``). A check fails only when ``P(worse)
≥ 1 − α/m``: α (default 0.05) is the chance that a comparison of an unchanged build
fails at all, split over its m checks (Bonferroni). A tiny change fails never (it is
within its allowance), however sure; a large one fails only when the samples show it
beyond the noise. The table gives each change with its 95 % interval and
``P(worse)``. A figure that surely fell by more than its allowance is ``better``
(information); one over its limit that the test is not sure of is ``over, not
significant`` (it passes, with its reason and numbers under the table: never ``ok``).
An unknown stage, or a ``--stage`` the baseline has no samples of, is bad input.

Where a run has no usable ``run.mcap`` (only a ``summary.json``), its figures are
compared as points, as the gate did before: ``p50``/``p99``/``std`` fail when they
exceed ``baseline + allowance``; the table says ``point`` for those.

Always: a vehicle or stage of the baseline missing in RUN (or without samples there)
is a regression; one new in RUN is information. A RUN that ended early (``ended_by``
not ``duration``; or killed before its summary: ``gate_samples.UNFINISHED``) is a
regression. Different scenario, seed or config hash are
noted, not failed.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, replace
from enum import Enum
from typing import Any

import numpy as np

from hil.harness.check.gate_render import percent, render
from hil.harness.check.gate_samples import UNFINISHED, RunSamples, VehicleSamples, load_run
from hil.harness.check.gate_tolerances import (
                                                   LATENCY_METRICS,
                                                   Tolerance,
                                                   Tolerances,
                                                   add_tolerance_args,
                                                   load_tolerances,
                                                   parse_tolerances,
                                                   tolerances_from_args,
                                                   )
from hil.common.errors import ConfigError
from hil.timing.gate import DEFAULT_RESAMPLES, Metric, Shift, compare_metric
from hil.timing.records import STAGES

POINT_METRICS = ("p50", "p99", "std")  # what summary.json holds of LATENCY_METRICS
EXIT_OK, EXIT_REGRESSION = 0, 1


class Verdict(str, Enum):
    OK = "ok"
    BETTER = "better"
    REGRESSION = "REGRESSION"
    MISSING = "MISSING"
    NEW = "new"
    NO_DATA = "no data"
    NOT_SIGNIFICANT = "over, not significant"  # over its limit, but the samples do not make it sure

    @property
    def fails(self) -> bool:
        return self in (Verdict.REGRESSION, Verdict.MISSING)


class Method(str, Enum):
    """How a check was judged: from per-frame samples, or two summary figures."""

    SAMPLES = "samples"
    POINT = "point"
    NONE = "-"


@dataclass(frozen=True)
class GateSettings:
    """``alpha``: chance that a comparison of an unchanged build fails (split over its
    checks); ``resamples`` per bootstrap; ``seed`` of the bootstrap (same inputs,
    same verdict); ``confidence`` of the interval shown."""

    alpha: float = 0.05
    resamples: int = DEFAULT_RESAMPLES
    seed: int = 0
    confidence: float = 0.95

    def check(self) -> None:
        """Raises ConfigError naming the bad setting."""
        if not 0 < self.alpha < 1:
            raise ConfigError(f"--alpha: got {self.alpha:g}; expected a number between 0 and 1")
        if self.resamples < 100:
            raise ConfigError(f"--resamples: got {self.resamples}; expected at least 100")


@dataclass(frozen=True)
class Check:
    """One compared figure. ``limit``: baseline + allowance (``None`` where no limit
    applies). Judged from samples: ``ci`` (interval of the change at the settings'
    confidence), ``p_worse`` (probability that it grew beyond the allowance) and
    ``need`` (the ``p_worse`` at which it fails). ``reason``: why a figure over its
    limit did not fail (``Verdict.NOT_SIGNIFICANT``)."""

    vehicle: str
    stage: str
    metric: str
    baseline: float | None
    run: float | None
    limit: float | None
    verdict: Verdict
    note: str = ""
    method: Method = Method.NONE
    ci: tuple[float, float] | None = None
    p_worse: float | None = None
    need: float | None = None
    reason: str = ""


# --- comparing ---------------------------------------------------------------------------


def _stage_order(names: Sequence[str]) -> list[str]:
    return [s for s in STAGES if s in names] + sorted(s for s in names if s not in STAGES)


def _num(d: Mapping[str, Any], key: str) -> float | None:
    v = d.get(key)
    return float(v) if isinstance(v, (int, float)) and not isinstance(v, bool) else None


def _judge(vehicle: str, stage: str, metric: str, base: float | None, run: float | None,
           tol: Tolerance) -> Check:
    """A point check: ``run`` against ``baseline + allowance``."""
    if base is None and run is None:
        return Check(vehicle, stage, metric, None, None, None, Verdict.NO_DATA, "no samples on either side")
    if base is None:
        return Check(vehicle, stage, metric, None, run, None, Verdict.NEW, "no baseline samples")
    if run is None:
        return Check(vehicle, stage, metric, base, None, None, Verdict.MISSING, "no samples in the run")
    allowed = tol.allowance(base)
    limit = base + allowed
    if run > limit + 1e-12:
        verdict = Verdict.REGRESSION
    elif run < base - allowed:
        verdict = Verdict.BETTER
    else:
        verdict = Verdict.OK
    return Check(vehicle, stage, metric, base, run, limit, verdict, method=Method.POINT)


@dataclass
class _Pending:
    at: int            # index in the check list
    shift: Shift


def _shift(base: np.ndarray, run: np.ndarray, metric: Metric, tol: Tolerance, noise: Tolerance,
           settings: GateSettings, rng: np.random.Generator, on_judged: Callable[[], None] | None) -> Shift:
    allowed = tol.allowance(metric.of(np.asarray(base, np.float64)))
    shift = compare_metric(base, run, metric, allowed=allowed, confidence=settings.confidence,
                           run_noise_rel=noise.rel, run_noise_abs=noise.abs, resamples=settings.resamples, rng=rng)
    if on_judged is not None:
        on_judged()
    return shift


def compare(baseline: Mapping[str, Any], run: Mapping[str, Any], tol: Tolerances | None = None, *,
            base_samples: RunSamples | None = None, run_samples: RunSamples | None = None,
            settings: GateSettings | None = None, on_judged: Callable[[], None] | None = None) -> list[Check]:
    """Every check of ``run`` against ``baseline`` (two parsed summary.json), judged
    from the per-frame samples where both runs have them for a vehicle, else as
    points (see the module docstring). ``on_judged`` is called after each check
    judged from samples (a bootstrap each: the long part on long runs)."""
    tol = tol or Tolerances()
    settings = settings or GateSettings()
    rng = np.random.default_rng(settings.seed)
    checks: list[Check] = []
    pending: list[_Pending] = []
    ended = run.get("ended_by")
    if ended is not None and ended != "duration":
        checks.append(Check("(run)", "-", "ended_by", None, None, None, Verdict.REGRESSION, f"ended early: {ended}"))
    bv, rv = baseline.get("vehicles") or {}, run.get("vehicles") or {}
    for vehicle in list(bv) + [v for v in rv if v not in bv]:
        if vehicle not in rv:
            checks.append(Check(vehicle, "-", "vehicle", None, None, None, Verdict.MISSING,
                                "vehicle missing in the run"))
            continue
        if vehicle not in bv:
            checks.append(Check(vehicle, "-", "vehicle", None, None, None, Verdict.NEW, "vehicle new in the run"))
            continue
        b, r = bv[vehicle] or {}, rv[vehicle] or {}
        xb = base_samples.vehicles.get(vehicle) if base_samples is not None else None
        xr = run_samples.vehicles.get(vehicle) if run_samples is not None else None
        if xb is not None and xr is not None and xb.dropped.size and xr.dropped.size:
            pending.append(_Pending(len(checks), _shift(xb.dropped, xr.dropped, Metric.MEAN, tol.drop_rate,
                                                         Tolerance(0.0, 0.0), settings, rng, on_judged)))
            checks.append(Check(vehicle, "-", "drop_rate", None, None, None, Verdict.OK))
        else:
            checks.append(_judge(vehicle, "-", "drop_rate", _num(b, "drop_rate"), _num(r, "drop_rate"),
                                 tol.drop_rate))
        bl, rl = b.get("latency_ms") or {}, r.get("latency_ms") or {}
        for stage in _stage_order(list(bl) + [s for s in rl if s not in bl]):
            if not tol.checks_stage(stage):
                continue
            if stage not in rl:
                checks.append(Check(vehicle, stage, "stage", None, None, None, Verdict.MISSING,
                                    "stage missing in the run"))
                continue
            if stage not in bl:
                checks.append(Check(vehicle, stage, "stage", None, None, None, Verdict.NEW, "stage new in the run"))
                continue
            sb, sr = _stage_samples(xb, stage), _stage_samples(xr, stage)
            if sb is not None and sr is not None:
                for metric in LATENCY_METRICS:
                    pending.append(_Pending(len(checks), _shift(sb, sr, Metric(metric), tol.for_stage(metric, stage),
                                                                 tol.noise_of(metric, stage), settings, rng,
                                                                 on_judged)))
                    checks.append(Check(vehicle, stage, metric, None, None, None, Verdict.OK))
                continue
            for metric in POINT_METRICS:
                checks.append(_judge(vehicle, stage, metric, _num(bl[stage] or {}, f"{metric}_ms"),
                                     _num(rl[stage] or {}, f"{metric}_ms"), tol.for_stage(metric, stage)))
    need = 1.0 - settings.alpha / max(len(pending), 1)
    for p in pending:
        s = p.shift
        verdict = (Verdict.REGRESSION if s.p_worse >= need else Verdict.BETTER if s.p_better >= need
                   else Verdict.OK)
        reason = ""
        if verdict is Verdict.OK and s.run > s.base + s.allowed + 1e-12:
            # Over its limit, and the test is not sure enough to fail it: never shown as a plain "ok".
            verdict = Verdict.NOT_SIGNIFICANT
            reason = f"over the limit but not significant (P(worse) {percent(s.p_worse)} < {percent(need, 2)})"
        checks[p.at] = replace(checks[p.at], baseline=s.base, run=s.run, limit=s.base + s.allowed, verdict=verdict,
                               method=Method.SAMPLES, ci=(s.ci_lo, s.ci_hi), p_worse=s.p_worse, need=need,
                               note=f"{s.n_base}/{s.n_run} frames", reason=reason)
    return checks


def check_selection(baseline: Mapping[str, Any], tol: Tolerances) -> None:
    """Refuse a stage selection (``--stage``, ``only_stages``) that checks nothing: a
    named stage of which no vehicle of the baseline has samples.

    Raises:
        ConfigError: names the stage and the stages the baseline has.
    """
    have = {stage for v in (baseline.get("vehicles") or {}).values() if isinstance(v, dict)
            for stage, st in (v.get("latency_ms") or {}).items() if isinstance(st, dict) and st.get("count")}
    for stage in tol.only_stages:
        if stage not in have:
            raise ConfigError(f"--stage {stage}: the baseline has no samples of this stage, so nothing would be "
                              f"checked (its stages with samples: {', '.join(_stage_order(sorted(have))) or 'none'})")


def samples_checks(xb: RunSamples, xr: RunSamples, tol: Tolerances) -> int:
    """How many checks ``compare`` judges from samples (the drop rate and four per
    stage of each vehicle both runs have samples of)."""
    n = 0
    for v, b in xb.vehicles.items():
        r = xr.vehicles.get(v)
        if r is None:
            continue
        n += bool(b.dropped.size and r.dropped.size)
        n += len(LATENCY_METRICS) * sum(1 for s in b.stages_ms if tol.checks_stage(s) and _stage_samples(b, s) is not None
                                        and _stage_samples(r, s) is not None)
    return n


def _stage_samples(x: VehicleSamples | None, stage: str) -> np.ndarray | None:
    if x is None:
        return None
    a = x.stages_ms.get(stage)
    return a if a is not None and a.size else None


def differences(baseline: Mapping[str, Any], run: Mapping[str, Any]) -> list[str]:
    """What differs between the two runs' setups (scenario, parameters, seed, config)."""
    out = []
    for key in ("scenario", "scenario_params", "seed", "config_hash"):
        if baseline.get(key) != run.get(key):
            out.append(f"{key} differs: baseline {baseline.get(key)!r}, run {run.get(key)!r}")
    return out


# --- the command -------------------------------------------------------------------------


def add_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """Register ``hil compare`` on the CLI's subparsers."""
    p = sub.add_parser("compare", help="fail (exit 1) when RUN's latency regressed against BASELINE",
                       description="Compare two runs' per-frame latencies (from run.mcap) and exit 1 when one "
                                   "grew beyond its allowance with confidence: block bootstrap plus run-to-run "
                                   "noise, alpha split over the checks. Allowances: p1 and p50 max(10%, 0.5 ms), "
                                   "p99 max(20%, 2 ms), std max(25%, 1 ms), drop_rate 0.01.")
    p.add_argument("baseline", help="the reference run folder or its summary.json")
    p.add_argument("run", help="the run to check (folder or summary.json)")
    add_tolerance_args(p)
    p.add_argument("--alpha", type=float, default=0.05, metavar="P",
                   help="chance that comparing an unchanged build fails, split over the checks (default 0.05)")
    p.add_argument("--resamples", type=int, default=DEFAULT_RESAMPLES, metavar="N",
                   help=f"bootstrap resamples per check (default {DEFAULT_RESAMPLES})")
    p.add_argument("--seed", type=int, default=0, help="bootstrap seed (default 0: same runs, same verdict)")
    p.add_argument("--point", action="store_true",
                   help="compare the summaries' figures as points (no samples, no statistics)")
    p.add_argument("--failures-only", action="store_true", help="list only the failing checks")
    from hil.harness.report.ci_outputs import add_ci_args

    add_ci_args(p)


def cmd(args: argparse.Namespace) -> int:
    """``hil compare``: 0 no regression, 1 regression; ConfigError (exit 2) on bad input."""
    from rich.console import Console

    from hil.harness.report.progress import WorkProgress
    from hil.harness.report.ci_outputs import check_ci_args, write_ci_outputs
    from hil.harness.check.gate_render import judged_lines, outcome_lines, render

    check_ci_args(args)
    tol = tolerances_from_args(args)
    settings = GateSettings(alpha=args.alpha, resamples=args.resamples, seed=args.seed)
    settings.check()
    console = Console()
    if not console.is_terminal:
        console.width = max(console.width, 150)
    # Long runs: reading both recordings and a bootstrap per check take a while; on a
    # terminal a bar says how far it got and the time left (nothing in CI logs).
    with WorkProgress(console, what="reading the runs", total=2, unit="runs", lines=False) as progress:
        baseline, xb = load_run(args.baseline)
        progress.advance(note=str(args.baseline))
        run, xr = load_run(args.run, unfinished=True)
        progress.advance(note=str(args.run))
    check_selection(baseline, tol)
    if args.point:
        xb = xr = RunSamples({}, "--point")
    with WorkProgress(console, what="judging", total=samples_checks(xb, xr, tol), unit="checks",
                      lines=False) as progress:
        checks = compare(baseline, run, tol, base_samples=xb, run_samples=xr, settings=settings,
                         on_judged=progress.advance)
    notes = differences(baseline, run) if run.get("ended_by") != UNFINISHED else []
    for note in notes:
        console.print(f"[yellow]note: {note}[/yellow]")
    for name, x in (("baseline", xb), ("run", xr)):
        if x.note and not args.point:
            console.print(f"[yellow]note: {name}: {x.note}: its figures are compared as points[/yellow]")
    console.print(render(checks, failures_only=args.failures_only, confidence=settings.confidence))
    for line in [*judged_lines(checks, tol, settings), *outcome_lines(checks)]:
        console.print(line, highlight=False)
    code = EXIT_REGRESSION if any(c.verdict.fails for c in checks) else EXIT_OK
    from hil.harness.check.ci_cases import of_compare

    write_ci_outputs(of_compare(checks, baseline=str(args.baseline), run=str(args.run), exit_code=code, notes=notes),
                     args)
    return code


__all__ = ["Check", "GateSettings", "Method", "Tolerance", "Tolerances", "Verdict", "add_parser", "check_selection", "cmd",
           "compare", "differences", "load_run", "load_tolerances", "parse_tolerances", "percent", "render",
           "tolerances_from_args"]
