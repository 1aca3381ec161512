"""The tree's junction rule: a join's undrifted features, under the link as its own map knows it (step 2).

A tree join's link is its left piece's end pose, and its prior variance there is the end pose's in the piece's
frame: every junction of the piece summed, relative to the piece's *first* map (docs/method.md#data-association,
step 2; 1.17 m and 0.032 rad at level 5 of the 8240 simulation, 3.4 m at level 6). The sequential join gates the
same junction with 0.14-0.33 m. That wide prior is right for the piece's oldest features, but those carry their own
drift ``D`` (:mod:`mapjoin.association.feature_drift`, steps 6-8); the features the link's own map saw, and those the
right piece's first map saw, are known relative to the link up to that map's end pose and its junction, as a sequential
join's are. Gated under the piece's variance, they meet their neighbours as rivals wherever features are nearer
than the gate is wide (a 3 m lattice on 8240: the true partner at d^2 = 0.0-0.3, the lattice's neighbours at 5-7,
inside the clear margin of 9.2), and steps 2-5 leave the whole overlap new.

So at every level after the first a tree join also associates its *undrifted* features alone, ``D = 0`` on both
sides (:func:`undrifted`: the left features last seen by the link's map, the right ones first seen by the right
piece's first map), steps 2-5 under the link's variance relative to its own map (:func:`own_link_variances`), and
adds the pairs whose two features the join's association left unpaired (:func:`free_pairs`): a pair it had made is
kept, never replaced. On 8240's tree this recovers 18 of the 25 links missed at maps 16, 32, 48; every pair added
on the three datasets is true.
"""

from __future__ import annotations

import numpy as np

from ..covariance import placed_variances

__all__ = ["free_pairs", "own_link_variances", "undrifted"]


def own_link_variances(end_pose_variances: np.ndarray, junction_sums: np.ndarray, end_points: np.ndarray
                       ) -> np.ndarray:
    """The variance ``(var_t, p_phi)`` of each link relative to its own map's features: the map's end-pose variance
    (``end_pose_variances``, n x 2: spherical position and heading, in the map's frame, as the tree's first level
    holds them; ``end_points``: the end pose's position in that frame, complex) placed through its junction's
    posterior (``junction_sums``: rows ``v, p, ...`` of :attr:`mapjoin.association.feature_drift.SightingDrift.sums` for
    that junction alone) as a join places a point (:func:`mapjoin.covariance.placed_variances`:
    ``v + var_t + |x|^2 p / 2``), the headings' variances summed (``p_phi + p``)."""
    v, p = junction_sums[:, 0], junction_sums[:, 1]
    return np.column_stack([placed_variances(v, p, end_pose_variances[:, 0], np.abs(end_points) ** 2),
                            end_pose_variances[:, 1] + p])


def undrifted(left_last_map: np.ndarray, left_link_map: np.ndarray, right_first_map: np.ndarray,
              right_link_map: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The rows without drift relative to their join's link: left features last seen by the link's map
    (``left_link_map``, per row) and right features first seen by the map after it (the right piece's first)."""
    return np.flatnonzero(left_last_map == left_link_map), np.flatnonzero(right_first_map == right_link_map + 1)


def free_pairs(left: np.ndarray, right: np.ndarray, near_left: np.ndarray, near_right: np.ndarray) -> np.ndarray:
    """Which of the junction's pairs ``(near_left, near_right)`` join two features the join's pairs ``(left, right)``
    left unpaired (rows of one join's or level's features)."""
    return ~np.isin(near_left, left) & ~np.isin(near_right, right)
