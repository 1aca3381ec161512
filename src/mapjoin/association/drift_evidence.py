"""Whether a tree join's pieces drifted apart: its drifted features' near misses against the pairs steps 2-5 made.

The drift ``D`` of steps 6-8 (:mod:`mapjoin.association.feature_drift`) sums the junctions' posteriors. In the default
``information`` covariance mode those are conditional variances, and they leave out what each map's own dead reckoning
adds before the next junction: on the default simulation (maps whose covariances are exact) the junctions' heading
variances are 100-200 times below the maps' own end-pose variances, and a tree join at level 5 or 6 finds the far end
of its right piece turned by 0.1-0.2 rad, its features 3-14 m from their partners where ``D`` allows 0.5 m
(docs/method.md#data-association, step 2). Of the hundreds of right features there, the few that land within the gate
of a *different* feature, with no rival, are taken by steps 2-5 (171 false links over seeds 0-7 of 50 maps). On
VicPark's maps, whose covariances are pessimistic, the same sums with the maps' own variances added are 30-90 times too
large, and step 7 then leaves true pairs new (its tree 36 -> 70 links missed).

The association itself tells the two apart. Where the chain has not drifted beyond ``D``, a right feature of the right
piece's later maps that steps 2-5 predict near a left feature (within twice its gate's radius, :data:`NEAR`) is mostly
that feature seen again, and is paired; where it has, such coincidences are chance, and the gate holds a quarter of
the disc at most. :func:`drifting` calls a join drifted when fewer than :data:`SHARE` of those near right features were
paired: on VicPark's and DLR's trees 0.7-1.0 at every join before DLR's loop closures, on the simulation's upper levels
0.14-0.67.
"""

from __future__ import annotations

import numpy as np

from .gate import _threshold
from .grid import pairs_within
from .rounds import Matches, _join_maxima

__all__ = ["NEAR", "SHARE", "drifting"]

#: a right feature is near a left one within this many times the squared radius of their gate (twice the radius:
#: a chance neighbour falls within the gate a quarter of the time)
NEAR = 4.0
#: a join has drifted when fewer than this share of its near drifted right features were paired (halfway between
#: all of them, as where it has not, and the gate's quarter of the disc)
SHARE = 0.5


def drifting(found: Matches, left: np.ndarray, left_covariances: np.ndarray, left_join: np.ndarray,
             link_xy: np.ndarray, link_phi: np.ndarray, link_variances: np.ndarray, right: np.ndarray,
             right_covariances: np.ndarray, right_join: np.ndarray, beyond: np.ndarray, gate: float) -> np.ndarray:
    """Which joins drifted (a mask over them): ``found`` are the pairs of steps 2-5 (:func:`match_features` of these
    arguments: complex points, covariances as rows ``[xx, xy, yy]`` in left's frame, each link's prior variances
    ``(var_t, p_phi)``); ``beyond`` marks the right features the right piece's first map did not see (they carry the
    piece's drift). Each is predicted through its join's link as steps 2-5 corrected it, and is *near* when a left
    feature of its join lies within :data:`NEAR` times its gate's squared radius (``gate``: the chi-square level; the
    radius isotropic, from the two features' half-traces and the link's spread there); a join with near ones drifted
    when fewer than :data:`SHARE` of them were paired."""
    joins = len(link_xy)
    rows = np.flatnonzero(beyond)
    if not len(rows) or not len(left):
        return np.zeros(joins, dtype=bool)
    join = right_join[rows]
    correction = found.correction[join]
    predicted = link_xy[join] + correction[:, 0] + 1j * correction[:, 1] + \
        np.exp(1j * (link_phi[join] + correction[:, 2])) * right[rows]
    left_noise = (left_covariances[:, 0] + left_covariances[:, 2]) / 2
    right_noise = (right_covariances[rows, 0] + right_covariances[rows, 2]) / 2 \
        + link_variances[join, 0] + link_variances[join, 1] * np.abs(right[rows]) ** 2
    reach = NEAR * float(_threshold(gate, 1))
    widest = _join_maxima(left_noise, left_join, joins)
    i, p = pairs_within(left, left_join, predicted, join, np.sqrt(reach * (widest[join] + right_noise)) * (1 + 1e-9),
                        joins)
    close = np.abs(left[i] - predicted[p]) ** 2 <= reach * (left_noise[i] + right_noise[p])
    near = np.zeros(len(rows), dtype=bool)
    near[p[close]] = True
    paired = np.isin(rows, found.right)
    return np.bincount(join[near & paired], minlength=joins) < SHARE * np.bincount(join[near], minlength=joins)
