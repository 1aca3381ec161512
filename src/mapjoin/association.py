"""Data association: which features of an incoming map are features of the map it is joined onto.

Maps whose feature ids are local to each map (a front end's submaps) cannot be joined by id.
:func:`join_associated` joins them as :func:`mapjoin.joining.join` does, deciding before each
join (sequential and tree) which features of the right piece are features of the left one
(docs/method.md#data-association):

1. **Prediction.** Right's features ``z`` are predicted in left's frame through left's end pose
   ``(o, phi_o)``, the join's link: ``x = o + R(phi_o) z``. An error ``(dt, dphi)`` of the link
   moves the prediction by ``dt + R'(phi_o) z dphi``; with the spherical variances of the link
   ``(var_t, p_phi)``, of left's feature ``var0`` and of right's ``var1``, a pair's innovation
   ``r = f - x`` has covariance ``S = a I + p_phi u u^T`` with ``a = var0 + var1 + var_t`` and
   ``u = R'(phi_o) z`` (the heading error's lever is perpendicular to ``z``, so ``S`` is not
   spherical).
2. **Gate.** A pair is a candidate when its Mahalanobis distance ``r^T S^-1 r`` is within the
   ``gate`` quantile of a chi-square with 2 degrees of freedom (default 0.999: a true pair is
   refused once in a thousand).
3. **Ambiguity, nearest neighbour.** A right feature with two or more candidates, or whose
   candidate is also another right feature's candidate, is *ambiguous* and left new: never guessed.
   Every other gated right feature has one candidate, its nearest neighbour.
4. **Joint compatibility.** The pairs share the link's error, so they are tested together: the
   joint Mahalanobis distance of all their innovations (covariance ``diag(a_j) + H P_link H^T``,
   ``H_j = [I, u_j]``, evaluated in 3-D by the Woodbury identity) must be within the ``gate``
   quantile of a chi-square with ``2k`` degrees of freedom. When it is not, the largest jointly
   compatible subset is kept: by exhaustive search over every subset at once (as arrays) when at
   most :data:`EXHAUSTIVE_PAIRS` pairs remain (the optimum branch and bound would find), after
   removing, one at a time, the pair with the largest residual once the link is corrected
   while more remain. Pairs removed are *rejected* and their right features left new.
5. **Second pass.** Gate, ambiguity and joint test once more around the prediction corrected by the
   link error the pairs explain, with its posterior covariance, the variances scaled by the first
   pass's a-posteriori variance factor (when it is above 1).

The accepted pairs are the join's common features; every other right feature becomes a new
feature of the global map. The global ids are numbered from 0 in order of first sighting:
by map, then by local id.

Cost: :func:`match_features` associates all the joins of a tree level at once (as the tree joins
them), and the sequential join is a batch of one; candidates are all pairs of a join up to
:data:`BRUTE_FORCE_PAIRS`, else found with a k-d tree. Only a join whose pairs fail the joint test
is searched on its own.

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

from .covariance import DEFAULT_COVARIANCE, CovarianceMode
from .joining import JoinRecord, Strategy, join
from .maps import GlobalMap, LocalMap, locate

if TYPE_CHECKING:
    from .joining import _Pieces
    from .onestep import Solver

__all__ = ["DEFAULT_GATE", "link_errors", "EXHAUSTIVE_PAIRS", "AssociatedJoinRecord", "AssociatedJoin", "FeatureAssociation",
           "Matches", "chi2_quantile", "correspondence_rows", "join_associated", "local_ids", "match_features"]

#: default chi-square level of the individual gate and of the joint compatibility test
DEFAULT_GATE = 0.999
#: the joint test searches every subset of at most this many pairs (2^10 = 1024 subsets, as arrays)
EXHAUSTIVE_PAIRS = 10
#: candidate pairs are found by brute force up to this many (left x right) pairs, else by a k-d tree
BRUTE_FORCE_PAIRS = 1 << 16
#: the variance factor of the second pass needs at least this many degrees of freedom (2k - 3 for k pairs)
MIN_DOF = 4


@dataclass(frozen=True)
class Matches:
    """The association of one or more joins: ``left[i]`` and ``right[i]`` are rows of the same feature (sorted
    by right row); per join, ``ambiguous`` right features had two candidates (or shared theirs) and
    ``rejected`` ones failed the joint test."""

    left: np.ndarray
    right: np.ndarray
    ambiguous: np.ndarray
    rejected: np.ndarray


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


def chi2_quantile(level: float, dof: np.ndarray | int) -> np.ndarray:
    """The ``level`` quantile of a chi-square with an even number ``dof = 2k`` of degrees of freedom.

    For even ``dof`` the survival function is closed-form, ``Q(x) = exp(-x/2) sum_{i<k} (x/2)^i / i!`` (a
    Poisson tail), with derivative ``-exp(-x/2) (x/2)^(k-1) / (2 (k-1)!)``; Newton's method on it from the
    Wilson-Hilferty approximation converges in a few steps (as arrays, without scipy). For 2 dof the
    quantile is ``-2 ln(1 - level)``.
    """
    from statistics import NormalDist

    k = np.atleast_1d(np.asarray(dof, dtype=np.int64)) // 2
    n = 2.0 * k
    x = n * (1 - 2 / (9 * n) + NormalDist().inv_cdf(level) * np.sqrt(2 / (9 * n))) ** 3
    terms = np.arange(int(k.max(initial=1)))
    log_factorial = np.concatenate([[0.0], np.cumsum(np.log(np.arange(1, len(terms))))])
    outside = terms[None, :] >= k[:, None]
    for _ in range(12):
        x = np.maximum(x, 1e-3 * n)  # Newton from above converges monotonically; keep it positive
        half = x[:, None] / 2
        log_terms = np.where(outside, -np.inf, terms * np.log(half) - log_factorial - half)
        survival = np.exp(log_terms).sum(axis=1)
        density = np.exp((k - 1) * np.log(x / 2) - log_factorial[k - 1] - x / 2) / 2
        x = x + (survival - (1.0 - level)) / density
    return x if np.ndim(dof) else x[0]


_QUANTILES: dict[float, np.ndarray] = {}  # level -> chi2_quantile(level, 2k) for k = 0, 1, 2, ...


def _threshold(level: float, pairs: np.ndarray | int) -> np.ndarray:
    """``chi2_quantile(level, 2 * pairs)`` from a table grown by doubling (the joint test asks it per join)."""
    table = _QUANTILES.get(level, np.zeros(1))
    largest = int(np.max(pairs, initial=0))
    if largest >= len(table):
        table = np.concatenate([[0.0], chi2_quantile(level, 2 * np.arange(1, max(2 * len(table), largest + 1)))])
        _QUANTILES[level] = table
    return table[pairs]


def _check_gate(gate: float) -> None:
    if not 0.0 < gate < 1.0:
        raise ValueError(f"gate must be a chi-square level in (0, 1), got {gate!r}")


def _segments(group: np.ndarray, count: int) -> tuple[np.ndarray, np.ndarray]:
    """Rows grouped by ``group`` (non-decreasing, values < ``count``): each group's first row and size."""
    sizes = np.bincount(group, minlength=count)
    return np.cumsum(sizes) - sizes, sizes


def _candidates(left: np.ndarray, left_join: np.ndarray, predicted: np.ndarray, right_join: np.ndarray,
                radius: np.ndarray, joins: int) -> tuple[np.ndarray, np.ndarray]:
    """Pairs (left row, right row) of the same join whose Euclidean distance is at most ``radius[right]``
    (complex points; rows grouped by join): every pair of a join at once when there are few in all, else
    from a k-d tree (scipy.spatial, imported then) of the points lifted to 3-D, the join as the third
    coordinate, far apart, so that one tree serves every join."""
    if joins == 1 and len(left) * len(predicted) <= BRUTE_FORCE_PAIRS:  # one join: the outer difference
        return np.nonzero(np.abs(left[:, None] - predicted[None, :]) <= radius[None, :])
    left_start, left_size = _segments(left_join, joins)
    right_start, right_size = _segments(right_join, joins)
    per_join = left_size * right_size
    total = int(per_join.sum())
    if total <= BRUTE_FORCE_PAIRS:
        join = np.repeat(np.arange(joins), per_join)
        q = np.arange(total) - np.repeat(np.cumsum(per_join) - per_join, per_join)
        i = left_start[join] + q // right_size[join]
        j = right_start[join] + q % right_size[join]
        near = np.abs(left[i] - predicted[j]) <= radius[j]
        return i[near], j[near]
    from scipy.spatial import cKDTree

    apart = 2.0 ** math.ceil(math.log2(4 * float(radius.max(initial=1.0)) + 1))
    tree = cKDTree(np.column_stack([left.real, left.imag, left_join * apart]))
    found = tree.query_ball_point(np.column_stack([predicted.real, predicted.imag, right_join * apart]), radius)
    counts = np.fromiter(map(len, found), np.intp, len(predicted))
    i = np.concatenate(found).astype(np.intp) if counts.sum() else np.zeros(0, np.intp)
    return i, np.repeat(np.arange(len(predicted)), counts)


def _joint_terms(r: np.ndarray, a: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each pair's share of the joint test: ``|r|^2 / a``, ``H^T r / a`` (k x 3) and ``H^T H / a`` (k x 9),
    ``H = [I, u]`` (complex ``r``, ``u``)."""
    weight = 1.0 / a
    ux, uy = u.real * weight, u.imag * weight
    g = np.stack([r.real * weight, r.imag * weight, (np.conj(u) * r).real * weight], axis=1)
    zero = np.zeros_like(weight)
    h = np.stack([weight, zero, ux, zero, weight, uy, ux, uy, ux * u.real + uy * u.imag], axis=1)
    return (r.real**2 + r.imag**2) * weight, g, h


def _joint_distances(masks: np.ndarray, terms, link_information: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The joint Mahalanobis distance of each subset of pairs (``masks``, s x k, 0/1) and the link correction
    that explains it best: ``D^2 = sum |r|^2/a - g^T M^-1 g`` with ``M = P_link^-1 + sum H^T H / a``
    (Woodbury: the pairs' covariance ``diag(a) + H P_link H^T`` inverted through the 3-D link)."""
    c, g, h = terms
    big_g = masks @ g
    big_m = (masks @ h).reshape(-1, 3, 3) + link_information
    correction = np.linalg.solve(big_m, big_g[..., None])[..., 0]
    return masks @ c - np.einsum("si,si->s", big_g, correction), correction


def _jointly_compatible(terms, r: np.ndarray, a: np.ndarray, u: np.ndarray, link_information: np.ndarray,
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
        ux, uy = u.real, u.imag
        dx, dy, dphi = correction[0]
        residual = np.abs(r - (dx + 1j * dy) - (ux + 1j * uy) * dphi) ** 2 / a
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


def _segment_sums(values: np.ndarray, group: np.ndarray, count: int) -> np.ndarray:
    """Sums of the rows of ``values`` (p x c) by ``group`` (count x c)."""
    if count == 1:
        return values.sum(axis=0)[None]
    return np.stack([np.bincount(group, values[:, column], minlength=count) for column in range(values.shape[1])],
                    axis=1)


def _gate(left: np.ndarray, left_variances: np.ndarray, left_join: np.ndarray, predicted: np.ndarray,
          lever: np.ndarray, right_variances: np.ndarray, right_join: np.ndarray, link: np.ndarray, g2: float
          ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The unambiguous candidate pairs (left rows, right rows) of every join, and each join's number of
    ambiguous right features.

    A pair's innovation ``r = f - x`` has covariance ``S = (var0 + var1) I + H link H^T`` with ``H = [I, u]``
    (``link[join]``: the 3 x 3 covariance of the join's link error); it is a candidate when ``r^T S^-1 r <= g2``.
    """
    joins = len(link)
    ux, uy = lever.real, lever.imag
    own = link[right_join]
    # H link H^T = link_tt + u link_phi,t + link_t,phi u^T + link_phiphi u u^T, per right feature
    sxx = own[:, 0, 0] + 2 * ux * own[:, 0, 2] + own[:, 2, 2] * ux * ux
    syy = own[:, 1, 1] + 2 * uy * own[:, 1, 2] + own[:, 2, 2] * uy * uy
    sxy = own[:, 0, 1] + ux * own[:, 1, 2] + uy * own[:, 0, 2] + own[:, 2, 2] * ux * uy
    largest = np.zeros(joins)
    np.maximum.at(largest, left_join, left_variances)
    radius = np.sqrt(g2 * (2 * largest[right_join] + 2 * right_variances + sxx + syy))  # >= the largest eigenvalue's
    i, j = _candidates(left, left_join, predicted, right_join, radius, joins)
    r = left[i] - predicted[j]
    base = left_variances[i] + right_variances[j]
    a, b, c = base + sxx[j], sxy[j], base + syy[j]
    d2 = (c * r.real**2 - 2 * b * r.real * r.imag + a * r.imag**2) / (a * c - b * b)
    gated = d2 <= g2
    i, j = i[gated], j[gated]
    per_right = np.bincount(j, minlength=len(predicted))
    per_left = np.bincount(i, minlength=len(left))
    single = (per_right[j] == 1) & (per_left[i] == 1)
    ambiguous = (np.bincount(right_join[per_right > 0], minlength=joins)
                 - np.bincount(right_join[j[single]], minlength=joins))
    return i[single], j[single], ambiguous


def match_features(left: np.ndarray, left_variances: np.ndarray, left_join: np.ndarray, link_xy: np.ndarray,
                   link_phi: np.ndarray, link_variances: np.ndarray, right: np.ndarray,
                   right_variances: np.ndarray, right_join: np.ndarray, gate: float = DEFAULT_GATE) -> Matches:
    """Associate right's features with left's in several independent joins at once (complex points, spherical
    variances, rows grouped by join; see the module docstring): predict through each join's link
    ``(link_xy, link_phi)`` with variances ``link_variances`` (joins x 2: var_t, p_phi), gate, leave ambiguous
    features new, test the rest jointly; then once more with each link corrected by the pairs found (its
    posterior covariance in the gate), which finds the pairs the link's error had hidden.

    Every step is array operations over all joins; only a join whose pairs fail the joint test is searched
    on its own (:func:`_jointly_compatible`).
    """
    _check_gate(gate)
    joins = len(link_xy)
    turn = np.exp(1j * link_phi)
    predicted = link_xy[right_join] + turn[right_join] * right
    lever = 1j * turn[right_join] * right  # R'(phi_o) z
    var_t, p_phi = link_variances[:, 0], link_variances[:, 1]
    prior_information = np.zeros((joins, 3, 3))
    prior_information[:, 0, 0] = prior_information[:, 1, 1] = 1.0 / var_t
    prior_information[:, 2, 2] = 1.0 / p_phi
    link = np.zeros((joins, 3, 3))
    link[:, 0, 0] = link[:, 1, 1] = var_t
    link[:, 2, 2] = p_phi
    g2 = float(_threshold(gate, 1))
    scale = np.ones(joins)
    done = np.zeros(joins, dtype=bool)  # joins whose first pass found no pair keep its outcome
    outcome = None
    for _ in range(2):
        i, j, ambiguous = _gate(left, scale[left_join] * left_variances, left_join, predicted, lever,
                                scale[right_join] * right_variances, right_join, link, g2)
        pair_join = right_join[j]
        r = left[i] - (link_xy[pair_join] + turn[pair_join] * right[j])
        a = scale[pair_join] * (left_variances[i] + right_variances[j])
        terms = _joint_terms(r, a, lever[j])
        information = prior_information / scale[:, None, None]
        keep = _joint_test(terms, r, a, lever[j], pair_join, information, gate, joins)
        rejected = np.bincount(pair_join[~keep], minlength=joins)
        if outcome is None:
            outcome = (i[keep], j[keep], ambiguous, rejected)
        else:
            kept = keep & ~done[pair_join]
            old_i, old_j, old_ambiguous, old_rejected = outcome
            stay = done[right_join[old_j]]
            outcome = (np.concatenate([old_i[stay], i[kept]]), np.concatenate([old_j[stay], j[kept]]),
                       np.where(done, old_ambiguous, ambiguous), np.where(done, old_rejected, rejected))
            break
        done = np.bincount(pair_join[keep], minlength=joins) == 0
        # each link's correction and posterior covariance from its kept pairs; the a-posteriori variance factor
        c, g, h = (term[keep] for term in terms)
        kept_join = pair_join[keep]
        posterior = np.linalg.inv(information + _segment_sums(h, kept_join, joins).reshape(joins, 3, 3))
        correction = np.einsum("jab,jb->ja", posterior, _segment_sums(g, kept_join, joins))
        shift = correction[:, 0] + 1j * correction[:, 1]
        residual = r[keep] - shift[kept_join] - lever[j[keep]] * correction[kept_join, 2]
        dof = 2 * np.bincount(kept_join, minlength=joins) - 3
        factor = np.bincount(kept_join, np.abs(residual) ** 2 / a[keep], minlength=joins) / np.maximum(dof, 1)
        scale = np.where(dof >= MIN_DOF, np.maximum(1.0, factor), scale)
        link = posterior  # a join without pairs: its prior, uncorrected
        predicted = predicted + shift[right_join] + lever * correction[right_join, 2]
    order = np.argsort(outcome[1], kind="stable")
    return Matches(outcome[0][order], outcome[1][order], outcome[2], outcome[3])


def _joint_test(terms, r: np.ndarray, a: np.ndarray, u: np.ndarray, pair_join: np.ndarray,
                information: np.ndarray, gate: float, joins: int) -> np.ndarray:
    """The pairs kept by the joint compatibility test of every join (a mask over the pairs, grouped by join):
    each join's joint distance at once; a join that fails is searched alone by :func:`_jointly_compatible`."""
    c, g, h = terms
    sizes = np.bincount(pair_join, minlength=joins)
    big_g = _segment_sums(g, pair_join, joins)
    big_m = _segment_sums(h, pair_join, joins).reshape(joins, 3, 3) + information
    distance = np.bincount(pair_join, c, minlength=joins) - np.einsum(
        "ji,ji->j", big_g, np.linalg.solve(big_m, big_g[..., None])[..., 0])
    keep = np.ones(len(r), dtype=bool)
    starts = np.cumsum(sizes) - sizes
    for join in np.flatnonzero((sizes > 0) & (distance > _threshold(gate, sizes))).tolist():
        rows = slice(starts[join], starts[join] + sizes[join])
        keep[rows] = _jointly_compatible((c[rows], g[rows], h[rows]), r[rows], a[rows], u[rows],
                                         information[join], gate)
    return keep


class _Associator:
    """The hooks :mod:`mapjoin.joining` calls before each join (``associate=``), numbering features as they are
    matched. Compact ids (indices of the joins' arrays) are handed out in order of first sighting; the
    tree renames a right piece's features to the left piece's ids, so each input row's current id is kept."""

    def __init__(self, sizes: Sequence[int], gate: float):
        self.gate = gate
        self.offsets = np.concatenate([[0], np.cumsum(sizes)]).astype(np.intp)
        self.row_ids = np.full(self.offsets[-1], -1, dtype=np.int64)  # input rows in _prepare's order
        self.count = 0
        self.counts: list[tuple[int, int]] = []  # (ambiguous, rejected) per join, in the report's order

    def _fresh(self, number: int) -> np.ndarray:
        ids = np.arange(self.count, self.count + number)
        self.count += number
        return ids

    # sequential strategy -----------------------------------------------------------------
    def first(self, size: int) -> np.ndarray:
        """Compact ids of the first map's rows: all new."""
        ids = self._fresh(size)
        self.row_ids[:size] = ids
        return ids

    def next(self, k: int, positions: np.ndarray, variances: np.ndarray, link_xy: complex, link_phi: float,
             link_variances: tuple[float, float], z: np.ndarray, var: np.ndarray
             ) -> tuple[np.ndarray, np.ndarray, int]:
        """Map ``k`` (rows ``z``, ``var``) against the global map so far (compact ids 0 .. count-1): the order of
        its rows (matched first, then new, each in input order), their compact ids in that order, and how many
        are matched."""
        used = self.count
        found = match_features(positions[:used], variances[:used], np.zeros(used, np.intp), np.array([link_xy]),
                               np.array([link_phi]), np.array([link_variances]), z, var,
                               np.zeros(len(z), np.intp), self.gate)
        self.counts.append((int(found.ambiguous[0]), int(found.rejected[0])))
        matched = np.zeros(len(z), dtype=bool)
        matched[found.right] = True
        order = np.concatenate([found.right, np.flatnonzero(~matched)])  # found.right is sorted
        ids = np.empty(len(z), dtype=np.int64)
        ids[:len(found.right)] = found.left
        ids[len(found.right):] = self._fresh(len(z) - len(found.right))
        self.row_ids[self.offsets[k] + order] = ids
        return order, ids, len(found.right)

    # tree strategy -----------------------------------------------------------------------
    def level(self, pieces: _Pieces, level: int) -> _Pieces:
        """Before a level of the tree: each right piece's features renamed to the ids of their matches in the left
        piece, the others to new ids (``level`` joins have merged pieces of ``2^(level-1)`` maps)."""
        if self.count == 0:  # the maps' own (compact local) ids are not global: every row new
            ids = self.first(len(pieces.feature_ids))
            self.row_ids[:] = ids
            pieces = dataclasses.replace(pieces, feature_ids=ids)
        count = pieces.count // 2
        ends = np.searchsorted(pieces.pose_piece, np.arange(pieces.count), side="right") - 1
        link = ends[0:2 * count:2]  # each left piece's end pose
        joined = pieces.feature_piece < 2 * count
        left = np.flatnonzero(joined & (pieces.feature_piece % 2 == 0))
        right = np.flatnonzero(joined & (pieces.feature_piece % 2 == 1))
        found = match_features(pieces.features[left], pieces.feature_variances[left], pieces.feature_piece[left] // 2,
                               pieces.pose_xy[link], pieces.pose_phi[link], pieces.pose_variances[link],
                               pieces.features[right], pieces.feature_variances[right],
                               pieces.feature_piece[right] // 2, self.gate)
        self.counts += list(zip(found.ambiguous.tolist(), found.rejected.tolist()))
        ids = pieces.feature_ids.copy()
        renamed = self._fresh(len(right))
        renamed[found.right] = ids[left[found.left]]
        ids[right] = renamed
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

    def global_ids(self) -> tuple[np.ndarray, np.ndarray]:
        """Global ids numbered by first sighting: for each compact id (-1 if unused) and for each input row."""
        final = self.row_ids
        unique, first = np.unique(final, return_index=True)
        numbering = np.full(self.count, -1, dtype=np.int64)
        numbering[unique[np.argsort(first)]] = np.arange(len(unique))
        return numbering, numbering[final]


def join_associated(maps: Sequence[LocalMap], covariance: CovarianceMode = DEFAULT_COVARIANCE,
                    solver: Solver = "bisection", strategy: Strategy = "sequential", *,
                    gate: float = DEFAULT_GATE, progress: Callable[[int], None] | None = None) -> AssociatedJoin:
    """Join ``maps`` whose feature ids are local to each map, associating their features before each join
    (see the module docstring; ``gate`` is the chi-square level of the gate and of the joint test). The
    tree runs in one process."""
    _check_gate(gate)
    associator = _Associator([m.size for m in maps], gate)
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
    report = tuple(AssociatedJoinRecord(**{f.name: getattr(record, f.name) for f in dataclasses.fields(record)},
                                        ambiguous=ambiguous, rejected=rejected)
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
