"""Steps 6 to 8 of data association: the pairs the chain's drift hides and those it only seems to confirm
(docs/method.md#data-association).

:func:`match_with_drift` is :func:`~mapjoin.association.rounds.match_features` (steps 2 to 5) with each feature's
drift since its sighting (:mod:`mapjoin.association.feature_drift`): less the drifted pairs with a rival within their
drift where the map so far is strained (step 7: :func:`_unstrained`, :mod:`mapjoin.association.strain`) and the lone
drifted pairs beside a second copy and a rival (step 8: :func:`_unconfirmed`, :mod:`mapjoin.association.lone`); then
with the loop closures among the features left unpaired (step 6: :func:`_closed_loops`, the rigid correction voted by
:mod:`mapjoin.association.loop_votes`, its pairs kept where :mod:`mapjoin.association.loop_scope` says it holds), and
among the undrifted features still unpaired that the link's correction moved.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from .covariance_blocks import blocks
from .gate import DEFAULT_GATE, DEFAULT_MARGIN, _candidates, _threshold
from .link_frame import LinkFrame
from .link_pairs import linked_again
from .lone import LONE_MARGIN, lone_drifted
from .loop_scope import LinkSighting, VoterDrift, beyond_voters
from .loop_votes import rigid_votes
from .rounds import Matches, _join_maxima, _segment_medians, match_features
from .strain import drift_rivals

__all__ = ["LOOP_CLEAR", "LOOP_SUPPORT", "match_with_drift", "with_drift"]

#: a loop closure needs at least this many right features voting for its offset (and twice the runner-up's), and
#: this many pairs once associated around it
LOOP_SUPPORT = 4
#: ... and its pairs of right features agreeing on the correction at least this many times the runner-up's (a
#: rival association's: :func:`mapjoin.association.loop_votes.rigid_votes`)
LOOP_CLEAR = 2


def match_with_drift(left: np.ndarray, left_covariances: np.ndarray, left_join: np.ndarray, link_xy: np.ndarray,
                     link_phi: np.ndarray, link_variances: np.ndarray, right: np.ndarray,
                     right_covariances: np.ndarray, right_join: np.ndarray, drift: tuple[np.ndarray, ...] | None,
                     gate: float = DEFAULT_GATE, margin: float = DEFAULT_MARGIN,
                     left_sightings: np.ndarray | None = None, right_sightings: np.ndarray | None = None,
                     pair_drift: Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray] | None = None,
                     scope: VoterDrift | None = None, across: LinkSighting | None = None,
                     link_frame: LinkFrame | None = None) -> Matches:
    """:func:`match_features`, less the drifted pairs with a rival within their drift when ``pair_drift(left rows,
    right rows, their noise)`` gives the pairs' drift (:func:`_unstrained`, :mod:`mapjoin.association`, step 7: the
    associator's, through the chain's ties; compared with the noise only, it may stop at it where the way is long)
    and the lone drifted pairs beside a second copy and a rival (:func:`_unconfirmed`, step 8; both only where a
    pair's drift reaches its noise),
    then the loop closures among the features left unpaired (:func:`_closed_loops`, step 6), then those among the
    undrifted features still unpaired that the link's correction moved (``moved=True``):
    ``drift`` = (left ``D``, left heading variance, right ``D``, right heading variance), one per feature
    (:mod:`mapjoin.association.feature_drift`), or None for none; ``scope`` gives a loop closure's pairs their drift
    relative to its voters (:mod:`mapjoin.association.loop_scope`; None: the correction holds for every pair);
    ``across`` compares the closure's pairs of the link's own map where that map and the next saw them (a sequential
    join's: :data:`mapjoin.association.loop_scope.LinkSighting`; None: no such check); ``link_frame`` the left
    features steps 2 to 5 compare in the link's own frame (:mod:`mapjoin.association.link_frame`; None: none)."""
    left_covariances, right_covariances = blocks(left_covariances), blocks(right_covariances)
    found = match_features(left, left_covariances, left_join, link_xy, link_phi, link_variances, right,
                           right_covariances, right_join, gate, margin, left_sightings, right_sightings)
    if link_frame is not None:
        found = linked_again(found, left, left_covariances, left_join, link_xy, link_phi, link_variances, right,
                             right_covariances, right_join, link_frame, gate, margin, left_sightings, right_sightings)
    if drift is None:
        return found
    return with_drift(found, left, left_covariances, left_join, link_xy, link_phi, link_variances, right,
                      right_covariances, right_join, drift, gate, margin, left_sightings, right_sightings, pair_drift,
                      scope, across=across)


def with_drift(found: Matches, left: np.ndarray, left_covariances: np.ndarray, left_join: np.ndarray,
               link_xy: np.ndarray, link_phi: np.ndarray, link_variances: np.ndarray, right: np.ndarray,
               right_covariances: np.ndarray, right_join: np.ndarray, drift: tuple[np.ndarray, ...],
               gate: float = DEFAULT_GATE, margin: float = DEFAULT_MARGIN, left_sightings: np.ndarray | None = None,
               right_sightings: np.ndarray | None = None,
               pair_drift: Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray] | None = None,
               scope: VoterDrift | None = None, bent: np.ndarray | None = None,
               across: LinkSighting | None = None) -> Matches:
    """Steps 7, 8 and 6 of :func:`match_with_drift` after its steps 2 to 5 (``found``, :func:`match_features` of the
    same arguments; covariances as rows ``[xx, xy, yy]``): a tree level runs them itself, to choose each join's drift
    from what steps 2 to 5 found (:mod:`mapjoin.association.drift_evidence`); ``bent`` marks those joins, whose
    right piece's regions vote for corrections of their own (:func:`mapjoin.association.loop_votes.rigid_votes`);
    ``across`` as there."""
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
                           right_covariances, right_join, drift, gate, margin, left_sightings, right_sightings, scope,
                           bent=bent, across=across)
    found = found if closed is None else closed
    closed = _closed_loops(found, left, left_covariances, left_join, link_xy, link_phi, link_variances, right,
                           right_covariances, right_join, drift, gate, margin, left_sightings, right_sightings, scope,
                           moved=True, bent=bent, across=across)
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
                  scope: VoterDrift | None = None, moved: bool = False, bent: np.ndarray | None = None,
                  across: LinkSighting | None = None) -> Matches | None:
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
    drifted pairs is, for the features near the link, a drift of its own). ``bent``: the joins whose right piece is a
    drifted chain, where only a rival pairing the voters' right features counts against a correction
    (:func:`mapjoin.association.loop_votes.rigid_votes`), a reference holds a pair only within the gate of its
    noise and drift there (:func:`mapjoin.association.loop_scope.beyond_voters`, ``within``) and the correction only
    the pairs whose drift relative to its voters is below their noise (``near_voters``).

    ``across`` (read with ``scope``, as the sequential join passes both): whichever reference holds it, a pair whose
    left feature the link's own map saw last is left new (rejected) when that map's sighting and the right map's,
    dead-reckoned, lie beyond the gate of the pair's noise, that map's end-pose variance there and the link's spread:
    the two maps saw those features through one junction, whatever the map so far made of them since
    (docs/method.md#data-association, step 6)."""
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
                        joins, closeness, bent)
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
        bent_pairs = None if bent is None or not bent.any() else bent[pair_join_again]
        within = None if bent_pairs is None else np.where(bent_pairs, g2, np.inf)
        held = ~beyond_voters(left, left_join, pair_left, left_sightings,
                              (position, noise + variance, scope(pair_left, pair_right, pair_join_again, *voters)),
                              (predicted[place[pair_right]], noise, left_drift[pair_left] + right_drift[pair_right]),
                              within=within, near_voters=bent_pairs)
        if across is not None:
            offset2, variance = across(pair_left, pair_right)
            held &= offset2 <= g2 * (noise + variance + link_spread[place[pair_right]])
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
