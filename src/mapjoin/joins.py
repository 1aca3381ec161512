"""The data of joins: a join's record in the report, a joined result, and a chain's pieces as they are joined.

:mod:`mapjoin.joining` makes them; the consistency check, the drift model, the association and
the confirmation read them. They live here, below all of those, so that each can name them
without importing the join strategies.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np

from .maps import GlobalMap

__all__ = ["STRATEGIES", "JoinRecord", "JoinResult", "Strategy"]

Strategy = Literal["sequential", "tree"]
STRATEGIES: tuple[str, ...] = ("sequential", "tree")


@dataclass(frozen=True)
class JoinRecord:
    """One join of the report: what came in, Theorem 2's certificate, and the optimum found.

    ``map`` names the right piece ("first to last" local map when it is a run of them),
    ``start_id``/``end_id`` its first and last pose; ``level`` is the join's depth (the
    join number for the sequential strategy). ``phi`` is phi*, the orientation of right's
    start pose in left's frame, ``cost`` f_1(phi*); ``phi2``/``cost2`` the other local
    minimum when ``minima`` is 2.

    The consistency check (:mod:`mapjoin.consistency`, docs/method.md#calibration): ``dof`` the
    degrees of freedom, ``variance_factor`` the a-posteriori variance factor ``s`` from the joins
    before it (a tree join: from the joins of its own level and the levels below); ``chi2`` the statistic: the join's own minimum (``cost``, or ``c0 - 2 a0`` for a map
    joined by its features alone) when that passes the gate (``p`` of ``chi2 / s`` at least
    ``gate``), else the same minimum with the chain's drift added to the common features'
    variances (docs/method.md#drift), which is never larger; ``features_cost`` the minimum without
    the heading link (c0 - 2 a0) of the same problem; ``p`` the upper tail probability of
    ``chi2 / s``, ``flag`` whether the join failed the gate (or has two minima). ``action``:
    ``joined``, ``features only`` (joined without the heading link) or ``left out`` (its features
    dropped, its end pose kept), as the policy decided. ``exact_chi2``, ``exact_p``: the exact statistic
    of a join that failed the gate, when it was confirmed (:mod:`mapjoin.confirmation`,
    docs/method.md#confirmation; then ``flag`` is its verdict), else None.
    """

    join: int
    map: str
    start_id: int
    end_id: int
    common: int
    new: int
    a: float
    c_phi: float
    minima: int
    phi: float
    cost: float
    phi2: float | None
    cost2: float | None
    iterations: int
    level: int
    features_cost: float = math.nan
    chi2: float = math.nan
    dof: int = 0
    variance_factor: float = 1.0
    p: float = 1.0
    flag: bool = False
    action: str = "joined"
    exact_chi2: float | None = None
    exact_p: float | None = None


@dataclass(frozen=True)
class JoinResult:
    """A joined global map and its per-join report."""

    global_map: GlobalMap
    report: tuple[JoinRecord, ...]


@dataclass
class _Pieces:
    """Consecutive pieces of the chain as flat arrays, each in the frame of its own start pose.

    Points are complex numbers ``x + iy`` (a rotation is one product). Feature rows are
    grouped by piece (``feature_piece`` non-decreasing) and sorted by compact id within a
    piece; pose rows are the end poses of the piece's maps, in chain order, so a piece's
    last pose row is its end pose. ``first``/``last`` are the indices of each piece's first
    and last local map.
    """

    feature_piece: np.ndarray
    feature_ids: np.ndarray
    features: np.ndarray
    feature_variances: np.ndarray
    pose_piece: np.ndarray
    pose_xy: np.ndarray
    pose_phi: np.ndarray
    pose_variances: np.ndarray
    first: np.ndarray
    last: np.ndarray

    @property
    def count(self) -> int:
        return len(self.first)

    def block(self, start: int, stop: int) -> _Pieces:
        """Pieces ``start .. stop-1``, renumbered from 0."""
        f = slice(*np.searchsorted(self.feature_piece, [start, stop]))
        p = slice(*np.searchsorted(self.pose_piece, [start, stop]))
        return _Pieces(self.feature_piece[f] - start, self.feature_ids[f], self.features[f],
                       self.feature_variances[f], self.pose_piece[p] - start, self.pose_xy[p], self.pose_phi[p],
                       self.pose_variances[p], self.first[start:stop], self.last[start:stop])
