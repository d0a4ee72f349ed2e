"""Ranked assignment (Murty 1968): the k cheapest assignments of rows to distinct columns.

Each k-best step solves a linear assignment problem (scipy's `linear_sum_assignment`) on a
subproblem of the previous best: Murty's partition forbids one of its (row, column) pairs and
fixes the pairs before it, so every assignment is found once, in order of increasing cost.
"""

from __future__ import annotations

import heapq

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import linear_sum_assignment

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

_FORBIDDEN = 1e15
"""Finite stand-in for an infinite cost, for the solver; a solution that uses one is infeasible."""


def _solve(cost: FloatArray) -> tuple[float, IntArray] | None:
    """The cheapest assignment of every row (its columns and total cost), or None if none exists."""
    finite = np.where(np.isfinite(cost), cost, _FORBIDDEN)
    rows, cols = linear_sum_assignment(finite)
    picked = finite[rows, cols]
    if np.any(picked >= _FORBIDDEN):
        return None
    return float(picked.sum()), cols.astype(np.int64)


def k_best(cost: FloatArray, k: int, max_gap: float = np.inf) -> list[tuple[float, IntArray]]:
    """Up to k assignments (total cost, column of each row), cheapest first (Murty's algorithm).

    `cost` is (n, c) with n <= c; +inf forbids a pair. The search stops early once the next
    assignment costs more than `max_gap` above the best (its weight exp(-gap) is negligible).
    """
    n = cost.shape[0]
    if n == 0:
        return [(0.0, np.zeros(0, dtype=np.int64))]
    best = _solve(cost)
    if best is None:
        return []
    heap: list[tuple[float, int, IntArray, FloatArray]] = [(best[0], 0, best[1], cost)]
    counter = 1
    found: list[tuple[float, IntArray]] = []
    while heap and len(found) < k:
        total, _, cols, sub = heapq.heappop(heap)
        if total - best[0] > max_gap:
            break
        found.append((total, cols))
        fixed = sub.copy()
        for row in range(n):
            child = fixed.copy()
            child[row, cols[row]] = np.inf  # Murty: the child forbids this pair ...
            solved = _solve(child)
            if solved is not None:
                heapq.heappush(heap, (solved[0], counter, solved[1], child))
                counter += 1
            keep = fixed[row, cols[row]]  # ... and the next children fix it
            fixed[row, :] = np.inf
            fixed[:, cols[row]] = np.inf
            fixed[row, cols[row]] = keep
    return found
