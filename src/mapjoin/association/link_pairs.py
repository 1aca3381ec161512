"""The right features steps 2-5 leave ambiguous, compared again in the link's own frame
(docs/method.md#data-association, step 2, the link rule).

Steps 2 to 5 compare every left feature with a right one in left's frame, under ``C0 + C1 + H P_link H^T``. For the
features the link's own map saw, ``C0`` (relative to that map's start) and ``P_link`` (its end pose) share the map's
dead reckoning, and counted as independent they make a long map's features near its end metres wide where they are
known to centimetres relative to the link: their neighbours lie within the clear margin, and the pairs are left
ambiguous (:mod:`mapjoin.association.link_frame`). The right features left ambiguous are associated again, steps 2
to 5, with the unpaired left features, those of the link's own map in the link's frame (:func:`linked_again`), and
the pairs of those are added (their features were all free).
"""

from __future__ import annotations

import numpy as np

from .link_frame import LinkFrame
from .rounds import Matches, match_features

__all__ = ["linked_again"]


def linked_again(found: Matches, left: np.ndarray, left_covariances: np.ndarray, left_join: np.ndarray,
                 link_xy: np.ndarray, link_phi: np.ndarray, link_variances: np.ndarray, right: np.ndarray,
                 right_covariances: np.ndarray, right_join: np.ndarray, link_frame: LinkFrame, gate: float,
                 margin: float, left_sightings: np.ndarray | None, right_sightings: np.ndarray | None) -> Matches:
    """``found`` (steps 2-5 of these arguments) with the pairs steps 2-5 take between the right rows ``found`` left
    undecided (candidates, none clear) and the left rows not in a pair, those of ``link_frame`` in the link's frame
    (its points and covariances, no link term), the others as in ``found`` (rivals under the link's error); only the
    pairs of ``link_frame``'s rows are added, and their right features are no longer undecided. Measured
    (docs/method.md#data-association, step 2): every unpaired right feature instead of the undecided ones cost DLR's
    sequential join 3 links (99 -> 102 missed); without the other left features as rivals VicPark 6898's first 1000
    maps had a false link more (map 742: a right feature's partner an older feature); with their pairs added as well,
    VicPark 200 and DLR a false link each."""
    free = np.ones(len(left), dtype=bool)
    free[found.left] = False
    lefts = np.flatnonzero(free)  # every unpaired left feature: the others stay rivals, under the link's error
    mine = free[link_frame.rows]
    rights = found.undecided
    if not mine.any() or not len(rights):
        return found
    again = match_features(left[lefts], left_covariances[lefts], left_join[lefts], link_xy, link_phi, link_variances,
                           right[rights], right_covariances[rights], right_join[rights], gate, margin,
                           None if left_sightings is None else left_sightings[lefts],
                           None if right_sightings is None else right_sightings[rights],
                           LinkFrame(np.searchsorted(lefts, link_frame.rows[mine]), link_frame.points[mine],
                                     link_frame.covariances[mine]))
    taken = np.isin(lefts[again.left], link_frame.rows)  # the pairs in the link's frame
    if not taken.any():
        return found
    return found.with_pairs(lefts[again.left[taken]], rights[again.right[taken]], right_join)
