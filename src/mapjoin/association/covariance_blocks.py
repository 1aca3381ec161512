"""The features' 2 x 2 covariances in data association, each as one row ``[xx, xy, yy]``
(docs/method.md#data-association, step 1).

Each right feature's uncertainty relative to the join's link is its 2 x 2 marginal covariance in its local map (the
map's full covariance, which the spherical weights of the fast join are not: :func:`feature_covariances`), rotated
into left's frame (:func:`rotated`); each left feature carries the covariances of its sightings fused as independent
estimates (:func:`fused`). A symmetric 2 x 2 matrix held as one row ``[xx, xy, yy]`` makes a join's features one
array: their inverses in closed form (:func:`inverted`) and the quadratic forms of the gate and of the joint test
(:func:`_mahalanobis`) are array operations.
"""

from __future__ import annotations

import numpy as np

from ..maps import LocalMap

__all__ = ["blocks", "end_relative", "feature_covariances", "fused", "inverted", "rotated"]

def blocks(variances: np.ndarray) -> np.ndarray:
    """2 x 2 covariances as rows ``[xx, xy, yy]``: ``variances`` as they are (n x 3) or spherical (n,)."""
    variances = np.asarray(variances, dtype=float)
    if variances.ndim == 2:
        return variances
    return np.column_stack([variances, np.zeros_like(variances), variances])


def rotated(covariances: np.ndarray, phi: np.ndarray | float) -> np.ndarray:
    """``R(phi) C R(phi)^T`` of 2 x 2 covariances (rows ``[xx, xy, yy]``; ``phi`` one angle or one per row)."""
    c, s = np.cos(phi), np.sin(phi)
    xx, xy, yy = covariances.T
    out = np.empty((len(covariances), 3))
    out[:, 0] = c * c * xx - 2 * c * s * xy + s * s * yy
    out[:, 1] = c * s * (xx - yy) + (c * c - s * s) * xy
    out[:, 2] = s * s * xx + 2 * c * s * xy + c * c * yy
    return out


_ADJUGATE_SIGNS = np.array([1.0, -1.0, 1.0])


def inverted(covariances: np.ndarray) -> np.ndarray:
    """The inverses of 2 x 2 symmetric matrices (rows ``[xx, xy, yy]``), in closed form."""
    det = covariances[:, 0] * covariances[:, 2] - covariances[:, 1] * covariances[:, 1]
    return covariances[:, ::-1] * _ADJUGATE_SIGNS / det[:, None]  # [yy, -xy, xx] / det


def fused(first: np.ndarray, second: np.ndarray) -> np.ndarray:
    """The covariance of two independent estimates of one point fused: ``(C1^-1 + C2^-1)^-1`` (rows ``[xx, xy, yy]``)."""
    return inverted(inverted(first) + inverted(second))


_BLOCK_ROWS, _BLOCK_COLUMNS = np.array([0, 0, 1]), np.array([0, 1, 1])  # a 2 x 2 block's xx, xy, yy


def feature_covariances(local_map: LocalMap) -> np.ndarray:
    """Each feature's 2 x 2 marginal covariance in ``local_map``'s frame (rows ``[xx, xy, yy]``, in the order of
    the sorted feature ids, as :mod:`mapjoin.joining` holds them): the blocks of the full covariance when the map
    has one, else its spherical variances. They are the uncertainty of a feature *relative to the map's start*,
    the join's link, which the gate needs (docs/method.md#data-association)."""
    order = np.argsort(local_map.feature_ids, kind="stable")
    if local_map.covariance is None:
        return blocks(local_map.feature_variances[order])
    rows = 3 + 2 * order[:, None]  # each feature's x row; its [xx, xy, yy] entries in one gather
    return local_map.covariance[rows + _BLOCK_ROWS, rows + _BLOCK_COLUMNS]


def end_relative(local_map: LocalMap) -> tuple[np.ndarray, np.ndarray] | None:
    """Each feature of ``local_map`` relative to its *end pose*, in the end pose's frame (in the order of the sorted
    feature ids): its position ``g = R(-phi) (f - p)`` (complex) and 2 x 2 covariance (rows ``[xx, xy, yy]``), from
    the full covariance of ``[p, phi, f]``; None when the map has no full covariance (the cross terms are unknown).

    The next map's start is this end pose, the join's link, so ``g`` is where the next map should see the feature,
    and this covariance how far it may be off (docs/method.md#data-association, steps 1-2): the feature and the end
    pose share the map's dead reckoning, which the marginal covariance relative to the start (:func:`feature_covariances`)
    and the end pose's own variance count twice over. First order, ``dg = R^T (df - dp) - i g dphi``: per feature
    ``J B J^T`` with ``B`` its 5 x 5 block of ``[x, y, phi, f_x, f_y]`` and ``J = [-R^T, -i g, R^T]``, all at once."""
    if local_map.covariance is None:
        return None
    order = np.argsort(local_map.feature_ids, kind="stable")
    x, y, phi = local_map.end_pose
    c, s = np.cos(phi), np.sin(phi)
    g = (local_map.features[order, 0] - x + 1j * (local_map.features[order, 1] - y)) * complex(c, -s)
    index = np.concatenate([np.broadcast_to(np.arange(3), (len(order), 3)), 3 + 2 * order[:, None] + np.arange(2)],
                           axis=1)  # each feature's [x, y, phi, f_x, f_y] rows of the covariance
    block = local_map.covariance[index[:, :, None], index[:, None, :]]
    back = np.array([[c, s], [-s, c]])  # R^T
    jacobian = np.zeros((len(order), 2, 5))
    jacobian[:, :, :2] = -back
    jacobian[:, 0, 2], jacobian[:, 1, 2] = g.imag, -g.real  # -i g
    jacobian[:, :, 3:] = back
    covariance = np.einsum("nai,nij,nbj->nab", jacobian, block, jacobian)
    return g, covariance[:, _BLOCK_ROWS, _BLOCK_COLUMNS]


def _mahalanobis(r: np.ndarray, information: np.ndarray) -> np.ndarray:
    """``r^T W r`` of complex ``r`` and 2 x 2 ``W`` (rows ``[xx, xy, yy]``)."""
    return information[:, 0] * r.real**2 + 2 * information[:, 1] * r.real * r.imag + information[:, 2] * r.imag**2
