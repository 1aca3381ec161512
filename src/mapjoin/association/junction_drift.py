"""A sequential junction's drift as the previous map's own uncertainty puts it (docs/method.md#data-association, 6).

Join ``k`` places map ``k``'s start by the features it shares with map ``k - 1``. The join's posterior is the
conditional variance of its one-step solve: it treats the map so far as exact and, in the default ``information``
mode, weighs each feature by its conditional variance, so it says how well the *solve* is determined, not how far
the junction may lie from where map ``k - 1``'s start puts it. That error is the error of the shared features'
placement in map ``k - 1`` relative to its start (map ``k``'s own features, seen near its start, add little): a
rigid fit of the shared features moves the junction by their centroid's error plus the fit's turn about the
centroid, and the features' errors are correlated (they share the map's pose errors), so the fit is known no
better than the map's full covariance says. :func:`fit_variances` is that variance (spherical, half-trace, as the
drift's sums take it) and the fit's turn variance; :class:`mapjoin.association.drift_scale.DriftScale` decides
how much of its excess over the posterior the data bear out.
"""

from __future__ import annotations

import numpy as np

__all__ = ["fit_variances"]


def fit_variances(covariance: np.ndarray, points: np.ndarray, end_point: complex) -> tuple[float, float]:
    """The translation variance (half-trace) at ``end_point`` and the turn variance of an unweighted rigid fit of
    ``points`` (the shared features, complex, in their map's frame) whose errors have ``covariance``
    (2n x 2n, rows ``x_1, y_1, x_2, ...``). The fit's error is linear in the features' errors ``e``: translation
    ``mean(e)``, turn ``sum(u_j x e_j) / sum |u_j|^2`` with ``u_j`` the features about their centroid ``c``, and the
    junction at ``end_point`` moves by the translation plus the turn times ``i (end_point - c)``. One feature
    fixes no turn (0)."""
    count = len(points)
    centre = points.mean()
    centred = points - centre
    spread = float(centred.real @ centred.real + centred.imag @ centred.imag)
    weights = np.zeros((2 * count, 3))  # the fit's error (centroid x, y; turn) = weights^T e
    weights[0::2, 0] = weights[1::2, 1] = 1.0 / count
    if count > 1 and spread > 0.0:
        weights[0::2, 2], weights[1::2, 2] = -centred.imag / spread, centred.real / spread
    fit = weights.T @ covariance @ weights  # the centroid's and the turn's 3 x 3 covariance
    lever = end_point - centre  # the junction moves by the translation plus the turn times i lever
    moved = fit[0, 0] + fit[1, 1] + 2 * (lever.real * fit[1, 2] - lever.imag * fit[0, 2]) + fit[2, 2] * abs(lever) ** 2
    return float(moved) / 2, float(fit[2, 2])
