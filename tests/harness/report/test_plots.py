"""The report's charts: tick labels a reader can tell apart."""

from __future__ import annotations

from hil.harness.report.plots import nice_ticks, tick_labels


def test_tick_labels_take_the_decimals_their_ticks_need() -> None:
    # An inference histogram of 150.011-150.204 ms labelled its ticks "150 150 150 150 150".
    ticks = nice_ticks(150.011, 150.204, 4)
    labels = tick_labels(ticks)
    assert len(set(labels)) == len(ticks) == 4 and labels[0] == "150.05", labels
    assert tick_labels([0.0, 50.0, 100.0]) == ["0", "50", "100"]  # whole ticks stay short
    assert tick_labels([0.0, 0.5, 1.0]) == ["0", "0.5", "1"]


def test_a_short_last_rate_bin_is_left_out() -> None:
    # Bins of 5 periods at 10 fps over 2.2 s: the last, of 2 periods, is left out (a
    # frame more or less there reads as a jump); every bin left reads 10 a second.
    import numpy as np

    from hil.harness.report.timeseries import rate_bins

    times = np.arange(22) * 0.1 + 0.05
    centres, rates = rate_bins(times, start_s=0.0, period_s=0.1, frames=5, end_s=2.15)
    assert list(np.round(rates, 6)) == [10.0] * 4 and centres[-1] == 1.75
    _, whole = rate_bins(times, start_s=0.0, period_s=0.1, frames=5, end_s=2.45)  # a last bin of 5: kept
    assert len(whole) == 5


def test_a_one_point_line_is_drawn_as_a_dot() -> None:
    # A study of one N drew six empty charts: a line through one vertex draws nothing.
    from hil.harness.report.plots import Series, line_chart

    svg = line_chart(series=[Series("total", [1.0], [20.0], "#4c78a8", "line")], x_label="N", y_label="frames/s")
    assert 'stroke-linecap="round"' in svg and "h0" in svg
    two = line_chart(series=[Series("total", [1.0, 2.0], [20.0, 40.0], "#4c78a8", "line")], x_label="N",
                     y_label="frames/s")
    assert "h0" not in two  # a line with neighbours draws as a line
