"""Nearest points by dense distances, a block of rows at a time: for the few hundred points a join's loop votes or an
evaluation's sample look at, where building scipy's k-d tree (and importing scipy, 0.3 s of a command) costs more
than the distances."""

from __future__ import annotations

import numpy as np

__all__ = ["nearest"]

#: squared distances held at once (a block of rows of the points x candidates table)
BLOCK = 1 << 22


def nearest(points: np.ndarray, candidates: np.ndarray, k: int = 1, exclude: np.ndarray | None = None
            ) -> tuple[np.ndarray, np.ndarray]:
    """Each complex point's ``k`` nearest ``candidates`` (complex): their indices (one row each, in no order; ties
    broken either way) and squared distances. ``exclude[i]``: a candidate point i may not take (itself, when the
    candidates are the points)."""
    index, squared = np.empty((len(points), k), np.intp), np.empty((len(points), k))
    block = max(1, BLOCK // max(len(candidates), 1))
    for low in range(0, len(points), block):
        rows = np.arange(low, min(low + block, len(points)))
        table = (points.real[rows, None] - candidates.real[None, :]) ** 2
        table += (points.imag[rows, None] - candidates.imag[None, :]) ** 2
        if exclude is not None:
            table[np.arange(len(rows)), exclude[rows]] = np.inf
        index[rows] = np.argpartition(table, k - 1, axis=1)[:, :k]
        squared[rows] = np.take_along_axis(table, index[rows], axis=1)
    return index, squared
