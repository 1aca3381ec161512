"""Pairs that are clear only if the map so far were not strained: a drifted feature with a rival within its drift.

The clear nearest neighbour of :mod:`mapjoin.association` (step 3) measures distances with the features' own
covariances and the link's error. A left feature last seen many maps before the link has drifted since, relative
to the link, by ``D`` (:mod:`mapjoin.association.feature_drift`): where ``D`` exceeds the pair's noise, the pair's small
offset is no evidence that it is the right feature rather than a neighbour within the drift. On DLR, whose markers
lie 0.5-1 m apart, a right feature met again after 4 m of drift lands 0.1-0.3 m from a *different* old feature,
with its own feature metres away: each such pair passes the gate, the margin and the joint test
(docs/method.md#data-association, step 7). :func:`drift_rivals` names those pairs: a drifted pair (``D`` at least
its noise) is dropped when another left feature of its join, seen in one map with the chosen one, is nearer than
:data:`DRIFT_MARGIN` farther in squared distance over ``D`` plus the noise (the nearest is not clearly likelier
under the drift).
"""

from __future__ import annotations

import numpy as np

from .grid import pairs_within

__all__ = ["DRIFT_MARGIN", "drift_rivals"]

#: a drifted pair keeps its left feature when every rival is at least this much farther, in squared distance
#: over the pair's drift and noise (chosen between DLR's false pairs, whose rivals are 0.02-0.2 farther, and
#: VicPark's true drifted pairs, 2.7 and more; 0.3 already lets a false link through on DLR: benchmarks/README.md,
#: "Data association")
DRIFT_MARGIN = 1.0


def drift_rivals(left: np.ndarray, left_join: np.ndarray, pair_left: np.ndarray, predicted: np.ndarray,
                 noise: np.ndarray, drift: np.ndarray, left_sightings: np.ndarray | None = None,
                 margin: float = DRIFT_MARGIN) -> np.ndarray:
    """Which pairs to leave new (a mask over them): pair ``p`` joins left row ``pair_left[p]`` (``left``: complex
    points, ``left_join`` their joins) with a right feature predicted at ``predicted[p]`` (after the link's
    correction); ``noise[p]`` is its half-trace variance without drift, ``drift[p]`` its drift ``D``. A pair with
    ``drift >= noise`` is dropped when a rival left feature ``r`` of the same join (seen in a same map as the chosen
    one: ``left_sightings``, :func:`mapjoin.association.sighting_bits`; without them every other left feature)
    has ``|f_r - x|^2 < |f_i - x|^2 + margin (noise + drift)`` (``margin``: :data:`DRIFT_MARGIN`; step 8 asks with
    :data:`mapjoin.association.lone.LONE_MARGIN` without sightings, then with step 3's margin and sightings)."""
    pair_left = np.asarray(pair_left, dtype=np.intp)
    drop = np.zeros(len(pair_left), dtype=bool)
    flagged = np.flatnonzero(drift >= noise)
    if not len(flagged) or not len(left):
        return drop
    chosen = pair_left[flagged]
    own = np.abs(left[chosen] - predicted[flagged]) ** 2
    reach = own + margin * (noise[flagged] + drift[flagged])
    # the left features of each flagged pair's join within its reach (a grid; a hair wider, then the exact test)
    r, p = pairs_within(left, left_join, predicted[flagged], left_join[chosen], np.sqrt(reach) * (1 + 1e-9),
                        int(left_join.max()) + 1)
    near = (np.abs(left[r] - predicted[flagged[p]]) ** 2 < reach[p]) & (r != chosen[p])
    if left_sightings is not None:
        near &= (left_sightings[r] & left_sightings[chosen[p]]).any(axis=1)
    drop[flagged[p[near]]] = True
    return drop
