"""Spherical covariances: the summaries of a local map's covariance, and their propagation through joins.

The one-step solver needs spherical covariances (docs/method.md#definition-2): ``sigma^2 I_2`` per
feature, ``diag(sigma_xy^2, sigma_xy^2, p_phi)`` per pose. Real local maps carry full
covariances, so each 2x2 (or pose) block is summarised in one of the ``COVARIANCE_MODES``
(:func:`spherical_variances`).

After a join the global map needs spherical variances again for the next join; they are
propagated to first order, each 2x2 covariance summarised by half its trace:

- a common feature fuses both estimates: ``1 / (1/var0 + 1/var1)`` (:func:`fuse`, Theorem 1's X_L);
- the joined pose r1 gets ``var_phi = 1 / (f''(phi*)/2)`` and ``var_t = 1/W + |m1|^2 var_phi / 2``
  (:func:`translation_variance`; W, m1 from Theorem 1's reduction);
- a point ``z`` placed by the join ``t + R(phi) z`` gets ``var_t + var_z + |z|^2 var_phi / 2``
  (:func:`placed_variances`), a pose orientation ``var_phi + p_phi``.

Points of the propagation are complex numbers ``x + iy``, as in :mod:`mapjoin.joining`.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING, Literal

import numpy as np

from .maps import marginal_variances, size_groups, spherical_diagonal

if TYPE_CHECKING:
    from .maps import LocalMap

__all__ = [
    "COVARIANCE_MODES",
    "DEFAULT_COVARIANCE",
    "CovarianceMode",
    "batch_spherical_variances",
    "fuse",
    "placed_variances",
    "spherical_variances",
    "squared_norm",
    "state_covariance",
    "state_variances",
    "translation_variance",
]

CovarianceMode = Literal["identity", "marginal", "information"]
COVARIANCE_MODES: tuple[str, ...] = ("identity", "marginal", "information")
# Measured against the exact least-squares joins (docs/joining.md, "Covariance modes"): closest on
# VicPark 200 and both simulations; "marginal" is closer on DLR 200 only.
DEFAULT_COVARIANCE: CovarianceMode = "information"


def spherical_variances(local_map: LocalMap, mode: CovarianceMode) -> tuple[np.ndarray, np.ndarray]:
    """Spherical ``(feature_variances, pose_variances)`` of ``local_map`` in ``mode``.

    - ``identity``: every variance 1, as in the paper's experiment (Section 7).
    - ``marginal``: the mean of the diagonal of each 2x2 block of the covariance (the
      average marginal variance of x and y), and ``P_phiphi`` for the orientation.
    - ``information``: the same from the information matrix ``P^-1``: ``sigma^2 =
      2 / trace(Lambda_jj)``, the conditional variance of a block given the rest of the map.

    A map without a full covariance is block-diagonal spherical already, so
    ``marginal`` and ``information`` both return its stored variances. One map is a batch
    of one of :func:`batch_spherical_variances`.
    """
    features, poses = batch_spherical_variances([local_map], mode)
    return features, poses[0]


def batch_spherical_variances(maps: Sequence[LocalMap], mode: CovarianceMode) -> tuple[np.ndarray, np.ndarray]:
    """:func:`spherical_variances` of many maps: all feature variances concatenated, and (len(maps), 2) pose ones.

    Maps with full covariances of one size are summarised together (one batched inverse
    per size for ``information``), so the cost is not a Python loop of matrix calls.
    (numpy's batched inverse makes one LAPACK call per matrix; exact alternatives built from
    batched products or Cholesky factors were measured no faster for these small matrices.)
    """
    if mode not in COVARIANCE_MODES:
        raise ValueError(f"unknown covariance mode {mode!r}; expected one of {', '.join(COVARIANCE_MODES)}")
    sizes = np.fromiter((m.size for m in maps), np.intp, len(maps))
    offsets = np.concatenate([[0], np.cumsum(sizes)])
    if mode == "identity":
        return np.ones(offsets[-1]), np.ones((len(maps), 2))
    features = np.concatenate([m.feature_variances for m in maps]) if maps else np.zeros(0)
    poses = np.array([m.pose_variances for m in maps]).reshape(-1, 2)
    full = np.flatnonzero(np.fromiter((m.covariance is not None for m in maps), bool, len(maps)))
    for group in size_groups(sizes[full]):
        members = full[group]
        size = 3 + 2 * int(sizes[members[0]])
        stacked = np.concatenate([maps[i].covariance for i in members.tolist()]).reshape(-1, size, size)
        if mode == "information":  # sigma^2 = 2 / trace of each block of P^-1 = 1 / its mean
            feature_part, pose_part = spherical_diagonal(np.diagonal(np.linalg.inv(stacked), axis1=1, axis2=2), -1.0)
        else:
            feature_part, pose_part = marginal_variances(stacked)
        features[(offsets[members][:, None] + np.arange(feature_part.shape[1])).ravel()] = feature_part.ravel()
        poses[members] = pose_part
    return features, poses


def state_variances(local_map: LocalMap) -> np.ndarray:
    """The diagonal covariance of a local map's state vector ``[x, y, phi, x1, y1, ...]`` that its
    spherical variances stand for (a map read without a full covariance, e.g. from CSV)."""
    return np.concatenate([local_map.pose_variances[[0, 0, 1]], np.repeat(local_map.feature_variances, 2)])


def state_covariance(local_map: LocalMap) -> np.ndarray:
    """The covariance of a local map's state vector: the full one when the map has it, else the
    diagonal of :func:`state_variances`."""
    if local_map.covariance is not None:
        return local_map.covariance
    return np.diag(state_variances(local_map))


def spherical_summary(pose_covariances: np.ndarray, feature_covariances: np.ndarray
                      ) -> tuple[np.ndarray, np.ndarray]:
    """The spherical summary ``(pose variances (p, 2), feature variances (n,))`` of marginal
    covariances (p, 3, 3) and (n, 2, 2): half the trace of each x/y block, and the
    orientation variance as is."""
    pose_variances = np.stack([(pose_covariances[:, 0, 0] + pose_covariances[:, 1, 1]) / 2,
                               pose_covariances[:, 2, 2]], axis=1)
    return pose_variances, np.trace(feature_covariances, axis1=1, axis2=2) / 2


def squared_norm(points):
    """|z|^2 of complex points (a number or an array): the lever arm of an orientation error."""
    return points.real**2 + points.imag**2


def translation_variance(weight, mean1, phi_variance):
    """var_t = 1/W + |m1|^2 var_phi / 2 of the joined pose r1 = (t, phi) (numbers or arrays).

    ``t = m0 - R(phi) m1`` (Theorem 1): 1/W is its variance at fixed phi, and an error of phi
    moves it by ``|m1|`` times that error.
    """
    return 1.0 / weight + squared_norm(mean1) * phi_variance / 2


def placed_variances(t_variance, phi_variance, variances, squared):
    """The spherical variances of points ``z`` placed by a join at ``t + R(phi) z``: ``var_t + var_z +
    |z|^2 var_phi / 2``, with ``squared = |z|^2`` (numbers or arrays, broadcast)."""
    return t_variance + variances + squared * phi_variance / 2


def fuse(z0: np.ndarray, var0: np.ndarray, placed: np.ndarray, information1: np.ndarray
         ) -> tuple[np.ndarray, np.ndarray]:
    """Theorem 1's X_L: each common feature as the information-weighted mean of both estimates, and its variance.

    ``information1`` is ``1 / var1``, the weight of the ``placed`` estimates.
    """
    w0 = 1.0 / var0
    total = w0 + information1
    return (w0 * z0 + information1 * placed) / total, 1.0 / total
