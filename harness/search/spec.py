"""The campaign spec: what a corner-case search runs, validated before anything starts.

A spec is a YAML mapping (``hil_configs/search.yaml``)::

    name: stopped-car-search
    seed: 1                      # the campaign's seed: every episode's seed and draw derive from it
    episodes: 32
    base: regression.yaml        # a run config (relative to this file); optional
    run: {duration_s: 4}         # run-config fields over the base (same keys as hil run's YAML)
    params:                      # the scenario parameters searched; omitted: all of its space
      gap_m: [15, 60]            #   a narrowed range
      ego_speed_mps:             #   empty: the parameter's whole range
    latency:                     # lockstep.latency fields searched (omitted: not searched)
      kind: normal               #   constant | normal | lognormal (default: normal when std_ms
      ms: [0, 300]               #   is searched, else constant)
      std_ms: [0, 50]
      camera_ms.back: [0, 200]   #   a rig camera's own delay / loss (camera_drop_prob.<name>)
    strategy: {kind: cem, generation: 8, elite_frac: 0.25, explore: 0.25, sigma: 0.1}
    score: {near_miss_m: 5}

Every episode runs the base config in lockstep with its drawn values. The scenario
parameters not searched keep the base's values. In lockstep only what the simulation
decides comes back the same on every machine (truth, the AI's estimates, mismatches
under the latency profile); wall-clock timing anomalies (a deadline miss, a latency
spike) depend on the machine's load. So an episode records them (``/events``, the
episode's ``anomalies`` count) but opens no corner case for them
(``corner_cases.on_anomalies`` is emptied): a campaign's cases and case ids are the
same however it is sharded, on any machine, and every one replays. ``resolve_spec`` returns a frozen
``Campaign`` whose ``campaign_id`` (sha256 of the resolved spec: the full run config,
the search space, the strategy, the seed and the episode count) names the campaign;
shards of one campaign share it, and ``hil search merge`` refuses others.

Raises: ``ConfigError`` (one line naming the spec field) for every mistake,
including an empty range (``lo >= hi``).
"""

from __future__ import annotations

import copy
import hashlib
import json
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from enum import Enum
from pathlib import Path
from types import MappingProxyType
from typing import Any

import yaml
from pydantic import BaseModel, Field, ValidationError

from hil.harness.config.loading import dump_config, load_config, parse_config
from hil.harness.config.model import LatencyConfig, LatencyKind, RunConfig
from hil.common.errors import ConfigError
from hil.harness.config.types import MODEL_CONFIG, Float, Int

LATENCY_PREFIX = "latency."
# Latency fields a search may draw (whichever of these LatencyConfig has: a drop
# probability joins the list once lockstep.latency supports one).
LATENCY_DIMS = ("ms", "std_ms", "sigma", "min_ms", "max_ms", "drop_prob", "drop_rate")
# A rig camera's own share, searched as "<group>.<camera name>" (bounds of one value).
CAMERA_DIMS: Mapping[str, tuple[float, float]] = MappingProxyType(
    {"camera_ms": (0.0, 60_000.0), "camera_drop_prob": (0.0, 1.0)})
_LATENCY_KINDS = (LatencyKind.CONSTANT, LatencyKind.NORMAL, LatencyKind.LOGNORMAL)


class StrategyKind(str, Enum):
    """How episodes' parameters are drawn (see harness/search/sampling.py)."""

    RANDOM = "random"  # uniform over the space, each episode on its own
    CEM = "cem"        # cross-entropy: a normal fit on the worst episodes so far
    MUTATE = "mutate"  # local mutation around the worst episodes so far


class StrategySpec(BaseModel):
    """Guided strategies work in generations of ``generation`` episodes; each draws
    from what the earlier ones found. ``explore`` of each guided generation stays
    uniform; ``sigma`` is the mutation step (cem: the least spread), as a fraction of
    each parameter's range; ``elite_frac`` of the episodes so far are the "worst"."""

    model_config = MODEL_CONFIG

    kind: StrategyKind = StrategyKind.RANDOM
    generation: Int = Field(8, ge=2, le=100_000)
    elite_frac: Float = Field(0.25, gt=0, le=1)
    explore: Float = Field(0.25, ge=0, lt=1)
    sigma: Float = Field(0.1, gt=0, le=1)


class ScoreSpec(BaseModel):
    """How bad an episode is (sampling.score): mismatches by kind, collisions, and a
    near miss when an ego came closer than ``near_miss_m`` to an obstacle."""

    model_config = MODEL_CONFIG

    near_miss_m: Float = Field(5.0, gt=0, le=1000)


class SpecModel(BaseModel):
    model_config = MODEL_CONFIG

    name: str = Field("search", pattern=r"^[A-Za-z0-9_.-]+$")
    seed: Int = Field(0, ge=0, le=2**63 - 1)
    episodes: Int = Field(16, ge=1, le=10_000_000)
    base: str | None = None
    run: dict[str, Any] = Field(default_factory=dict)
    params: dict[str, list[Float] | None] | None = None
    latency: dict[str, Any] = Field(default_factory=dict)
    strategy: StrategySpec = Field(default_factory=StrategySpec)
    score: ScoreSpec = Field(default_factory=ScoreSpec)


@dataclass(frozen=True)
class Dim:
    """One searched dimension: a scenario parameter (``name`` as in the scenario) or a
    latency field (``latency.<field>``), drawn in ``[lo, hi]`` (whole numbers when
    ``integer``)."""

    name: str
    lo: float
    hi: float
    unit: str = ""
    integer: bool = False

    @property
    def is_latency(self) -> bool:
        return self.name.startswith(LATENCY_PREFIX)

    @property
    def field(self) -> str:
        return self.name.removeprefix(LATENCY_PREFIX)

    def value(self, u: float) -> float:
        """The value at ``u`` in [0, 1] of the range (integers: equal-width bins)."""
        if self.integer:
            return float(min(self.hi, math.floor(self.lo + u * (self.hi - self.lo + 1))))
        return float(self.lo + u * (self.hi - self.lo))

    def unit_of(self, value: float) -> float:
        """Inverse of ``value`` (the centre of an integer's bin)."""
        if self.integer:
            return min(1.0, max(0.0, (value - self.lo + 0.5) / (self.hi - self.lo + 1)))
        return min(1.0, max(0.0, (value - self.lo) / (self.hi - self.lo)))


@dataclass(frozen=True)
class Campaign:
    """A resolved, validated campaign (see the module docstring)."""

    name: str
    seed: int
    episodes: int
    run: dict[str, Any]            # the full base run config (dump_config form)
    scenario: str
    dims: tuple[Dim, ...]
    latency_kind: str | None       # set on every episode when latency is searched
    strategy: StrategySpec
    score: ScoreSpec
    campaign_id: str
    source: str = "<spec>"

    def as_json(self) -> dict[str, Any]:
        """The resolved spec: self-contained (no file references), what the id hashes."""
        return {
            "name": self.name, "seed": self.seed, "episodes": self.episodes, "scenario": self.scenario,
            "dims": [{"name": d.name, "lo": d.lo, "hi": d.hi, "unit": d.unit, "integer": d.integer}
                     for d in self.dims],
            "latency_kind": self.latency_kind, "strategy": self.strategy.model_dump(mode="json"),
            "score": self.score.model_dump(mode="json"), "run": self.run,
        }

    def episode_config(self, *, index: int, seed: int, values: Mapping[str, float]) -> RunConfig:
        """The run config of episode ``index``: the base in lockstep, without progress
        display and without timing-anomaly corner cases (see the module docstring),
        with ``seed`` and the drawn ``values`` set.

        Raises:
            ConfigError: a drawn value the run config refuses (cannot happen for a
                validated campaign unless the config's rules changed).
        """
        data = copy.deepcopy(self.run)
        data.update(name=f"{self.name}-e{index:05d}", seed=int(seed), mode="lockstep", progress=False)
        data.setdefault("corner_cases", {})["on_anomalies"] = []  # wall clock: recorded, never a case
        scen = data.setdefault("scenario", {})
        scen["params"] = dict(scen.get("params") or {})
        lat = data.setdefault("lockstep", {}).setdefault("latency", {})
        if self.latency_kind is not None:
            lat["kind"] = self.latency_kind
        for d in self.dims:
            v = values[d.name]
            if d.is_latency and "." in d.field:  # a rig camera's: camera_ms.<name>
                group, camera = d.field.split(".", 1)
                lat.setdefault(group, {})[camera] = v
            elif d.is_latency:
                lat[d.field] = v
                if d.field == "max_ms":
                    lat["min_ms"] = min(float(lat.get("min_ms", 0.0)), v)
            else:
                scen["params"][d.name] = v
        return parse_config(data, source=f"{self.source} (episode {index})")

    @classmethod
    def from_json(cls, data: Mapping[str, Any], *, source: str = "<campaign.sqlite>") -> Campaign:
        """A campaign back from its stored resolved spec (``as_json``)."""
        try:
            dims = tuple(Dim(str(d["name"]), float(d["lo"]), float(d["hi"]), str(d.get("unit", "")),
                             bool(d.get("integer", False))) for d in data["dims"])
            c = cls(name=str(data["name"]), seed=int(data["seed"]), episodes=int(data["episodes"]),
                    run=dict(data["run"]), scenario=str(data["scenario"]), dims=dims,
                    latency_kind=data.get("latency_kind"),
                    strategy=StrategySpec.model_validate(data["strategy"]),
                    score=ScoreSpec.model_validate(data["score"]), campaign_id="", source=source)
        except (KeyError, TypeError, ValueError, ValidationError) as err:
            raise ConfigError(f"{source}: not a campaign spec ({type(err).__name__}: {err})") from err
        return _with_id(c)


def _with_id(c: Campaign) -> Campaign:
    canonical = json.dumps(c.as_json(), sort_keys=True, separators=(",", ":"))
    cid = hashlib.sha256(canonical.encode("utf-8")).hexdigest()[:16]
    return Campaign(**{**c.__dict__, "campaign_id": cid})


# --- loading --------------------------------------------------------------------------


def load_spec(path: str | Path, *, overrides: Sequence[str] = (), episodes: int | None = None,
              seed: int | None = None, strategy: str | None = None) -> Campaign:
    """Read a campaign spec, apply ``dotted.path=value`` overrides to its run config
    (``--set duration_s=2``) and the command line's ``episodes``/``seed``/``strategy``,
    and resolve it.

    Raises:
        ConfigError: file missing or not YAML, an unknown key, a bad value, an
            unknown scenario parameter, an empty or out-of-space range, or a base run
            config that does not validate (its own message).
    """
    p = Path(path)
    if not p.is_file():
        raise ConfigError(f"campaign spec not found: {p}" + (" (a directory)" if p.is_dir() else ""))
    try:
        data = yaml.safe_load(p.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError) as err:
        raise ConfigError(f"cannot read campaign spec {p}: {err}") from err
    except yaml.YAMLError as err:
        raise ConfigError(" ".join(f"{p}: YAML error: {err}".split())) from err
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise ConfigError(f"{p}: a campaign spec is a mapping of keys to values, got {type(data).__name__}")
    for key, value in (("episodes", episodes), ("seed", seed)):
        if value is not None:
            data[key] = value
    if strategy is not None:
        data["strategy"] = dict(data.get("strategy") or {}, kind=strategy)
    return resolve_spec(data, source=str(p), base_dir=p.parent, overrides=overrides)


def resolve_spec(data: Mapping[str, Any], *, source: str = "<spec>", base_dir: Path = Path("."),
                 overrides: Sequence[str] = ()) -> Campaign:
    """Validate a parsed spec mapping (see ``load_spec``). Raises ConfigError."""
    try:
        spec = SpecModel.model_validate(dict(data))
    except ValidationError as err:
        e = err.errors(include_url=False)[0]
        loc = ".".join(str(x) for x in e["loc"]) or "<root>"
        if e["type"] == "extra_forbidden":
            valid = ", ".join(SpecModel.model_fields) if len(e["loc"]) == 1 else "see the spec's docstring"
            raise ConfigError(f"{source}: unknown key {loc!r} (valid keys: {valid})") from err
        raise ConfigError(f"{source}: spec error at {loc}: got {e['input']!r}; expected "
                          f"{e['msg'].removeprefix('Input should be ').removeprefix('Value error, ')}") from err
    run = _run_config(spec, source, base_dir, overrides)
    from hil import scenarios

    sdef = scenarios.get(run.scenario.name)
    base_params = sdef.resolve(run.scenario.params)
    dims = _scenario_dims(spec, sdef, source) + _latency_dims(spec, source)
    if not dims:
        raise ConfigError(f"{source}: nothing to search: params is empty and no latency dimension is given")
    lat_kind = _latency_kind(spec, run, dims, source)
    run_dump = dump_config(run)
    run_dump["scenario"]["params"] = base_params
    c = _with_id(Campaign(name=spec.name, seed=spec.seed, episodes=spec.episodes, run=run_dump,
                          scenario=sdef.name, dims=tuple(dims), latency_kind=lat_kind, strategy=spec.strategy,
                          score=spec.score, campaign_id="", source=source))
    # Both corners of the space must make valid run configs: fail now, not mid-campaign.
    for u in (0.0, 1.0):
        c.episode_config(index=0, seed=0, values={d.name: d.value(u) for d in dims})
    return c


def _run_config(spec: SpecModel, source: str, base_dir: Path, overrides: Sequence[str]) -> RunConfig:
    base: dict[str, Any] = {}
    if spec.base:
        bpath = Path(spec.base) if Path(spec.base).is_absolute() else base_dir / spec.base
        if not bpath.is_file():
            raise ConfigError(f"{source}: base: run config not found: {bpath}")
        base = dump_config(load_config(bpath))
    merged = _deep_merge(base, spec.run)
    return parse_config(merged, source=f"{source} (run)", overrides=overrides)


def _deep_merge(a: Mapping[str, Any], b: Mapping[str, Any]) -> dict[str, Any]:
    out = copy.deepcopy(dict(a))
    for k, v in b.items():
        if isinstance(v, Mapping) and isinstance(out.get(k), Mapping):
            out[k] = _deep_merge(out[k], v)
        else:
            out[k] = copy.deepcopy(v)
    return out


def _range(source: str, where: str, given: list[float] | None, lo: float, hi: float, unit: str) -> tuple[float, float]:
    if given is None:
        r = (lo, hi)
    elif len(given) != 2:
        raise ConfigError(f"{source}: {where}: got {given!r}; expected a range [lo, hi] (or nothing: the whole "
                          f"range [{lo:g}, {hi:g}] {unit})".rstrip())
    else:
        r = (float(given[0]), float(given[1]))
    if not (r[0] < r[1]):
        space = f"[{lo:g}, {hi:g}] {unit}".rstrip()
        raise ConfigError(f"{source}: {where}: empty range [{r[0]:g}, {r[1]:g}]; expected lo < hi within "
                          f"{space} (to hold a value fixed, leave it out of the search and set it in the "
                          "run config)")
    if r[0] < lo or r[1] > hi:
        raise ConfigError(f"{source}: {where}: range [{r[0]:g}, {r[1]:g}] leaves the space [{lo:g}, {hi:g}] {unit}"
                          .rstrip())
    return r


def _scenario_dims(spec: SpecModel, sdef: Any, source: str) -> list[Dim]:
    space = {p.name: p for p in sdef.params}
    wanted = spec.params if spec.params is not None else {name: None for name in space}
    dims = []
    for name, given in wanted.items():
        p = space.get(name)
        if p is None:
            valid = "; ".join(q.describe() for q in sdef.params)
            raise ConfigError(f"{source}: params.{name}: unknown parameter of scenario {sdef.name!r}; valid: {valid}")
        lo, hi = _range(source, f"params.{name}", given, p.lo, p.hi, p.unit)
        if p.integer and not (float(lo).is_integer() and float(hi).is_integer()):
            raise ConfigError(f"{source}: params.{name}: integer parameter; got range [{lo:g}, {hi:g}]")
        dims.append(Dim(name, lo, hi, p.unit, p.integer))
    return dims


def _latency_dims(spec: SpecModel, source: str) -> list[Dim]:
    fields = LatencyConfig.model_fields
    allowed = [f for f in LATENCY_DIMS if f in fields]
    dims = []
    for key, given in spec.latency.items():
        if key == "kind":
            continue
        group = key.split(".", 1)[0] if "." in key else None
        if key not in allowed and group not in CAMERA_DIMS:
            hint = " (link drops are searched as drop_prob)" if "drop" in key else ""
            raise ConfigError(f"{source}: latency.{key}: not a searchable latency field; valid: kind, "
                              f"{', '.join(allowed)}, " + ", ".join(f"{g}.<camera>" for g in CAMERA_DIMS) + hint)
        if given is not None and not (isinstance(given, list) and all(
                isinstance(x, (int, float)) and not isinstance(x, bool) for x in given)):
            raise ConfigError(f"{source}: latency.{key}: got {given!r}; expected a range [lo, hi]")
        lo, hi = CAMERA_DIMS[group] if group is not None else _field_bounds(fields[key])
        unit = "ms" if (group or key).endswith("ms") else ""
        r = _range(source, f"latency.{key}", given, lo, hi, unit)
        dims.append(Dim(LATENCY_PREFIX + key, r[0], r[1], unit))
    return dims


def _field_bounds(info: Any) -> tuple[float, float]:
    lo, hi = -math.inf, math.inf
    for m in info.metadata:
        for attr, is_lo in (("ge", True), ("gt", True), ("le", False), ("lt", False)):
            v = getattr(m, attr, None)
            if v is not None:
                lo, hi = (max(lo, float(v)), hi) if is_lo else (lo, min(hi, float(v)))
    return lo, hi


def _latency_kind(spec: SpecModel, run: RunConfig, dims: list[Dim], source: str) -> str | None:
    lat_fields = {d.field for d in dims if d.is_latency}
    profile_fields = {f for f in lat_fields if "." not in f}  # a camera's share needs no profile kind
    given = spec.latency.get("kind")
    if given is not None:
        valid = [k.value for k in _LATENCY_KINDS]
        if given not in valid:
            raise ConfigError(f"{source}: latency.kind: got {given!r}; expected one of {', '.join(valid)}")
        if not lat_fields:
            raise ConfigError(f"{source}: latency.kind: {given!r} without a latency field to search; "
                              f"set the profile in the run config's lockstep.latency instead")
        return str(given)
    if not profile_fields:
        return None
    if run.lockstep.latency.kind in _LATENCY_KINDS:
        return run.lockstep.latency.kind.value
    return "normal" if profile_fields & {"std_ms", "min_ms", "max_ms"} else "constant"


__all__ = ["CAMERA_DIMS", "Campaign", "Dim", "ScoreSpec", "StrategyKind", "StrategySpec", "load_spec", "resolve_spec"]
