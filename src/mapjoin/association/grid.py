"""Candidate pairs of data association by a grid: the points of one join within each point's reach.

The gate of :mod:`mapjoin.association` (docs/method.md#data-association, step 2) bounds every pair it can accept by
a Euclidean radius per right feature; :func:`pairs_within` finds the (left, right) pairs of the same join within it.
Every pair of a join at once costs the product of the two sides (a tree level's upper joins: hundreds by hundreds),
a k-d tree per call returns Python lists per point; a grid costs what the points and the pairs found cost. Each
join gets square cells as wide as its largest radius, so a right point's partners lie in the 3 x 3 cells around
its own: the left points are sorted once by (join, cell), and each right point's nine cells, three runs of
consecutive keys, are two binary searches per run, as arrays.
"""

from __future__ import annotations

import numpy as np

__all__ = ["ALL_PAIRS", "pairs_within"]

#: up to this many (left x right) pairs, every pair is compared (no grid)
ALL_PAIRS = 1 << 14
#: a join's cells across the points' extent, at most (2^16 + 3)^2 per join: keys of up to 2^20 joins exact in floats
_MOST_CELLS = 2.0 ** 16
#: the 3 x 3 neighbourhood of a cell: three columns (offsets in x), each three consecutive keys (y - 1 .. y + 1)
_AROUND_X = np.arange(-1, 2)


def pairs_within(left: np.ndarray, left_join: np.ndarray, right: np.ndarray, right_join: np.ndarray,
                 radius: np.ndarray, joins: int) -> tuple[np.ndarray, np.ndarray]:
    """The pairs ``(i, j)`` of rows of ``left`` and ``right`` (complex points) in the same join (``left_join``,
    ``right_join``: each row's join, ``< joins``) with ``|left[i] - right[j]| <= radius[j]``, sorted by ``i`` then
    ``j`` (the order of every pair enumerated row by row). Up to :data:`ALL_PAIRS` pairs, every pair is compared."""
    empty = np.zeros(0, np.intp)
    if not len(left) or not len(right):
        return empty, empty
    if len(left) * len(right) <= ALL_PAIRS:  # few: every pair compared at once costs less than sorting cells
        i, j = np.nonzero((np.abs(left[:, None] - right[None, :]) <= radius) & (left_join[:, None] == right_join))
        return i, j
    cell = np.zeros(joins)
    np.fmax.at(cell, right_join, radius)  # (a NaN radius reaches nothing, as in the comparison below)
    # cells at least 2^-16 of the points' extent (wider cells only hold more points): their keys stay exact
    span = max(np.ptp(left.real), np.ptp(left.imag), np.ptp(right.real), np.ptp(right.imag))
    cell = np.maximum(cell * (1 + 1e-9), max(span, 1.0) / _MOST_CELLS)  # a hair wider: no rounding skips a cell
    left_x, left_y = np.floor(left.real / cell[left_join]), np.floor(left.imag / cell[left_join])
    right_x, right_y = np.floor(right.real / cell[right_join]), np.floor(right.imag / cell[right_join])
    low_x, low_y = min(left_x.min(), right_x.min() - 1), min(left_y.min(), right_y.min() - 1)
    width = max(left_x.max(), right_x.max() + 1) - low_x + 1
    height = max(left_y.max(), right_y.max() + 1) - low_y + 1
    left_key = (left_join * width + (left_x - low_x)) * height + (left_y - low_y)
    order = np.argsort(left_key.astype(np.int64), kind="stable")
    sorted_key = left_key.astype(np.int64)[order]
    column = ((right_join[:, None] * width + (right_x[:, None] + _AROUND_X - low_x)) * height
              + (right_y[:, None] - low_y)).astype(np.int64).ravel()
    first = np.searchsorted(sorted_key, column - 1, side="left")
    count = np.searchsorted(sorted_key, column + 1, side="right") - first
    total = int(count.sum())
    j = np.repeat(np.arange(len(column)) // 3, count)
    i = order[np.repeat(first - (np.cumsum(count) - count), count) + np.arange(total)]
    near = np.abs(left[i] - right[j]) <= radius[j]
    i, j = i[near], j[near]
    by_left = np.lexsort((j, i))
    return i[by_left], j[by_left]
