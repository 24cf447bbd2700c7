"""Statistics of the latency regression gate: how sure is it that a figure grew?

Two runs of the same build never give the same p50/p99/std: the machine's load, the
scheduler and caches move every per-frame sample a little, and a p99 of a few hundred
frames rests on its two or three largest values. ``compare_metric`` therefore looks
at the per-frame samples of both runs, not at their summaries, and answers two
questions about ``Δ = metric(run) − metric(base)``:

* **Is it real?** A circular block bootstrap resamples each run's samples (blocks of
  consecutive frames, so a burst of load that slowed several frames in a row counts
  as one event, not as many independent ones) and gives the standard error of Δ, the
  interval ``Δ ± z·SE`` and the probability that the true growth exceeds what is
  allowed: ``P(worse) = Φ((Δ − allowed) / SE)`` (normal approximation of the
  bootstrap distribution; it stays smooth at the very small error levels that many
  checks at once need, where bootstrap percentiles would need 10⁵ resamples).
* **Does it matter?** ``allowed`` is the practical threshold (``max(rel × base,
  abs)``): a growth that is surely real but smaller than that passes.

A check fails only when ``P(worse) ≥ 1 − α`` — sure, at level α, that the growth is
larger than allowed. The caller splits a family-wise α over its checks
(Bonferroni). ``better`` is the mirror image (sure that it fell by more than
allowed).

Pure numpy; deterministic for a given ``seed``.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from enum import Enum
from statistics import NormalDist

import numpy as np

#: Resamples per bootstrap: enough for a standard error to ~2 % (1/sqrt(2B)).
DEFAULT_RESAMPLES = 1000
#: Values resampled per batch (bounds memory for long runs: 2M floats = 16 MiB).
_BATCH_VALUES = 2_000_000


class Metric(str, Enum):
    """What is compared: a percentile (``p1``: the floor, what the pipeline takes when
    nothing else on the machine gets in its way), the standard deviation (jitter), or
    the mean (of 0/1 drop indicators: the drop rate)."""

    P1 = "p1"
    P50 = "p50"
    P99 = "p99"
    STD = "std"
    MEAN = "mean"

    def of(self, x: np.ndarray) -> float:
        """The metric of 1-D samples ``x`` (percentiles as ``numpy.percentile``,
        linear; std with ddof 0: the same figures as ``summary.json``)."""
        return float(self.rows(x[np.newaxis, :])[0])

    def rows(self, x: np.ndarray) -> np.ndarray:
        """The metric of every row of 2-D ``x``."""
        out: np.ndarray
        if self is Metric.P1:
            out = np.percentile(x, 1, axis=1)
        elif self is Metric.P50:
            out = np.percentile(x, 50, axis=1)
        elif self is Metric.P99:
            out = np.percentile(x, 99, axis=1)
        elif self is Metric.STD:
            out = x.std(axis=1)
        else:
            out = x.mean(axis=1)
        return out


@dataclass(frozen=True)
class Shift:
    """One compared metric. Values in the samples' unit (ms for latencies).

    ``se``: standard error of ``delta`` (``se_boot``, the bootstrap's, with the
    run-to-run noise added); ``ci_lo``/``ci_hi``: the two-sided
    interval at the confidence asked for; ``p_worse``: probability that the growth
    exceeds ``allowed``; ``p_better``: that it fell by more than ``allowed``."""

    base: float
    run: float
    delta: float
    se: float
    se_boot: float
    ci_lo: float
    ci_hi: float
    allowed: float
    p_worse: float
    p_better: float
    n_base: int
    n_run: int


def block_length(n: int) -> int:
    """Bootstrap block length for ``n`` samples: ``ceil(n^(1/3))`` (the usual rate
    for a block bootstrap of a variance-like statistic), at least 1."""
    root: float = n ** (1 / 3)
    return max(1, math.ceil(root))


def block_resample_rows(x: np.ndarray, count: int, rng: np.random.Generator) -> np.ndarray:
    """``count`` circular-block-bootstrap resamples of 1-D ``x`` (rows of a 2-D array).

    Raises:
        ValueError: ``x`` is empty.
    """
    n = int(x.size)
    if n == 0:
        raise ValueError("cannot resample an empty sample")
    length = block_length(n)
    blocks = -(-n // length)
    starts = rng.integers(0, n, size=(count, blocks))
    idx = (starts[:, :, np.newaxis] + np.arange(length)) % n
    out: np.ndarray = x[idx.reshape(count, blocks * length)[:, :n]]
    return out


def bootstrap(x: np.ndarray, stat: Callable[[np.ndarray], np.ndarray], *, resamples: int,
              rng: np.random.Generator) -> np.ndarray:
    """``stat`` (row-wise) of ``resamples`` block resamples of ``x``, in batches."""
    per = max(1, _BATCH_VALUES // max(int(x.size), 1))
    out = []
    left = resamples
    while left > 0:
        k = min(per, left)
        out.append(stat(block_resample_rows(x, k, rng)))
        left -= k
    return np.concatenate(out)


_NORMAL = NormalDist()


def _phi(z: float) -> float:
    return _NORMAL.cdf(z)


def z_of(p: float) -> float:
    """The standard normal quantile ``Φ⁻¹(p)``.

    Raises:
        ValueError: ``p`` outside (0, 1).
    """
    if not 0.0 < p < 1.0:
        raise ValueError(f"probability must lie in (0, 1), got {p}")
    return _NORMAL.inv_cdf(p)


def compare_metric(base: np.ndarray, run: np.ndarray, metric: Metric, *, allowed: float, confidence: float = 0.95,
                   run_noise_rel: float = 0.0, run_noise_abs: float = 0.0, resamples: int = DEFAULT_RESAMPLES,
                   rng: np.random.Generator) -> Shift:
    """How ``metric`` moved from ``base`` to ``run`` (1-D samples in frame order) and
    how sure that is (see the module docstring). ``confidence``: of the interval
    ``ci_lo..ci_hi``. ``run_noise_rel``/``run_noise_abs``: the run-to-run standard
    deviation of the metric between runs of one build, ``sqrt((run_noise_rel ×
    base)² + run_noise_abs²)`` (what one pair of runs cannot show: the machine's
    load changing between them); twice its square is added to the bootstrap
    variance: the variance of the
    difference of two runs of the baseline's build, which is what the test's null
    hypothesis (no change) says both runs are.

    Raises:
        ValueError: an empty sample, ``allowed`` < 0, or ``confidence``/``resamples``
            out of range.
    """
    if base.size == 0 or run.size == 0:
        raise ValueError("both samples need at least one value")
    if allowed < 0 or min(run_noise_rel, run_noise_abs) < 0 or not 0 < confidence < 1 or resamples < 2:
        raise ValueError(f"allowed {allowed} >= 0, run noise {run_noise_rel}/{run_noise_abs} >= 0, 0 < confidence "
                         f"{confidence} < 1 and resamples {resamples} >= 2 expected")
    b = np.asarray(base, np.float64)
    r = np.asarray(run, np.float64)
    m_base, m_run = metric.of(b), metric.of(r)
    delta = m_run - m_base
    d = (bootstrap(r, metric.rows, resamples=resamples, rng=rng)
         - bootstrap(b, metric.rows, resamples=resamples, rng=rng))
    se_boot = float(d.std(ddof=1))
    se = math.sqrt(se_boot ** 2 + 2 * ((run_noise_rel * m_base) ** 2 + run_noise_abs ** 2))
    if se > 0:
        z = z_of(0.5 + confidence / 2)
        lo, hi = delta - z * se, delta + z * se
        p_worse, p_better = _phi((delta - allowed) / se), _phi((-delta - allowed) / se)
    else:  # no spread at all (constant samples): the change is what it is
        lo = hi = delta
        p_worse = 1.0 if delta > allowed else 0.0
        p_better = 1.0 if -delta > allowed else 0.0
    return Shift(base=m_base, run=m_run, delta=delta, se=se, se_boot=se_boot, ci_lo=lo, ci_hi=hi, allowed=allowed,
                 p_worse=p_worse, p_better=p_better, n_base=int(b.size), n_run=int(r.size))


__all__ = ["DEFAULT_RESAMPLES", "Metric", "Shift", "block_length", "block_resample_rows", "bootstrap",
           "compare_metric", "z_of"]
