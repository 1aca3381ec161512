"""Steps 2 and 3 of data association: the gate around each right feature's prediction and the clear nearest
neighbour (docs/method.md#data-association).

Right's features are predicted in left's frame through the join's link; a pair is a candidate when its innovation's
squared Mahalanobis distance is within the ``gate`` quantile of a chi-square with 2 degrees of freedom (:func:`_gate`;
the quantiles of the gate and of the joint test: :func:`_threshold`). Every candidate lies within a Euclidean radius
of its right feature's prediction, so the pairs within it are found first (:func:`_candidates`: every pair of a small
join at once, else by the grid of :mod:`mapjoin.association.grid`; :class:`_Searched` for the rounds, which mostly
search again where they searched before). A candidate is taken when it is the clear nearest neighbour of both its
features (:func:`_clear`): the nearest *rival*, a candidate seen in one map with the nearest one
(:func:`sighting_bits`), is at least ``margin`` farther.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from ..consistency import chi2_quantile
from .grid import pairs_within

__all__ = ["DEFAULT_GATE", "DEFAULT_MARGIN", "sighting_bits"]

#: default chi-square level of the individual gate and of the joint compatibility test
DEFAULT_GATE = 0.999
#: a single join's candidate pairs are found by brute force up to this many (left x right) pairs, else by a grid
BRUTE_FORCE_PAIRS = 1 << 16
#: the rounds' candidate search reaches this many times each right feature's radius, so that the later rounds mostly
#: take its pairs (:class:`_Searched`; VicPark's and DLR's sequential joins search in 48 % and 55 % of their rounds,
#: against 76 % and 90 % at 1)
SEARCH_REACH = 1.25
#: a feature's nearest candidate is taken when the next one is at least this much farther (squared Mahalanobis
#: distance: twice the log-likelihood ratio of the two hypotheses; 9.2 = 2 ln 100)
DEFAULT_MARGIN = 9.2
_QUANTILES: dict[float, np.ndarray] = {}  # level -> chi2_quantile(level, 2k) for k = 0, 1, 2, ...
_NO_QUANTILES = np.zeros(1)


def _threshold(level: float, pairs: np.ndarray | int) -> np.ndarray:
    """``chi2_quantile(level, 2 * pairs)`` from a table grown by doubling (the joint test asks it per join)."""
    table = _QUANTILES.get(level, _NO_QUANTILES)
    largest = pairs if isinstance(pairs, int) else int(pairs.max(initial=0))
    if largest >= len(table):
        table = np.concatenate([[0.0], chi2_quantile(level, 2 * np.arange(1, max(2 * len(table), largest + 1)))])
        _QUANTILES[level] = table
    return table[pairs]


def _check_gate(gate: float) -> None:
    if not 0.0 < gate < 1.0:
        raise ValueError(f"gate must be a chi-square level in (0, 1), got {gate!r}")


def _candidates(left: np.ndarray, left_join: np.ndarray, predicted: np.ndarray, right_join: np.ndarray,
                radius: np.ndarray, joins: int) -> tuple[np.ndarray, np.ndarray]:
    """Pairs (left row, right row) of the same join whose Euclidean distance is at most ``radius[right]``
    (complex points; rows grouped by join), sorted by left row then right row: for one join with few pairs in
    reach of the right points' bounding box, every such pair at once; else by a grid
    (:func:`mapjoin.association.grid.pairs_within`)."""
    if joins == 1 and len(predicted):  # one join: the left points in the right ones' reach, then the outer difference
        reach = float(radius.max())
        rows = ((left.real >= predicted.real.min() - reach) & (left.real <= predicted.real.max() + reach)
                & (left.imag >= predicted.imag.min() - reach) & (left.imag <= predicted.imag.max() + reach)).nonzero()[0]
        if len(rows) * len(predicted) <= BRUTE_FORCE_PAIRS:
            i, j = np.nonzero(np.abs(left[rows, None] - predicted[None, :]) <= radius[None, :])
            return rows[i], j
    return pairs_within(left, left_join, predicted, right_join, radius, joins)


class _Searched:
    """:func:`_candidates` remembering its last search, for the rounds of
    :func:`mapjoin.association.rounds.match_features`: a round whose every right feature's reach (its radius about its
    prediction) lies inside its reach in the last search has no candidate the last search did not find, so it takes
    the last search's pairs (more, maybe: the gate's ``d^2`` drops those, as every pair in the gate lies within the
    radius, :func:`_gate`). A search reaches :data:`SEARCH_REACH` times the radius (the pairs it adds cost little): the
    corrected link's posterior is tighter than the prior and its correction small, so that the rounds after the first
    mostly lie inside its search."""

    def __init__(self) -> None:
        self.last: tuple | None = None

    def __call__(self, left: np.ndarray, left_join: np.ndarray, predicted: np.ndarray, right_join: np.ndarray,
                 radius: np.ndarray, joins: int) -> tuple[np.ndarray, np.ndarray]:
        last = self.last
        if (last is not None and last[0] is left and len(last[1]) == len(predicted)
                and (np.abs(predicted - last[1]) + radius <= last[2] * (1 - 1e-9)).all()):
            return last[3], last[4]
        radius = radius * SEARCH_REACH
        i, j = _candidates(left, left_join, predicted, right_join, radius, joins)
        self.last = (left, predicted, radius, i, j)
        return i, j


def _clear(group: np.ndarray, other: np.ndarray, d2: np.ndarray, sightings: np.ndarray | None, margin: float
           ) -> np.ndarray:
    """For each pair (``group``: its feature on one side, ``other``: on the other): whether it is the nearest of its
    group and its group's nearest *rival* is at least ``margin`` farther (in ``d2``; none: infinitely). A rival is
    another candidate that is a different feature from the nearest: one seen in a same map as it (``sightings``: each
    other-side feature's maps, :func:`sighting_bits`; without them every other candidate is a rival). Two candidates
    never seen together may be one feature mapped twice, and either is the right match. A join's groups are mostly of
    one candidate: then each is clear, without sorting."""
    if len(group) < 2 or np.bincount(group).max() == 1:
        return np.ones(len(group), dtype=bool)
    order = np.lexsort((d2, group))
    grouped, others, distances = group[order], other[order], d2[order]
    first = np.ones(len(order), dtype=bool)
    first[1:] = grouped[1:] != grouped[:-1]
    head = np.maximum.accumulate(np.where(first, np.arange(len(order)), 0))  # each pair's group's nearest
    rival = ~first
    if sightings is not None:
        rival &= (sightings[others] & sightings[others[head]]).any(axis=1)
    second = np.full(len(order), np.inf)
    np.minimum.at(second, head[rival], distances[rival])
    clear = np.zeros(len(order), dtype=bool)
    clear[order] = first & (second[head] - distances >= margin)
    return clear


def sighting_bits(maps: np.ndarray) -> np.ndarray:
    """Each map index as one bit of a 128-bit set (2 x uint64: bit ``k mod 128``): a feature's sightings are the
    union of its maps'. Two features whose sets intersect may have been seen in one map (a collision modulo 128
    says so wrongly, which only leaves a choice ambiguous); disjoint sets were never seen together."""
    maps = np.asarray(maps, dtype=np.int64) % 128
    bits = np.zeros((len(maps), 2), dtype=np.uint64)
    bits[np.arange(len(maps)), maps // 64] = np.left_shift(np.uint64(1), (maps % 64).astype(np.uint64))
    return bits


def _gate(left: np.ndarray, left_covariances: np.ndarray, left_join: np.ndarray, largest: np.ndarray,
          predicted: np.ndarray, lever: np.ndarray, right_covariances: np.ndarray, right_join: np.ndarray,
          link: np.ndarray, scale: np.ndarray | None, g2: float, margin: float = DEFAULT_MARGIN,
          left_sightings: np.ndarray | None = None, right_sightings: np.ndarray | None = None,
          search: Callable[..., tuple[np.ndarray, np.ndarray]] = _candidates, attached: np.ndarray | None = None
          ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The unambiguous candidate pairs (left rows, right rows) of every join, and the ambiguous right rows
    (sorted); the pairs within each right feature's radius are found by ``search`` (:func:`_candidates`, or a
    :class:`_Searched`).

    A pair's innovation ``r = f - x`` has covariance ``S = C0 + C1 + H link H^T`` with ``H = [I, u]`` (``C0``,
    ``C1``: the features' 2 x 2 covariances, rows ``[xx, xy, yy]``, times their join's variance factor ``scale``
    (None: 1);
    ``largest[join]``: the largest trace of its left ``C0`` before the factor; ``link[join]``: the 3 x 3 covariance
    of the join's link error); it is a candidate when ``d^2 = r^T S^-1 r <= g2``. A candidate is taken when it is its
    right feature's nearest and its left feature's nearest, and each one's nearest rival (:func:`_clear`, given the
    features' ``sightings``) is at least ``margin`` farther (in ``d^2``); the other right features with candidates
    are ambiguous. A pair whose left feature is ``attached`` (a mask over the left rows; None: none) is compared in
    the link's own frame (:mod:`mapjoin.association.link_frame`): no link term in its ``S``.
    """
    joins = len(link)
    ux, uy = lever.real, lever.imag
    own = link[right_join]
    # H link H^T = link_tt + u link_phi,t + link_t,phi u^T + link_phiphi u u^T, per right feature
    sxx = own[:, 0, 0] + 2 * ux * own[:, 0, 2] + own[:, 2, 2] * ux * ux
    syy = own[:, 1, 1] + 2 * uy * own[:, 1, 2] + own[:, 2, 2] * uy * uy
    sxy = own[:, 0, 1] + ux * own[:, 1, 2] + uy * own[:, 0, 2] + own[:, 2, 2] * ux * uy
    # the trace bounds the largest eigenvalue: every pair in the gate is within this Euclidean radius
    own_trace = largest[right_join] + right_covariances[:, 0] + right_covariances[:, 2]
    radius = np.sqrt(g2 * ((own_trace if scale is None else scale[right_join] * own_trace) + sxx + syy))
    i, j = search(left, left_join, predicted, right_join, radius, joins)
    r = left[i] - predicted[j]
    if scale is None:  # a factor of 1 changes nothing
        own_covariances = left_covariances[i] + right_covariances[j]
    else:
        own_covariances = (scale[left_join[i], None] * left_covariances[i]
                           + scale[right_join[j], None] * right_covariances[j])
    if attached is None:
        xx, xy, yy = own_covariances[:, 0] + sxx[j], own_covariances[:, 1] + sxy[j], own_covariances[:, 2] + syy[j]
    else:
        linked = ~attached[i]
        xx = own_covariances[:, 0] + linked * sxx[j]
        xy, yy = own_covariances[:, 1] + linked * sxy[j], own_covariances[:, 2] + linked * syy[j]
    det = xx * yy - xy * xy  # S^-1 in closed form (as inverted), its quadratic form (as _mahalanobis)
    # det <= 0: S singular to rounding (a heading variance carried far, u link_phiphi u^T, dwarfs the rest and the
    # rest is lost): no candidate, the feature stays new
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        d2 = np.where(det > 0, (yy / det) * r.real**2 + 2 * (-xy / det) * r.real * r.imag + (xx / det) * r.imag**2,
                      np.inf)
    gated = d2 <= g2
    i, j, d2 = i[gated], j[gated], d2[gated]
    taken = _clear(j, i, d2, left_sightings, margin) & _clear(i, j, d2, right_sightings, margin)
    i, taken_j = i[taken], j[taken]
    undecided = np.zeros(len(predicted), dtype=bool)  # the right rows with candidates, none taken (sorted)
    undecided[j] = True
    undecided[taken_j] = False
    return i, taken_j, undecided.nonzero()[0]
