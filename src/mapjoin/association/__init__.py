"""Data association: which features of an incoming map are features of the map it is joined onto.

Maps whose feature ids are local to each map (a front end's submaps) cannot be joined by id.
:func:`join_associated` joins them as :func:`mapjoin.joining.join` does, deciding before each
join (sequential and tree) which features of the right piece are features of the left one
(docs/method.md#data-association):

1. **Covariances.** Each right feature's uncertainty relative to the join's link is its 2 x 2 marginal
   covariance in its local map (the map's full covariance, which the spherical weights of the fast join
   are not: :func:`feature_covariances`), rotated into left's frame. Each left feature carries the
   covariances of its sightings fused as independent estimates: its uncertainty relative to the maps
   that saw it, whose common drift is left to the link's error (3).
2. **Prediction and gate.** Right's features ``z`` are predicted in left's frame through left's end pose
   ``(o, phi_o)``, the join's link: ``x = o + R(phi_o) z``. A link error ``(dt, dphi)`` moves the
   prediction by ``H (dt, dphi)``, ``H = [I, u]``, ``u = R'(phi_o) z``; a pair's innovation
   ``r = f - x`` has covariance ``S = s (C0 + C1) + H P_link H^T``. A pair is a candidate when
   ``r^T S^-1 r`` is within the ``gate`` quantile of a chi-square with 2 degrees of freedom
   (default 0.999: a true pair is refused once in a thousand).
   A tree join also associates its undrifted features alone, under the link's variance relative to its own map,
   and adds the pairs of features left unpaired (the junction rule, :mod:`mapjoin.association.junction`).
3. **Nearest neighbour, when clear.** A pair is taken when each of its features is the other's nearest
   candidate and each one's nearest *rival* is at least ``margin`` farther (squared Mahalanobis distance;
   default 9.2 = 2 ln 100: the nearest is a hundred times likelier). A rival is a candidate that is a
   different feature from the nearest one: seen in one map with it. Two candidates never seen in one map may
   be one feature mapped twice (an earlier miss), and taking the nearest then joins no two features; this
   stops a miss from making every later sighting of the feature ambiguous. Other right features with
   candidates are *ambiguous* and left new.
4. **Joint compatibility.** The pairs share the link's error, so they are tested together: the
   joint Mahalanobis distance of all their innovations (covariance ``blockdiag(s (C0 + C1)) + H P_link H^T``,
   evaluated in 3-D by the Woodbury identity) must be within the ``gate``
   quantile of a chi-square with ``2k`` degrees of freedom. When it is not, the largest jointly
   compatible subset is kept: by exhaustive search over every subset at once (as arrays) when at
   most :data:`EXHAUSTIVE_PAIRS` pairs remain (the optimum branch and bound would find), after
   removing, one at a time, the pair with the largest residual once the link is corrected
   while more remain. Pairs removed are *rejected* and their right features left new.
5. **Rounds.** The pairs give the link's correction and its posterior covariance ``P_link``, and the
   a-posteriori variance factor ``s``: the median of the pairs' squared residuals (Mahalanobis, after the
   correction) over the median of a chi-square with 2 degrees of freedom, robust to a few wrong pairs,
   at least 1, once the pairs have :data:`MIN_DOF` degrees of freedom. Steps 2 to 4 run again around the
   corrected prediction until the pairs repeat (at most :data:`ROUNDS` rounds), which removes the link's
   error and finds the pairs it had hidden (as ICP does).

6. **Loop closures** (:func:`match_with_drift`). Where a map meets features last seen many maps before, the
   chain's drift since then has moved them, relative to the link, by more than the gate and the features'
   spacing. Each feature's drift variance ``D`` since its last sighting (a right piece's feature: up to its
   first) comes from :mod:`mapjoin.association.feature_drift`, which the hooks fill as the joins are made; among the
   features steps 2 to 5 left unpaired, the candidates within the drift's gate vote, two pairs at a time, for
   the one rigid correction of the link that the drift made (:mod:`mapjoin.association.loop_votes`); a join whose
   best correction is clearly the best (:data:`LOOP_SUPPORT` right features, :data:`LOOP_CLEAR` times any other
   correction's agreement) associates its unpaired features again, steps 2 to 5 around the corrected link, and keeps
   a pair where it is clear under the correction with its drift relative to the voters, or under the link with its
   drift (:mod:`mapjoin.association.loop_scope`). Then the undrifted features the link's correction moved by more than
   their noise vote once more, the same way, each with the squared distance it moved its prediction as its spread:
   a correction set by drifted pairs is a drift of its own for the features near the link.
7. **A strained map so far** (:mod:`mapjoin.association.strain`). Before step 6, a pair of
   steps 2 to 5 whose left feature has drifted (``D`` at least the pair's noise) is left new when another left
   feature seen in one map with it lies within its drift (:data:`mapjoin.association.strain.DRIFT_MARGIN`): its
   small offset is no evidence then. ``D`` is taken the shorter way through the chain's ties (a join that matched
   :data:`TIE_SUPPORT` drifted feature ties its map to theirs; a tree join's ties are those inside its pieces)
   plus the strain of the joins that fused features partway between two estimates (a quarter of each pair's
   squared residual, per feature and per tie; :meth:`mapjoin.association.feature_drift.SightingDrift.settled`,
   :meth:`~mapjoin.association.feature_drift.SightingDrift.settled_after`).
8. **A lone drifted pair** (:mod:`mapjoin.association.lone`). After step 7, a pair whose drift is
   :data:`~mapjoin.association.lone.LONE_DRIFT` times its noise, in a join with fewer than
   :data:`~mapjoin.association.lone.CHECKED` such pairs (nothing confirms its drift), is left new when another left
   feature, even one never seen with the chosen one (its second copy), lies within half its drift
   (:data:`~mapjoin.association.lone.LONE_MARGIN`) and a rival seen with it is within ``margin`` under the drift.

The accepted pairs are the join's common features; every other right feature becomes a new
feature of the global map. The global ids are numbered from 0 in order of first sighting:
by map, then by local id.

Cost: :func:`match_features` associates all the joins of a tree level at once (as the tree joins
them), and the sequential join is a batch of one; candidates are all pairs of a join up to
:data:`BRUTE_FORCE_PAIRS`, else found with a grid (:mod:`mapjoin.association.grid`). Only a join whose pairs fail
the joint test is searched on its own.

:func:`local_ids` turns a map set with global ids into one with ids local to each map and
returns the true correspondence (tests, benchmarks, ``simulate --local-ids``).
"""

from __future__ import annotations

import collections
import dataclasses
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from ..consistency import chi2_quantile
from ..covariance import DEFAULT_COVARIANCE, CovarianceMode
from ..joining import join
from ..joins import JoinRecord, Strategy
from ..maps import GlobalMap, LocalMap, locate
from ..onestep import as_complex
from .feature_drift import SightingDrift
from .grid import pairs_within
from .junction import free_pairs, own_link_variances, undrifted
from .lone import LONE_MARGIN, lone_drifted
from .loop_scope import VoterDrift, beyond_voters, voters_drift
from .loop_votes import rigid_votes
from .strain import drift_rivals

if TYPE_CHECKING:
    from ..joins import _Pieces
    from ..onestep import Solver

__all__ = [
    "DEFAULT_GATE",
    "DEFAULT_MARGIN",
    "EXHAUSTIVE_PAIRS",
    "LOOP_CLEAR",
    "LOOP_SUPPORT",
    "ROUNDS",
    "TIE_SUPPORT",
    "AssociatedJoin",
    "AssociatedJoinRecord",
    "FeatureAssociation",
    "Matches",
    "blocks",
    "correspondence_rows",
    "feature_covariances",
    "fused",
    "inverted",
    "join_associated",
    "link_errors",
    "local_ids",
    "match_features",
    "match_with_drift",
    "rotated",
    "sighting_bits",
]

#: default chi-square level of the individual gate and of the joint compatibility test
DEFAULT_GATE = 0.999
#: the joint test searches every subset of at most this many pairs (2^10 = 1024 subsets, as arrays)
EXHAUSTIVE_PAIRS = 10
#: a single join's candidate pairs are found by brute force up to this many (left x right) pairs, else by a grid
BRUTE_FORCE_PAIRS = 1 << 16
#: the rounds' candidate search reaches this many times each right feature's radius, so that the later rounds mostly
#: take its pairs (:class:`_Searched`; VicPark's and DLR's sequential joins search in 48 % and 55 % of their rounds,
#: against 76 % and 90 % at 1)
SEARCH_REACH = 1.25
#: the variance factor of a round needs at least this many degrees of freedom (2k - 3 for k pairs)
MIN_DOF = 4
#: a feature's nearest candidate is taken when the next one is at least this much farther (squared Mahalanobis
#: distance: twice the log-likelihood ratio of the two hypotheses; 9.2 = 2 ln 100)
DEFAULT_MARGIN = 9.2
#: at most this many rounds of associate, correct the link, re-predict (they stop when the pairs repeat)
ROUNDS = 4
#: a loop closure needs at least this many right features voting for its offset (and twice the runner-up's), and
#: this many pairs once associated around it
LOOP_SUPPORT = 4
#: ... and its pairs of right features agreeing on the correction at least this many times the runner-up's (a
#: rival association's: :func:`mapjoin.association.loop_votes.rigid_votes`)
LOOP_CLEAR = 2
#: a join ties its map to the map that last saw its drifted pairs' features when it has at least this many (step 7):
#: one, since a chain of small maps meets its old features one to three a join (VicPark 6898: with 4, as a loop
#: closure's support, the chain was tied almost nowhere and D summed every junction since; benchmarks/README.md)
TIE_SUPPORT = 1
#: the median of a chi-square with 2 degrees of freedom, 2 ln 2: the robust variance factor's reference
CHI2_2_MEDIAN = 2 * math.log(2)


@dataclass(frozen=True)
class Matches:
    """The association of one or more joins: ``left[i]`` and ``right[i]`` are rows of the same feature (sorted
    by right row); per join, ``ambiguous`` right features had two candidates (or shared theirs) and
    ``rejected`` ones failed the joint test."""

    left: np.ndarray
    right: np.ndarray
    ambiguous: np.ndarray
    rejected: np.ndarray
    #: the right rows that had candidates but no pair (the ambiguous ones, as rows), and each join's link correction
    #: ``(dx, dy, dphi)`` in the round that gave the pairs (made by the rounds before it; zeros in the first)
    undecided: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0, np.intp))
    correction: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros((0, 3)))


@dataclass(frozen=True)
class AssociatedJoinRecord(JoinRecord):
    """A join's report row when associating: ``common`` features were matched, ``new`` were not, of which
    ``ambiguous`` had two candidates in the gate and ``rejected`` failed the joint compatibility test."""

    ambiguous: int = 0
    rejected: int = 0


@dataclass(frozen=True)
class FeatureAssociation:
    """One row of ``join --associations``: feature ``local_id`` of input map ``map`` (1-based) is ``global_id``."""

    map: int
    local_id: int
    global_id: int


@dataclass(frozen=True)
class AssociatedJoin:
    """A join with data association: the result (global ids numbered by first sighting, report rows
    :class:`AssociatedJoinRecord`), each input feature's global id (``maps[k]``'s ``feature_ids[j]`` is
    ``global_ids[k][j]``)."""

    global_map: GlobalMap
    report: tuple[AssociatedJoinRecord, ...]
    global_ids: tuple[np.ndarray, ...]

    def relabel(self, maps: Sequence[LocalMap]) -> tuple[LocalMap, ...]:
        """The input ``maps`` with their features' global ids: a known-id join of them is the same join."""
        return tuple(dataclasses.replace(m, feature_ids=ids) for m, ids in zip(maps, self.global_ids))

    def rows(self, maps: Sequence[LocalMap]) -> list[FeatureAssociation]:
        """The ``--associations`` table of the input ``maps``: one row per feature, by map then local id."""
        return [FeatureAssociation(k + 1, int(local), int(found)) for k, m in enumerate(maps)
                for local, found in sorted(zip(m.feature_ids.tolist(), self.global_ids[k].tolist()))]


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


def _same(first: np.ndarray, second: np.ndarray) -> bool:
    """``np.array_equal`` of two 1-D arrays, without its wrapper's cost (a round compares its pairs two or three
    times)."""
    return len(first) == len(second) and bool((first == second).all())


def _segments(group: np.ndarray, count: int) -> tuple[np.ndarray, np.ndarray]:
    """Rows grouped by ``group`` (non-decreasing, values < ``count``): each group's first row and size."""
    sizes = np.bincount(group, minlength=count)
    return np.cumsum(sizes) - sizes, sizes


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
    """:func:`_candidates` remembering its last search, for the rounds of :func:`match_features`: a round whose every
    right feature's reach (its radius about its prediction) lies inside its reach in the last search has no candidate
    the last search did not find, so it takes the last search's pairs (more, maybe: the gate's ``d^2`` drops those, as
    every pair in the gate lies within the radius, :func:`_gate`). A search reaches :data:`SEARCH_REACH` times the radius
    (the pairs it adds cost little): the corrected link's posterior is tighter than the prior and its correction small,
    so that the rounds after the first mostly lie inside its search."""

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


def blocks(variances: np.ndarray) -> np.ndarray:
    """2 x 2 covariances as rows ``[xx, xy, yy]``: ``variances`` as they are (n x 3) or spherical (n,)."""
    variances = np.asarray(variances, dtype=float)
    if variances.ndim == 2:
        return variances
    return np.column_stack([variances, np.zeros_like(variances), variances])


def rotated(covariances: np.ndarray, phi: np.ndarray | float) -> np.ndarray:
    """``R(phi) C R(phi)^T`` of 2 x 2 covariances (rows ``[xx, xy, yy]``; ``phi`` one angle or one per row)."""
    c, s = np.cos(phi), np.sin(phi)
    xx, xy, yy = covariances.T
    out = np.empty((len(covariances), 3))
    out[:, 0] = c * c * xx - 2 * c * s * xy + s * s * yy
    out[:, 1] = c * s * (xx - yy) + (c * c - s * s) * xy
    out[:, 2] = s * s * xx + 2 * c * s * xy + c * c * yy
    return out


_ADJUGATE_SIGNS = np.array([1.0, -1.0, 1.0])


def inverted(covariances: np.ndarray) -> np.ndarray:
    """The inverses of 2 x 2 symmetric matrices (rows ``[xx, xy, yy]``), in closed form."""
    det = covariances[:, 0] * covariances[:, 2] - covariances[:, 1] * covariances[:, 1]
    return covariances[:, ::-1] * _ADJUGATE_SIGNS / det[:, None]  # [yy, -xy, xx] / det


def fused(first: np.ndarray, second: np.ndarray) -> np.ndarray:
    """The covariance of two independent estimates of one point fused: ``(C1^-1 + C2^-1)^-1`` (rows ``[xx, xy, yy]``)."""
    return inverted(inverted(first) + inverted(second))


_BLOCK_ROWS, _BLOCK_COLUMNS = np.array([0, 0, 1]), np.array([0, 1, 1])  # a 2 x 2 block's xx, xy, yy


def feature_covariances(local_map: LocalMap) -> np.ndarray:
    """Each feature's 2 x 2 marginal covariance in ``local_map``'s frame (rows ``[xx, xy, yy]``, in the order of
    the sorted feature ids, as :mod:`mapjoin.joining` holds them): the blocks of the full covariance when the map
    has one, else its spherical variances. They are the uncertainty of a feature *relative to the map's start*,
    the join's link, which the gate needs (docs/method.md#data-association)."""
    order = np.argsort(local_map.feature_ids, kind="stable")
    if local_map.covariance is None:
        return blocks(local_map.feature_variances[order])
    rows = 3 + 2 * order[:, None]  # each feature's x row; its [xx, xy, yy] entries in one gather
    return local_map.covariance[rows + _BLOCK_ROWS, rows + _BLOCK_COLUMNS]


def _mahalanobis(r: np.ndarray, information: np.ndarray) -> np.ndarray:
    """``r^T W r`` of complex ``r`` and 2 x 2 ``W`` (rows ``[xx, xy, yy]``)."""
    return information[:, 0] * r.real**2 + 2 * information[:, 1] * r.real * r.imag + information[:, 2] * r.imag**2


def _joint_terms(r: np.ndarray, w: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each pair's share of the joint test, ``W`` its innovation's information without the link (k x 3, rows
    ``[xx, xy, yy]``): ``r^T W r``, ``H^T W r`` (k x 3) and ``H^T W H`` (k x 9), ``H = [I, u]`` (complex ``r``, ``u``)."""
    wxx, wxy, wyy = w.T
    ux, uy = u.real, u.imag
    g, h = np.empty((len(r), 3)), np.empty((len(r), 9))  # filled by columns (fewer calls than stacking)
    g[:, 0] = qx = wxx * r.real + wxy * r.imag  # W r
    g[:, 1] = qy = wxy * r.real + wyy * r.imag
    g[:, 2] = ux * qx + uy * qy
    h[:, 2] = h[:, 6] = px = wxx * ux + wxy * uy  # W u
    h[:, 5] = h[:, 7] = py = wxy * ux + wyy * uy
    h[:, 0], h[:, 1], h[:, 3], h[:, 4], h[:, 8] = wxx, wxy, wxy, wyy, ux * px + uy * py
    return r.real * qx + r.imag * qy, g, h


def _joint_distances(masks: np.ndarray, terms, link_information: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The joint Mahalanobis distance of each subset of pairs (``masks``, s x k, 0/1) and the link correction
    that explains it best: ``D^2 = sum r^T W r - g^T M^-1 g`` with ``g = sum H^T W r``, ``M = P_link^-1 + sum
    H^T W H`` (Woodbury: the pairs' covariance ``blockdiag(W^-1) + H P_link H^T`` inverted through the 3-D link)."""
    c, g, h = terms
    big_g = masks @ g
    big_m = (masks @ h).reshape(-1, 3, 3) + link_information
    correction = np.linalg.solve(big_m, big_g[..., None])[..., 0]
    return masks @ c - np.einsum("si,si->s", big_g, correction), correction


def _jointly_compatible(terms, r: np.ndarray, w: np.ndarray, u: np.ndarray, link_information: np.ndarray,
                        gate: float) -> np.ndarray:
    """The pairs kept by the joint compatibility test (a boolean mask over the k pairs, whose
    :func:`_joint_terms` are ``terms``): all of them when compatible, else the largest compatible subset
    (ties: the smallest joint distance)."""
    k = len(r)
    keep = np.ones(k, dtype=bool)
    if not k:
        return keep
    c, g, h = terms
    while True:  # remove the worst pair while too many remain for the exhaustive search
        distance, correction = _joint_distances(keep[None].astype(float), terms, link_information)
        if distance[0] <= _threshold(gate, int(keep.sum())):
            return keep
        if keep.sum() <= EXHAUSTIVE_PAIRS:
            break
        dx, dy, dphi = correction[0]
        residual = _mahalanobis(r - (dx + 1j * dy) - u * dphi, w)
        keep[np.flatnonzero(keep)[np.argmax(residual[keep])]] = False
    rows = np.flatnonzero(keep)
    count = len(rows)
    masks = ((np.arange(1, 2**count)[:, None] >> np.arange(count)) & 1).astype(float)  # every non-empty subset
    sub = (c[rows], g[rows], h[rows])
    distance, _ = _joint_distances(masks, sub, link_information)
    sizes = masks.sum(axis=1)
    compatible = distance <= _threshold(gate, sizes.astype(np.intp))
    keep[:] = False
    if compatible.any():
        best = np.lexsort((distance, -sizes, ~compatible))[0]
        keep[rows[masks[best] > 0]] = True
    return keep


def _join_maxima(values: np.ndarray, join: np.ndarray, joins: int) -> np.ndarray:
    """The largest of ``values`` (non-negative) in each of ``joins`` joins (0 for a join without any)."""
    if joins == 1:  # the sequential join: no scatter
        return values.max(initial=0.0)[None]
    largest = np.zeros(joins)
    np.maximum.at(largest, join, values)
    return largest


def _segment_sums(values: np.ndarray, group: np.ndarray, count: int) -> np.ndarray:
    """Sums of the rows of ``values`` (p x c) by ``group`` (count x c)."""
    if count == 1:
        return values.sum(axis=0)[None]
    return np.stack([np.bincount(group, values[:, column], minlength=count) for column in range(values.shape[1])],
                    axis=1)


def _median(values: np.ndarray) -> float:
    """``np.median(values)`` (the mean of the middle two of an even count, as a float), by one sort: on a join's few
    pairs ``np.median``'s own overhead is ten times the sort's."""
    ordered = np.sort(values)
    middle = len(ordered) // 2
    return float(ordered[middle]) if len(ordered) % 2 else (float(ordered[middle - 1]) + float(ordered[middle])) / 2


def _segment_medians(values: np.ndarray, group: np.ndarray, count: int) -> np.ndarray:
    """The median of ``values`` in each group (the upper one of an even group; NaN for an empty group)."""
    if count == 1:
        return np.sort(values)[len(values) // 2:][:1] if len(values) else np.full(1, np.nan)
    order = np.lexsort((values, group))
    start, size = _segments(group[order], count)
    middle = np.minimum(start + size // 2, max(len(values) - 1, 0))
    return np.where(size > 0, values[order][middle] if len(values) else np.nan, np.nan)


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
          search: Callable[..., tuple[np.ndarray, np.ndarray]] = _candidates) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
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
    are ambiguous.
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
    xx, xy, yy = own_covariances[:, 0] + sxx[j], own_covariances[:, 1] + sxy[j], own_covariances[:, 2] + syy[j]
    det = xx * yy - xy * xy  # S^-1 in closed form (as inverted), its quadratic form (as _mahalanobis)
    d2 = (yy / det) * r.real**2 + 2 * (-xy / det) * r.real * r.imag + (xx / det) * r.imag**2
    gated = d2 <= g2
    i, j, d2 = i[gated], j[gated], d2[gated]
    taken = _clear(j, i, d2, left_sightings, margin) & _clear(i, j, d2, right_sightings, margin)
    i, taken_j = i[taken], j[taken]
    undecided = np.zeros(len(predicted), dtype=bool)  # the right rows with candidates, none taken (sorted)
    undecided[j] = True
    undecided[taken_j] = False
    return i, taken_j, undecided.nonzero()[0]


def match_features(left: np.ndarray, left_covariances: np.ndarray, left_join: np.ndarray, link_xy: np.ndarray,
                   link_phi: np.ndarray, link_variances: np.ndarray, right: np.ndarray,
                   right_covariances: np.ndarray, right_join: np.ndarray, gate: float = DEFAULT_GATE,
                   margin: float = DEFAULT_MARGIN, left_sightings: np.ndarray | None = None,
                   right_sightings: np.ndarray | None = None) -> Matches:
    """Associate right's features with left's in several independent joins at once (complex points; their
    covariances as rows ``[xx, xy, yy]`` in left's frame, or spherical variances; rows grouped by join; see the
    module docstring): predict through each join's link ``(link_xy, link_phi)`` with variances
    ``link_variances`` (joins x 2: var_t, p_phi), gate, take the clear nearest neighbours, test them jointly;
    then correct each link by its pairs, re-predict with the link's posterior covariance and the robust
    variance factor of the pairs' residuals, and associate again, until the pairs repeat (at most
    :data:`ROUNDS` rounds).

    Every step is array operations over all joins; only a join whose pairs fail the joint test is searched
    on its own (:func:`_jointly_compatible`).
    """
    _check_gate(gate)
    left_covariances, right_covariances = blocks(left_covariances), blocks(right_covariances)
    joins = len(link_xy)
    turn = np.exp(1j * link_phi)
    prior_prediction = link_xy[right_join] + turn[right_join] * right
    lever = 1j * turn[right_join] * right  # R'(phi_o) z
    var_t, p_phi = link_variances[:, 0], link_variances[:, 1]
    prior_information = np.zeros((joins, 3, 3))
    prior_information[:, 0, 0] = prior_information[:, 1, 1] = 1.0 / var_t
    prior_information[:, 2, 2] = 1.0 / p_phi
    link = np.zeros((joins, 3, 3))
    link[:, 0, 0] = link[:, 1, 1] = var_t
    link[:, 2, 2] = p_phi
    predicted = prior_prediction
    correction = np.zeros((joins, 3))
    g2 = float(_threshold(gate, 1))
    scale = np.ones(joins)
    largest = _join_maxima(left_covariances[:, 0] + left_covariances[:, 2], left_join, joins)
    previous = None
    search = _Searched()  # the rounds' candidate pairs, found again only where a round reaches beyond the last
    tested = None  # the last round's pairs before the joint test (over every join), its scale and its rejected counts
    live = np.ones(joins, dtype=bool)  # the joins whose next round may differ from their last
    all_live = True  # live.all(), kept as the joins settle
    settled: list[tuple] = []  # the outcomes of the others: their state repeats, so would their rounds
    for round_number in range(ROUNDS):
        first_round = previous is None  # the factor is 1 (a product or a division by it changes nothing)
        if all_live:
            i, j, undecided = _gate(left, left_covariances, left_join, largest, predicted, lever, right_covariances,
                                    right_join, link, None if first_round else scale, g2, margin, left_sightings,
                                    right_sightings, search)
        else:  # the live joins' rows only; each join's pairs are what they would be among all
            rows, columns = np.flatnonzero(live[left_join]), np.flatnonzero(live[right_join])
            i, j, undecided = _gate(left[rows], left_covariances[rows], left_join[rows], largest, predicted[columns],
                                    lever[columns], right_covariances[columns], right_join[columns], link, scale, g2,
                                    margin, None if left_sightings is None else left_sightings[rows],
                                    None if right_sightings is None else right_sightings[columns])
            i, j, undecided = rows[i], columns[j], columns[undecided]
        ambiguous = np.bincount(right_join[undecided], minlength=joins)
        if tested is not None and all_live and _repeated(tested, i, j, scale):
            # the last round's joint test of the same pairs in the same scale: its outcome, the pairs repeat
            outcome = (previous[0], previous[1], ambiguous, tested[3], undecided, correction)
            break
        if all_live:
            tested = (i, j, np.ones(joins) if first_round else scale, None)
        pair_join = right_join[j]
        r = left[i] - prior_prediction[j]  # the link's correction is estimated afresh from the prior each round
        unscaled = inverted(left_covariances[i] + right_covariances[j])
        w = unscaled if first_round else unscaled / scale[pair_join, None]
        terms = _joint_terms(r, w, lever[j])
        information = prior_information if first_round else prior_information / scale[:, None, None]
        keep, sum_g, sum_m = _joint_test(terms, r, w, lever[j], pair_join, information, gate, joins)
        rejected = np.bincount(pair_join[~keep], minlength=joins)
        if tested is not None:
            tested = (*tested[:3], rejected)
        if not keep.all():  # mostly all are kept: then the pairs and the joint test's sums as they are
            i, j, r, unscaled, pair_join = i[keep], j[keep], r[keep], unscaled[keep], pair_join[keep]
            sum_g = _segment_sums(terms[1][keep], pair_join, joins)
            sum_m = information + _segment_sums(terms[2][keep], pair_join, joins).reshape(joins, 3, 3)
        outcome = (i, j, ambiguous, rejected, undecided, correction)
        if previous is not None and _same(previous[0], i) and _same(previous[1], j):
            break
        previous = outcome
        # each link's correction and posterior covariance from its kept pairs; the robust variance factor
        posterior = np.linalg.inv(sum_m)
        fresh = np.einsum("jab,jb->ja", posterior, sum_g)
        shift = fresh[:, 0] + 1j * fresh[:, 1]
        residual = r - shift[pair_join] - lever[j] * fresh[pair_join, 2]
        dof = 2 * np.bincount(pair_join, minlength=joins) - 3
        factor = _segment_medians(_mahalanobis(residual, unscaled), pair_join, joins) / CHI2_2_MEDIAN
        fresh_scale = np.where(dof >= MIN_DOF, np.maximum(1.0, factor), 1.0)
        fresh_link = posterior * (fresh_scale / scale)[:, None, None]  # the posterior in the new scale's units
        if joins > 1 and round_number < ROUNDS - 1:  # a join whose state repeats would repeat its round: settled
            repeats = live & (fresh_scale == scale) & (fresh == correction).all(axis=1) & (fresh_link == link).all(
                axis=(1, 2))
            if repeats.any():
                settled.append(_settled_outcome(outcome, repeats, right_join))
                live &= ~repeats
                all_live = False
                going = live[pair_join]
                previous = (i[going], j[going])
            fresh = np.where(live[:, None], fresh, correction)  # settled joins keep their state
            fresh_scale = np.where(live, fresh_scale, scale)
            fresh_link = np.where(live[:, None, None], fresh_link, link)
        correction, scale, link = fresh, fresh_scale, fresh_link
        predicted = prior_prediction + (correction[:, 0] + 1j * correction[:, 1])[right_join] \
            + lever * correction[right_join, 2]
    if settled:
        outcome = _with_settled(outcome, settled, right_join)
    order = np.argsort(outcome[1], kind="stable")
    return Matches(outcome[0][order], outcome[1][order], *outcome[2:])


def _repeated(tested: tuple, i: np.ndarray, j: np.ndarray, scale: np.ndarray) -> bool:
    """Whether a round's pairs before the joint test (``i``, ``j``) and its variance factors ``scale`` are the last
    round's (``tested``): then its joint test is the last one's (the innovations are taken from the prior prediction,
    the same for the same pairs), and so are the pairs it keeps."""
    return _same(tested[0], i) and _same(tested[1], j) and _same(tested[2], scale)


def _settled_outcome(outcome: tuple, joins: np.ndarray, right_join: np.ndarray) -> tuple:
    """The part of a round's ``outcome`` (left rows, right rows, ambiguous, rejected, undecided, correction) that
    belongs to the ``joins`` (a mask over them)."""
    i, j, ambiguous, rejected, undecided, _ = outcome
    mine = joins[right_join[j]]
    return i[mine], j[mine], joins, ambiguous, rejected, undecided[joins[right_join[undecided]]]


def _with_settled(outcome: tuple, settled: list[tuple], right_join: np.ndarray) -> tuple:
    """The last round's ``outcome`` of the live joins with the outcomes of the joins settled before it."""
    i, j, ambiguous, rejected, undecided, correction = outcome
    ambiguous, rejected = ambiguous.copy(), rejected.copy()
    for _, _, joins, their_ambiguous, their_rejected, _ in settled:  # a few rounds at most
        ambiguous[joins], rejected[joins] = their_ambiguous[joins], their_rejected[joins]
    return (np.concatenate([i, *(part[0] for part in settled)]), np.concatenate([j, *(part[1] for part in settled)]),
            ambiguous, rejected, np.sort(np.concatenate([undecided, *(part[5] for part in settled)])), correction)


def match_with_drift(left: np.ndarray, left_covariances: np.ndarray, left_join: np.ndarray, link_xy: np.ndarray,
                     link_phi: np.ndarray, link_variances: np.ndarray, right: np.ndarray,
                     right_covariances: np.ndarray, right_join: np.ndarray, drift: tuple[np.ndarray, ...] | None,
                     gate: float = DEFAULT_GATE, margin: float = DEFAULT_MARGIN,
                     left_sightings: np.ndarray | None = None, right_sightings: np.ndarray | None = None,
                     pair_drift: Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray] | None = None,
                     scope: VoterDrift | None = None) -> Matches:
    """:func:`match_features`, less the drifted pairs with a rival within their drift when ``pair_drift(left rows,
    right rows, their noise)`` gives the pairs' drift (:func:`_unstrained`, module docstring, step 7: the
    associator's, through the chain's ties; compared with the noise only, it may stop at it where the way is long)
    and the lone drifted pairs beside a second copy and a rival (:func:`_unconfirmed`, step 8; both only where a
    pair's drift reaches its noise),
    then the loop closures among the features left unpaired (:func:`_closed_loops`, step 6), then those among the
    undrifted features still unpaired that the link's correction moved (``moved=True``):
    ``drift`` = (left ``D``, left heading variance, right ``D``, right heading variance), one per feature
    (:mod:`mapjoin.association.feature_drift`), or None for none; ``scope`` gives a loop closure's pairs their drift
    relative to its voters (:mod:`mapjoin.association.loop_scope`; None: the correction holds for every pair)."""
    left_covariances, right_covariances = blocks(left_covariances), blocks(right_covariances)
    found = match_features(left, left_covariances, left_join, link_xy, link_phi, link_variances, right,
                           right_covariances, right_join, gate, margin, left_sightings, right_sightings)
    if drift is None:
        return found
    if pair_drift is not None:
        noise = _pair_noise(left_covariances, right_covariances, found.left, found.right)
        drifts = pair_drift(found.left, found.right, noise)
        if (drifts >= noise).any():  # else no pair is drifted: steps 7 and 8 drop none
            unstrained = _unstrained(found, left, left_join, link_xy, link_phi, right, right_join, drifts, noise,
                                     left_sightings)
            if unstrained is not found:
                kept = np.isin(found.right, unstrained.right)
                drifts, noise = drifts[kept], noise[kept]
            found = _unconfirmed(unstrained, left, left_join, link_xy, link_phi, right, right_join, drifts, noise,
                                 left_sightings, margin)
    closed = _closed_loops(found, left, left_covariances, left_join, link_xy, link_phi, link_variances, right,
                           right_covariances, right_join, drift, gate, margin, left_sightings, right_sightings, scope)
    found = found if closed is None else closed
    closed = _closed_loops(found, left, left_covariances, left_join, link_xy, link_phi, link_variances, right,
                           right_covariances, right_join, drift, gate, margin, left_sightings, right_sightings, scope,
                           moved=True)
    return found if closed is None else closed


def _unstrained(found: Matches, left: np.ndarray, left_join: np.ndarray, link_xy: np.ndarray, link_phi: np.ndarray,
                right: np.ndarray, right_join: np.ndarray, drift: np.ndarray, noise: np.ndarray,
                left_sightings: np.ndarray | None) -> Matches:
    """``found`` less the pairs :func:`mapjoin.association.strain.drift_rivals` names (``drift``, ``noise``: each
    pair's, :func:`_pair_noise`), whose right features are left new and counted ambiguous (``found`` itself when
    none); the right features are predicted through each join's link as ``found`` corrected it."""
    drop = drift_rivals(left, left_join, found.left, _corrected(found, link_xy, link_phi, right, right_join), noise,
                        drift, left_sightings)
    if not drop.any():
        return found
    undecided = np.union1d(found.undecided, found.right[drop])
    return Matches(found.left[~drop], found.right[~drop], np.bincount(right_join[undecided], minlength=len(link_xy)),
                   found.rejected, undecided, found.correction)


def _pair_noise(left_covariances: np.ndarray, right_covariances: np.ndarray, left_rows: np.ndarray,
                right_rows: np.ndarray) -> np.ndarray:
    """Each pair's isotropic noise without drift (steps 6 and 7): the half trace of its two features' covariances."""
    return (left_covariances[left_rows, 0] + left_covariances[left_rows, 2]
            + right_covariances[right_rows, 0] + right_covariances[right_rows, 2]) / 2


def _unconfirmed(found: Matches, left: np.ndarray, left_join: np.ndarray, link_xy: np.ndarray, link_phi: np.ndarray,
                 right: np.ndarray, right_join: np.ndarray, drift: np.ndarray, noise: np.ndarray,
                 left_sightings: np.ndarray | None = None, margin: float = DEFAULT_MARGIN) -> Matches:
    """``found`` less its lone drifted pairs (:func:`mapjoin.association.lone.lone_drifted`; ``drift``, ``noise``:
    each pair's)
    that have both another left feature of their join within half their drift, seen with the chosen one or not (a
    second copy: :func:`mapjoin.association.strain.drift_rivals` without ``left_sightings``, margin
    :data:`mapjoin.association.lone.LONE_MARGIN`), and a rival seen with it within step 3's ``margin`` (the same
    function with the sightings; step 8); their right features are left new and counted ambiguous."""
    lone = lone_drifted(right_join[found.right], noise, drift, len(link_xy))
    if not lone.any():
        return found
    drop = np.zeros(len(found.left), dtype=bool)
    asked = (left, left_join, found.left[lone], _corrected(found, link_xy, link_phi, right, right_join)[lone],
             noise[lone], drift[lone])
    drop[lone] = drift_rivals(*asked, None, LONE_MARGIN)
    if drop.any():
        drop[lone] &= drift_rivals(*asked, left_sightings, margin)
    if not drop.any():
        return found
    undecided = np.union1d(found.undecided, found.right[drop])
    return Matches(found.left[~drop], found.right[~drop], np.bincount(right_join[undecided], minlength=len(link_xy)),
                   found.rejected, undecided, found.correction)


def _corrected(found: Matches, link_xy: np.ndarray, link_phi: np.ndarray, right: np.ndarray, right_join: np.ndarray
               ) -> np.ndarray:
    """Each of ``found``'s right features predicted through its join's link as ``found`` corrected it."""
    pair_join = right_join[found.right]
    correction = found.correction[pair_join]
    return link_xy[pair_join] + correction[:, 0] + 1j * correction[:, 1] + \
        np.exp(1j * (link_phi[pair_join] + correction[:, 2])) * right[found.right]


def _closed_loops(found: Matches, left: np.ndarray, left_covariances: np.ndarray, left_join: np.ndarray,
                  link_xy: np.ndarray, link_phi: np.ndarray, link_variances: np.ndarray, right: np.ndarray,
                  right_covariances: np.ndarray, right_join: np.ndarray, drift: tuple[np.ndarray, ...], gate: float,
                  margin: float, left_sightings: np.ndarray | None, right_sightings: np.ndarray | None,
                  scope: VoterDrift | None = None, moved: bool = False) -> Matches | None:
    """``found`` with the pairs of the loop closures among the features it left unpaired, or None when there are
    none. Candidate pairs within the drift's gate (the noise, ``D`` of both features and the link's spread)
    whose drift is at least their noise vote for rigid corrections of the link as ``found`` corrected it
    (:func:`mapjoin.association.loop_votes.rigid_votes`; cells: twice the typical noise, and the turn it makes over
    the free right features' extent); a join whose best correction has :data:`LOOP_SUPPORT` right features and
    :data:`LOOP_CLEAR` times the runner-up's agreement is associated again, its unpaired features only, around
    its link so corrected (:func:`match_features`: the gate, the clear nearest neighbour, the joint test, the
    rounds); a pair so found is kept when it is clear under the correction with its drift relative to the voters
    (``scope``: the votes within a cell of the correction) or under the link with its drift
    (:func:`mapjoin.association.loop_scope.beyond_voters`), else counted rejected; a loop closure of fewer than
    :data:`LOOP_SUPPORT` pairs is dropped.

    ``moved``: the same for the *undrifted* pairs (``D`` of both features below their noise) whose prediction the
    correction of steps 2 to 5 moved, with the squared distance it moved them as their spread in place of ``D`` and
    the square of its turn as their heading variance (docs/method.md#data-association, step 6: a correction set by
    drifted pairs is, for the features near the link, a drift of its own)."""
    left_drift, left_heading, right_drift, right_heading = drift
    joins = len(link_xy)
    free = np.ones(len(left), dtype=bool)
    free[found.left] = False
    lefts = free.nonzero()[0]
    free = np.ones(len(right), dtype=bool)
    free[found.right] = False
    rights = free.nonzero()[0]
    if len(lefts) < LOOP_SUPPORT or len(rights) < LOOP_SUPPORT:
        return None
    correction = found.correction
    turn = np.exp(1j * (link_phi + correction[:, 2]))
    corrected_xy = link_xy + correction[:, 0] + 1j * correction[:, 1]
    r_join = right_join[rights]
    predicted = corrected_xy[r_join] + turn[r_join] * right[rights]
    left_noise = (left_covariances[lefts, 0] + left_covariances[lefts, 2]) / 2
    right_noise = (right_covariances[rights, 0] + right_covariances[rights, 2]) / 2
    if moved:  # how far the correction moved each free right feature's prediction: its spread
        reach = np.abs(predicted - link_xy[r_join] - np.exp(1j * link_phi[r_join]) * right[rights]) ** 2
    if not _may_vote(left_noise, left_drift[lefts], right_noise, reach if moved else right_drift[rights], moved):
        return None
    g2 = float(_threshold(gate, 1))
    link_spread = link_variances[r_join, 0] + link_variances[r_join, 1] * np.abs(right[rights]) ** 2  # isotropic
    widest = _join_maxima(left_noise + left_drift[lefts], left_join[lefts], joins)
    # how far each free right feature's spread reaches: its drift, or how far the correction moved its prediction
    reach = reach if moved else right_drift[rights]
    radius = np.sqrt(g2 * (widest[r_join] + right_noise + reach + link_spread))
    a, b = _candidates(left[lefts], left_join[lefts], predicted, r_join, radius, joins)
    offsets = left[lefts[a]] - predicted[b]
    noise = left_noise[a] + right_noise[b]
    spread = left_drift[lefts[a]] + right_drift[rights[b]]
    if moved:  # the undrifted pairs only, spread by the correction's move
        spread = np.where(spread < noise, reach[b], 0.0)
    closeness = np.abs(offsets) ** 2 / (noise + spread + link_spread[b])  # in the drift's gate's units
    voting = (closeness <= g2) & (spread >= noise)
    voter = np.zeros(len(rights), dtype=bool)  # the right features with a candidate in the drift's gate, counted first
    voter[b[voting]] = True
    if not (np.bincount(r_join[voter], minlength=joins) >= LOOP_SUPPORT).any():
        return None
    order = np.flatnonzero(voting)[np.argsort(r_join[b[voting]], kind="stable")]
    a, b, noise, closeness = a[order], b[order], noise[order], closeness[order]
    heading = correction[r_join[b], 2] ** 2 if moved else left_heading[lefts[a]] + right_heading[rights[b]]
    turning = np.sqrt(g2 * (heading + link_variances[r_join[b], 1]))
    pair_join = r_join[b]
    sizes = np.maximum(np.bincount(r_join, minlength=joins), 1)  # the free right features' centroid and extent
    centre = (np.bincount(r_join, predicted.real, joins) + 1j * np.bincount(r_join, predicted.imag, joins)) / sizes
    extent = np.sqrt(np.bincount(r_join, np.abs(predicted - centre[r_join]) ** 2, joins) / sizes)
    typical = np.sqrt(np.nan_to_num(_segment_medians(noise, pair_join, joins)))
    turn_cell = 2 * np.sqrt(2) * typical / np.maximum(extent, 1e-9) + 1e-12
    offset_cell = 2 * typical + turn_cell * extent / 2 + 1e-12
    votes = rigid_votes(left[lefts], predicted, a, b, pair_join, centre, noise, turning, turn_cell, offset_cell,
                        joins, closeness)
    closing = np.flatnonzero((votes.support >= LOOP_SUPPORT) & (votes.agreement >= LOOP_CLEAR * votes.runner_up))
    if not len(closing):
        return None
    number = np.full(joins, -1)
    number[closing] = np.arange(len(closing))

    def under_correction(rows: np.ndarray, join: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        # free right features (positions in ``predicted``) as the votes' correction predicts them, and its variance
        lever = predicted[rows] - centre[join]
        return (centre[join] + votes.offset[join] + np.exp(1j * votes.turn[join]) * lever,
                offset_cell[join] ** 2 + turn_cell[join] ** 2 * np.abs(lever) ** 2)

    if scope is not None:  # the voters: the pairs whose votes made the correction, where it is exact
        voters = (lefts[a[votes.voters]], rights[b[votes.voters]], votes.voter_join)
        place = np.full(len(right), -1)
        place[rights] = np.arange(len(rights))  # each free right row's position in ``predicted``
    lefts, rights = lefts[number[left_join[lefts]] >= 0], rights[number[right_join[rights]] >= 0]
    # the link corrected, moved to the free right features' centroid (their mean z_c in right's frame, at c in
    # left's): there the correction's turn moves them least. Right's features, relative to it, are predicted at
    # c + o + R(phi + dphi) (z - z_c), the votes' correction of the prediction.
    r_join_kept = number[right_join[rights]]
    local_centre = (np.bincount(r_join_kept, right[rights].real, len(closing))
                    + 1j * np.bincount(r_join_kept, right[rights].imag, len(closing))) / np.maximum(
                        np.bincount(r_join_kept, minlength=len(closing)), 1)
    loop_phi = link_phi[closing] + correction[closing, 2] + votes.turn[closing]
    loop_variances = np.column_stack([offset_cell[closing] ** 2, turn_cell[closing] ** 2])
    again = match_features(left[lefts], left_covariances[lefts], number[left_join[lefts]],
                           centre[closing] + votes.offset[closing], loop_phi, loop_variances,
                           right[rights] - local_centre[r_join_kept], right_covariances[rights], r_join_kept,
                           gate, margin, None if left_sightings is None else left_sightings[lefts],
                           None if right_sightings is None else right_sightings[rights])
    closed = number[right_join[rights[again.right]]]
    outside = np.zeros(len(closing), np.int64)
    if scope is not None and len(again.right):
        pair_left, pair_right = lefts[again.left], rights[again.right]
        pair_join_again = right_join[pair_right]
        position, variance = under_correction(place[pair_right], pair_join_again)
        noise = _pair_noise(left_covariances, right_covariances, pair_left, pair_right)
        held = ~beyond_voters(left, left_join, pair_left, left_sightings,
                              (position, noise + variance, scope(pair_left, pair_right, pair_join_again, *voters)),
                              (predicted[place[pair_right]], noise, left_drift[pair_left] + right_drift[pair_right]))
        outside = np.bincount(closed[~held], minlength=len(closing))
        again = Matches(again.left[held], again.right[held], again.ambiguous, again.rejected, again.undecided,
                        again.correction)
        closed = closed[held]
    taken = (np.bincount(closed, minlength=len(closing)) >= LOOP_SUPPORT)[closed]
    if not taken.any():
        return None
    pairs_left = np.concatenate([found.left, lefts[again.left[taken]]])
    pairs_right = np.concatenate([found.right, rights[again.right[taken]]])
    order = np.argsort(pairs_right, kind="stable")
    undecided = np.setdiff1d(np.union1d(found.undecided, rights[again.undecided]), pairs_right)
    rejected = found.rejected.copy()
    rejected[closing] += again.rejected + outside
    return Matches(pairs_left[order], pairs_right[order], np.bincount(right_join[undecided], minlength=joins),
                   rejected, undecided, correction)


def _may_vote(left_noise: np.ndarray, left_drift: np.ndarray, right_noise: np.ndarray, right_spread: np.ndarray,
              moved: bool) -> bool:
    """Whether any (free left, free right) pair could vote in :func:`_closed_loops`, over all pairs at once (O(1)
    calls, whatever the features' joins): a voting pair's spread is at least its noise, ``left_noise + right_noise``.
    The spread is the two features' drift (``right_spread``: the right one's), or, ``moved``, the right feature's move
    (``right_spread``) for a pair whose drift is below its noise; so no pair votes when the largest spread less the
    right noise is below the least left noise (moved), or the largest drift less noise of each side sums below 0.
    The answer is no only when clearly so (by more than a rounding of the noise), so that it never drops a vote."""
    slack = 1e-9 * (left_noise.max() + right_noise.max())
    if moved:
        return bool((right_spread - right_noise).max() + slack >= left_noise.min())
    return bool((left_drift - left_noise).max() + (right_spread - right_noise).max() + slack >= 0.0)


def _joint_test(terms, r: np.ndarray, w: np.ndarray, u: np.ndarray, pair_join: np.ndarray,
                information: np.ndarray, gate: float, joins: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The pairs kept by the joint compatibility test of every join (a mask over the pairs, grouped by join):
    each join's joint distance at once; a join that fails is searched alone by :func:`_jointly_compatible`.
    Also each join's ``sum H^T W r`` (joins x 3) and ``P_link^-1 + sum H^T W H`` (joins x 3 x 3) over all its
    pairs: the link's correction when every pair is kept."""
    c, g, h = terms
    sizes = np.bincount(pair_join, minlength=joins)
    big_g = _segment_sums(g, pair_join, joins)
    big_m = _segment_sums(h, pair_join, joins).reshape(joins, 3, 3) + information
    distance = np.bincount(pair_join, c, minlength=joins) - np.einsum(
        "ji,ji->j", big_g, np.linalg.solve(big_m, big_g[..., None])[..., 0])
    keep = np.ones(len(r), dtype=bool)
    failing = (sizes > 0) & (distance > _threshold(gate, sizes))
    if not failing.any():  # mostly every join's pairs are compatible
        return keep, big_g, big_m
    starts = np.cumsum(sizes) - sizes
    for failed in np.flatnonzero(failing).tolist():
        rows = slice(starts[failed], starts[failed] + sizes[failed])
        keep[rows] = _jointly_compatible((c[rows], g[rows], h[rows]), r[rows], w[rows], u[rows],
                                         information[failed], gate)
    return keep, big_g, big_m


def _asked_once(pair_drift: Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray]
                ) -> Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray]:
    """``pair_drift`` remembering its last pairs and answers: step 7 asks it for a join's pairs, the chain's ties ask
    it again after step 6, which mostly changed few pairs. A pair's answer is its own (its left row, right row and
    noise decide it, elementwise), so only the pairs not asked last time are asked (a tree level's step 6 adds its
    loop closures' and junctions' pairs to thousands)."""
    last: list = []

    def remembered(i: np.ndarray, j: np.ndarray, noise: np.ndarray) -> np.ndarray:
        if last and _same(last[0], i) and _same(last[1], j) and _same(last[3], noise):
            return last[2]
        if not (last and len(last[0])):
            last[:] = [i, j, pair_drift(i, j, noise), noise]
            return last[2]
        before_i, before_j, before, before_noise = last
        span = np.int64(max(int(i.max(initial=0)), int(before_i.max(initial=0))) + 1)
        keys = before_j.astype(np.int64) * span + before_i
        order = np.argsort(keys)
        position, known = locate(keys, j.astype(np.int64) * span + i, order)
        known &= before_noise[position] == noise
        answer = np.empty(len(i))
        answer[known] = before[position[known]]
        fresh = ~known
        if fresh.any():
            answer[fresh] = pair_drift(i[fresh], j[fresh], noise[fresh])
        last[:] = [i, j, answer, noise]
        return answer

    return remembered


class _Associator:
    """The hooks :mod:`mapjoin.joining` calls before each join (``associate=``), numbering features as they are
    matched, and after each sequential join (:meth:`placed`: its posterior, for the drift; the tree's are read
    from the pieces at the next level). Compact ids (indices of the joins' arrays) are handed out in order of
    first sighting; the tree renames a right piece's features to the left piece's ids, so each input row's
    current id is kept. ``points``: each map's feature positions (sorted by id, complex), ``end_poses`` the
    maps' end poses, for :class:`mapjoin.association.feature_drift.SightingDrift`."""

    def __init__(self, covariances: Sequence[np.ndarray], points: Sequence[np.ndarray], end_poses: np.ndarray,
                 gate: float, margin: float = DEFAULT_MARGIN):
        self.gate, self.margin = gate, margin
        self.offsets = np.concatenate([[0], np.cumsum([len(c) for c in covariances])]).astype(np.intp)
        self.row_ids = np.full(self.offsets[-1], -1, dtype=np.int64)  # input rows in _prepare's order
        self.row_covariances = np.concatenate([np.zeros((0, 3)), *covariances])  # in each map's frame
        self.row_maps = np.repeat(np.arange(len(covariances)), np.diff(self.offsets))
        # the chain's drift between sightings and links (each map's rows' positions in its frame: their sightings)
        self.drift = SightingDrift.of(end_poses, len(self.row_ids))
        self.row_points = np.concatenate([np.zeros(0, complex), *points])
        self.links = np.zeros(0, np.intp)  # the tree's last level's junctions (left pieces' end pose rows)
        self.end_points = end_poses[:, 0] + 1j * end_poses[:, 1]  # each map's end position in its frame
        self.own_pose_variances = np.zeros((0, 2))  # each map's end-pose variance in its frame (the tree's first level)
        self.count = 0
        # each compact id's 2 x 2 covariance relative to the maps that saw it (rows [xx, xy, yy]), in its piece's
        # frame: the sightings' marginal covariances fused as independent (their common drift is the link's error)
        self.covariances = np.zeros((max(len(self.row_ids), 1), 3))
        self.row_sightings = sighting_bits(np.repeat(np.arange(len(covariances)), np.diff(self.offsets)))
        self.sightings = np.zeros((len(self.covariances), 2), dtype=np.uint64)  # each compact id's maps (bits)
        self.counts: list[tuple[int, int]] = []  # (ambiguous, rejected) per join, in the report's order

    def _fresh(self, number: int) -> np.ndarray:
        ids = np.arange(self.count, self.count + number)
        self.count += number
        if self.count > len(self.covariances):  # the tree hands out new ids at every level
            more = max(self.count, len(self.covariances))
            self.covariances = np.concatenate([self.covariances, np.zeros((more, 3))])
            self.sightings = np.concatenate([self.sightings, np.zeros((more, 2), dtype=np.uint64)])
        self.drift = self.drift.grown(self.count)
        return ids

    def _sighted(self, ids: np.ndarray, covariances: np.ndarray, sightings: np.ndarray, matched: np.ndarray | slice,
                 new: np.ndarray | slice) -> None:
        """Features ``ids`` seen with ``covariances`` (in their frame) by maps ``sightings``: fused into the
        ``matched`` ones, the ``new`` ones (the others; a mask and its negation, or two slices) new."""
        self.covariances[ids[matched]] = fused(self.covariances[ids[matched]], covariances[matched])
        self.covariances[ids[new]] = covariances[new]
        self.sightings[ids[matched]] |= sightings[matched]
        self.sightings[ids[new]] = sightings[new]

    # sequential strategy -----------------------------------------------------------------
    def first(self, size: int) -> np.ndarray:
        """Compact ids of the first map's rows: all new."""
        ids = self._fresh(size)
        self.row_ids[:size] = ids
        self.covariances[ids] = self.row_covariances[:size]
        self.sightings[ids] = self.row_sightings[:size]
        self.drift.seen(ids, self.row_maps[:size], self.row_points[:size])
        return ids

    def placed(self, k: int, t_variance: float, phi_variance: float) -> None:
        """Join ``k`` placed map ``k``'s start (junction ``k``) with these posterior variances (the drift's sums)."""
        self.drift.placed(k, t_variance, phi_variance)

    def next(self, k: int, positions: np.ndarray, variances: np.ndarray, link_xy: complex, link_phi: float,
             link_variances: tuple[float, float], z: np.ndarray, var: np.ndarray
             ) -> tuple[np.ndarray, np.ndarray, int]:
        """Map ``k`` (rows ``z``, ``var``) against the global map so far (compact ids 0 .. count-1): the order of
        its rows (matched first, then new, each in input order), their compact ids in that order, and how many
        are matched."""
        used = self.count
        rows = slice(self.offsets[k], self.offsets[k + 1])
        right_covariances = rotated(self.row_covariances[rows], link_phi)
        nothing = np.zeros(len(z))  # map k's own features: no drift relative to its start
        drift = (*self.drift.before(slice(None, used), k - 1), nothing, nothing)
        pair_drift = _asked_once(lambda i, j, noise: self.drift.settled(i, k - 1, level=noise, direct=drift[0][i]))

        found = match_with_drift(positions[:used], self.covariances[:used], np.zeros(used, np.intp),
                                 np.array([link_xy]), np.array([link_phi]), np.array([link_variances]), z,
                                 right_covariances, np.zeros(len(z), np.intp), drift, self.gate, self.margin,
                                 self.sightings[:used], self.row_sightings[rows], pair_drift,
                                 voters_drift(self.drift, None, None))
        self.counts.append((int(found.ambiguous[0]), int(found.rejected[0])))
        left_ids = found.left
        strain = self._tie(found, positions[:used], left_ids, np.array([link_xy]), np.array([link_phi]), z,
                           np.zeros(len(z), np.intp), right_covariances, pair_drift, np.array([k]))
        matched = np.zeros(len(z), dtype=bool)
        matched[found.right] = True
        order = np.concatenate([found.right, np.flatnonzero(~matched)])  # found.right is sorted
        ids = np.empty(len(z), dtype=np.int64)
        ids[:len(found.right)] = found.left
        ids[len(found.right):] = self._fresh(len(z) - len(found.right))
        self._sighted(ids, right_covariances[order], self.row_sightings[rows][order], slice(None, len(found.right)),
                      slice(len(found.right), None))
        self.row_ids[self.offsets[k] + order] = ids
        points, matched_count = self.row_points[rows][order], len(found.right)
        self.drift.seen_again(ids[:matched_count], k, points[:matched_count], strain)
        self.drift.seen(ids[matched_count:], k, points[matched_count:])
        return order, ids, len(found.right)

    def _tie(self, found: Matches, left: np.ndarray, left_ids: np.ndarray, link_xy: np.ndarray, link_phi: np.ndarray,
             right: np.ndarray, right_join: np.ndarray, right_covariances: np.ndarray,
             pair_drift: Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray], junctions: np.ndarray
             ) -> np.ndarray:
        """The strain of each of ``found``'s pairs (a quarter of its squared residual around the link as the join's
        pairs corrected it: a fused feature sits about halfway), and the chain's ties: a join whose pairs include
        :data:`TIE_SUPPORT` drifted ones (``pair_drift``: each pair's before the join, at least its noise) measured its
        link, at ``junctions[join]``, relative to the map that last saw their left features (``left_ids``, compact;
        the median), strained by their strains' median (:meth:`mapjoin.association.feature_drift.SightingDrift.tie`)."""
        pair_join = right_join[found.right]
        strain = np.abs(left[found.left] - _corrected(found, link_xy, link_phi, right, right_join)) ** 2 / 4
        noise = _pair_noise(self.covariances, right_covariances, left_ids, found.right)
        drifted = pair_drift(found.left, found.right, noise) >= noise
        for tying in np.flatnonzero(np.bincount(pair_join[drifted], minlength=len(junctions)) >= TIE_SUPPORT).tolist():
            pairs = drifted & (pair_join == tying)
            self.drift.tie(int(_median(self.drift.last_map[left_ids[pairs]])), int(junctions[tying]),
                           float(_median(strain[pairs])))
        return strain

    # tree strategy -----------------------------------------------------------------------
    def level(self, pieces: _Pieces, level: int) -> _Pieces:
        """Before a level of the tree: each right piece's features renamed to the ids of their matches in the left
        piece, the others to new ids (``level`` joins have merged pieces of ``2^(level-1)`` maps)."""
        if self.count == 0:  # the maps' own (compact local) ids are not global: every row new
            ids = self.first(len(pieces.feature_ids))
            self.row_ids[:] = ids
            pieces = dataclasses.replace(pieces, feature_ids=ids)
            self.own_pose_variances = pieces.pose_variances.copy()
        count = pieces.count // 2
        ends = np.searchsorted(pieces.pose_piece, np.arange(pieces.count), side="right") - 1
        link = ends[0:2 * count:2]  # each left piece's end pose
        # the last level's junctions (pose row m: map m's end, pose m + 1) hold their joins' posteriors until moved
        self.drift.placed(self.links + 1, pieces.pose_variances[self.links, 0], pieces.pose_variances[self.links, 1])
        self.links = link
        joined = pieces.feature_piece < 2 * count
        left = np.flatnonzero(joined & (pieces.feature_piece % 2 == 0))
        right = np.flatnonzero(joined & (pieces.feature_piece % 2 == 1))
        right_join = pieces.feature_piece[right] // 2
        right_covariances = rotated(self.covariances[pieces.feature_ids[right]], pieces.pose_phi[link][right_join])
        left_join = pieces.feature_piece[left] // 2
        link_map = pieces.last[0:2 * count:2]  # each join's left piece's last map
        start = pieces.first[0:2 * count:2]  # ... and its first: the ties inside it
        left_ids = pieces.feature_ids[left]
        drift = (*self.drift.before(left_ids, link_map[left_join]),
                 *self.drift.after(pieces.feature_ids[right], link_map[right_join]))
        end = pieces.last[1:2 * count:2]  # each join's right piece's last map
        right_ids = pieces.feature_ids[right]

        @_asked_once
        def pair_drift(i: np.ndarray, j: np.ndarray, noise: np.ndarray) -> np.ndarray:
            # compared with the pairs' noise only: the ties are searched for the pairs whose direct ways reach it
            left_way = (left_ids[i], link_map[left_join[i]], start[left_join[i]])
            right_way = (right_ids[j], link_map[right_join[j]], end[right_join[j]])
            drift = self.drift.settled(*left_way, level=np.inf) + self.drift.settled_after(*right_way, level=np.inf)
            reach = np.flatnonzero(drift >= noise)
            if len(reach):
                drift[reach] = (self.drift.settled(*(part[reach] for part in left_way))
                                + self.drift.settled_after(*(part[reach] for part in right_way)))
            return drift

        found = match_with_drift(pieces.features[left], self.covariances[left_ids], left_join,
                                 pieces.pose_xy[link], pieces.pose_phi[link], pieces.pose_variances[link],
                                 pieces.features[right], right_covariances, right_join, drift, self.gate, self.margin,
                                 self.sightings[left_ids], self.sightings[pieces.feature_ids[right]], pair_drift,
                                 voters_drift(self.drift, left_ids, right_ids))
        if level > 1:  # the junction's own features, under the link's variance relative to its own map (step 2)
            found = self._junction_pairs(found, pieces.features[left], left_ids, left_join, pieces.pose_xy[link],
                                         pieces.pose_phi[link], link_map, pieces.features[right], right_ids,
                                         right_covariances, right_join)
        self.counts += list(zip(found.ambiguous.tolist(), found.rejected.tolist()))
        strain = self._tie(found, pieces.features[left], left_ids[found.left], pieces.pose_xy[link],
                           pieces.pose_phi[link], pieces.features[right], right_join, right_covariances, pair_drift,
                           link_map + 1)
        ids = pieces.feature_ids.copy()
        renamed = self._fresh(len(right))
        renamed[found.right] = ids[left[found.left]]
        ids[right] = renamed
        matched = np.zeros(len(right), dtype=bool)
        matched[found.right] = True
        self._sighted(renamed, right_covariances, self.sightings[pieces.feature_ids[right]], matched, ~matched)
        # a match's last sighting is its right feature's; a new id has its old one's sightings
        self.drift.merged(renamed[matched], pieces.feature_ids[right][matched])
        self.drift.strain[renamed[found.right]] = strain
        self.drift.copied(renamed[~matched], pieces.feature_ids[right][~matched])
        # every input row of a right piece follows its feature's new id
        shift = level - 1
        piece_of_row = np.repeat(np.arange(len(self.offsets) - 1), np.diff(self.offsets)) >> shift
        moved = np.flatnonzero((piece_of_row % 2 == 1) & (piece_of_row // 2 < count))
        span = int(max(self.count, 1))
        keys = pieces.feature_piece.astype(np.int64) * span + pieces.feature_ids
        position, found_all = locate(keys, piece_of_row[moved].astype(np.int64) * span + self.row_ids[moved])
        assert found_all.all()
        self.row_ids[moved] = ids[position]
        return dataclasses.replace(pieces, feature_ids=ids)

    def _junction_pairs(self, found: Matches, left: np.ndarray, left_ids: np.ndarray, left_join: np.ndarray,
                        link_xy: np.ndarray, link_phi: np.ndarray, link_map: np.ndarray, right: np.ndarray,
                        right_ids: np.ndarray, right_covariances: np.ndarray, right_join: np.ndarray) -> Matches:
        """``found`` (a tree level's association) with the pairs of its joins' undrifted features
        (:mod:`mapjoin.association.junction`): steps 2-5 among them under each link's variance relative to its own
        map, a pair kept when ``found`` left both its features unpaired."""
        lefts, rights = undrifted(self.drift.last_map[left_ids], link_map[left_join], self.drift.first_map[right_ids],
                                  link_map[right_join])
        if not len(lefts) or not len(rights):
            return found
        junction = self.drift.sums[link_map + 1] - self.drift.sums[link_map]
        own = own_link_variances(self.own_pose_variances[link_map], junction, self.end_points[link_map])
        near = match_features(left[lefts], self.covariances[left_ids[lefts]], left_join[lefts], link_xy, link_phi,
                              own, right[rights], right_covariances[rights], right_join[rights], self.gate,
                              self.margin, self.sightings[left_ids[lefts]], self.sightings[right_ids[rights]])
        added = free_pairs(found.left, found.right, lefts[near.left], rights[near.right])
        if not added.any():
            return found
        pairs_left = np.concatenate([found.left, lefts[near.left[added]]])
        pairs_right = np.concatenate([found.right, rights[near.right[added]]])
        order = np.argsort(pairs_right, kind="stable")
        undecided = np.setdiff1d(found.undecided, pairs_right)
        return Matches(pairs_left[order], pairs_right[order], np.bincount(right_join[undecided], minlength=len(link_xy)),
                       found.rejected, undecided, found.correction)

    def global_ids(self) -> tuple[np.ndarray, np.ndarray]:
        """Global ids numbered by first sighting: for each compact id (-1 if unused) and for each input row."""
        final = self.row_ids
        unique, first = np.unique(final, return_index=True)
        numbering = np.full(self.count, -1, dtype=np.int64)
        numbering[unique[np.argsort(first)]] = np.arange(len(unique))
        return numbering, numbering[final]


def join_associated(maps: Sequence[LocalMap], covariance: CovarianceMode = DEFAULT_COVARIANCE,
                    solver: Solver = "bisection", strategy: Strategy = "sequential", *,
                    gate: float = DEFAULT_GATE, progress: Callable[[int], None] | None = None,
                    margin: float = DEFAULT_MARGIN) -> AssociatedJoin:
    """Join ``maps`` whose feature ids are local to each map, associating their features before each join
    (see the module docstring; ``gate`` is the chi-square level of the gate and of the joint test, ``margin``
    how much farther a rival candidate must be). The tree runs in one process."""
    _check_gate(gate)
    if not margin >= 0.0:
        raise ValueError(f"margin must be a squared distance >= 0, got {margin!r}")
    points = [as_complex(m.features[np.argsort(m.feature_ids, kind="stable")]) for m in maps]
    associator = _Associator([feature_covariances(m) for m in maps], points,
                             np.array([m.end_pose for m in maps]).reshape(-1, 3), gate, margin)
    # one map is no join: numbered as the sequential strategy's first map (the tree's hook runs per level)
    result = join(maps, covariance, solver, strategy if len(maps) > 1 else "sequential", 1, progress,
                  associate=associator)
    numbering, row_global = associator.global_ids()
    global_map = result.global_map
    if global_map.provenance.strategy != strategy:
        global_map = dataclasses.replace(global_map, provenance=dataclasses.replace(global_map.provenance,
                                                                                    strategy=strategy))
    relabelled = numbering[global_map.feature_ids]
    order = np.argsort(relabelled, kind="stable")
    global_map = dataclasses.replace(global_map, feature_ids=relabelled[order], features=global_map.features[order],
                                     feature_variances=global_map.feature_variances[order])
    report = tuple(AssociatedJoinRecord(**vars(record), ambiguous=ambiguous, rejected=rejected)
                   for record, (ambiguous, rejected) in zip(result.report, associator.counts))
    offsets = associator.offsets.tolist()
    per_map = []
    for k, local_map in enumerate(maps):  # rows in _prepare's order: each map's ids sorted
        order_ids = np.argsort(local_map.feature_ids, kind="stable")
        ids = np.empty(local_map.size, dtype=np.int64)
        ids[order_ids] = row_global[offsets[k]:offsets[k + 1]]
        per_map.append(ids)
    return AssociatedJoin(global_map, report, tuple(per_map))


def local_ids(maps: Sequence[LocalMap]) -> tuple[tuple[LocalMap, ...], tuple[np.ndarray, ...]]:
    """``maps`` with each map's feature ids replaced by ids local to it (0 .. m-1, in the order of the global
    ids), and the truth: ``truth[k][local_id]`` is the global id of map k's feature ``local_id``."""
    relabelled, truth = [], []
    for local_map in maps:
        order = np.argsort(local_map.feature_ids, kind="stable")
        ranks = np.empty(local_map.size, dtype=np.int64)
        ranks[order] = np.arange(local_map.size)
        relabelled.append(dataclasses.replace(local_map, feature_ids=ranks))
        truth.append(local_map.feature_ids[order].copy())
    return tuple(relabelled), tuple(truth)


def correspondence_rows(truth: Sequence[np.ndarray]) -> list[FeatureAssociation]:
    """:func:`local_ids`' truth as the rows ``join --associations`` writes (map 1-based, by local id)."""
    return [FeatureAssociation(k + 1, local, int(found)) for k, ids in enumerate(truth)
            for local, found in enumerate(ids.tolist())]


def link_errors(local: Sequence[LocalMap], truth: Sequence[np.ndarray], found: AssociatedJoin) -> tuple[int, int, int]:
    """How an association compares with the true one: (true links, links missed, false links).

    A link is a feature seen again by a later map. ``truth[k]`` are map k's true global ids in the
    order of its sorted local ids (as :func:`local_ids` returns them); ``found`` the association's
    global ids. Both partition the input features: a true feature split over several found ones
    counts the extra parts as missed links, a found feature joining several true ones counts the
    extra ones as false links."""
    true = np.concatenate(truth)
    mine = np.concatenate([found.global_ids[k][np.argsort(m.feature_ids)] for k, m in enumerate(local)])
    pairs = set(zip(mine.tolist(), true.tolist()))
    per_found = collections.Counter(f for f, _ in pairs)
    per_true = collections.Counter(t for _, t in pairs)
    return (len(true) - len(set(true.tolist())), sum(c - 1 for c in per_true.values()),
            sum(c - 1 for c in per_found.values()))
