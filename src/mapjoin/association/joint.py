"""Step 4 of data association: joint compatibility (docs/method.md#data-association).

A join's pairs share the link's error, so they are tested together: the joint Mahalanobis distance of all their
innovations (covariance ``blockdiag(s (C0 + C1)) + H P_link H^T``, evaluated in 3-D by the Woodbury identity:
:func:`_joint_terms`, :func:`_joint_distances`) must be within the ``gate`` quantile of a chi-square with ``2k``
degrees of freedom. The joins of a tree level are tested at once (:func:`_joint_test`); a join that fails keeps its
largest jointly compatible subset (:func:`_jointly_compatible`: every subset at once when at most
:data:`EXHAUSTIVE_PAIRS` pairs remain, after removing the worst pair one at a time while more remain).
"""

from __future__ import annotations

import numpy as np

from .covariance_blocks import _mahalanobis
from .gate import _threshold

__all__ = ["EXHAUSTIVE_PAIRS"]

#: the joint test searches every subset of at most this many pairs (2^10 = 1024 subsets, as arrays)
EXHAUSTIVE_PAIRS = 10


def _joint_terms(r: np.ndarray, w: np.ndarray, u: np.ndarray, linked: np.ndarray | None = None
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each pair's share of the joint test, ``W`` its innovation's information without the link (k x 3, rows
    ``[xx, xy, yy]``): ``r^T W r``, ``H^T W r`` (k x 3) and ``H^T W H`` (k x 9), ``H = [I, u]`` (complex ``r``, ``u``);
    ``H = 0`` where ``linked`` (a mask; None: every pair) is false: a pair compared in the link's own frame
    (:mod:`mapjoin.association.link_frame`), which no link error moves."""
    wxx, wxy, wyy = w.T
    ux, uy = u.real, u.imag
    g, h = np.empty((len(r), 3)), np.empty((len(r), 9))  # filled by columns (fewer calls than stacking)
    g[:, 0] = qx = wxx * r.real + wxy * r.imag  # W r
    g[:, 1] = qy = wxy * r.real + wyy * r.imag
    g[:, 2] = ux * qx + uy * qy
    h[:, 2] = h[:, 6] = px = wxx * ux + wxy * uy  # W u
    h[:, 5] = h[:, 7] = py = wxy * ux + wyy * uy
    h[:, 0], h[:, 1], h[:, 3], h[:, 4], h[:, 8] = wxx, wxy, wxy, wyy, ux * px + uy * py
    c = r.real * qx + r.imag * qy
    if linked is not None:
        g *= linked[:, None]
        h *= linked[:, None]
    return c, g, h


def _joint_distances(masks: np.ndarray, terms, link_information: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The joint Mahalanobis distance of each subset of pairs (``masks``, s x k, 0/1) and the link correction
    that explains it best: ``D^2 = sum r^T W r - g^T M^-1 g`` with ``g = sum H^T W r``, ``M = P_link^-1 + sum
    H^T W H`` (Woodbury: the pairs' covariance ``blockdiag(W^-1) + H P_link H^T`` inverted through the 3-D link)."""
    c, g, h = terms
    big_g = masks @ g
    big_m = (masks @ h).reshape(-1, 3, 3) + link_information
    correction = _solved(big_m, big_g)
    return masks @ c - np.einsum("si,si->s", big_g, correction), correction


def _solved(big_m: np.ndarray, big_g: np.ndarray) -> np.ndarray:
    """``M^-1 g`` for each stack of 3 x 3 ``M`` and 3-vector ``g``; NaN where ``M`` is singular to rounding (variances
    many orders apart, a heading variance carried far: what the boundary accepts). Such a set of pairs cannot be
    tested, so it is never compatible: its features stay new, as the gate leaves a pair whose ``S`` is singular."""
    try:
        return np.linalg.solve(big_m, big_g[..., None])[..., 0]
    except np.linalg.LinAlgError:  # rare: find the singular ones (a loop over the joins, only on this path)
        correction = np.full(big_g.shape, np.nan)
        for k in range(len(big_m)):
            try:
                correction[k] = np.linalg.solve(big_m[k], big_g[k])
            except np.linalg.LinAlgError:
                pass
        return correction


def _jointly_compatible(terms, r: np.ndarray, w: np.ndarray, u: np.ndarray, link_information: np.ndarray,
                        gate: float, linked: np.ndarray | bool = True) -> np.ndarray:
    """The pairs kept by the joint compatibility test (a boolean mask over the k pairs, whose
    :func:`_joint_terms` are ``terms``, ``linked`` as there): all of them when compatible, else the largest compatible
    subset (ties: the smallest joint distance)."""
    k = len(r)
    keep = np.ones(k, dtype=bool)
    if not k:
        return keep
    c, g, h = terms
    while True:  # remove the worst pair while too many remain for the exhaustive search
        distance, correction = _joint_distances(keep[None].astype(float), terms, link_information)
        if distance[0] <= _threshold(gate, int(keep.sum())):
            return keep
        if keep.sum() <= EXHAUSTIVE_PAIRS:
            break
        dx, dy, dphi = correction[0]
        residual = _mahalanobis(r - linked * ((dx + 1j * dy) + u * dphi), w)
        keep[np.flatnonzero(keep)[np.argmax(residual[keep])]] = False
    rows = np.flatnonzero(keep)
    count = len(rows)
    masks = ((np.arange(1, 2**count)[:, None] >> np.arange(count)) & 1).astype(float)  # every non-empty subset
    sub = (c[rows], g[rows], h[rows])
    distance, _ = _joint_distances(masks, sub, link_information)
    sizes = masks.sum(axis=1)
    compatible = distance <= _threshold(gate, sizes.astype(np.intp))
    keep[:] = False
    if compatible.any():
        best = np.lexsort((distance, -sizes, ~compatible))[0]
        keep[rows[masks[best] > 0]] = True
    return keep


def _segment_sums(values: np.ndarray, group: np.ndarray, count: int) -> np.ndarray:
    """Sums of the rows of ``values`` (p x c) by ``group`` (count x c)."""
    if count == 1:
        return values.sum(axis=0)[None]
    return np.stack([np.bincount(group, values[:, column], minlength=count) for column in range(values.shape[1])],
                    axis=1)


def _joint_test(terms, r: np.ndarray, w: np.ndarray, u: np.ndarray, pair_join: np.ndarray,
                information: np.ndarray, gate: float, joins: int, linked: np.ndarray | None = None
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The pairs kept by the joint compatibility test of every join (a mask over the pairs, grouped by join; ``linked``
    as :func:`_joint_terms`'s):
    each join's joint distance at once; a join that fails is searched alone by :func:`_jointly_compatible`.
    Also each join's ``sum H^T W r`` (joins x 3) and ``P_link^-1 + sum H^T W H`` (joins x 3 x 3) over all its
    pairs: the link's correction when every pair is kept."""
    c, g, h = terms
    sizes = np.bincount(pair_join, minlength=joins)
    big_g = _segment_sums(g, pair_join, joins)
    big_m = _segment_sums(h, pair_join, joins).reshape(joins, 3, 3) + information
    distance = np.bincount(pair_join, c, minlength=joins) - np.einsum("ji,ji->j", big_g, _solved(big_m, big_g))
    keep = np.ones(len(r), dtype=bool)
    failing = (sizes > 0) & ~(distance <= _threshold(gate, sizes))  # NaN (singular M) fails
    if not failing.any():  # mostly every join's pairs are compatible
        return keep, big_g, big_m
    starts = np.cumsum(sizes) - sizes
    for failed in np.flatnonzero(failing).tolist():
        rows = slice(starts[failed], starts[failed] + sizes[failed])
        keep[rows] = _jointly_compatible((c[rows], g[rows], h[rows]), r[rows], w[rows], u[rows],
                                         information[failed], gate, True if linked is None else linked[rows])
    return keep, big_g, big_m
