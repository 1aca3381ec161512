"""Groups of local maps evaluated together, and the per-map algebra of the exact join.

The derivatives of the exact joining problem (docs/method.md#exact-joining) are evaluated for
a group of maps at once, with no Python loop over maps or features: maps of nearby sizes,
padded with features of zero weight to the largest (:func:`size_classes` chooses the runs of
sizes, balancing the fixed cost of a group against the padding). Each map's residual is
whitened once with the inverse of the lower Cholesky factor of its covariance ``P_k``
(:func:`whitening`), so chi^2 is the sum of squared whitened residuals.

Each map's block of ``J^T J`` is its information matrix with the x/y parts rotated by the
base angle (:func:`own_blocks`), plus the base pose's rows and columns, combinations of the
map's own (:func:`base_blocks`, O(d^2) per map, one matrix-vector product). For maps whose
points are independent (block-diagonal covariances, as raw odometry with its observations
has), only each point's own entries are evaluated (:func:`piece_layout`).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from ..errors import JoinError
from .triangular import lower_inverses

_GROUP_OVERHEAD = 2e4      # entries of a map's block worth one group's Python overhead in the evaluation


@dataclass
class Group:
    """Maps with up to ``m`` features (state dimension ``d = 3 + 2m``), evaluated together:
    a map with fewer is padded with features of zero weight (zero rows and columns of its
    whitening matrix, a spare residual row and unknown), which change nothing.

    Inside a group a map's state is reordered as ``[x of the points, y of the points, phi]``,
    the points being the end pose position then the features, so that every block of the
    Jacobian is a slice. Columns: ``[x of pose k, x of the features, y ..., phi of pose k,
    x, y, phi of the base pose]`` (``w = d + 3``).
    """

    maps: np.ndarray          # (G,) map indices
    base: np.ndarray          # (G,) pose index of the start pose (the map's own pose at the origin)
    has_base: np.ndarray      # (G,) False: the map starts at the origin (zero base columns)
    features: np.ndarray      # (G, m) feature indices
    whitening: np.ndarray     # (G, d, d) inverse lower Cholesky factor of the reordered P_k
    measurement: np.ndarray   # (G, d) reordered state s_k
    rows: np.ndarray          # (G, d) residual rows (map order) of the reordered entries
    columns: np.ndarray       # (G, w) unknowns of the Jacobian block's columns
    nodes: np.ndarray         # (G, m + 2) nodes [pose k, features, base pose]
    coupled: np.ndarray       # (G, m + 2, m + 2) node pairs whose block of J_k^T J_k can be non-zero
    layout: PieceLayout      # which entries of J_k^T J_k are evaluated (see piece_layout)
    rotated: tuple = ()       # parts of P_k^-1 = W^T W, see rotated_information
    block_offset: int = 0     # where the group's J_k^T J_k blocks start in the flat buffer
    gradient_offset: int = 0  # where its J_k^T r_k start



def size_classes(sizes: np.ndarray, independent: np.ndarray) -> list[np.ndarray]:
    """The maps of each group (:class:`Group`): per kind (dense or independent points),
    runs of consecutive sizes padded to the largest, chosen by dynamic programming to
    minimise a fixed cost per group plus the padded work (~w^2 per map)."""
    classes = []
    for kind in (False, True):
        ks = np.flatnonzero(independent == kind)
        if not ks.size:
            continue
        distinct, counts = np.unique(sizes[ks], return_counts=True)
        work = (2.0 * distinct + 6) ** 2
        count = np.concatenate([[0], np.cumsum(counts)])
        best, cut = np.zeros(len(distinct) + 1), np.zeros(len(distinct) + 1, dtype=np.int64)
        for j in range(1, len(distinct) + 1):         # best[j]: the sizes up to distinct[j - 1]
            options = best[:j] + _GROUP_OVERHEAD + (count[j] - count[:j]) * work[j - 1]
            cut[j] = np.argmin(options)
            best[j] = options[cut[j]]
        j, runs = len(distinct), []
        while j:
            runs.append((distinct[cut[j]], distinct[j - 1]))
            j = cut[j]
        classes.extend(ks[(sizes[ks] >= low) & (sizes[ks] <= high)] for low, high in reversed(runs))
    return classes


def independent_points(covariances: np.ndarray) -> np.ndarray:
    """(G,): which blocks' covariances (G, 3 + 2m, 3 + 2m), order [x, y, phi, f1x, f1y, ...],
    correlate no two of their points (the end pose and each feature: block-diagonal)."""
    d = covariances.shape[1]
    point = np.concatenate([[0, 0, 0], np.repeat(np.arange(1, (d - 3) // 2 + 1), 2)])
    across = point[:, None] != point[None, :]
    # a first look at the end pose's x with the features settles most full covariances (all of the 10^4 simulated
    # maps', where looking at all of every covariance took 0.4 s of set-up); only the others are looked at whole
    independent = ~np.any(covariances[:, 0, 3:] != 0, axis=1)
    candidates = np.flatnonzero(independent)
    if candidates.size:
        independent[candidates] = ~np.any(covariances[candidates][:, across] != 0, axis=1)
    return independent


def _block_whitening(stacks: list[tuple[np.ndarray, np.ndarray]], point: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Whitening W (G, d, d) and information W^T W of maps whose points are independent
    (block-diagonal covariances, given by size: ``(which maps, (g, 3 + 2r, 3 + 2r))``), in
    the order [x of the points, y of the points, phi], padding zero: block by block, the
    end pose's 3 x 3 and each feature's 2 x 2, as the full factor would come out."""
    G, p = point.shape
    m = p - 1
    pose, feature = np.empty((G, 3, 3)), np.broadcast_to(np.eye(2), (G, m, 2, 2)).copy()
    for mine, stack in stacks:
        r = (stack.shape[1] - 3) // 2
        pose[mine] = stack[:, :3, :3]
        if r:
            own = np.arange(r)
            feature[mine, :r] = stack[:, 3:, 3:].reshape(-1, r, 2, r, 2)[:, own, :, own, :].transpose(1, 0, 2, 3)
    Wp = _inverse_cholesky(pose)
    Wf = _inverse_cholesky(feature) * point[:, 1:, None, None]
    d = 2 * p + 1
    where_pose = np.array([0, p, 2 * p])
    where_feature = np.stack([np.arange(1, p), p + np.arange(1, p)], axis=1)         # (m, 2): x, y of feature i
    whitening, information = np.zeros((G, d, d)), np.zeros((G, d, d))
    whitening[:, where_pose[:, None], where_pose] = Wp
    whitening[:, where_feature[:, :, None], where_feature[:, None, :]] = Wf
    information[:, where_pose[:, None], where_pose] = np.matmul(Wp.transpose(0, 2, 1), Wp)
    information[:, where_feature[:, :, None], where_feature[:, None, :]] = np.matmul(Wf.transpose(0, 1, 3, 2), Wf)
    return whitening, information


def _inverse_cholesky(covariance: np.ndarray) -> np.ndarray:
    """``W = L^-1`` for the lower Cholesky factors ``L`` of a stack of covariances (W^T W is
    their inverse, W whitens a residual)."""
    try:
        k = covariance.shape[-1]
        return lower_inverses(np.linalg.cholesky(covariance.reshape(-1, k, k))).reshape(covariance.shape)
    except np.linalg.LinAlgError:
        raise JoinError("a local map's covariance is not positive definite") from None


def coupled_nodes(information: np.ndarray, point: np.ndarray, independent: bool) -> np.ndarray:
    """(G, m + 2, m + 2): which node pairs [pose k, features, base] of each map's block of
    J^T J can be non-zero, from the map's information matrix (G, d, d) in the order [x of
    the points, y of the points, phi] and its real (not padding) points (G, m + 1): two of
    its own nodes couple only through a non-zero information entry (``independent``
    points, as raw observations are, couple with themselves only); the base pose couples
    with every real node."""
    G, d, _ = information.shape
    p = (d - 1) // 2
    coupled = np.ones((G, p + 1, p + 1), dtype=bool)
    if independent:
        coupled[:, :p, :p] = np.eye(p, dtype=bool) & point[:, :, None]
    else:
        magnitude = np.abs(information)
        xy = magnitude[:, :2 * p, :2 * p].reshape(G, 2, p, 2, p).sum(axis=(1, 3))      # point by point
        xy[:, 0, :] += magnitude[:, 2 * p, :2 * p].reshape(G, 2, p).sum(axis=1)        # phi is pose k's
        xy[:, :, 0] += magnitude[:, :2 * p, 2 * p].reshape(G, 2, p).sum(axis=1)
        coupled[:, :p, :p] = xy > 0
    coupled[:, :p, p] = coupled[:, p, :p] = point
    return coupled


class PieceLayout(NamedTuple):
    """Which entries of a map's block of J^T J are evaluated, among its columns ``[x of the p
    points, y ..., phi, base x, y, phi]``: ``pairs`` (i >= j) of points whose x/x and y/y
    entries, ``cross`` (i, j) whose x_i/y_j entries; the pieces' ``shapes`` per map and the
    local (row, column) of every entry, in layout order (see :func:`pieces`)."""

    pairs: tuple[np.ndarray, np.ndarray]
    cross: tuple[np.ndarray, np.ndarray]
    shapes: tuple[tuple[int, ...], ...]
    rows: np.ndarray
    cols: np.ndarray


@functools.lru_cache(maxsize=512)
def piece_layout(p: int, independent: bool) -> PieceLayout:
    """The layout of maps with ``p`` points: every pair of points, or with ``independent``
    points (no information between two of them, as raw observations have) each point with itself."""
    if independent:
        pairs = cross = (np.arange(p), np.arange(p))
    else:
        pairs, cross = np.tril_indices(p), (np.repeat(np.arange(p), p), np.tile(np.arange(p), p))
    d = 2 * p + 1
    a, b = np.tril_indices(3)
    points = np.arange(p)
    rows = [pairs[0], p + pairs[0], cross[0], points, p + points, [2 * p], np.tile(np.arange(d), 3), d + a]
    cols = [pairs[1], p + pairs[1], p + cross[1], np.full(p, 2 * p), np.full(p, 2 * p), [2 * p],
            np.repeat(d + np.arange(3), d), d + b]
    shapes = ((len(pairs[0]),), (len(pairs[0]),), (len(cross[0]),), (p,), (p,), (), (3, d), (6,))
    return PieceLayout(pairs, cross, shapes, np.concatenate(rows).astype(np.intp),
                        np.concatenate(cols).astype(np.intp))


def pieces(buffer: np.ndarray, group: Group) -> list[np.ndarray]:
    """Views into the flat buffer of a group's ``G`` maps, one entry per evaluated unordered
    pair of columns: x/x and y/y over the layout's pairs, x/y over its cross pairs, x/phi,
    y/phi (G, p), phi/phi (G,), own/base (G, 3, d: base column a, own row i) and the
    base/base lower triangle (G, 6), laid out in this order (see :func:`piece_layout`)."""
    G = len(group.maps)
    views, offset = [], group.block_offset
    for shape in group.layout.shapes:
        size = G * math.prod(shape)
        views.append(buffer[offset:offset + size].reshape((G,) + shape))
        offset += size
    return views


def entries(rows: np.ndarray, cols: np.ndarray, node_of: np.ndarray, offset_of: np.ndarray, placed: np.ndarray,
             full: np.ndarray, csc: tuple) -> np.ndarray:
    """(G, pairs): CSC index of the entry on or below the diagonal of J^T J of each pair (row,
    column) of a group's columns (``node_of``, ``offset_of``: each column's node among the map's
    and scalar within it; ``placed``: the nodes' positions (G, nodes); ``full[g, a, b]``: the
    node entry of column node a, row node b, -1 if uncoupled, whose pairs go to a spare slot
    past the end). Found node pair by node pair: with ``csc = (column_start, col_length,
    row_offset, spare)``, node entry t (column node C, row node below it) holds scalar (i, j) at
    ``column_start[C] + j * col_length[C] + row_offset[t] + i``."""
    column_start, col_length, row_offset, spare = csc
    m2 = full.shape[1]
    a, b, i, j = node_of[rows], node_of[cols], offset_of[rows], offset_of[cols]
    i, j = np.where(a == b, np.maximum(i, j), i), np.where(a == b, np.minimum(i, j), j)   # one node: its lower half
    pairs, pair = np.unique(a * m2 + b, return_inverse=True)
    a, b = pairs // m2, pairs % m2
    lower = placed[:, a] >= placed[:, b]                      # (G, node pairs): row node a at or below b
    t = np.where(lower, full[:, b, a], full[:, a, b])
    C = np.where(lower, placed[:, b], placed[:, a])
    first = np.where(t >= 0, column_start[C] + row_offset[t], spare)
    stride = np.where(t >= 0, col_length[C], 0)
    lower, first, stride = lower[:, pair], first[:, pair], stride[:, pair]
    return first + np.where(lower, j * stride + i, i * stride + j) * (stride > 0)


def state_order(m: int) -> np.ndarray:
    """Where each entry of a group's reordered state ``[x of the points, y of the points, phi]``
    (points: the end pose position, then ``m`` features) sits in a map's state ``[x, y, phi,
    f1x, f1y, ...]``."""
    return np.concatenate([[0], 3 + 2 * np.arange(m), [1], 4 + 2 * np.arange(m), [2]])


def whitening(stacks: list[tuple[np.ndarray, np.ndarray]], point: np.ndarray, independent: bool
              ) -> tuple[np.ndarray, np.ndarray]:
    """Whitening W (G, d, d) and information ``P_k^-1 = W^T W`` of a group's maps in the
    reordered state (:func:`state_order`), padding zero, from their covariances by size
    (``(which maps, (g, 3 + 2r, 3 + 2r))``); ``point`` (G, m + 1): which points are real.
    ``independent`` points: block by block (:func:`_block_whitening`)."""
    if independent:
        return _block_whitening(stacks, point)
    G, p = point.shape
    m = p - 1
    entry = np.concatenate([point, point, np.ones((G, 1), dtype=bool)], axis=1)
    local = state_order(m)
    covariance = np.zeros((G, 3 + 2 * m, 3 + 2 * m))
    for mine, stack in stacks:
        covariance[mine, :stack.shape[1], :stack.shape[1]] = stack
    real = point.sum(axis=1) - 1
    diagonal = np.arange(3 + 2 * m)
    covariance[:, diagonal, diagonal] += diagonal >= 3 + 2 * real[:, None]     # padding: unit variances
    # the padding is uncorrelated, so the real part of W is that of the map alone; zero the rest
    W = _inverse_cholesky(covariance[:, local[:, None], local])
    W *= entry[:, :, None] & entry[:, None, :]
    return W, np.matmul(W.transpose(0, 2, 1), W)


def rotated_information(information: np.ndarray, layout: PieceLayout) -> tuple[np.ndarray, ...]:
    """The fixed parts of a group's information matrices (G, d, d) that :func:`own_blocks` and
    :func:`base_blocks` rotate by the base angle: over the layout's pairs ``T`` (the x/x and
    y/y mean), ``D`` (their half difference), ``A`` (the x/y mean), over its cross pairs ``D``
    and ``A`` again and ``K`` (the x/y half difference), then the x/phi, y/phi and phi/phi
    parts, and the matrix's rows summed over the x's and over the y's. Not the whole matrix:
    :func:`base_blocks` multiplies by it as ``W^T (W v)``, and a group's whitening W is kept
    anyway (at 10^4 maps the matrices would hold another 150 MB)."""
    p = (information.shape[1] - 1) // 2
    (pi, pj), (ci, cj) = layout.pairs, layout.cross
    Lxy, Lyx = information[:, ci, p + cj], information[:, p + ci, cj]
    return ((information[:, pi, pj] + information[:, p + pi, p + pj]) / 2,
            (information[:, pi, pj] - information[:, p + pi, p + pj]) / 2,
            (information[:, pi, p + pj] + information[:, p + pi, pj]) / 2,
            (information[:, ci, cj] - information[:, p + ci, p + cj]) / 2, (Lxy + Lyx) / 2, (Lxy - Lyx) / 2,
            information[:, :p, 2 * p].copy(), information[:, p:2 * p, 2 * p].copy(),
            information[:, 2 * p, 2 * p].copy(),
            information[:, :, :p].sum(axis=2), information[:, :, p:2 * p].sum(axis=2))


# ---- per-map blocks of J^T J and J^T r (see ExactProblem.linearise) ------------------------


def own_blocks(group: Group, c: np.ndarray, s: np.ndarray, views: list[np.ndarray]) -> None:
    """Fill the own columns' block ``B^T Lambda B`` (B: the rotation by the base angle theta,
    ``c``, ``s`` its cosine and sine (G, 1)): ``T +- (cos 2theta D - sin 2theta A)`` for x/x
    and y/y, ``K + sin 2theta D + cos 2theta A`` for x/y, the x/phi and y/phi parts rotated."""
    Ttri, Dtri, Atri, D, A, K, Lxphi, Lyphi, Lphiphi, *_ = group.rotated
    xx, yy, xy, xphi, yphi, phiphi, *_ = views
    c2 = c * c - s * s
    s2 = 2 * c * s
    Q = c2 * Dtri
    Q -= s2 * Atri
    np.add(Ttri, Q, out=xx)
    np.subtract(Ttri, Q, out=yy)
    np.multiply(s2, D, out=xy)
    xy += c2 * A
    xy += K
    np.multiply(c, Lxphi, out=xphi)
    xphi -= s * Lyphi
    np.multiply(s, Lxphi, out=yphi)
    yphi += c * Lyphi
    phiphi[...] = Lphiphi


def base_blocks(group: Group, c: np.ndarray, s: np.ndarray, lx: np.ndarray, ly: np.ndarray,
                views: list[np.ndarray]) -> np.ndarray:
    """Fill the base pose's blocks: with ``v_a`` the change of the predicted state when the
    base moves along x, y or turns (``(-c, s, 0)``, ``(-s, -c, 0)``, ``(ly, -lx, -1)`` for the
    x's, y's and phi; ``lx``, ``ly`` the points in the base frame) and ``u_a = Lambda v_a``,
    own/base ``B^T u_a`` and base/base ``v_a . u_b``. Returns ``v_phi`` (G, d)."""
    *_, rsx, rsy = group.rotated
    *_, mc, cmc = views
    W = group.whitening
    G, d = W.shape[:2]
    p = (d - 1) // 2
    base = group.has_base.astype(float)[:, None]
    v = np.concatenate([ly, -lx, -np.ones((G, 1))], axis=1)
    u = np.empty((G, 3, d))
    np.multiply(s * rsy - c * rsx, base, out=u[:, 0])
    np.multiply(-(s * rsx + c * rsy), base, out=u[:, 1])
    Lambda_v = np.matmul(W.transpose(0, 2, 1), np.matmul(W, v[:, :, None]))[:, :, 0]   # W^T (W v)
    np.multiply(Lambda_v, base, out=u[:, 2])
    ux, uy = u[:, :, :p], u[:, :, p:2 * p]
    cb, sb = c[:, :, None], s[:, :, None]
    np.multiply(cb, ux, out=mc[:, :, :p])
    mc[:, :, :p] -= sb * uy
    np.multiply(sb, ux, out=mc[:, :, p:2 * p])
    mc[:, :, p:2 * p] += cb * uy
    mc[:, :, 2 * p] = u[:, :, 2 * p]
    sx, sy = ux.sum(axis=2), uy.sum(axis=2)                      # (G, 3)
    tx = s * sy - c * sx                                          # v_tx . u_a
    ty = -(s * sx + c * sy)                                       # v_ty . u_a
    tphi = np.einsum("gad,gd->ga", u, v)                          # v_phi . u_a
    cmc[:, 0], cmc[:, 1], cmc[:, 2] = tx[:, 0], ty[:, 0], ty[:, 1]
    cmc[:, 3], cmc[:, 4], cmc[:, 5] = tphi[:, 0], tphi[:, 1], tphi[:, 2]
    return v


def gradient(group: Group, c: np.ndarray, s: np.ndarray, mu: np.ndarray, v: np.ndarray, g: np.ndarray) -> None:
    """Fill ``g`` (G, w) with J^T r: ``-B^T mu`` for the own columns, ``-v_a . mu`` for the
    base (``mu = W^T r = P^-1 e``, ``v`` from :func:`base_blocks`)."""
    d = mu.shape[1]
    p = (d - 1) // 2
    mx, my = mu[:, :p], mu[:, p:2 * p]
    g[:, :p] = s * my - c * mx
    g[:, p:2 * p] = -(s * mx + c * my)
    g[:, 2 * p] = -mu[:, 2 * p]
    smx, smy = mx.sum(axis=1), my.sum(axis=1)
    b = group.has_base
    g[:, d] = (c[:, 0] * smx - s[:, 0] * smy) * b
    g[:, d + 1] = (s[:, 0] * smx + c[:, 0] * smy) * b
    g[:, d + 2] = -np.einsum("gd,gd->g", v, mu) * b


def curvature(group: Group, c: np.ndarray, s: np.ndarray, lx: np.ndarray, ly: np.ndarray,
              mu: np.ndarray) -> np.ndarray:
    """The second-order term ``-sum_j mu_j d^2 H_j`` (G, w): only in the row and column of the
    base angle, this row."""
    G, d = mu.shape
    p = (d - 1) // 2
    mx, my = mu[:, :p], mu[:, p:2 * p]
    h = np.empty((G, d + 3))
    h[:, :p] = s * mx + c * my
    h[:, p:2 * p] = s * my - c * mx
    h[:, 2 * p] = 0.0
    h[:, d] = -h[:, :p].sum(axis=1)
    h[:, d + 1] = -h[:, p:2 * p].sum(axis=1)
    h[:, d + 2] = np.einsum("gp,gp->g", mx, lx) + np.einsum("gp,gp->g", my, ly)
    h *= group.has_base.astype(float)[:, None]
    return h
