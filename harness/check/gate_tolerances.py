"""Tolerances of ``hil compare``: how much each figure may grow (the practical
threshold) and how much it moves between runs of one build (run-to-run noise).

Defaults (``--tolerances FILE.yaml`` sets any of these, flags win over the file)::

    p1:  {rel: 0.10, abs_ms: 0.5}     # the floor (fastest 1 % of frames)
    p50: {rel: 0.10, abs_ms: 0.5}
    p99: {rel: 0.20, abs_ms: 2.0}
    std: {rel: 0.25, abs_ms: 1.0}     # jitter
    drop_rate: {abs: 0.01}
    noise:                            # run-to-run: rel (fraction) and abs_ms, combined
      p1:  {rel: 0.05, abs_ms: 0.1}   #   as sqrt((rel x value)^2 + abs_ms^2); a bare
      p50: {rel: 0.25, abs_ms: 1.0}   #   number sets rel
      p99: {rel: 0.60, abs_ms: 3.0}
      std: {rel: 0.60, abs_ms: 1.0}
    stages:                           # per stage, any of p1 / p50 / p99 / std, and noise
      transport: {p99: {abs_ms: 5.0}}
      render: {noise: {p1: 0.25}}     # (a default: see below)
    skip_stages: [apply_delay]        # not checked
    only_stages: [end_to_end]         # check these alone (same as --stage, repeatable)

A stage name that is not one of ``summary.json``'s stages (``STAGES``), an unknown
key or metric, is refused with the valid names: a typo must not switch a check off.

A figure may grow by ``max(rel × baseline, abs)``. ``noise`` is the standard
deviation of each figure between runs of the same build, ``sqrt((rel × value)² +
abs²)``: the run-to-run variation that one pair of runs cannot show (the machine's
load changing between them slows every frame by a share, CPU sharing, and adds
delays of its own, scheduling: both parts). The defaults were measured with
``bench/bench_gate.py`` (it prints them per stage) on a shared 2-core machine (load
average 3-7): the floor of the AI's stages moved 4-8 % between runs of one build,
the median 6-25 %, the tail and the jitter 50-75 %. Stages of the harness itself
move more: ``render`` (software rendering on the CPUs that the load takes; its
floor jumps between ~7 and ~11 ms) and ``apply_delay``/``to_apply`` (when a control
lands relative to the physics steps); they get their own defaults
(``STAGE_NOISE``). On a quiet, dedicated machine measure yours and set them lower:
the gate then sees smaller changes.
"""

from __future__ import annotations

import argparse
import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from hil.common.errors import ConfigError
from hil.timing.records import STAGES

LATENCY_METRICS = ("p1", "p50", "p99", "std")
_DEFAULTS = {"p1": (0.10, 0.5), "p50": (0.10, 0.5), "p99": (0.20, 2.0), "std": (0.25, 1.0)}


@dataclass(frozen=True)
class Tolerance:
    """How much a value may grow: ``rel`` (fraction of the baseline) or ``abs`` (ms,
    or a rate for drop_rate), whichever allows more."""

    rel: float
    abs: float

    def allowance(self, baseline: float) -> float:
        return max(self.rel * abs(baseline), self.abs)


#: Run-to-run noise per metric (rel: fraction of the value; abs: ms), measured by bench_gate.py.
RUN_NOISE: Mapping[str, Tolerance] = {"p1": Tolerance(0.05, 0.1), "p50": Tolerance(0.25, 1.0),
                                      "p99": Tolerance(0.60, 3.0), "std": Tolerance(0.60, 1.0)}
#: ... and for the harness's own stages that move more (same measurement).
STAGE_NOISE: Mapping[str, Mapping[str, Tolerance]] = {
    "render": {"p1": Tolerance(0.25, 0.1)}, "to_apply": {"p1": Tolerance(0.25, 0.1)},
    "apply_delay": {"p1": Tolerance(0.25, 0.1), "p50": Tolerance(0.60, 1.0)}}


@dataclass(frozen=True)
class Tolerances:
    """The gate's tolerances (defaults in the module docstring)."""

    p1: Tolerance = Tolerance(0.10, 0.5)
    p50: Tolerance = Tolerance(0.10, 0.5)
    p99: Tolerance = Tolerance(0.20, 2.0)
    std: Tolerance = Tolerance(0.25, 1.0)
    drop_rate: Tolerance = Tolerance(0.0, 0.01)
    noise: Mapping[str, Tolerance] = field(default_factory=lambda: dict(RUN_NOISE))
    stage_noise: Mapping[str, Mapping[str, Tolerance]] = field(
        default_factory=lambda: {k: dict(v) for k, v in STAGE_NOISE.items()})
    stages: Mapping[str, Mapping[str, Tolerance]] = field(default_factory=dict)
    only_stages: tuple[str, ...] = ()
    skip_stages: tuple[str, ...] = ()

    def for_stage(self, metric: str, stage: str) -> Tolerance:
        return self.stages.get(stage, {}).get(metric, getattr(self, metric))

    def noise_of(self, metric: str, stage: str | None = None) -> Tolerance:
        """Run-to-run noise of ``metric`` (of ``stage`` where it has its own): ``rel``
        (fraction of the value) and ``abs`` (ms); none where unset."""
        own = self.stage_noise.get(stage or "", {})
        return own[metric] if metric in own else self.noise.get(metric, Tolerance(0.0, 0.0))

    def checks_stage(self, stage: str) -> bool:
        return stage not in self.skip_stages and (not self.only_stages or stage in self.only_stages)

    def with_metric(self, metric: str, tol: Tolerance) -> Tolerances:
        """A copy with the tolerance of ``metric`` (one of ``LATENCY_METRICS``) set to ``tol``.

        Raises:
            ValueError: ``metric`` is not a latency metric.
        """
        match metric:
            case "p1":
                return dataclasses.replace(self, p1=tol)
            case "p50":
                return dataclasses.replace(self, p50=tol)
            case "p99":
                return dataclasses.replace(self, p99=tol)
            case "std":
                return dataclasses.replace(self, std=tol)
        raise ValueError(f"not a latency metric: {metric!r}; expected one of {LATENCY_METRICS}")


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


def check_stage(name: str, where: str) -> str:
    """``name`` when it is a stage of ``summary.json`` (``STAGES``).

    Raises:
        ConfigError: ``where`` (a flag or a key path) names an unknown stage; the
            message lists the valid ones. A typo must not switch a check off.
    """
    if name not in STAGES:
        raise ConfigError(f"{where}: unknown stage {name!r} (valid: {', '.join(STAGES)})")
    return name


def _stage_list(v: Any, where: str, source: str) -> tuple[str, ...]:
    if not isinstance(v, list) or not all(isinstance(s, str) for s in v):
        raise ConfigError(f"{source}: tolerances error at {where}: got {v!r}; expected a list of stage names")
    return tuple(check_stage(s, f"{source}: tolerances error at {where}") for s in v)


def _noise(node: Any, base: Mapping[str, Tolerance], source: str, where: str = "noise") -> dict[str, Tolerance]:
    if not isinstance(node, dict):
        raise ConfigError(f"{source}: tolerances error at {where}: got {node!r}; expected a mapping of "
                          f"{'/'.join(LATENCY_METRICS)} to {{rel, abs_ms}} or a fraction >= 0")
    out = dict(base)
    for k, v in node.items():
        if k not in LATENCY_METRICS:
            raise ConfigError(f"{source}: tolerances error at {where}: unknown metric {k!r} "
                              f"(valid: {', '.join(LATENCY_METRICS)})")
        was = out.get(k, RUN_NOISE.get(k, Tolerance(0.0, 0.0)))
        if isinstance(v, dict):
            out[k] = _tolerance(v, was, f"{where}.{k}", source, abs_key="abs_ms")
            continue
        if isinstance(v, bool) or not isinstance(v, (int, float)) or v < 0:
            raise ConfigError(f"{source}: tolerances error at {where}.{k}: got {v!r}; expected a number >= 0 "
                              "or {rel, abs_ms}")
        out[k] = Tolerance(float(v), was.abs)
    return out


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
    valid = (*LATENCY_METRICS, "drop_rate", "noise", "stages", "only_stages", "skip_stages")
    for key, node in data.items():
        if key in LATENCY_METRICS:
            tol = tol.with_metric(key, _tolerance(node, getattr(tol, key), key, source, abs_key="abs_ms"))
        elif key == "drop_rate":
            tol = dataclasses.replace(tol, drop_rate=_tolerance(node, tol.drop_rate, key, source, abs_key="abs"))
        elif key == "noise":
            tol = dataclasses.replace(tol, noise=_noise(node, tol.noise, source))
        elif key == "only_stages":
            tol = dataclasses.replace(tol, only_stages=_stage_list(node, key, source))
        elif key == "skip_stages":
            tol = dataclasses.replace(tol, skip_stages=_stage_list(node, key, source))
        elif key == "stages":
            if not isinstance(node, dict):
                raise ConfigError(f"{source}: tolerances error at stages: got {node!r}; expected a mapping "
                                  "of stage name to {p1|p50|p99|std: {rel, abs_ms}}")
            stages = {k: dict(v) for k, v in tol.stages.items()}
            stage_noise = {k: dict(v) for k, v in tol.stage_noise.items()}
            for stage, per in node.items():
                check_stage(str(stage), f"{source}: tolerances error at stages")
                if not isinstance(per, dict):
                    raise ConfigError(f"{source}: tolerances error at stages.{stage}: got {per!r}; expected a "
                                      "mapping of p1/p50/p99/std to {rel, abs_ms}, and noise")
                for metric, t in per.items():
                    if metric == "noise":
                        stage_noise[stage] = _noise(t, stage_noise.get(stage, {}), source, f"stages.{stage}.noise")
                        continue
                    if metric not in LATENCY_METRICS:
                        raise ConfigError(f"{source}: tolerances error at stages.{stage}: unknown metric "
                                          f"{metric!r} (valid: {', '.join(LATENCY_METRICS)})")
                    stages.setdefault(stage, {})[metric] = _tolerance(
                        t, tol.for_stage(metric, stage), f"stages.{stage}.{metric}", source, abs_key="abs_ms")
            tol = dataclasses.replace(tol, stages=stages, stage_noise=stage_noise)
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


def add_tolerance_args(p: argparse.ArgumentParser) -> None:
    """The tolerance flags of ``hil compare``."""
    p.add_argument("--tolerances", type=Path, default=None, metavar="FILE.yaml",
                   help="tolerances YAML: p1/p50/p99/std {rel, abs_ms}, drop_rate {abs}, noise, stages, "
                        "skip_stages, only_stages (README); the flags below win over it")
    for metric, (rel, abs_ms) in _DEFAULTS.items():
        p.add_argument(f"--{metric}-rel", type=float, default=None, metavar="FRACTION",
                       help=f"{metric} may grow by this fraction of the baseline (default {rel:g})")
        p.add_argument(f"--{metric}-abs-ms", type=float, default=None, metavar="MS",
                       help=f"... or by this many ms, whichever is larger (default {abs_ms:g})")
    p.add_argument("--drop-rate-abs", type=float, default=None, metavar="RATE",
                   help="drop rate may grow by this much, absolute (default 0.01)")
    p.add_argument("--stage", action="append", default=[], metavar="NAME",
                   help="check only this stage (repeatable; default all)")


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
        tol = tol.with_metric(metric, Tolerance(t.rel if rel is None else rel, t.abs if abs_ms is None else abs_ms))
    if args.drop_rate_abs is not None:
        if args.drop_rate_abs < 0:
            raise ConfigError(f"--drop-rate-abs: got {args.drop_rate_abs:g}; expected a number >= 0")
        tol = dataclasses.replace(tol, drop_rate=Tolerance(tol.drop_rate.rel, args.drop_rate_abs))
    if args.stage:
        tol = dataclasses.replace(tol, only_stages=tuple(check_stage(s, "--stage") for s in args.stage))
    return tol


__all__ = ["LATENCY_METRICS", "RUN_NOISE", "STAGE_NOISE", "Tolerance", "Tolerances", "add_tolerance_args",
           "check_stage", "load_tolerances", "parse_tolerances", "tolerances_from_args"]
