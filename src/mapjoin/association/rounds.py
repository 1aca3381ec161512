"""Steps 2 to 5 of data association, for one join or a tree level's joins at once: the rounds of link correction
(docs/method.md#data-association).

:func:`match_features` gates and takes the clear nearest neighbours (:mod:`mapjoin.association.gate`), tests them
jointly (:mod:`mapjoin.association.joint`), and corrects each link by its pairs: its correction, its posterior
covariance and the robust variance factor of the pairs' residuals. The association runs again around the corrected
prediction until the pairs repeat (at most :data:`ROUNDS` rounds), which removes the link's error and finds the pairs
it had hidden (as ICP does); a join whose state repeats is settled and leaves the others' rounds. Its result,
:class:`Matches`, is what the later steps take and give.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from .covariance_blocks import _mahalanobis, blocks, inverted
from .gate import DEFAULT_GATE, DEFAULT_MARGIN, _check_gate, _gate, _Searched, _threshold
from .joint import _joint_terms, _joint_test, _segment_sums
from .link_frame import LinkFrame

__all__ = ["ROUNDS", "Matches", "match_features"]

#: the variance factor of a round needs at least this many degrees of freedom (2k - 3 for k pairs)
MIN_DOF = 4
#: at most this many rounds of associate, correct the link, re-predict (they stop when the pairs repeat)
ROUNDS = 4
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

    def with_pairs(self, left: np.ndarray, right: np.ndarray, right_join: np.ndarray) -> Matches:
        """These matches with the pairs ``(left, right)`` of features they left free added (a later rule's pairs):
        sorted by right row again, their right features no longer undecided nor counted ambiguous (``right_join``:
        each right row's join)."""
        pairs_left, pairs_right = np.concatenate([self.left, left]), np.concatenate([self.right, right])
        order = np.argsort(pairs_right, kind="stable")
        undecided = np.setdiff1d(self.undecided, pairs_right)
        return Matches(pairs_left[order], pairs_right[order], np.bincount(right_join[undecided],
                                                                          minlength=len(self.ambiguous)),
                       self.rejected, undecided, self.correction)


def _same(first: np.ndarray, second: np.ndarray) -> bool:
    """``np.array_equal`` of two 1-D arrays, without its wrapper's cost (a round compares its pairs two or three
    times)."""
    return len(first) == len(second) and bool((first == second).all())


def _segments(group: np.ndarray, count: int) -> tuple[np.ndarray, np.ndarray]:
    """Rows grouped by ``group`` (non-decreasing, values < ``count``): each group's first row and size."""
    sizes = np.bincount(group, minlength=count)
    return np.cumsum(sizes) - sizes, sizes


def _join_maxima(values: np.ndarray, join: np.ndarray, joins: int) -> np.ndarray:
    """The largest of ``values`` (non-negative) in each of ``joins`` joins (0 for a join without any)."""
    if joins == 1:  # the sequential join: no scatter
        return values.max(initial=0.0)[None]
    largest = np.zeros(joins)
    np.maximum.at(largest, join, values)
    return largest


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


def match_features(left: np.ndarray, left_covariances: np.ndarray, left_join: np.ndarray, link_xy: np.ndarray,
                   link_phi: np.ndarray, link_variances: np.ndarray, right: np.ndarray,
                   right_covariances: np.ndarray, right_join: np.ndarray, gate: float = DEFAULT_GATE,
                   margin: float = DEFAULT_MARGIN, left_sightings: np.ndarray | None = None,
                   right_sightings: np.ndarray | None = None, link_frame: LinkFrame | None = None) -> Matches:
    """Associate right's features with left's in several independent joins at once (complex points; their
    covariances as rows ``[xx, xy, yy]`` in left's frame, or spherical variances; rows grouped by join; see
    :mod:`mapjoin.association`): predict through each join's link ``(link_xy, link_phi)`` with variances
    ``link_variances`` (joins x 2: var_t, p_phi), gate, take the clear nearest neighbours, test them jointly;
    then correct each link by its pairs, re-predict with the link's posterior covariance and the robust
    variance factor of the pairs' residuals, and associate again, until the pairs repeat (at most
    :data:`ROUNDS` rounds). ``link_frame`` (None: none) holds the left features the link's own map saw, relative
    to its end: they are compared in the link's frame, give the link no correction and move with it
    (:mod:`mapjoin.association.link_frame`).

    Every step is array operations over all joins; only a join whose pairs fail the joint test is searched
    on its own (:func:`mapjoin.association.joint._jointly_compatible`).
    """
    _check_gate(gate)
    left_covariances, right_covariances = blocks(left_covariances), blocks(right_covariances)
    joins = len(link_xy)
    turn = np.exp(1j * link_phi)
    prior_prediction = link_xy[right_join] + turn[right_join] * right
    attached = left_lever = None  # which left rows are in the link's frame (None: none)
    if link_frame is not None and len(link_frame.rows):
        left, left_covariances, attached, left_lever = link_frame.placed(left, left_covariances, left_join, link_xy,
                                                                         link_phi)
    placed_left = left  # the left points, the attached ones where the corrected link puts them
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
            i, j, undecided = _gate(placed_left, left_covariances, left_join, largest, predicted, lever,
                                    right_covariances, right_join, link, None if first_round else scale, g2, margin,
                                    left_sightings, right_sightings, search, attached)
        else:  # the live joins' rows only; each join's pairs are what they would be among all
            rows, columns = np.flatnonzero(live[left_join]), np.flatnonzero(live[right_join])
            i, j, undecided = _gate(placed_left[rows], left_covariances[rows], left_join[rows], largest,
                                    predicted[columns], lever[columns], right_covariances[columns], right_join[columns],
                                    link, scale, g2, margin, None if left_sightings is None else left_sightings[rows],
                                    None if right_sightings is None else right_sightings[columns],
                                    attached=None if attached is None else attached[rows])
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
        linked = None if attached is None else ~attached[i]  # the pairs a link error moves
        terms = _joint_terms(r, w, lever[j], linked)
        information = prior_information if first_round else prior_information / scale[:, None, None]
        keep, sum_g, sum_m = _joint_test(terms, r, w, lever[j], pair_join, information, gate, joins, linked)
        rejected = np.bincount(pair_join[~keep], minlength=joins)
        if tested is not None:
            tested = (*tested[:3], rejected)
        if not keep.all():  # mostly all are kept: then the pairs and the joint test's sums as they are
            i, j, r, unscaled, pair_join = i[keep], j[keep], r[keep], unscaled[keep], pair_join[keep]
            linked = None if linked is None else linked[keep]
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
        moved = shift[pair_join] + lever[j] * fresh[pair_join, 2]
        residual = r - (moved if linked is None else linked * moved)
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
        if attached is not None:
            placed_left = left + attached * ((correction[:, 0] + 1j * correction[:, 1])[left_join]
                                             + left_lever * correction[left_join, 2])
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
