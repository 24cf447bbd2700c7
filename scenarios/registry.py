"""The scenario registry: names to factories with typed parameter spaces."""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass

from hil.common.errors import ConfigError
from hil.scenarios.params import Param, resolve_params
from hil.scenarios.world import CameraSpec, WorldSpec

BuildFn = Callable[..., WorldSpec]


@dataclass(frozen=True)
class ScenarioDef:
    """A registered scenario.

    ``build(params=..., seed=..., camera=..., physics_step_s=...)`` returns the world;
    it must be deterministic in ``(params, seed)``.
    """

    name: str
    summary: str
    params: tuple[Param, ...]
    build_fn: BuildFn

    def resolve(self, given: Mapping[str, float]) -> dict[str, float]:
        return resolve_params(self.name, self.params, given)

    def build(self, *, params: Mapping[str, float], seed: int, camera: CameraSpec,
              physics_step_s: float, shadows: bool = False, reflections: bool = False) -> WorldSpec:
        resolved = self.resolve(params)
        return self.build_fn(params=resolved, seed=seed, camera=camera, physics_step_s=physics_step_s,
                             shadows=shadows, reflections=reflections)


class _Registry:
    def __init__(self) -> None:
        self._defs: dict[str, ScenarioDef] = {}

    def add(self, d: ScenarioDef) -> None:
        if d.name in self._defs:
            raise ValueError(f"scenario {d.name!r} registered twice")
        self._defs[d.name] = d

    def get(self, name: str) -> ScenarioDef:
        try:
            return self._defs[name]
        except KeyError:
            raise ConfigError(
                f"scenario.name: unknown scenario {name!r}; valid: {', '.join(sorted(self._defs))}"
            ) from None

    def names(self) -> list[str]:
        return sorted(self._defs)


# The one registry, filled at import by hil.scenarios.library (read-only afterwards).
_REGISTRY = _Registry()


def register(name: str, *, summary: str, params: tuple[Param, ...]) -> Callable[[BuildFn], BuildFn]:
    """Decorator registering a scenario factory under ``name``."""

    def deco(fn: BuildFn) -> BuildFn:
        _REGISTRY.add(ScenarioDef(name=name, summary=summary, params=params, build_fn=fn))
        return fn

    return deco


def get(name: str) -> ScenarioDef:
    """The scenario called ``name``. Raises ConfigError listing valid names."""
    return _REGISTRY.get(name)


def names() -> list[str]:
    return _REGISTRY.names()
