"""Where each episode's parameters come from: seeds, generations, strategies, scores.

Every draw is a pure function of the campaign and, for guided strategies, of the
results of earlier generations, so an episode is reproducible from the campaign's
seed and its index (and is stored with its seed and values anyway):

* episode ``i``'s run seed is ``SeedSequence([campaign_seed, i])``'s first word;
* ``random``: episode ``i`` draws uniformly from ``default_rng([campaign_seed, i,
  RANDOM_STREAM])`` — independent of every other episode, of the order they run in
  and of sharding;
* guided (``cem``, ``mutate``): episodes are grouped in generations of
  ``strategy.generation``; generation 0 is random as above. Generation ``g`` is
  drawn all at once from ``default_rng([campaign_seed, g, GUIDED_STREAM])`` and a
  fit on the *history* handed in (the episodes of generations before ``g`` that
  ran): ``cem`` samples a normal with the mean and spread of the elite (the
  ``elite_frac`` highest-scoring episodes, spread at least ``sigma``), ``mutate``
  perturbs each elite in turn by ``sigma`` (a fraction of each range). The first
  ``explore`` of each generation stays uniform, and a generation whose history has
  no episode scoring above 0 is uniform entirely (nothing to concentrate on yet).
  Values leaving the space are reflected back into it.

All draws are in the unit cube; ``Dim.value`` maps them onto each range.

The score (higher: worse, more interesting) uses only what lockstep makes
deterministic: the detector's mismatches weighted by kind, egos that collided, and
how far inside ``near_miss_m`` of an obstacle each ego came. Timing anomalies and
the number of corner-case windows depend on wall-clock speed and are left out.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from hil.harness.search.spec import Campaign, StrategyKind

RANDOM_STREAM = 0x5EA
GUIDED_STREAM = 0xC3E
MISMATCH_WEIGHT = {"collision_while_safe": 10.0, "late_reaction": 10.0, "state_mismatch": 3.0,
                   "missed_object": 2.0, "position_error": 1.0, "ghost_object": 1.0}
COLLISION_WEIGHT = 5.0
NEAR_MISS_WEIGHT = 2.0


@dataclass(frozen=True)
class Draw:
    """One episode's draw: its run seed, its point in the unit cube, its values."""

    index: int
    generation: int
    seed: int
    unit: tuple[float, ...]
    values: dict[str, float]
    origin: str


@dataclass(frozen=True)
class Past:
    """What a guided strategy needs of an episode that ran."""

    index: int
    unit: tuple[float, ...]
    score: float


def episode_seed(campaign_seed: int, index: int) -> int:
    """The run seed of episode ``index`` (a 32-bit whole number)."""
    return int(np.random.SeedSequence([campaign_seed, index]).generate_state(1, np.uint32)[0])


def generation_size(c: Campaign) -> int:
    return c.strategy.generation


def generation_of(c: Campaign, index: int) -> int:
    return index // c.strategy.generation


def generation_indices(c: Campaign, generation: int) -> range:
    g = c.strategy.generation
    return range(generation * g, min((generation + 1) * g, c.episodes))


def is_guided(c: Campaign) -> bool:
    return c.strategy.kind != StrategyKind.RANDOM


def _uniform(c: Campaign, index: int) -> np.ndarray:
    return np.random.default_rng([c.seed, index, RANDOM_STREAM]).random(len(c.dims))


def _reflect(x: np.ndarray) -> np.ndarray:
    """Fold values back into [0, 1] (mirror at both ends)."""
    x = np.mod(x, 2.0)
    return np.where(x > 1.0, 2.0 - x, x)


def _make(c: Campaign, index: int, unit: np.ndarray, origin: str) -> Draw:
    u = tuple(float(v) for v in unit)
    return Draw(index=index, generation=generation_of(c, index), seed=episode_seed(c.seed, index), unit=u,
                values={d.name: d.value(x) for d, x in zip(c.dims, u)}, origin=origin)


def draw_generation(c: Campaign, generation: int, history: Sequence[Past] = ()) -> list[Draw]:
    """Every episode of ``generation`` (all of them, whatever shard runs them).

    ``history``: episodes that ran; only those of earlier generations are used.
    A random campaign ignores it.
    """
    idx = generation_indices(c, generation)
    if not is_guided(c) or generation == 0:
        return [_make(c, i, _uniform(c, i), "random") for i in idx]
    start = idx.start
    past = sorted((p for p in history if p.index < start), key=lambda p: p.index)
    scored = [p for p in past if p.score > 0]
    if not scored:
        return [_make(c, i, _uniform(c, i), "random (no signal yet)") for i in idx]
    s = c.strategy
    k = max(1, math.ceil(s.elite_frac * len(past)))
    elite = sorted(scored, key=lambda p: (-p.score, p.index))[:k]
    units = np.array([p.unit for p in elite], float)
    rng = np.random.default_rng([c.seed, generation, GUIDED_STREAM])
    z = rng.standard_normal((len(idx), len(c.dims)))
    n_explore = round(s.explore * len(idx))
    out = []
    if s.kind == StrategyKind.CEM:
        mean = units.mean(axis=0)
        std = np.maximum(units.std(axis=0), s.sigma)
        origin = f"cem (elite of {len(elite)}, score >= {elite[-1].score:g})"
    for r, i in enumerate(idx):
        if r < n_explore:
            out.append(_make(c, i, _uniform(c, i), "explore"))
        elif s.kind == StrategyKind.CEM:
            out.append(_make(c, i, _reflect(mean + std * z[r]), origin))
        else:
            parent = elite[(r - n_explore) % len(elite)]
            out.append(_make(c, i, _reflect(np.asarray(parent.unit) + s.sigma * z[r]),
                             f"mutate e{parent.index:05d} (score {parent.score:g})"))
    return out


def score(*, mismatches: Mapping[str, int], collided_egos: int, min_gaps_m: Sequence[float | None],
          near_miss_m: float) -> float:
    """How bad an episode went (see the module docstring). ``mismatches``: the
    summary's ``kind/cause`` counts over all vehicles."""
    s = 0.0
    for key, n in mismatches.items():
        s += MISMATCH_WEIGHT.get(key.split("/", 1)[0], 1.0) * int(n)
    s += COLLISION_WEIGHT * collided_egos
    for gap in min_gaps_m:
        if gap is not None and math.isfinite(gap):
            s += NEAR_MISS_WEIGHT * max(0.0, 1.0 - max(gap, 0.0) / near_miss_m)
    return round(s, 6)


__all__ = ["Draw", "Past", "draw_generation", "episode_seed", "generation_indices", "generation_of",
           "is_guided", "score"]
