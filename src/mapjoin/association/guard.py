"""Step 9 of data association: the join's own consistency as a guard on its association
(docs/method.md#data-association).

Steps 2 to 8 judge the pairs under the local maps' covariances and the chain's drift ``D``; the one-step join then
solves with the pairs taken, and its own statistic (docs/method.md#each-join) sees what they could not: on the
default simulation ``D`` is 30 to 100 times too small, and a feature met again after the chain drifted metres lands
within the gate of a *different* feature 1 to 3 m from its partner. Such a pair is an outlier of the join's own
solve: its squared residual over its spherical variances lies far beyond the other pairs'. When a join is
inconsistent (:func:`inconsistent`: its minimum beyond the chi-square ``gate`` of :mod:`mapjoin.consistency`) *and*
one of its pairs lies outside the association's gate under the join's robust variance factor (:func:`outlying`: the
pairs' median over :data:`~mapjoin.association.rounds.CHI2_2_MEDIAN`, as step 5's), the associator associates it
again with every drift ``D`` times :data:`GUARD_DRIFT` (:func:`widened`) and keeps that association when it keeps at
least half of the first one's pairs (:func:`kept_majority`: the median scale that found the outlier presumes a
majority of true pairs; an association that drops most of them is another association, not a guard against a few).
The join is then solved again (:data:`Solve`: :mod:`mapjoin.joining` hands the associator the solve of its pairs and
takes back the one it used, so an unguarded join is solved once). A guard that left pairs out has shown the chain's
drift too small: the associator widens it for every later join (its ``drift_too_small``).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Protocol

import numpy as np

from ..consistency import DEFAULT_GATE
from .gate import _threshold
from .rounds import CHI2_2_MEDIAN, MIN_DOF, _median

__all__ = ["GUARD_DRIFT", "Solve", "Solved", "inconsistent", "kept_majority", "outlying", "widened"]


class Solved(Protocol):
    """A one-step join of one pair of pieces (:mod:`mapjoin.joining`): right's points ``z`` land at ``t + turn z``
    in left's frame; ``cost`` is its minimum f_1(phi*)."""

    t: complex
    turn: complex

    @property
    def cost(self) -> float:
        """The join's minimum."""


#: the join of the associated pairs (left compact ids, right rows), as :mod:`mapjoin.joining` makes it
Solve = Callable[[np.ndarray, np.ndarray], Solved]

#: a guarded join is associated again with every drift ``D`` this many times larger: the chain's drift on the default
#: simulation is 30 to 100 times ``D`` (true pairs met again 5 to 15 maps later lie a median 60 times their variance
#: from their prediction); with 10, 4 runs of 50 maps kept 23 false links against 14, 1000 cut no more than 100
#: (docs/method.md#data-association, step 9)
GUARD_DRIFT = 100.0


def inconsistent(cost: float, pairs: int, gate: float = DEFAULT_GATE) -> bool:
    """Whether a join of ``pairs`` pairs whose one-step minimum is ``cost`` fails the chi-square ``gate`` of its own
    check (p below it at ``2 pairs`` degrees of freedom, docs/method.md#each-join) with enough pairs for a median
    (``2 pairs - 3`` at least step 5's ``MIN_DOF``): a lookup in a table of quantiles, all a consistent join pays."""
    return 2 * pairs - 3 >= MIN_DOF and cost > float(_threshold(1.0 - gate, pairs))


def outlying(ratios: np.ndarray, level: float) -> bool:
    """Whether one of a join's pairs, ``ratios`` its squared residuals after the one-step solve over their spherical
    variances, lies beyond the association's gate quantile ``level`` (chi-square, 2 degrees of freedom) times the
    join's robust variance factor: their median over that chi-square's median, as step 5's factor. At 0.999 a pair
    ten times the median: a true pair once in a thousand, if the residuals were the model's."""
    return bool(ratios.max() > _threshold(level, 1) / CHI2_2_MEDIAN * _median(ratios))


def widened(drift: tuple[np.ndarray, ...], pair_drift: Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray]
            ) -> tuple[tuple[np.ndarray, ...], Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray]]:
    """The drift of steps 6 to 8 times :data:`GUARD_DRIFT`: each feature's ``D`` and heading variance, and each
    pair's drift through the chain's ties (``pair_drift(left rows, right rows, noise)``, which may stop once it
    reaches the noise it is given: given the noise over the factor)."""
    def pair_widened(i: np.ndarray, j: np.ndarray, noise: np.ndarray) -> np.ndarray:
        return pair_drift(i, j, noise / GUARD_DRIFT) * GUARD_DRIFT

    return tuple(part * GUARD_DRIFT for part in drift), pair_widened


def kept_majority(left: np.ndarray, right: np.ndarray, again_left: np.ndarray, again_right: np.ndarray) -> int | None:
    """How many pairs ``(left, right)`` of an association the guard's association ``(again_left, again_right)`` (each
    sorted by right row) left out, or None when it keeps fewer than half of them (the guard then keeps the first)."""
    position = np.minimum(np.searchsorted(again_right, right), max(len(again_right) - 1, 0))
    kept = int(np.count_nonzero((again_right[position] == right) & (again_left[position] == left))) \
        if len(again_right) else 0
    return None if 2 * kept < len(left) else len(left) - kept
