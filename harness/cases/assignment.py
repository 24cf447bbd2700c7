"""The optimal assignment the detector matches objects with (the Hungarian method).

The detector's matrices are small (the objects one frame shows: a few estimates by a
few truths), so plain Python is quick; ``scipy.optimize.linear_sum_assignment`` did the
same work but importing ``scipy.optimize`` cost ~0.4 s of every run's start (measured
with ``python -X importtime``), more than the whole matching of a long run. The tests
hold this to scipy's answer on random matrices.
"""

from __future__ import annotations

from collections.abc import Sequence

_UNSET = float("inf")


def assign(cost: Sequence[Sequence[float]]) -> list[tuple[int, int]]:
    """The (row, column) pairs of a minimum-cost assignment of a rectangular matrix
    of finite costs: min(rows, columns) pairs, each row and column at most once,
    sorted by row (as ``scipy.optimize.linear_sum_assignment`` gives them)."""
    rows = len(cost)
    cols = len(cost[0]) if rows else 0
    if not rows or not cols:
        return []
    if rows > cols:  # the method below wants rows <= columns
        return sorted((r, c) for c, r in assign([[cost[r][c] for r in range(rows)] for c in range(cols)]))
    # Potentials u (rows) and v (columns); owner[j]: the row holding column j (1-based,
    # 0 = free; column 0 is the virtual start of each augmenting path).
    u = [0.0] * (rows + 1)
    v = [0.0] * (cols + 1)
    owner = [0] * (cols + 1)
    way = [0] * (cols + 1)
    for i in range(1, rows + 1):
        owner[0] = i
        j0 = 0
        minv = [_UNSET] * (cols + 1)
        used = [False] * (cols + 1)
        while True:
            used[j0] = True
            i0, delta, j1 = owner[j0], _UNSET, 0
            row = cost[i0 - 1]
            for j in range(1, cols + 1):
                if not used[j]:
                    reduced = row[j - 1] - u[i0] - v[j]
                    if reduced < minv[j]:
                        minv[j], way[j] = reduced, j0
                    if minv[j] < delta:
                        delta, j1 = minv[j], j
            for j in range(cols + 1):
                if used[j]:
                    u[owner[j]] += delta
                    v[j] -= delta
                else:
                    minv[j] -= delta
            j0 = j1
            if owner[j0] == 0:
                break
        while j0:  # flip the augmenting path
            j1 = way[j0]
            owner[j0] = owner[j1]
            j0 = j1
    return sorted((owner[j] - 1, j - 1) for j in range(1, cols + 1) if owner[j])
