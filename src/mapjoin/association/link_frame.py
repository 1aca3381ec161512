"""The left features the link's own map saw, in the link's frame (docs/method.md#data-association, steps 1-5).

A sequential join's link is the end pose of the previous map, the map that saw some of the left features last (the
tree's first level's, its left piece's one map's end pose: that map saw every left feature). Those features and that
end pose share the map's dead reckoning:
relative to the end pose a feature the map saw near its end is known to centimetres, while its marginal covariance
relative to the map's start and the end pose's variance are each metres (:func:`mapjoin.association.covariance_blocks.
end_relative`). Such a feature is compared with a right feature in the link's own frame, ``g - z`` with covariance
``C_end + C1``: no link error enters it (the link *is* that frame), so it gives the link no correction and is moved with
the link's correction as the right features are (:class:`LinkFrame`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .covariance_blocks import rotated

__all__ = ["LinkFrame"]


@dataclass(frozen=True)
class LinkFrame:
    """Left rows ``rows`` (ascending) seen by their join's link map, at ``points`` (complex) with 2 x 2 covariances
    ``covariances`` (rows ``[xx, xy, yy]``), both in the link's frame (relative to the link map's end pose)."""

    rows: np.ndarray
    points: np.ndarray
    covariances: np.ndarray

    def placed(self, left: np.ndarray, left_covariances: np.ndarray, left_join: np.ndarray, link_xy: np.ndarray,
               link_phi: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """``left`` and ``left_covariances`` (left's frame) with these rows put where their join's link puts them,
        ``o + R(phi_o) g``, with ``R C_end R^T``; which rows they are (a mask) and their levers ``R'(phi_o) g`` (0
        elsewhere), by which a correction of the link moves them as it moves the right features' predictions."""
        join = left_join[self.rows]
        turn = np.exp(1j * link_phi[join])
        left, left_covariances = left.copy(), left_covariances.copy()
        left[self.rows] = link_xy[join] + turn * self.points
        left_covariances[self.rows] = rotated(self.covariances, link_phi[join])
        attached = np.zeros(len(left), dtype=bool)
        attached[self.rows] = True
        lever = np.zeros(len(left), dtype=complex)
        lever[self.rows] = 1j * turn * self.points
        return left, left_covariances, attached, lever
