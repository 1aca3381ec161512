"""A loop closure's rigid correction holds near its voters: the drift relative to them scopes its pairs.

Step 6 (:mod:`mapjoin.association.loop_votes`, docs/method.md#data-association) corrects a join's link by the one rigid
correction its voting pairs agree on and associates the features left unpaired again around the corrected link. The
correction is the chain's drift as the *voters* saw it: exact at the maps that saw them, it degrades with the chain
between those maps and the maps that saw another feature. On DLR's tree with step 2's junction rule, a level-8 loop
closure's 42 voters lie on right features first seen by maps 135-151; its 64 true pairs on maps 128-152; 7 false
ones on maps 186-198, whose features the one correction places 5-7.5 m from their true partners, 0.06-0.27 m from
other markers. Their residual under the correction is as small as a true pair's: the test that they fit their drift
relative to the voters passes them all, since a marker lies within any gate that wide. What the drift takes away
is the clear nearest neighbour's evidence (step 3), as step 7 says of a drifted pair around the link.

So each pair of the re-association has two references where its prediction is exact up to a drift: the correction,
with the pair's drift relative to the voters (:func:`voter_drift`: ``D`` over the junctions between the map that
last saw its left feature and the nearest map, along the chain or through one of its ties, that last saw a voter's,
plus the same between its right feature's first sighting and the voters'), and the link as steps 2-5 corrected it,
with the pair's drift relative to the link. It is kept when it is clear under one of them: its drift there below its
noise, or no rival left feature within step 7's margin over that drift (:func:`beyond_voters`). The DLR level-8
pairs' drift relative to the voters is 2.6-3.8 m for the 7 false ones, 0-0.06 m for the 64 true ones.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from .feature_drift import SightingDrift
from .strain import drift_rivals

__all__ = ["LinkSighting", "VoterDrift", "beyond_voters", "chain_drift", "voter_drift", "voters_drift"]

#: a loop closure's pairs (left rows, right rows, joins) and its voters (the same) -> each pair's drift relative to
#: its join's voters (both sides summed)
VoterDrift = Callable[[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray], np.ndarray]
#: a sequential join's loop closure pairs (left rows, right rows) -> each pair's squared offset where the link's own map
#: and the next one saw its features, and that offset's variance beyond the pair's noise (infinite for a left feature
#: another map saw last): :meth:`mapjoin.association.feature_drift.SightingDrift.across_link`
LinkSighting = Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]


def chain_drift(drift: SightingDrift, maps: np.ndarray, others: np.ndarray, points: np.ndarray,
                rows: np.ndarray | None = None) -> np.ndarray:
    """``D`` between the sightings by ``maps`` and by ``others`` (one each) of features at ``points`` (dead-reckoned,
    as seen by ``maps``) over the shorter way: the junctions between the two maps, either way along the chain, or
    through one of the chain's ties ``(m, c)`` (:meth:`mapjoin.association.feature_drift.SightingDrift.tie`) the
    junctions from the sighting to one end of the tie, its strain and those from the other end (the feature moved by the
    two ends' places) to the other map, as :meth:`~mapjoin.association.feature_drift.SightingDrift.settled` takes a
    link's.
    ``rows``: each of ``others`` compared with feature ``rows[k]`` of ``maps`` and ``points`` (None: one each), so
    that a feature's way to each tie is summed once however many maps it is compared with."""
    if rows is None:
        rows = np.arange(len(others))
    best = drift.between(maps[rows], others, points[rows])
    if not drift.ties or not len(others):
        return best
    old_map, junction, strain = drift.tie_arrays()
    poses = drift.chain.poses
    for near, far in ((old_map, junction), (junction, old_map)):  # the tie taken from either end
        moved = points[:, None] - poses[near] + poses[far]
        to_tie = drift.between(maps[:, None], near[None, :], points[:, None]) + strain  # per feature, then per comparison
        way = to_tie[rows] + drift.between(far[None, :], others[:, None], moved[rows])
        best = np.minimum(best, way.min(axis=1))
    return best


def voter_drift(drift: SightingDrift, maps: np.ndarray, points: np.ndarray, join: np.ndarray,
                voter_maps: np.ndarray, voter_join: np.ndarray) -> np.ndarray:
    """Each feature's drift variance relative to its join's voters: the least :func:`chain_drift` between its
    sighting map (``maps``, at its dead-reckoned ``points``) and a voter's sighting map of the same join
    (``voter_maps``, ``voter_join``); 0 when a voter was seen by the same map, infinite when the join has none.
    Each feature is compared with its join's distinct voter maps (a loop closure's few dozen)."""
    maps, join = np.asarray(maps, dtype=np.int64), np.asarray(join, dtype=np.int64)
    span = int(max(int(np.max(maps, initial=0)), int(np.max(voter_maps, initial=0)))) + 1
    keys = np.unique(np.asarray(voter_join, dtype=np.int64) * span + np.asarray(voter_maps, dtype=np.int64))
    start, stop = np.searchsorted(keys, join * span), np.searchsorted(keys, (join + 1) * span)
    count = stop - start
    feature = np.repeat(np.arange(len(maps)), count)
    other = keys[np.arange(int(count.sum())) + np.repeat(start - (np.cumsum(count) - count), count)] % span
    best = np.full(len(maps), np.inf)
    np.minimum.at(best, feature, chain_drift(drift, maps, other, points, feature))
    return best


def voters_drift(drift: SightingDrift, left_ids: np.ndarray | None, right_ids: np.ndarray | None) -> VoterDrift:
    """The associator's :data:`VoterDrift` of a join or a tree level whose left rows are the compact ids
    ``left_ids`` (None: the rows are the ids) and right rows ``right_ids`` (a right piece's; None: one map's own
    features, all first seen by the map, without drift between them): the left features' drift relative to the
    voters' left features since their last sightings, plus the right features' since their first."""

    def relative(pair_left: np.ndarray, pair_right: np.ndarray, join: np.ndarray, voter_left: np.ndarray,
                 voter_right: np.ndarray, voter_join: np.ndarray) -> np.ndarray:
        mine, theirs = (pair_left, voter_left) if left_ids is None else (left_ids[pair_left], left_ids[voter_left])
        value = voter_drift(drift, drift.last_map[mine], drift.last_point[mine], join, drift.last_map[theirs],
                            voter_join)
        if right_ids is not None:
            mine, theirs = right_ids[pair_right], right_ids[voter_right]
            value = value + voter_drift(drift, drift.first_map[mine], drift.first_point[mine], join,
                                        drift.first_map[theirs], voter_join)
        return value

    return relative


def beyond_voters(left: np.ndarray, left_join: np.ndarray, pair_left: np.ndarray, left_sightings: np.ndarray | None,
                  *references: tuple[np.ndarray, np.ndarray, np.ndarray], within: np.ndarray | None = None,
                  near_voters: np.ndarray | None = None) -> np.ndarray:
    """Which of a loop closure's pairs (left rows ``pair_left`` of ``left``, complex, by ``left_join``) no reference
    holds for (a mask). A reference is each pair's right feature predicted, its noise there (isotropic: the features'
    half-traces, plus the correction's variance) and its drift from where the prediction is exact: the correction
    with the pair's drift relative to the voters (:func:`voter_drift`), and the link as steps 2-5 corrected it with
    the pair's drift relative to the link. A pair fails one when that drift is at least the noise
    and a rival left feature seen with the chosen one is nearer than :data:`~mapjoin.association.strain.DRIFT_MARGIN`
    farther, in squared distance over drift and noise (:func:`mapjoin.association.strain.drift_rivals`, step 7's
    rule, ``left_sightings`` as there). ``within`` (None: everywhere infinite): each pair's bound on its squared
    distance from a reference's prediction over the noise and drift there (a chi-square quantile), beyond which that
    reference does not hold it, however small its drift: a bent piece's loop closure finds features at the link
    that the correction of another region placed metres from where the link has them (docs/method.md, step 6).
    ``near_voters`` (None: none): the pairs (a mask) the first reference, the correction, holds only where their drift
    relative to the voters is below their noise, whatever their rivals: in a bent piece the correction is its voters'
    region's own, and beyond it a right feature lands near a left one by chance, with no rival seen with it (the
    default simulations: such pairs 1.8-3.9 times their noise from the voters, the true ones a median 0)."""
    unclear = np.ones(len(pair_left), dtype=bool)
    for reference, (predicted, noise, drift) in enumerate(references):
        missed = drift_rivals(left, left_join, pair_left, predicted, noise, drift, left_sightings)
        if within is not None:
            missed |= np.abs(left[pair_left] - predicted) ** 2 > within * (noise + drift)
        if near_voters is not None and reference == 0:
            missed |= near_voters & (drift >= noise)
        unclear &= missed
    return unclear
