"""Streaming per-stage histograms: percentiles within HdrHistogram's 0.1 %, exact
moments, bounded memory, merging, and no negative or absurd values recorded."""

from __future__ import annotations

import numpy as np
import pytest

from hil.timing.histogram import MAX_STAGES, StageHistograms, _new_histogram, values_at_percentiles
from hil.timing.records import FrameStatus, PipelineRecord
from hil.timing.stats import summarize_ns

MS = 1_000_000


def lognormal_ns(seed: int, n: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return rng.lognormal(np.log(5 * MS), 0.4, n).astype(np.int64)


def test_percentiles_match_exact_summary_within_a_tenth_of_a_percent():
    values = lognormal_ns(1, 100_000)
    hist = StageHistograms()
    assert hist.record_many("end_to_end", values) == values.size
    got, exact = hist.percentiles_ms("end_to_end"), summarize_ns(values.tolist())
    assert got["count"] == exact["count"] == values.size
    for key in ("p50_ms", "p90_ms", "p99_ms"):
        assert got[key] == pytest.approx(exact[key], rel=2e-3, abs=2e-3)
    for key in ("max_ms", "min_ms", "mean_ms", "std_ms"):  # kept exactly beside the histogram
        assert got[key] == pytest.approx(exact[key], abs=1e-4)


@pytest.mark.parametrize("seed", range(6))
def test_percentiles_in_one_pass_are_the_librarys_own(seed: int) -> None:
    # Values from 1 µs to 60 s, a few or many, one value repeated, empty.
    rng = np.random.default_rng(seed)
    h = _new_histogram()
    n = [0, 1, 7, 200, 5000, 3][seed]
    values = rng.lognormal(7 + seed, 2.5, n).clip(1, 60_000_000).astype(int) if seed != 5 else [40_000] * 3
    for v in values:
        h.record_value(int(v))
    qs = (0, 0.1, 50, 90, 99, 99.9, 100)
    assert values_at_percentiles(h, qs) == [h.get_value_at_percentile(q) for q in qs]


def test_single_record_and_batches_agree():
    values = lognormal_ns(2, 2_000)
    one, batch = StageHistograms(), StageHistograms()
    for v in values:
        assert one.record("inference", int(v))
    batch.record_many("inference", values)
    assert one.percentiles_ms("inference") == batch.percentiles_ms("inference")


def test_merge_equals_recording_everything_in_one():
    a_vals, b_vals = lognormal_ns(3, 5_000), lognormal_ns(4, 7_000) * 3
    a, b, both = StageHistograms(), StageHistograms(), StageHistograms()
    a.record_many("end_to_end", a_vals)
    b.record_many("end_to_end", b_vals)
    b.record_many("transport", a_vals // 10)
    both.record_many("end_to_end", np.concatenate([a_vals, b_vals]))
    both.record_many("transport", a_vals // 10)
    a.merge(b)
    for stage in ("end_to_end", "transport"):
        got, want = a.percentiles_ms(stage), both.percentiles_ms(stage)
        assert got.keys() == want.keys()
        for k in got:
            assert got[k] == pytest.approx(want[k], rel=1e-9, abs=1e-4)
    assert b.percentiles_ms("end_to_end")["count"] == 7_000  # other is unchanged


def test_negative_values_are_rejected_and_huge_ones_clamped_and_counted():
    hist = StageHistograms()
    assert not hist.record("uplink", -5)
    assert hist.record_many("uplink", [-1, 3 * MS, 90_000 * MS]) == 2
    assert hist.rejected == 2 and hist.overflow == 1
    p = hist.percentiles_ms("uplink")
    assert p["count"] == 2 and p["min_ms"] == 3.0
    assert p["p99_ms"] == pytest.approx(60_000, rel=1e-3)  # clamped to the 60 s range


def test_sub_microsecond_values_are_recorded_not_lost():
    hist = StageHistograms()
    hist.record_many("capture_to_send", [0, 200, 499, 800])
    p = hist.percentiles_ms("capture_to_send")
    assert p["count"] == 4 and p["p50_ms"] <= 0.001
    assert p["mean_ms"] == round(375 / 1e6, 4)  # ms rounded to 0.1 µs, as summarize_ns


def test_unknown_or_empty_stage_gives_count_zero():
    hist = StageHistograms()
    assert hist.percentiles_ms("nope") == {"count": 0}
    hist.record_many("end_to_end", [])
    assert hist.percentiles_ms("end_to_end") == {"count": 0}


def test_memory_is_bounded_whatever_the_count():
    hist = StageHistograms()
    hist.record_many("end_to_end", lognormal_ns(5, 1_000))
    size = hist._hist["end_to_end"].counts_len
    for seed in range(6, 16):
        hist.record_many("end_to_end", lognormal_ns(seed, 50_000))
    assert hist._hist["end_to_end"].counts_len == size
    for i in range(MAX_STAGES - 1):
        hist.record(f"s{i}", MS)
    with pytest.raises(ValueError, match="stage"):
        hist.record("one_too_many", MS)


def test_records_feed_every_sync_free_stage_and_insane_ones_are_skipped():
    t0 = 10**15
    good = PipelineRecord("ego", 1, 0, t0, t0 + 20_000, FrameStatus.OK, 5 * 10**9, 5 * 10**9 + 10**5,
                          5 * 10**9 + 5 * MS, 5 * 10**9 + 5 * MS + 10**4, t0 + 6 * MS, t0 + 6 * MS + 10**5)
    backwards = PipelineRecord("ego", 2, 0, t0, t0 + 20_000, FrameStatus.OK, 5 * 10**9, 5 * 10**9 + 10**5,
                               4 * 10**9, 5 * 10**9 + 5 * MS, t0 + 6 * MS)
    hist = StageHistograms()
    assert hist.record_record(good) and not hist.record_record(backwards)
    assert sorted(hist.stages()) == sorted(good.stages_ns())
    assert hist.excluded_records == 1
    assert hist.summary_ms()["inference"]["p50_ms"] == pytest.approx(4.9, rel=1e-3)


@pytest.mark.parametrize("seed", [0, 1])
def test_values_recorded_at_once_fill_the_librarys_own_buckets(seed: int) -> None:
    # record_values does the library's bucket arithmetic on arrays: every count, the
    # total, min and max must be what record_value gives one value at a time, at the
    # edges of the buckets too; and a stage's pending values reach its percentiles.
    from hdrh.histogram import HdrHistogram

    from hil.timing.histogram import HIGHEST_US, LOWEST_US, PENDING, SIGNIFICANT_DIGITS, record_values

    rng = np.random.default_rng(seed)
    edges = [0, 1, 2, 1023, 1024, 2047, 2048, 2049, 4095, 4096, 65_535, 65_536, HIGHEST_US - 1, HIGHEST_US]
    us = np.concatenate([np.array(edges, dtype=np.int64), rng.integers(0, HIGHEST_US, 3000),
                         (rng.lognormal(9, 1.5, 3000)).astype(np.int64)])
    one, many = (HdrHistogram(LOWEST_US, HIGHEST_US, SIGNIFICANT_DIGITS) for _ in range(2))
    for v in us.tolist():
        one.record_value(v)
    record_values(many, us)
    counts = [np.ctypeslib.as_array(h.counts)[:h.counts_len].copy() for h in (one, many)]
    assert np.array_equal(counts[0], counts[1]) and counts[0].sum() == us.size
    assert (one.total_count, one.min_value, one.max_value) == (many.total_count, many.min_value, many.max_value)

    hist = StageHistograms()
    for v in us[:PENDING - 1].tolist():  # fewer than a batch: all still pending
        hist.record("end_to_end", v * 1000)
    exact = StageHistograms()
    exact.record_many("end_to_end", us[:PENDING - 1] * 1000)
    assert hist.percentiles_ms("end_to_end") == exact.percentiles_ms("end_to_end")
