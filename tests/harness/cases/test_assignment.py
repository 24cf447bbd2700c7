"""The detector's assignment gives scipy's optimum (the oracle here; the product
no longer imports scipy at run time)."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.optimize import linear_sum_assignment

from hil.harness.cases.assignment import assign

_INF = 1e9


@st.composite
def matrices(draw: st.DrawFn) -> list[list[float]]:
    rows, cols = draw(st.integers(1, 7)), draw(st.integers(1, 7))
    cell = st.one_of(st.just(_INF), st.floats(0.0, 50.0, allow_nan=False), st.sampled_from([0.0, 1.0, 2.0]))
    return [[draw(cell) for _ in range(cols)] for _ in range(rows)]


@settings(max_examples=400, deadline=None)
@given(matrices())
def test_the_same_optimum_as_scipy(cost: list[list[float]]) -> None:
    pairs = assign(cost)
    rows, cols = linear_sum_assignment(np.array(cost))
    assert len(pairs) == len(rows) == min(len(cost), len(cost[0]))
    assert len({r for r, _ in pairs}) == len({c for _, c in pairs}) == len(pairs)
    assert [r for r, _ in pairs] == sorted(r for r, _ in pairs)
    ours = sum(cost[r][c] for r, c in pairs)
    theirs = float(sum(cost[r][c] for r, c in zip(rows, cols)))
    assert abs(ours - theirs) <= 1e-6 * max(1.0, abs(theirs))
    # As the detector uses it: the same number of pairs under the gate.
    assert sum(cost[r][c] < _INF for r, c in pairs) == sum(cost[r][c] < _INF for r, c in zip(rows, cols))


def test_a_greedy_choice_is_not_taken() -> None:
    # Row 0's nearest column is 0, but giving it to row 1 costs less in all.
    assert assign([[1.0, 2.0], [1.5, 10.0]]) == [(0, 1), (1, 0)]
    assert assign([[5.0], [1.0], [3.0]]) == [(1, 0)]
    assert assign([]) == [] and assign([[]]) == []
