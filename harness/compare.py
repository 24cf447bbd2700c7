"""``hil compare BASELINE RUN``: the latency regression gate.

Compares two runs' ``summary.json`` (each argument a run folder or the file) and
exits 1 when RUN is worse than BASELINE beyond a tolerance, 0 otherwise, 2 on bad
input (missing, truncated or foreign file; bad tolerances).

Checked for every vehicle and stage of the baseline (``vehicles.V.latency_ms.S``):

=============  ==========================  ===============================
metric         may grow by                 flags
=============  ==========================  ===============================
``p50``        max(10 %, 0.5 ms)           ``--p50-rel``, ``--p50-abs-ms``
``p99``        max(20 %, 2 ms)             ``--p99-rel``, ``--p99-abs-ms``
``std``        max(25 %, 1 ms) (jitter)    ``--std-rel``, ``--std-abs-ms``
``drop_rate``  +0.01 absolute, per vehicle ``--drop-rate-abs``
=============  ==========================  ===============================

The limit is ``baseline + max(rel × baseline, abs)``. A value that falls by more than
that allowance is reported as ``better`` (information, not a failure). A vehicle or
stage of the baseline missing in RUN (or without samples there) is a regression; one
new in RUN is information. A RUN that ended early (``ended_by`` not ``duration``) is
a regression. Different scenario, seed or config hash are noted, not failed.

``--tolerances FILE.yaml`` sets any of these, and per-stage overrides; flags win over
the file, the file over the defaults::

    p50: {rel: 0.10, abs_ms: 0.5}
    p99: {rel: 0.20, abs_ms: 2.0}
    std: {rel: 0.25, abs_ms: 1.0}
    drop_rate: {abs: 0.01}
    stages:                       # per stage, any of p50 / p99 / std
      transport: {p99: {abs_ms: 5.0}}
    skip_stages: [apply_delay]    # not checked
    only_stages: [end_to_end]     # check these alone (same as --stage, repeatable)
"""

from __future__ import annotations

import argparse
import dataclasses
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from enum import Enum
from pathlib import Path
from typing import Any

import yaml

from harness.run_folder import load_summary
from timing.errors import ConfigError
from timing.records import STAGES

LATENCY_METRICS = ("p50", "p99", "std")
EXIT_OK, EXIT_REGRESSION = 0, 1


@dataclass(frozen=True)
class Tolerance:
    """How much a value may grow: ``rel`` (fraction of the baseline) or ``abs`` (ms,
    or a rate for drop_rate), whichever allows more."""

    rel: float
    abs: float

    def allowance(self, baseline: float) -> float:
        return max(self.rel * abs(baseline), self.abs)


@dataclass(frozen=True)
class Tolerances:
    """The gate's tolerances (defaults in the module docstring)."""

    p50: Tolerance = Tolerance(0.10, 0.5)
    p99: Tolerance = Tolerance(0.20, 2.0)
    std: Tolerance = Tolerance(0.25, 1.0)
    drop_rate: Tolerance = Tolerance(0.0, 0.01)
    stages: Mapping[str, Mapping[str, Tolerance]] = field(default_factory=dict)
    only_stages: tuple[str, ...] = ()
    skip_stages: tuple[str, ...] = ()

    def for_stage(self, metric: str, stage: str) -> Tolerance:
        return self.stages.get(stage, {}).get(metric, getattr(self, metric))

    def checks_stage(self, stage: str) -> bool:
        return stage not in self.skip_stages and (not self.only_stages or stage in self.only_stages)


class Verdict(str, Enum):
    OK = "ok"
    BETTER = "better"
    REGRESSION = "REGRESSION"
    MISSING = "MISSING"
    NEW = "new"
    NO_DATA = "no data"

    @property
    def fails(self) -> bool:
        return self in (Verdict.REGRESSION, Verdict.MISSING)


@dataclass(frozen=True)
class Check:
    """One compared figure. ``limit``: the largest passing value; ``None`` where no
    limit applies."""

    vehicle: str
    stage: str
    metric: str
    baseline: float | None
    run: float | None
    limit: float | None
    verdict: Verdict
    note: str = ""


# --- tolerances ------------------------------------------------------------------------


def _tolerance(node: Any, base: Tolerance, where: str, source: str, *, abs_key: str) -> Tolerance:
    if not isinstance(node, dict):
        raise ConfigError(f"{source}: tolerances error at {where}: got {node!r}; expected a mapping "
                          f"with rel and/or {abs_key}")
    out = base
    for k, v in node.items():
        if k not in ("rel", abs_key):
            raise ConfigError(f"{source}: tolerances error at {where}: unknown key {k!r} "
                              f"(valid keys: rel, {abs_key})")
        if isinstance(v, bool) or not isinstance(v, (int, float)) or v < 0:
            raise ConfigError(f"{source}: tolerances error at {where}.{k}: got {v!r}; expected a number >= 0")
        out = dataclasses.replace(out, **{"rel" if k == "rel" else "abs": float(v)})
    return out


def _stage_list(v: Any, where: str, source: str) -> tuple[str, ...]:
    if not isinstance(v, list) or not all(isinstance(s, str) for s in v):
        raise ConfigError(f"{source}: tolerances error at {where}: got {v!r}; expected a list of stage names")
    return tuple(v)


def parse_tolerances(data: Any, *, source: str = "<tolerances>", base: Tolerances | None = None) -> Tolerances:
    """Tolerances from a parsed YAML mapping, over ``base`` (default: the defaults).

    Raises:
        ConfigError: one line naming the key path and the bad value.
    """
    tol = base or Tolerances()
    if data is None:
        return tol
    if not isinstance(data, dict):
        raise ConfigError(f"{source}: tolerances error at <root>: got {data!r}; expected a mapping")
    valid = (*LATENCY_METRICS, "drop_rate", "stages", "only_stages", "skip_stages")
    for key, node in data.items():
        if key in LATENCY_METRICS:
            tol = dataclasses.replace(tol, **{key: _tolerance(node, getattr(tol, key), key, source, abs_key="abs_ms")})
        elif key == "drop_rate":
            tol = dataclasses.replace(tol, drop_rate=_tolerance(node, tol.drop_rate, key, source, abs_key="abs"))
        elif key in ("only_stages", "skip_stages"):
            tol = dataclasses.replace(tol, **{key: _stage_list(node, key, source)})
        elif key == "stages":
            if not isinstance(node, dict):
                raise ConfigError(f"{source}: tolerances error at stages: got {node!r}; expected a mapping "
                                  "of stage name to {p50|p99|std: {rel, abs_ms}}")
            stages = {k: dict(v) for k, v in tol.stages.items()}
            for stage, per in node.items():
                if not isinstance(per, dict):
                    raise ConfigError(f"{source}: tolerances error at stages.{stage}: got {per!r}; expected a "
                                      "mapping of p50/p99/std to {rel, abs_ms}")
                for metric, t in per.items():
                    if metric not in LATENCY_METRICS:
                        raise ConfigError(f"{source}: tolerances error at stages.{stage}: unknown metric "
                                          f"{metric!r} (valid: {', '.join(LATENCY_METRICS)})")
                    stages.setdefault(stage, {})[metric] = _tolerance(
                        t, tol.for_stage(metric, stage), f"stages.{stage}.{metric}", source, abs_key="abs_ms")
            tol = dataclasses.replace(tol, stages=stages)
        else:
            raise ConfigError(f"{source}: tolerances error: unknown key {key!r} (valid keys: {', '.join(valid)})")
    return tol


def load_tolerances(path: str | Path, *, base: Tolerances | None = None) -> Tolerances:
    """Read a tolerances YAML file (format in the module docstring).

    Raises:
        ConfigError: missing or unreadable file, bad YAML, or a bad value.
    """
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ConfigError(f"{p}: tolerances file not found") from None
    except (OSError, UnicodeDecodeError) as err:
        raise ConfigError(f"{p}: cannot read tolerances file: {getattr(err, 'strerror', None) or err}") from err
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as err:
        mark = getattr(err, "problem_mark", None)
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark else ""
        raise ConfigError(f"{p}: YAML syntax error{where}: {getattr(err, 'problem', None) or err}") from err
    return parse_tolerances(data, source=str(p), base=base)


# --- comparing ---------------------------------------------------------------------------


def _stage_order(names: Sequence[str]) -> list[str]:
    return [s for s in STAGES if s in names] + sorted(s for s in names if s not in STAGES)


def _num(d: Mapping[str, Any], key: str) -> float | None:
    v = d.get(key)
    return float(v) if isinstance(v, (int, float)) and not isinstance(v, bool) else None


def _judge(vehicle: str, stage: str, metric: str, base: float | None, run: float | None,
           tol: Tolerance) -> Check:
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
    return Check(vehicle, stage, metric, base, run, limit, verdict)


def compare(baseline: Mapping[str, Any], run: Mapping[str, Any], tol: Tolerances | None = None) -> list[Check]:
    """Every check of ``run`` against ``baseline`` (two parsed summary.json)."""
    tol = tol or Tolerances()
    checks: list[Check] = []
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
        checks.append(_judge(vehicle, "-", "drop_rate", _num(b, "drop_rate"), _num(r, "drop_rate"), tol.drop_rate))
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
            for metric in LATENCY_METRICS:
                checks.append(_judge(vehicle, stage, metric, _num(bl[stage] or {}, f"{metric}_ms"),
                                     _num(rl[stage] or {}, f"{metric}_ms"), tol.for_stage(metric, stage)))
    return checks


def differences(baseline: Mapping[str, Any], run: Mapping[str, Any]) -> list[str]:
    """What differs between the two runs' setups (scenario, parameters, seed, config)."""
    out = []
    for key in ("scenario", "scenario_params", "seed", "config_hash"):
        if baseline.get(key) != run.get(key):
            out.append(f"{key} differs: baseline {baseline.get(key)!r}, run {run.get(key)!r}")
    return out


# --- the command -------------------------------------------------------------------------


def _value(metric: str, v: float | None) -> str:
    if v is None:
        return "–"
    return f"{v * 100:.2f} %" if metric == "drop_rate" else f"{v:.3f} ms"


def _change(c: Check) -> str:
    if c.baseline is None or c.run is None:
        return c.note
    d = c.run - c.baseline
    if c.metric == "drop_rate":
        return f"{d * 100:+.2f} pp"
    if not c.baseline:
        return f"{d:+.3f} ms"
    ratio = c.run / c.baseline
    rel = f"×{ratio:.0f}" if abs(ratio) >= 10 else f"{(ratio - 1) * 100:+.1f} %"
    return f"{d:+.3f} ms ({rel})"


def render(checks: Sequence[Check], *, failures_only: bool = False) -> Any:
    """A rich table of ``checks``."""
    from rich.table import Table

    style = {Verdict.REGRESSION: "bold red", Verdict.MISSING: "bold red", Verdict.BETTER: "green",
             Verdict.NEW: "cyan", Verdict.NO_DATA: "dim", Verdict.OK: ""}
    t = Table(title="latency regression check (RUN against BASELINE)", title_justify="left")
    for col, just in (("vehicle", "left"), ("stage", "left"), ("metric", "left"), ("baseline", "right"),
                      ("run", "right"), ("change", "right"), ("limit", "right"), ("verdict", "left")):
        t.add_column(col, justify=just)  # type: ignore[arg-type]
    for c in checks:
        if failures_only and not c.verdict.fails:
            continue
        t.add_row(c.vehicle, c.stage, c.metric, _value(c.metric, c.baseline), _value(c.metric, c.run), _change(c),
                  "–" if c.limit is None else f"≤ {_value(c.metric, c.limit)}",
                  f"[{style[c.verdict]}]{c.verdict.value}[/]" if style[c.verdict] else c.verdict.value)
    return t


def add_parser(sub: Any) -> None:
    """Register ``hil compare`` on the CLI's subparsers."""
    p = sub.add_parser("compare", help="fail (exit 1) when RUN's latency regressed against BASELINE",
                       description="Compare two runs' summary.json with tolerances; exit 1 on any regression. "
                                   "Defaults: p50 may grow by max(10%, 0.5 ms), p99 by max(20%, 2 ms), "
                                   "std by max(25%, 1 ms), drop_rate by 0.01.")
    p.add_argument("baseline", help="the reference run folder or its summary.json")
    p.add_argument("run", help="the run to check (folder or summary.json)")
    p.add_argument("--tolerances", type=Path, default=None, metavar="FILE.yaml",
                   help="tolerances YAML: p50/p99/std {rel, abs_ms}, drop_rate {abs}, stages, "
                        "skip_stages, only_stages (README); the flags below win over it")
    for metric, rel, abs_ms in (("p50", 0.10, 0.5), ("p99", 0.20, 2.0), ("std", 0.25, 1.0)):
        p.add_argument(f"--{metric}-rel", type=float, default=None, metavar="FRACTION",
                       help=f"{metric} may grow by this fraction of the baseline (default {rel:g})")
        p.add_argument(f"--{metric}-abs-ms", type=float, default=None, metavar="MS",
                       help=f"... or by this many ms, whichever is larger (default {abs_ms:g})")
    p.add_argument("--drop-rate-abs", type=float, default=None, metavar="RATE",
                   help="drop rate may grow by this much, absolute (default 0.01)")
    p.add_argument("--stage", action="append", default=[], metavar="NAME",
                   help="check only this stage (repeatable; default all)")
    p.add_argument("--failures-only", action="store_true", help="list only the failing checks")


def tolerances_from_args(args: argparse.Namespace) -> Tolerances:
    """Defaults, then ``--tolerances``, then the flags.

    Raises:
        ConfigError: bad file, or a negative flag value.
    """
    tol = load_tolerances(args.tolerances) if args.tolerances is not None else Tolerances()
    for metric in LATENCY_METRICS:
        t = getattr(tol, metric)
        rel, abs_ms = getattr(args, f"{metric}_rel"), getattr(args, f"{metric}_abs_ms")
        for flag, v in ((f"--{metric}-rel", rel), (f"--{metric}-abs-ms", abs_ms)):
            if v is not None and v < 0:
                raise ConfigError(f"{flag}: got {v:g}; expected a number >= 0")
        tol = dataclasses.replace(tol, **{metric: Tolerance(t.rel if rel is None else rel,
                                                            t.abs if abs_ms is None else abs_ms)})
    if args.drop_rate_abs is not None:
        if args.drop_rate_abs < 0:
            raise ConfigError(f"--drop-rate-abs: got {args.drop_rate_abs:g}; expected a number >= 0")
        tol = dataclasses.replace(tol, drop_rate=Tolerance(tol.drop_rate.rel, args.drop_rate_abs))
    if args.stage:
        tol = dataclasses.replace(tol, only_stages=tuple(args.stage))
    return tol


def cmd(args: argparse.Namespace) -> int:
    """``hil compare``: 0 no regression, 1 regression; ConfigError (exit 2) on bad input."""
    from rich.console import Console

    tol = tolerances_from_args(args)
    baseline = load_summary(args.baseline)
    run = load_summary(args.run)
    checks = compare(baseline, run, tol)
    console = Console()
    if not console.is_terminal:
        console.width = max(console.width, 120)
    for note in differences(baseline, run):
        console.print(f"[yellow]note: {note}[/yellow]")
    console.print(render(checks, failures_only=args.failures_only))
    failed = [c for c in checks if c.verdict.fails]
    if failed:
        names = ", ".join(f"{c.vehicle} {c.stage} {c.metric}".replace(" - ", " ") for c in failed[:8])
        console.print(f"[bold red]REGRESSION[/]: {len(failed)} of {len(checks)} checks failed ({names}"
                      + (", ..." if len(failed) > 8 else "") + ")")
        return EXIT_REGRESSION
    console.print(f"[green]ok[/]: all {len(checks)} checks within their limits")
    return EXIT_OK


__all__ = ["Check", "Tolerance", "Tolerances", "Verdict", "add_parser", "cmd", "compare", "differences",
           "load_tolerances", "parse_tolerances", "render", "tolerances_from_args"]
