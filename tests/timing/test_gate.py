"""hil.timing.gate: the block bootstrap and the test behind hil compare's verdicts."""

from __future__ import annotations

import numpy as np
import pytest

from hil.timing.gate import Metric, block_length, block_resample_rows, compare_metric, z_of


def test_block_resamples_keep_runs_of_consecutive_frames() -> None:
    x = np.arange(100.0)
    rows = block_resample_rows(x, 50, np.random.default_rng(0))
    assert rows.shape == (50, 100) and block_length(100) == 5
    steps = np.diff(rows, axis=1)
    # Within a block each value follows its predecessor (circularly): mostly steps of 1.
    assert ((steps == 1) | (steps == -99)).mean() > 0.75
    with pytest.raises(ValueError, match="empty"):
        block_resample_rows(np.array([]), 1, np.random.default_rng(0))


def test_metrics_match_the_summary_figures() -> None:
    x = np.random.default_rng(1).gamma(3.0, 1.0, 257)
    assert Metric.P50.of(x) == pytest.approx(np.percentile(x, 50))
    assert Metric.P99.of(x) == pytest.approx(np.percentile(x, 99))
    assert Metric.P1.of(x) == pytest.approx(np.percentile(x, 1))
    assert Metric.STD.of(x) == pytest.approx(x.std())
    assert z_of(0.975) == pytest.approx(1.959964, abs=1e-6)


def test_shift_is_judged_against_the_allowance_with_noise() -> None:
    rng = np.random.default_rng(2)
    base = 5 + rng.normal(0, 0.2, 400)
    run = base + 1.0
    s = compare_metric(base, run, Metric.P50, allowed=0.5, rng=np.random.default_rng(0))
    assert s.delta == pytest.approx(1.0) and s.ci_lo < 1.0 < s.ci_hi and s.p_worse > 0.999
    # A run-to-run noise of 20 % of 5 ms (1 ms per run) makes the same shift uncertain.
    noisy = compare_metric(base, run, Metric.P50, allowed=0.5, run_noise_rel=0.2, rng=np.random.default_rng(0))
    assert noisy.se > 1.0 and 0.5 < noisy.p_worse < 0.8
    fixed = compare_metric(base, run, Metric.P50, allowed=0.5, run_noise_abs=1.0, rng=np.random.default_rng(0))
    assert fixed.se == pytest.approx(noisy.se, rel=0.05)
    # Constant samples: no spread, the change is what it is.
    c = compare_metric(np.full(10, 2.0), np.full(10, 3.0), Metric.P50, allowed=0.5, rng=np.random.default_rng(0))
    assert c.se == 0 and c.p_worse == 1.0 and c.p_better == 0.0
    with pytest.raises(ValueError):
        compare_metric(base, run, Metric.P50, allowed=-1, rng=np.random.default_rng(0))
