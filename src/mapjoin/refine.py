"""Exact least-squares map joining (the problem I-SLSJF solves): sparse Gauss-Newton.

Problem (method.md, "Exact joining")::

    min_X  sum_k  e_k^T P_k^-1 e_k,    e_k = s_k - H_k(X)   (angle entry wrapped to [-pi, pi))

The unknowns ``X`` are the global end poses of all maps (pose ids = the maps' ``end_id``)
and the global positions of all features; the chain's first start pose is the fixed
origin. ``H_k`` expresses map k's end pose and the features it saw in the frame of the
global pose ``start_id`` of map k (the origin for the first map): the end pose as
``(R(phi_b)^T (t_k - t_b), phi_k - phi_b)`` and each feature as ``R(phi_b)^T (f - t_b)``.
``P_k`` is the map's full covariance, or for a map without one the diagonal of its
spherical variances. Each map's residual is whitened once and for all with the inverse of
the lower Cholesky factor of ``P_k``, so the cost is chi^2, the sum of squared whitened
residuals.

Solver (:func:`refine`): Gauss-Newton with safeguards: an overshooting step is first
halved (a line search along it), then Levenberg-Marquardt damping (Marquardt's ``lambda
diag(J^T J)``, steps accepted only if they lower the cost, lambda adapted by the gain ratio
as in Nielsen's rule) takes over; it switches to Newton's method (the exact Hessian:
``J^T J`` plus the second-order term, which only touches the base angles) once steps are
good, for quadratic convergence; started from the fast sequential join. The damping alone
would cut the directions ``J^T J`` hardly constrains (long chains of maps) by orders of
magnitude and creep; the halving keeps Gauss-Newton's direction.

Normal equations (:class:`ExactProblem`): analytic derivatives for a group of maps at
once (no Python loop over maps or features): maps of nearby sizes, padded with features
of zero weight to the largest (the runs of sizes chosen to balance the fixed cost of a
group against the padding). Each map's block of ``J^T J`` is its information matrix with
the x/y parts rotated by the base angle, plus the base pose's rows and columns, which are
combinations of the map's own (O(d^2) per map, one matrix-vector product); the blocks'
lower triangles go into the fixed sparse pattern of ``J^T J`` with one ``bincount``. For
blocks whose points are independent (block-diagonal covariances, as raw odometry with its
observations has), only each point's own entries are evaluated. That pattern is kept in a
fill-reducing order computed once: multiple minimum degree (SuperLU's) on the graph of
poses and features, then re-postordered so that supernodes chain. The normal equations
are factorised by SuperLU in symmetric mode, without pivoting (the matrix is positive
definite): ``J^T J = L D L^T``.

Marginal covariances (:meth:`ExactProblem.marginals`): the diagonal blocks of
``(J^T J)^-1`` at the optimum by supernodal selected inversion (Takahashi's recursion)
on that factor: only the entries of the inverse on the sparsity pattern of L (closed
under elimination) are computed, top-down along the supernodal elimination tree, never
the whole inverse.
"""

from __future__ import annotations

import functools
import itertools
import logging
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import scipy.linalg
import scipy.sparse as sp
from scipy.sparse.linalg import splu

from .errors import JoinError
from .joining import join_sequential
from .maps import GlobalMap, LocalMap, Provenance, locate
from .se2 import wrap

__all__ = ["TOLERANCE", "Blocks", "ExactProblem", "Minimum", "RefineResult", "exact_cost", "minimise", "refine"]

log = logging.getLogger("mapjoin")

_SUPERLU = {"diag_pivot_thresh": 0.0, "options": {"SymmetricMode": True}}
#: default stopping tolerance: relative chi^2 change, and step size relative to (1 + largest |unknown|);
#: 1e-12 puts the solution within ~1e-7 m of the optimum on the real datasets from either fast join
TOLERANCE = 1e-12
_MAX_DAMPING = 1e16  # Marquardt lambda at which the solver gives up looking for a decrease
_HALVINGS = 10       # an overshooting Gauss-Newton step is tried at 1/2 ... 1/2^10 of its length before damping
_SUPERNODE_OVERHEAD = 5e4  # flops worth one supernode's Python overhead in the selected inversion
_GROUP_OVERHEAD = 2e4      # entries of a map's block worth one group's Python overhead in the evaluation
_TRTRI = scipy.linalg.lapack.get_lapack_funcs("trtri", (np.zeros(1),))


@dataclass(frozen=True)
class RefineResult:
    """The exact join and how it was found.

    ``global_map``: poses and features at the optimum; with covariances, its
    ``feature_covariances`` (n, 2, 2) and ``pose_covariances`` (p, 3, 3) are the marginal
    blocks of ``(J^T J)^-1`` and its spherical variances their summary (half the trace of
    the x/y block, the orientation variance as is); without, the variances of the
    initial map are kept. ``cost``: chi^2 at the optimum. ``costs``: chi^2 before the
    first iteration and after each accepted one (decreasing; the last may rise by rounding,
    see :func:`minimise`). ``seconds``: time of the solve (problem
    set-up and iterations; neither the initial join nor the covariances),
    ``covariance_seconds``: time of the marginal covariances, ``initial_seconds``: time of
    the sequential join that gave the initial value (0 when one was given).
    ``gradient_norm``: max |J^T r| at the optimum (r whitened residuals). ``rejected``:
    steps computed but not taken (they did not lower chi^2, or a Newton step was no descent).
    """

    global_map: GlobalMap
    cost: float
    costs: tuple[float, ...]
    iterations: int
    converged: bool
    reason: str
    seconds: float
    covariance_seconds: float = 0.0
    initial_seconds: float = 0.0
    residuals: int = 0
    unknowns: int = 0
    gradient_norm: float = math.nan
    rejected: int = 0

    @property
    def degrees_of_freedom(self) -> int:
        """Residuals minus unknowns: the expected value of chi^2 at the optimum."""
        return self.residuals - self.unknowns


@dataclass
class _Group:
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
    layout: _PieceLayout      # which entries of J_k^T J_k are evaluated (see _piece_layout)
    rotated: tuple = ()       # parts of P_k^-1 = W^T W, see ExactProblem.linearise
    block_offset: int = 0     # where the group's J_k^T J_k blocks start in the flat buffer
    gradient_offset: int = 0  # where its J_k^T r_k start


@dataclass(frozen=True)
class Blocks:
    """Measurement blocks in the shape of local maps, as flat arrays (no LocalMap per block).

    Block k measures, in the frame of pose ``start_ids[k]``, the pose ``end_ids[k]`` and
    ``sizes[k]`` distinct features: with ``o`` the sum of the sizes before k, the features
    ``feature_ids[o:o + sizes[k]]``, measured as ``[end_poses[k], features[o:o +
    sizes[k]].ravel()]``. ``covariances(ks)`` gives the covariances of blocks ``ks`` (all of
    one size), stacked (G, 3 + 2m, 3 + 2m) in the order [x, y, phi, f1x, f1y, ...], and
    ``names(k)`` names block k in messages. A local map is one block; raw odometry with the
    observations made from its start pose is another (:mod:`mapjoin.build`).
    """

    start_ids: np.ndarray
    end_ids: np.ndarray
    end_poses: np.ndarray
    sizes: np.ndarray
    feature_ids: np.ndarray
    features: np.ndarray
    covariances: Callable[[np.ndarray], np.ndarray]
    names: Callable[[int], str]

    @classmethod
    def of_maps(cls, maps: Sequence[LocalMap]) -> Blocks:
        """One block per local map (a map without a full covariance: its spherical variances)."""
        def stacked(ks: np.ndarray) -> np.ndarray:
            return np.stack([_covariance(maps[k]) for k in ks])

        return cls(start_ids=np.array([m.start_id for m in maps], dtype=np.int64),
                   end_ids=np.array([m.end_id for m in maps], dtype=np.int64),
                   end_poses=np.array([m.end_pose for m in maps], dtype=float).reshape(-1, 3),
                   sizes=np.array([m.size for m in maps], dtype=np.int64),
                   feature_ids=np.concatenate([m.feature_ids for m in maps]),
                   features=np.concatenate([m.features for m in maps]),
                   covariances=stacked, names=lambda k: maps[k].name)


class ExactProblem:
    """The exact joining problem of a chain of local maps: residuals, Jacobian, normal equations.

    Unknowns ``x = [poses (N x 3, map order), features (n x 2, ascending id)]``; the
    whitened residual vector holds each map's ``3 + 2m`` entries in map order. A node is a
    pose (3 unknowns) or a feature (2); J^T J is kept in a fill-reducing node order
    (``position[i]``: row/column of unknown i), as a CSC matrix of fixed pattern.

    ``measurements``: the local maps, or :class:`Blocks` of the same shape. ``origins``: the
    pose ids held fixed at the origin (default: the first map's start). Maps starting at
    different origins make independent problems, solved together.
    """

    def __init__(self, measurements: Sequence[LocalMap] | Blocks, origins: Sequence[int] | None = None):
        if not isinstance(measurements, Blocks):
            measurements = list(measurements)
            if not measurements:
                raise JoinError("no local maps to join")
            measurements = Blocks.of_maps(measurements)
        blocks = measurements
        self.n_maps = N = len(blocks.end_ids)
        if not N:
            raise JoinError("no local maps to join")
        self.pose_ids = np.asarray(blocks.end_ids, dtype=np.int64)
        origins = np.array([blocks.start_ids[0]] if origins is None else origins, dtype=np.int64)
        order = np.argsort(self.pose_ids, kind="stable")
        ordered = self.pose_ids[order]
        twice = np.flatnonzero(ordered[1:] == ordered[:-1])
        if twice.size:
            raise JoinError(f"pose {ordered[twice[0]]} is the end pose of more than one map")
        starts = np.asarray(blocks.start_ids, dtype=np.int64)
        base, found = locate(self.pose_ids, starts, order)    # the map ending where each map starts
        at_origin = np.isin(starts, origins)
        clash = np.flatnonzero(at_origin & found)
        if clash.size:
            k = int(clash[0])
            raise JoinError(f"pose {starts[k]}, the start of {blocks.names(k)} and a fixed origin, "
                            f"is also the end pose of {blocks.names(int(base[k]))}")
        loose = np.flatnonzero(~at_origin & ~found)
        if loose.size:
            k = int(loose[0])
            where = f"pose {origins[0]}" if len(origins) == 1 else f"poses {', '.join(map(str, origins[:5]))}"
            raise JoinError(f"{blocks.names(k)} starts at pose {starts[k]}, which is neither the origin "
                            f"({where}) nor the end pose of any map")
        base = np.where(at_origin, -1, base)
        sizes = np.asarray(blocks.sizes, dtype=np.int64)
        self.feature_ids, compact = np.unique(blocks.feature_ids, return_inverse=True)
        compact = compact.ravel()
        self.n_features = n = len(self.feature_ids)
        self.n_unknowns = 3 * N + 2 * n
        self.row0 = np.concatenate([[0], np.cumsum(3 + 2 * sizes)])
        self.n_residuals = int(self.row0[-1])
        feature0 = np.concatenate([[0], np.cumsum(sizes)])
        measurement = np.zeros(self.n_residuals + 1)     # a spare last row for the padding of groups
        measurement[self.row0[:-1, None] + np.arange(3)] = blocks.end_poses
        owner = np.repeat(np.arange(N), sizes)
        first_row = self.row0[owner] + 3 + 2 * (np.arange(len(owner)) - feature0[owner])
        measurement[first_row[:, None] + np.arange(2)] = blocks.features

        covariances, independent = {}, np.zeros(N, dtype=bool)
        for m in np.unique(sizes).tolist():
            ks = np.flatnonzero(sizes == m)
            covariances[m] = ks, np.asarray(blocks.covariances(ks), dtype=float)
            independent[ks] = _independent(covariances[m][1])
        self.groups: list[_Group] = []
        for ks in _classes(sizes, independent):
            G, real, m = len(ks), sizes[ks], int(sizes[ks].max())
            p = m + 1
            point = np.arange(p) <= real[:, None]                   # real points (the rest is padding)
            entry = np.concatenate([point, point, np.ones((G, 1), dtype=bool)], axis=1)
            local = np.concatenate([[0], 3 + 2 * np.arange(m), [1], 4 + 2 * np.arange(m), [2]])
            stacks = []                                             # (which maps, their covariances) by size
            for r in np.unique(real).tolist():
                members, stack = covariances[r]
                mine = real == r
                stacks.append((mine, stack[np.searchsorted(members, ks[mine])]))
            layout = _piece_layout(p, bool(independent[ks[0]]))
            if independent[ks[0]]:
                whitening, information = _block_whitening(stacks, point)
            else:
                covariance = np.zeros((G, 3 + 2 * m, 3 + 2 * m))
                for mine, stack in stacks:
                    covariance[mine, :stack.shape[1], :stack.shape[1]] = stack
                diagonal = np.arange(3 + 2 * m)
                covariance[:, diagonal, diagonal] += diagonal >= 3 + 2 * real[:, None]     # padding: unit variances
                # the padding is uncorrelated, so the real part of W is that of the map alone; zero the rest
                whitening = _inverse_cholesky(covariance[:, local[:, None], local])
                whitening *= entry[:, :, None] & entry[:, None, :]
                information = np.matmul(whitening.transpose(0, 2, 1), whitening)
            (pi, pj), (ci, cj) = layout.pairs, layout.cross
            Lxy, Lyx = information[:, ci, p + cj], information[:, p + ci, cj]
            rotated = ((information[:, pi, pj] + information[:, p + pi, p + pj]) / 2,
                       (information[:, pi, pj] - information[:, p + pi, p + pj]) / 2,
                       (information[:, pi, p + pj] + information[:, p + pi, pj]) / 2,
                       (information[:, ci, cj] - information[:, p + ci, p + cj]) / 2, (Lxy + Lyx) / 2, (Lxy - Lyx) / 2,
                       information[:, :p, 2 * p].copy(), information[:, p:2 * p, 2 * p].copy(),
                       information[:, 2 * p, 2 * p].copy(),
                       information, information[:, :, :p].sum(axis=2), information[:, :, p:2 * p].sum(axis=2))
            has_base = base[ks] >= 0
            b = np.where(has_base, base[ks], ks)
            feature = point[:, 1:]
            fidx = np.where(feature, compact[np.where(feature, feature0[ks][:, None] + np.arange(m), 0)], 0)
            fx = np.where(feature, 3 * N + 2 * fidx, self.n_unknowns)     # padding: a spare unknown
            fy = np.where(feature, fx + 1, fx)
            pose = 3 * ks[:, None]
            columns = np.concatenate([pose, fx, pose + 1, fy, pose + 2, 3 * b[:, None] + np.arange(3)], axis=1)
            nodes = np.concatenate([ks[:, None], N + fidx, b[:, None]], axis=1)
            rows = np.where(entry, self.row0[ks][:, None] + local, self.n_residuals)
            coupled = _coupled(information, point, independent[ks[0]])
            coupled[~has_base, -1, :] = coupled[~has_base, :, -1] = False    # no base: its columns are zero
            self.groups.append(_Group(ks, b, has_base, fidx, whitening, measurement[rows], rows, columns, nodes,
                                      coupled, layout, rotated))
        self._position = None
        self._evaluated: tuple[np.ndarray, list] | None = None

    # ---- packing ----------------------------------------------------------------------

    def pack(self, global_map: GlobalMap) -> np.ndarray:
        """The unknowns as held by ``global_map`` (which must hold every pose and feature)."""
        poses = _lookup(global_map.pose_ids, global_map.poses, self.pose_ids, "pose", global_map.name)
        features = _lookup(global_map.feature_ids, global_map.features, self.feature_ids, "feature",
                           global_map.name)
        return np.concatenate([poses.ravel(), features.ravel()])

    def unpack(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(poses (N, 3) with angles wrapped to [-pi, pi), features (n, 2))`` of ``x``."""
        poses = np.array(x[:3 * self.n_maps], dtype=float).reshape(-1, 3)
        poses[:, 2] = wrap(poses[:, 2])
        return poses, np.array(x[3 * self.n_maps:], dtype=float).reshape(-1, 2)

    # ---- evaluation ---------------------------------------------------------------------

    def _geometry(self, group: _Group, x: np.ndarray):
        """Base pose, its rotation and the points (end pose position, features) in its frame."""
        N = self.n_maps
        poses = x[:3 * N].reshape(N, 3)
        features = x[3 * N:].reshape(-1, 2)
        bp = poses[group.base] * group.has_base[:, None]
        c, s = np.cos(bp[:, 2:]), np.sin(bp[:, 2:])
        gx = np.concatenate([poses[group.maps, :1], features[group.features, 0]], axis=1) - bp[:, :1]
        gy = np.concatenate([poses[group.maps, 1:2], features[group.features, 1]], axis=1) - bp[:, 1:2]
        return c, s, c * gx + s * gy, c * gy - s * gx, poses[group.maps, 2] - bp[:, 2], gx, gy

    def _residual(self, group: _Group, geometry) -> np.ndarray:
        _, _, lx, ly, phi, _, _ = geometry
        e = group.measurement - np.concatenate([lx, ly, phi[:, None]], axis=1)
        e[:, -1] = wrap(e[:, -1])
        return np.matmul(group.whitening, e[:, :, None])[:, :, 0]

    def _jacobian(self, group: _Group, geometry) -> np.ndarray:
        """(G, d, w): d r / d (the group's columns) for every map of the group."""
        c, s, lx, ly, _, _, _ = geometry
        W = group.whitening
        p = lx.shape[1]                              # points: m + 1
        Wx, Wy, Wphi = W[:, :, :p], W[:, :, p:2 * p], W[:, :, 2 * p]
        c, s = c[:, :, None], s[:, :, None]
        Jx = s * Wy - c * Wx                         # -W R^T, x and y of every point
        Jy = -(s * Wx + c * Wy)
        base = group.has_base[:, None]
        Jbx = -Jx.sum(axis=2) * base                 # the base translation moves every point back
        Jby = -Jy.sum(axis=2) * base
        Jbphi = (Wphi - np.matmul(Wx, ly[:, :, None])[:, :, 0] + np.matmul(Wy, lx[:, :, None])[:, :, 0]) * base
        return np.concatenate([Jx, Jy, -Wphi[:, :, None], Jbx[:, :, None], Jby[:, :, None],
                               Jbphi[:, :, None]], axis=2)

    def _evaluate(self, x: np.ndarray) -> list[tuple[tuple, np.ndarray]]:
        """Per group, the geometry and the whitened residuals at ``x``; those of the last point
        are kept, so that :meth:`linearise` at the point :meth:`cost` has just tried (as the
        solver does on accepting a step) does not compute them again."""
        x = np.asarray(x, dtype=float)
        if self._evaluated is not None and np.array_equal(self._evaluated[0], x):
            return self._evaluated[1]
        evaluated = []
        for group in self.groups:
            geometry = self._geometry(group, x)
            evaluated.append((geometry, self._residual(group, geometry)))
        self._evaluated = x.copy(), evaluated
        return evaluated

    def residual(self, x: np.ndarray) -> np.ndarray:
        """Whitened residuals of all maps, ``3 + 2m`` per map in map order: ``W_k (s_k -
        H_k(x))`` with ``W_k`` the inverse lower Cholesky factor of ``P_k`` taken in the order
        [x's, y's, phi] (any square root of ``P_k^-1`` gives the same chi^2)."""
        r = np.empty(self.n_residuals + 1)
        for group, (_, residual) in zip(self.groups, self._evaluate(x)):
            r[group.rows] = residual
        return r[:-1]

    def cost(self, x: np.ndarray) -> float:
        """chi^2: the sum of squared whitened residuals."""
        return sum(float(np.einsum("gi,gi->", r, r)) for _, r in self._evaluate(x))

    def jacobian(self, x: np.ndarray) -> sp.csr_matrix:
        """The sparse Jacobian of :meth:`residual` (CSR, n_residuals x n_unknowns)."""
        x = np.asarray(x, dtype=float)
        rows, cols, vals = [], [], []
        for group in self.groups:
            J = self._jacobian(group, self._geometry(group, x))
            rows.append(np.broadcast_to(group.rows[:, :, None], J.shape).ravel())
            cols.append(np.broadcast_to(group.columns[:, None, :], J.shape).ravel())
            vals.append(J.ravel())
        J = sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                          shape=(self.n_residuals + 1, self.n_unknowns + 1))     # spares: the padding
        return J[:-1, :-1]

    # ---- normal equations ---------------------------------------------------------------

    def _prepare(self) -> None:
        """Fill-reducing node order, the CSC pattern of J^T J in it, each map block's slots,
        and the closed (symbolic Cholesky) node pattern for the marginal covariances."""
        if self._position is not None:
            return
        N, n = self.n_maps, self.n_features
        n_nodes = N + n
        node_size = np.concatenate([np.full(N, 3), np.full(n, 2)])
        # node pattern: per map, the node pairs its information couples (a clique for a full covariance)
        keys = []
        for group in self.groups:
            nodes = group.nodes
            w = nodes.shape[1]
            pairs = np.repeat(nodes, w, axis=1) * n_nodes + np.tile(nodes, (1, w))
            keys.append(pairs[group.coupled.reshape(len(nodes), -1)])
        natural, inverse = np.unique(np.concatenate(keys), return_inverse=True)
        col, row = natural // n_nodes, natural % n_nodes
        # ordering: minimum degree on the node graph. The values make the matrix a weighted
        # Laplacian plus 1e-3 I: an M-matrix, so its factor has no cancellation (nor, as the
        # shift is small, decay to underflow), and its pattern is the symbolic one.
        off = row != col
        graph = sp.csc_matrix((np.where(off, -1.0, 1e-3 + np.bincount(col[off], minlength=n_nodes)[col]),
                               (row, col)), shape=(n_nodes, n_nodes))
        lu = splu(graph, permc_spec="MMD_AT_PLUS_A", **_SUPERLU)
        if not np.array_equal(lu.perm_r, lu.perm_c):
            raise np.linalg.LinAlgError("SuperLU pivoted on the node graph")
        order = np.asarray(lu.perm_c, dtype=np.int64)   # node -> position
        # symbolic Cholesky pattern of the node graph (closed), for the selected inversion; then
        # an equivalent order (a postorder of the same elimination tree: same fill) that puts
        # each node's heaviest child right before it, so that supernodes can be merged
        L = lu.L.tocsc()
        L.sort_indices()
        L = L.tocoo()
        lower = L.row > L.col
        pattern = L.col[lower].astype(np.int64) * n_nodes + L.row[lower]   # sorted; no cancellation: contains A's
        a_row, a_col = order[row[off]], order[col[off]]
        below = a_row > a_col
        found = np.searchsorted(pattern, a_col[below] * n_nodes + a_row[below])
        if not np.array_equal(pattern[np.minimum(found, len(pattern) - 1)], a_col[below] * n_nodes + a_row[below]):
            pattern = np.concatenate([pattern, a_col[below] * n_nodes + a_row[below]])   # (underflow): add A's
        pattern = _closed_pattern(pattern, n_nodes)
        relabel = _heavy_last_postorder(pattern, n_nodes)
        order = relabel[order]
        pattern = np.sort(relabel[pattern // n_nodes] * n_nodes + relabel[pattern % n_nodes])
        size = np.empty(n_nodes, dtype=np.int64)
        size[order] = node_size                           # node size by position
        start = np.concatenate([[0], np.cumsum(size)])
        unknown_node = np.concatenate([np.repeat(np.arange(N), 3), N + np.repeat(np.arange(n), 2)])
        unknown_offset = np.concatenate([np.tile(np.arange(3), N), np.tile(np.arange(2), n)])
        self._position = position = start[order[unknown_node]] + unknown_offset
        # node CSC pattern in positions
        pkeys = order[col] * n_nodes + order[row]
        sort = np.argsort(pkeys)
        rank = np.empty(len(sort), dtype=np.int64)
        rank[sort] = np.arange(len(sort))
        pkeys = pkeys[sort]
        ncol, nrow = pkeys // n_nodes, pkeys % n_nodes
        nptr = np.searchsorted(ncol, np.arange(n_nodes + 1))
        row_size = size[nrow]
        cum = np.concatenate([[0], np.cumsum(row_size)])
        row_offset = cum[:-1] - cum[nptr[ncol]]           # scalar rows above node entry t in its column
        col_length = cum[nptr[1:]] - cum[nptr[:-1]]       # scalar rows of each node column
        # scalar CSC: every scalar column of node column c holds the rows of c's node entries, in order
        # (a "template" per node column: node entry t and row offset i of each of its scalar rows)
        column_length = np.repeat(col_length, size)
        indptr = np.concatenate([[0], np.cumsum(column_length)])
        nnz = int(indptr[-1])
        template_entry = np.repeat(np.arange(len(pkeys)), row_size)
        template_row = start[nrow][template_entry] + np.arange(len(template_entry)) - cum[:-1][template_entry]
        # the lower triangle is accumulated; an entry above the diagonal takes its mirror's value
        transposed_slot = np.searchsorted(pkeys, nrow * n_nodes + ncol)
        template_mirror = row_offset[transposed_slot][template_entry]
        scalar_node = np.repeat(np.arange(n_nodes), size)
        column = np.repeat(np.arange(len(column_length)), column_length)
        template = np.arange(nnz) - np.repeat(indptr[:-1] - cum[nptr[scalar_node]], column_length)
        indices = template_row[template]
        within = np.repeat(np.arange(len(scalar_node)) - start[scalar_node], column_length)   # column offset j
        from_lower = np.where(indices >= column, np.arange(nnz), indptr[indices] + template_mirror[template] + within)
        indices = indices.astype(np.int32)
        self._from_lower = from_lower
        self._indptr, self._indices = indptr.astype(np.int32), indices
        self._nnz = int(indptr[-1])
        # slots of the map blocks: entry (i, j) of J_k^T J_k is row columns[i], column columns[j]
        slots = np.split(rank[inverse], np.cumsum([k.size for k in keys])[:-1])
        targets, gradient_columns, angle_targets = [], [], []
        block_offset = gradient_offset = 0
        csc = indptr[start[:-1]], col_length, row_offset, self._nnz    # see _entries
        for group, slot in zip(self.groups, slots):
            G, m2 = group.nodes.shape
            m = m2 - 2
            node_of = np.concatenate([[0], 1 + np.arange(m), [0], 1 + np.arange(m), [0], [m + 1] * 3])
            offset_of = np.concatenate([[0], np.zeros(m, int), [1], np.ones(m, int), [2], [0, 1, 2]])
            # node pair (column node a, row node b) -> its entry in the node pattern (-1: uncoupled)
            full = np.full((G, m2, m2), -1, dtype=np.int64)
            full[group.coupled] = slot
            placed = order[group.nodes]                   # node positions
            layout = group.layout
            pieces = _entries(layout.rows, layout.cols, node_of, offset_of, placed, full, csc)
            group.block_offset, group.gradient_offset = block_offset, gradient_offset
            block_offset += pieces.size
            gradient_offset += group.columns.size
            bounds = np.cumsum([0] + [math.prod(shape) for shape in layout.shapes])
            targets.extend(pieces[:, lo:hi].ravel() for lo, hi in itertools.pairwise(bounds))   # piece by piece
            gradient_columns.append(group.columns.ravel())
            w = group.columns.shape[1]
            angle_targets.append(_entries(np.full(w, w - 1), np.arange(w), node_of, offset_of, placed, full,
                                          csc).ravel())
        self._targets = np.concatenate(targets)
        self._gradient_columns = np.concatenate(gradient_columns)
        self._angle_targets = np.concatenate(angle_targets)
        self._block_size, self._gradient_size = block_offset, gradient_offset
        self._buffer, self._gradient_buffer = np.empty(block_offset), np.empty(gradient_offset)
        diagonal_slot = np.searchsorted(pkeys, np.arange(n_nodes) * (n_nodes + 1))
        self._diagonal = (indptr[position] + row_offset[diagonal_slot[order[unknown_node]]]
                          + unknown_offset)                # CSC index of A[i, i], natural order
        self._node_pattern, self._node_size = pattern, size

    @property
    def position(self) -> np.ndarray:
        """Row/column of each unknown in the factorised J^T J (a fill-reducing order)."""
        self._prepare()
        return self._position

    def linearise(self, x: np.ndarray, curvature: bool = False):
        """``(data, gradient, chi^2[, curvature data])`` at ``x``: the CSC data of J^T J (see
        :meth:`normal_matrix`), J^T r (natural order), and with ``curvature`` the data of the
        second-order term ``sum_i r_i d^2 r_i / dx^2`` (J^T J plus it is half the Hessian of chi^2).

        Per map, with ``Lambda = P_k^-1``: the own columns' block is ``B^T Lambda B``, B the
        rotation by the base angle theta of the x/y parts, i.e. ``T +- (cos 2theta D - sin
        2theta A)`` for x/x and y/y and ``K + sin 2theta D + cos 2theta A`` for x/y, with T, D,
        A, K fixed combinations of Lambda's blocks. The base pose's columns are combinations
        of the own columns, ``B c_a = v_a``, the change of the predicted state when the base
        moves along x, y or turns (``(-c, s, 0)``, ``(-s, -c, 0)``, ``(ly, -lx, -1)`` for the
        x's, y's and phi): base/own blocks ``B^T Lambda v_a``, base/base ``v_a^T Lambda v_b``.
        So a map costs one matrix-vector product and O(d^2) elementwise work. Only the lower
        triangle is accumulated (one ``bincount``), then mirrored.
        """
        self._prepare()
        x = np.asarray(x, dtype=float)
        buffer = self._buffer
        gradient_buffer = self._gradient_buffer
        extra = [] if curvature else None
        cost = 0.0
        for group, (geometry, r) in zip(self.groups, self._evaluate(x)):
            c, s, lx, ly, *_ = geometry
            cost += float(np.einsum("gi,gi->", r, r))
            mu = np.matmul(r[:, None, :], group.whitening)[:, 0, :]      # W^T r = P^-1 e
            G, d = r.shape
            p = (d - 1) // 2
            w = d + 3
            Ttri, Dtri, Atri, D, A, K, Lxphi, Lyphi, Lphiphi, Lam, rsx, rsy = group.rotated
            xx, yy, xy, xphi, yphi, phiphi, mc, cmc = _pieces(buffer, group)
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
            # base pose: u_a = Lambda v_a; own/base block B^T u_a; base/base v_a . u_b
            base = group.has_base.astype(float)[:, None]
            v = np.concatenate([ly, -lx, -np.ones((G, 1))], axis=1)
            u = np.empty((G, 3, d))
            np.multiply(s * rsy - c * rsx, base, out=u[:, 0])
            np.multiply(-(s * rsx + c * rsy), base, out=u[:, 1])
            np.multiply(np.matmul(Lam, v[:, :, None])[:, :, 0], base, out=u[:, 2])
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
            # gradient J^T r = -B^T mu for the own columns, -v_a . mu for the base
            mx, my = mu[:, :p], mu[:, p:2 * p]
            g = gradient_buffer[group.gradient_offset:group.gradient_offset + G * w].reshape(G, w)
            g[:, :p] = s * my - c * mx
            g[:, p:2 * p] = -(s * mx + c * my)
            g[:, 2 * p] = -mu[:, 2 * p]
            smx, smy = mx.sum(axis=1), my.sum(axis=1)
            b = group.has_base
            g[:, d] = (c[:, 0] * smx - s[:, 0] * smy) * b
            g[:, d + 1] = (s[:, 0] * smx + c[:, 0] * smy) * b
            g[:, d + 2] = -np.einsum("gd,gd->g", v, mu) * b
            if curvature:   # -sum_j mu_j d^2 H_j: only in the row and column of the base angle
                h = np.empty((G, w))
                h[:, :p] = s * mx + c * my
                h[:, p:2 * p] = s * my - c * mx
                h[:, 2 * p] = 0.0
                h[:, d] = -h[:, :p].sum(axis=1)
                h[:, d + 1] = -h[:, p:2 * p].sum(axis=1)
                h[:, d + 2] = np.einsum("gp,gp->g", mx, lx) + np.einsum("gp,gp->g", my, ly)
                h *= base
                extra.append(h.ravel())
        data = np.bincount(self._targets, buffer, minlength=self._nnz + 1)[self._from_lower]
        gradient = np.bincount(self._gradient_columns, gradient_buffer, minlength=self.n_unknowns + 1)[:-1]
        if not curvature:
            return data, gradient, cost
        second = np.bincount(self._angle_targets, np.concatenate(extra), minlength=self._nnz + 1)[self._from_lower]
        return data, gradient, cost, second

    def normal_matrix(self, data: np.ndarray) -> sp.csc_matrix:
        """J^T J as a CSC matrix in the factor's order: entry (position[i], position[j]) is (i, j)."""
        nv = self.n_unknowns
        return sp.csc_matrix((data, self._indices, self._indptr), shape=(nv, nv))

    def factorise(self, data: np.ndarray, damping: float = 0.0):
        """SuperLU factor of ``J^T J + damping diag(J^T J)`` (symmetric mode, fill-reducing order)."""
        if damping:
            data = data.copy()
            data[self._diagonal] *= 1.0 + damping
        return splu(self.normal_matrix(data), permc_spec="NATURAL", **_SUPERLU)

    def solve(self, factor, rhs: np.ndarray) -> np.ndarray:
        """``(J^T J)^-1 rhs`` (natural order; ``rhs`` a vector or a matrix of columns) with a
        factor from :meth:`factorise`."""
        permuted = np.empty(np.shape(rhs))
        permuted[self._position] = rhs
        return factor.solve(permuted)[self._position]

    def diagonal(self, data: np.ndarray) -> np.ndarray:
        """diag(J^T J) in natural order."""
        return data[self._diagonal]

    def marginals(self, factor) -> tuple[np.ndarray, np.ndarray]:
        """Marginal covariances ``(poses (N, 3, 3), features (n, 2, 2))``, the diagonal blocks
        of ``(J^T J)^-1``, by selected inversion of an undamped factor from :meth:`factorise`."""
        N, n = self.n_maps, self.n_features
        nv = self.n_unknowns
        if not (np.array_equal(factor.perm_r, factor.perm_c)):
            raise np.linalg.LinAlgError("SuperLU pivoted: not a symmetric factorisation")
        L = factor.L.tocoo()
        lower = L.row > L.col
        Lrow, Lcol, Lval = L.row[lower].astype(np.int64), L.col[lower].astype(np.int64), L.data[lower]
        D = factor.U.diagonal()
        natural = np.array_equal(factor.perm_c, np.arange(nv))
        where = self._position if natural else np.asarray(factor.perm_c)[self._position]
        blocks = [(where[:3 * N].reshape(N, 3), 3), (where[3 * N:].reshape(n, 2), 2)]
        rows = np.concatenate([np.repeat(b, size, axis=1).ravel() for b, size in blocks])
        cols = np.concatenate([np.tile(b, (1, size)).ravel() for b, size in blocks])
        wanted = (np.maximum(rows, cols), np.minimum(rows, cols))
        values = None
        if natural:   # the factor is in node order: use the symbolic node pattern
            structure = _Supernodes(self._node_pattern, self._node_size)
            values = _selected_inverse(structure, Lrow, Lcol, Lval, D, *wanted)
        if values is None:   # general: close the factor's own pattern (with that of J^T J)
            A = self.normal_matrix(np.ones(self._nnz)).tocoo()
            q = np.asarray(factor.perm_c)
            ar, ac = q[A.row], q[A.col]
            keep = ar > ac
            keys = _closed_pattern(np.concatenate([Lcol, ac[keep]]) * nv + np.concatenate([Lrow, ar[keep]]), nv)
            values = _selected_inverse(_Supernodes(keys, np.ones(nv, dtype=np.int64)), Lrow, Lcol, Lval, D,
                                       *wanted)
            if values is None:
                raise np.linalg.LinAlgError("the factor's pattern is not closed")
        split = 9 * N
        return values[:split].reshape(N, 3, 3), values[split:].reshape(n, 2, 2)


def _entries(rows: np.ndarray, cols: np.ndarray, node_of: np.ndarray, offset_of: np.ndarray, placed: np.ndarray,
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


def _closed_pattern(keys: np.ndarray, n: int) -> np.ndarray:
    """A superset of a strictly lower pattern (keys ``col * n + row``, row > col) closed
    under elimination, sorted keys: for every column j with parent p = min struct(j),
    struct(j) minus p lies in struct(p) (then any two rows of a column are linked by an
    entry, as Takahashi's recursion needs). One vectorised round per level of missing
    entries; a symbolic pattern passes the check in one round."""
    keys = np.asarray(keys, dtype=np.int64)
    if len(keys) > 1 and not (keys[1:] > keys[:-1]).all():
        keys = np.unique(keys)
    while True:
        c, r = keys // n, keys % n
        first = np.searchsorted(c, np.arange(n + 1))
        parent = np.full(n, -1, dtype=np.int64)
        has = first[1:] > first[:-1]
        parent[has] = r[first[:-1][has]]
        p = parent[c]
        need = r != p
        required = p[need] * n + r[need]
        at = np.searchsorted(keys, required)
        found = keys[np.minimum(at, len(keys) - 1)] == required if len(keys) else np.zeros(0, bool)
        if found.all():
            return keys
        keys = np.unique(np.concatenate([keys, required[~found]]))


class _PieceLayout(NamedTuple):
    """Which entries of a map's block of J^T J are evaluated, among its columns ``[x of the p
    points, y ..., phi, base x, y, phi]``: ``pairs`` (i >= j) of points whose x/x and y/y
    entries, ``cross`` (i, j) whose x_i/y_j entries; the pieces' ``shapes`` per map and the
    local (row, column) of every entry, in layout order (see :func:`_pieces`)."""

    pairs: tuple[np.ndarray, np.ndarray]
    cross: tuple[np.ndarray, np.ndarray]
    shapes: tuple[tuple[int, ...], ...]
    rows: np.ndarray
    cols: np.ndarray


@functools.lru_cache(maxsize=512)
def _piece_layout(p: int, independent: bool) -> _PieceLayout:
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
    return _PieceLayout(pairs, cross, shapes, np.concatenate(rows).astype(np.intp),
                        np.concatenate(cols).astype(np.intp))


def _pieces(buffer: np.ndarray, group: _Group) -> list[np.ndarray]:
    """Views into the flat buffer of a group's ``G`` maps, one entry per evaluated unordered
    pair of columns: x/x and y/y over the layout's pairs, x/y over its cross pairs, x/phi,
    y/phi (G, p), phi/phi (G,), own/base (G, 3, d: base column a, own row i) and the
    base/base lower triangle (G, 6), laid out in this order (see :func:`_piece_layout`)."""
    G = len(group.maps)
    views, offset = [], group.block_offset
    for shape in group.layout.shapes:
        size = G * math.prod(shape)
        views.append(buffer[offset:offset + size].reshape((G,) + shape))
        offset += size
    return views


def _heavy_last_postorder(keys: np.ndarray, n: int) -> np.ndarray:
    """``relabel[old] = new``: a postorder of the elimination tree of the closed pattern
    ``keys`` (parent = first row below the diagonal) visiting each node's children lightest
    subtree first, so the heaviest child comes right before its parent."""
    c, r = keys // n, keys % n
    first = np.searchsorted(c, np.arange(n + 1))
    parent = np.full(n, -1, dtype=np.int64)
    has = first[1:] > first[:-1]
    parent[has] = r[first[:-1][has]]
    parents = parent.tolist()
    weight = [1] * n                                   # subtree sizes; children precede parents
    for j, p in enumerate(parents):
        if p >= 0:
            weight[p] += weight[j]
    weight = np.array(weight, dtype=np.int64)
    # siblings (and roots) lightest first; a subtree occupies [first[v], first[v] + weight[v]),
    # its children's subtrees in that order, then v itself
    by = np.lexsort((weight, parent))
    grouped = parent[by]
    cumulative = np.cumsum(weight[by]) - weight[by]
    group_start = np.searchsorted(grouped, grouped)  # first sibling of each
    offset = np.empty(n, dtype=np.int64)
    offset[by] = cumulative - cumulative[group_start]
    offsets = offset.tolist()
    first = [0] * n
    for v in range(n - 1, -1, -1):                     # parents before children
        p = parents[v]
        first[v] = (first[p] if p >= 0 else 0) + offsets[v]
    return np.array(first, dtype=np.int64) + weight - 1


class _Supernodes:
    """Supernodal structure of a closed pattern given on "units" (nodes of ``unit_size``
    consecutive scalars each, in factor order): runs of units with nested identical
    structure become one supernode; per supernode J its scalar columns ``start .. start +
    size`` and the scalar rows ``S_J`` below them, the parent supernode (holding the first
    row of S_J), and where each row of S_J sits in the parent's block ``[P; S_P]``."""

    def __init__(self, keys: np.ndarray, unit_size: np.ndarray):
        nu = len(unit_size)
        kc, kr = keys // nu, keys % nu
        first = np.searchsorted(kc, np.arange(nu + 1))
        counts = np.diff(first)
        parent = np.full(nu, -1, dtype=np.int64)
        has = counts > 0
        parent[has] = kr[first[:-1][has]]
        joins = (parent[:-1] == np.arange(1, nu)) & (counts[:-1] == counts[1:] + 1)
        ustart = np.flatnonzero(np.concatenate([[True], ~joins]))
        ulast = np.append(ustart[1:], nu) - 1
        scalar = np.concatenate([[0], np.cumsum(unit_size)])
        ustart, ulast = _amalgamate(ustart, ulast, parent, scalar,
                                    np.bincount(kc, unit_size[kr], minlength=nu).astype(np.int64))
        self.n = n = int(scalar[-1])
        self.count = count = len(ustart)
        self.start = scalar[ustart]
        self.size = scalar[ulast + 1] - self.start
        self.super_of = np.repeat(np.arange(count), self.size)
        # S_J: the structure of J's last unit, expanded to scalars
        unit_counts = counts[ulast]
        unit_rows = kr[np.repeat(first[ulast] - np.concatenate([[0], np.cumsum(unit_counts)])[:-1], unit_counts)
                       + np.arange(unit_counts.sum())]
        expanded = unit_size[unit_rows]
        self.below = np.bincount(np.repeat(np.arange(count), unit_counts), expanded, minlength=count
                                 ).astype(np.int64)
        self.s_offset = np.concatenate([[0], np.cumsum(self.below)])
        base = np.repeat(scalar[unit_rows], expanded)
        within = np.arange(expanded.sum()) - np.repeat(np.concatenate([[0], np.cumsum(expanded)])[:-1], expanded)
        self.s_rows = base + within
        s_super = np.repeat(np.arange(count), self.below)
        self.s_keys = s_super * n + self.s_rows
        has_parent = self.below > 0
        self.parent = np.full(count, -1, dtype=np.int64)
        self.parent[has_parent] = self.super_of[self.s_rows[self.s_offset[:-1][has_parent]]]
        self.children = np.bincount(self.parent[has_parent], minlength=count)
        p = self.parent[s_super]
        self.relative = self.locate(p, self.s_rows)
        self.block_offset = np.concatenate([[0], np.cumsum(self.size * (self.size + self.below))])

    def locate(self, J: np.ndarray, rows: np.ndarray) -> np.ndarray | None:
        """Index of scalar row ``rows`` in the block ``[J; S_J]`` of supernode ``J`` (None if absent)."""
        inside = rows < self.start[J] + self.size[J]
        out = ~inside
        result = np.empty(len(rows), dtype=np.int64)
        result[inside] = rows[inside] - self.start[J[inside]]
        wanted = J[out] * self.n + rows[out]
        at = np.searchsorted(self.s_keys, wanted)
        if len(wanted) and (len(self.s_keys) == 0
                            or not np.array_equal(self.s_keys[np.minimum(at, len(self.s_keys) - 1)], wanted)):
            return None
        if (rows[inside] < self.start[J[inside]]).any():
            return None
        result[out] = self.size[J[out]] + at - self.s_offset[J[out]]
        return result


def _amalgamate(ustart: np.ndarray, ulast: np.ndarray, parent: np.ndarray, scalar: np.ndarray,
                below: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Merge runs of fundamental supernodes (first and last unit ``ustart``, ``ulast``) whose
    parent is the next one, while a merged supernode costs less than the pieces: dense
    work (b s^2 + b^2 s + b^3/3 for b columns and s rows below) plus a fixed overhead per
    supernode for the Python loop. The merged supernode takes the structure of its last
    piece (a superset of the others' below it: explicit zeros, still a closed pattern).
    ``below``: scalar rows below each unit (its structure, expanded)."""
    count = len(ustart)
    if count < 2:
        return ustart, ulast
    size = (scalar[ulast + 1] - scalar[ustart]).tolist()
    rows = below[ulast].tolist()
    super_of = np.repeat(np.arange(count), ulast - ustart + 1)
    up = parent[ulast]
    next_is_parent = (np.where(up >= 0, super_of[np.maximum(up, 0)], -1) == np.arange(count) + 1).tolist()

    def cost(b: int, s: int) -> float:
        return b * s * s + b * b * s + b * b * b / 3 + _SUPERNODE_OVERHEAD

    firsts = [0]
    b, work = size[0], cost(size[0], rows[0])
    for J in range(count - 1):
        nxt = J + 1
        if next_is_parent[J]:
            merged = cost(b + size[nxt], rows[nxt])
            if merged <= work + cost(size[nxt], rows[nxt]):
                b, work = b + size[nxt], merged
                continue
        firsts.append(nxt)
        b, work = size[nxt], cost(size[nxt], rows[nxt])
    firsts = np.array(firsts)
    return ustart[firsts], ulast[np.append(firsts[1:], count) - 1]


def _selected_inverse(structure: _Supernodes, Lrow: np.ndarray, Lcol: np.ndarray, Lval: np.ndarray,
                      D: np.ndarray, rows: np.ndarray, cols: np.ndarray) -> np.ndarray | None:
    """Entries ``(rows, cols)`` (rows >= cols, factor order) of ``A^-1`` for ``A = L D L^T``
    (unit lower L given by its strictly lower entries), by supernodal selected inversion
    (Takahashi's recursion); None if L does not fit the structure.

    Supernodes are visited from the last to the first. Supernode J needs ``Z[S, S]`` (S: the
    rows below it), a submatrix of the block ``Z[P+S_P, P+S_P]`` of its parent P, which is
    kept until P's last child is done. Per supernode: ``U = L_SJ L_JJ^-1``,
    ``Z_SJ = -Z_SS U``, ``Z_JJ = (L_JJ D_J L_JJ^T)^-1 - U^T Z_SJ``. Only these blocks of
    the inverse are formed, never the whole inverse.
    """
    st = structure
    J = st.super_of[Lcol]
    at = st.locate(J, Lrow)
    if at is None:
        return None
    flat = np.zeros(st.block_offset[-1])          # per supernode, row jc = column jc of [L_JJ; L_SJ]
    flat[st.block_offset[J] + (Lcol - st.start[J]) * (st.size[J] + st.below[J]) + at] = Lval
    result = np.empty(st.block_offset[-1])        # the same layout for [Z_JJ; Z_SJ]
    frontal: dict[int, np.ndarray] = {}
    children = st.children.copy()
    dtrtri = scipy.linalg.lapack.get_lapack_funcs("trtri", (D,))
    for J in range(st.count - 1, -1, -1):
        j0, b, s = st.start[J], st.size[J], st.below[J]
        o0, o1 = st.block_offset[J], st.block_offset[J + 1]
        block = flat[o0:o1].reshape(b, b + s)
        Linv, info = dtrtri(block[:, :b].T + np.eye(b), lower=1, unitdiag=1)
        if info:
            raise np.linalg.LinAlgError("singular diagonal block in the factor")
        Zjj = Linv.T @ (Linv / D[j0:j0 + b, None])
        out = result[o0:o1].reshape(b, b + s)
        if s:
            U = block[:, b:].T @ Linv                     # (s, b)
            P = st.parent[J]
            rel = st.relative[st.s_offset[J]:st.s_offset[J + 1]]
            Zss = frontal[P].take(rel, axis=0).take(rel, axis=1)
            children[P] -= 1
            if not children[P]:
                del frontal[P]
            Zsj = -Zss @ U
            Zjj -= U.T @ Zsj
            out[:, b:] = Zsj.T
        out[:, :b] = Zjj
        if children[J]:
            F = np.empty((b + s, b + s))
            F[:b, :b] = Zjj
            if s:
                F[b:, :b] = Zsj
                F[:b, b:] = Zsj.T
                F[b:, b:] = Zss
            frontal[J] = F
    J = st.super_of[cols]
    at = st.locate(J, rows)
    if at is None:
        raise np.linalg.LinAlgError("a wanted entry of the inverse is outside the factor's pattern")
    return result[st.block_offset[J] + (cols - st.start[J]) * (st.size[J] + st.below[J]) + at]


def _coupled(information: np.ndarray, point: np.ndarray, independent: bool) -> np.ndarray:
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


def _inverse_cholesky(covariance: np.ndarray) -> np.ndarray:
    """``W = L^-1`` for the lower Cholesky factors ``L`` of a stack of covariances (W^T W is
    their inverse, W whitens a residual)."""
    try:
        k = covariance.shape[-1]
        return _triangular_inverse(np.linalg.cholesky(covariance.reshape(-1, k, k))).reshape(covariance.shape)
    except np.linalg.LinAlgError:
        raise JoinError("a local map's covariance is not positive definite") from None


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


def _independent(covariances: np.ndarray) -> np.ndarray:
    """(G,): which blocks' covariances (G, 3 + 2m, 3 + 2m), order [x, y, phi, f1x, f1y, ...],
    correlate no two of their points (the end pose and each feature: block-diagonal)."""
    d = covariances.shape[1]
    point = np.concatenate([[0, 0, 0], np.repeat(np.arange(1, (d - 3) // 2 + 1), 2)])
    across = point[:, None] != point[None, :]
    return ~np.any(covariances[:, across] != 0, axis=1)


def _classes(sizes: np.ndarray, independent: np.ndarray) -> list[np.ndarray]:
    """The maps of each group (:class:`_Group`): per kind (dense or independent points),
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


def _triangular_inverse(L: np.ndarray) -> np.ndarray:
    """Inverses of a stack of lower triangular matrices (G, d, d): a third of the work of a
    general inverse. Few or large matrices one by one (LAPACK's trtri, on the transposes:
    no copies); many small ones row by row, the forward substitution vectorised over the stack."""
    G, d = L.shape[0], L.shape[-1]
    if d >= 24 or G < 4 * d:
        W = np.empty_like(L)
        for g in range(G):
            W[g].T[...] = _TRTRI(L[g].T, lower=0)[0]
        return W
    W = np.zeros_like(L)
    reciprocal = 1.0 / np.diagonal(L, axis1=1, axis2=2)
    W[:, 0, 0] = reciprocal[:, 0]
    for j in range(1, d):
        W[:, j, :j] = np.matmul(L[:, j:j + 1, :j], W[:, :j, :j])[:, 0, :] * -reciprocal[:, j:j + 1]
        W[:, j, j] = reciprocal[:, j]
    return W


def _covariance(local_map: LocalMap) -> np.ndarray:
    if local_map.covariance is not None:
        return local_map.covariance
    variances = np.concatenate([local_map.pose_variances[[0, 0, 1]],
                                np.repeat(local_map.feature_variances, 2)])
    return np.diag(variances)


def _lookup(ids: np.ndarray, values: np.ndarray, wanted: np.ndarray, what: str, source: str) -> np.ndarray:
    """The rows of ``values`` (one per id of the initial map ``source``) for the ids ``wanted``."""
    index, found = locate(ids, wanted, np.argsort(ids, kind="stable"))
    missing = ~found
    if missing.any():
        raise JoinError(f"the initial map {source} has no {what} {int(wanted[missing][0])} "
                        f"({int(missing.sum())} {what}s missing)")
    return np.asarray(values, dtype=float)[index]


def exact_cost(maps: Sequence[LocalMap], global_map: GlobalMap) -> float:
    """chi^2 of ``global_map`` in the exact joining problem of ``maps``."""
    problem = ExactProblem(maps)
    return problem.cost(problem.pack(global_map))


@dataclass
class Minimum:
    """Where :func:`minimise` stopped: the unknowns ``x``, the data of J^T J, J^T r and chi^2
    there, chi^2 before the first step and after each accepted one (``costs``), why it
    stopped, and ``factor``: the undamped Gauss-Newton factor of J^T J at ``x`` when the
    last one computed was that (else None)."""

    x: np.ndarray
    data: np.ndarray
    gradient: np.ndarray
    cost: float
    costs: list[float]
    iterations: int
    converged: bool
    reason: str
    rejected: int
    factor: object = None

    def final_factor(self, problem: ExactProblem):
        """The undamped factor of J^T J at the optimum (for covariances)."""
        return self.factor if self.factor is not None else problem.factorise(self.data)


def minimise(problem: ExactProblem, x: np.ndarray, *, max_iterations: int = 100, tolerance: float = TOLERANCE,
             progress: Callable[[int, float], None] | None = None) -> Minimum:
    """Minimise chi^2 of ``problem`` from ``x``: Gauss-Newton (``J^T J``), undamped while steps
    lower the cost (an overshooting one is first halved up to ten times: a backtracking line
    search along it), with Marquardt damping ``lambda diag(J^T J)`` adapted by the gain ratio
    (Nielsen) after one that does not; after a good undamped step, Newton's (``J^T J`` plus
    the second-order term, for quadratic convergence on these non-zero-residual problems),
    falling back to Gauss-Newton for good if a Newton step is not a descent or does not
    lower the cost. A step predicted to lower chi^2 by at most ``tolerance`` relative is
    accepted unless chi^2 rises by more than that: comparing the costs is rounding there,
    and it would make the stopping point random. Stops when an accepted step lowers chi^2
    by at most ``tolerance`` relative, or a step is at most ``tolerance * (1 + max |x|)`` in
    every unknown, or one predicted to lower chi^2 by at most ``tolerance`` relative raises
    it by more (these two not taken), or after ``max_iterations`` accepted steps. The relative
    tolerances on chi^2 are at least its rounding, ``sqrt(residuals)`` machine epsilons, so
    that ``tolerance=0`` means "to rounding" rather than a damped search for what rounding hides.
    ``progress(iteration, cost)`` is called with the initial chi^2 (iteration 0) and after
    each accepted step.
    """
    if max_iterations < 0:
        raise ValueError(f"max_iterations must be >= 0, got {max_iterations}")
    if not tolerance >= 0:
        raise ValueError(f"tolerance must be >= 0, got {tolerance}")
    # chi^2's own rounding (sqrt(residuals) machine epsilons, relative): comparing costs or predicted
    # decreases below it is noise, so a smaller tolerance (e.g. 0) stops there instead of damping on
    relative = max(tolerance, math.sqrt(problem.n_residuals) * np.finfo(float).eps)
    data, gradient, cost = problem.linearise(x)           # the first step is Gauss-Newton's
    second = None
    costs = [cost]
    factor_is_final = False
    if progress:
        progress(0, cost)
    damping, growth = 0.0, 2.0
    newton, newton_allowed = False, True
    iterations, rejected, reason, converged = 0, 0, "", False
    factor = None
    while True:
        if iterations >= max_iterations:
            reason = "max iterations reached"
            break
        try:
            factor = problem.factorise(data + second if newton else data, damping)
            step = problem.solve(factor, -gradient)
        except RuntimeError:          # SuperLU: exactly singular
            if not newton:
                raise JoinError("the normal equations of the exact join are singular") from None
            step = None
        finite = step is not None and bool(np.all(np.isfinite(step)))
        if finite and np.max(np.abs(step), initial=0.0) <= tolerance * (1.0 + np.max(np.abs(x), initial=0.0)):
            factor_is_final = damping == 0.0 and not newton
            reason, converged = "step below tolerance", True
            break
        if newton and (not finite or step @ gradient >= 0):
            newton = newton_allowed = False       # not a descent direction: Gauss-Newton from now on
            rejected += 1
            continue
        if not finite:
            raise JoinError("the normal equations of the exact join are singular")
        trial = x + step
        trial_cost = problem.cost(trial)
        # the model's decrease, -g.step + damping step.D.step (the gain ratio's denominator)
        predicted = -(step @ gradient) + damping * (step * step) @ problem.diagonal(data)
        negligible = 0 <= predicted <= relative * cost
        if trial_cost >= cost and not negligible and not newton and damping == 0.0:
            # Gauss-Newton's step overshoots: shorten it (its direction is one of descent) before damping,
            # which, scaled by diag(J^T J), would cut the directions J^T J hardly constrains by orders of
            # magnitude and let the solver creep along them (as on long runs with loop closures)
            for halving in range(1, _HALVINGS + 1):
                shorter = x + 0.5 ** halving * step
                shorter_cost = problem.cost(shorter)
                if shorter_cost < cost:
                    rejected += 1
                    trial, trial_cost = shorter, shorter_cost
                    predicted *= 0.5 ** halving * (2 - 0.5 ** halving)    # the model's decrease along it
                    break
        if negligible and trial_cost > cost * (1.0 + relative):
            # at the optimum to within rounding, and the model no longer holds: damped retries would only
            # shrink the step
            factor_is_final = damping == 0.0 and not newton
            reason, converged = "predicted decrease below tolerance", True
            break
        if trial_cost < cost or negligible:
            # a step of negligible predicted decrease is taken however chi^2 compares: at that level the
            # comparison is rounding noise (it would make where the solver stops random), and the model's
            # minimiser is the better estimate; the relative cost change then stops the solver
            ratio = (cost - trial_cost) / predicted if predicted > 0 else 1.0
            x, previous = trial, cost
            damping *= max(1.0 / 3.0, 1.0 - (2.0 * ratio - 1.0) ** 3)
            if damping < 1e-12:
                damping = 0.0
            growth = 2.0
            # near the optimum (a good undamped step), Newton's quadratic convergence
            newton = newton_allowed and damping == 0.0 and ratio > 0.5
            done = previous - trial_cost <= relative * previous
            if newton and not done:     # the second-order term only where a Newton step follows
                data, gradient, cost, second = problem.linearise(x, curvature=True)
            else:
                data, gradient, cost = problem.linearise(x)
            iterations += 1
            costs.append(cost)
            if progress:
                progress(iterations, cost)
            if done:
                reason, converged = "relative cost change below tolerance", True
                break
        elif newton:
            newton = newton_allowed = False       # Newton's model failed here: Gauss-Newton from now on
            rejected += 1
        else:
            rejected += 1
            damping = 1e-6 if damping == 0.0 else damping * growth
            growth *= 2.0
            if damping > _MAX_DAMPING:
                reason = "no step lowers the cost (damping limit reached)"
                break
    return Minimum(x, data, gradient, cost, costs, iterations, converged, reason, rejected,
                   factor if factor_is_final else None)


def refine(maps: Sequence[LocalMap], initial: GlobalMap | None = None, *, max_iterations: int = 100,
           tolerance: float = TOLERANCE, covariances: bool = True,
           progress: Callable[[int, float], None] | None = None) -> RefineResult:
    """Solve the exact least-squares joining problem of the chain ``maps``.

    Starts from ``initial`` (which must hold every pose and feature; extra ones are
    ignored) or else from ``join_sequential(maps)`` (which needs a chain); the steps and
    the stopping rules are those of :func:`minimise`. ``covariances``: compute the marginal
    covariances (else the initial map's variances are kept).
    """
    maps = list(maps)
    initial_seconds = 0.0
    if initial is None:
        start = time.perf_counter()
        initial = join_sequential(maps).global_map
        initial_seconds = time.perf_counter() - start
    start = time.perf_counter()
    problem = ExactProblem(maps)
    found = minimise(problem, problem.pack(initial), max_iterations=max_iterations, tolerance=tolerance,
                     progress=progress)
    seconds = time.perf_counter() - start

    poses, features = problem.unpack(found.x)
    start = time.perf_counter()
    if covariances:
        pose_covariances, feature_covariances = problem.marginals(found.final_factor(problem))
        feature_variances = np.trace(feature_covariances, axis1=1, axis2=2) / 2
        pose_variances = np.stack([(pose_covariances[:, 0, 0] + pose_covariances[:, 1, 1]) / 2,
                                   pose_covariances[:, 2, 2]], axis=1)
    else:
        pose_covariances = feature_covariances = None
        pose_variances = _lookup(initial.pose_ids, initial.pose_variances, problem.pose_ids, "pose",
                                 initial.name)
        feature_variances = _lookup(initial.feature_ids, initial.feature_variances, problem.feature_ids,
                                    "feature", initial.name)
    covariance_seconds = time.perf_counter() - start if covariances else 0.0
    global_map = GlobalMap(
        feature_ids=problem.feature_ids, features=features, feature_variances=feature_variances,
        pose_ids=problem.pose_ids, poses=poses, pose_variances=pose_variances,
        provenance=Provenance(tuple(m.name for m in maps), "full", "gauss-newton", "exact"),
        feature_covariances=feature_covariances, pose_covariances=pose_covariances)
    return RefineResult(
        global_map=global_map, cost=found.cost, costs=tuple(found.costs), iterations=found.iterations,
        converged=found.converged, reason=found.reason, seconds=seconds, covariance_seconds=covariance_seconds,
        initial_seconds=initial_seconds, residuals=problem.n_residuals, unknowns=problem.n_unknowns,
        gradient_norm=float(np.max(np.abs(found.gradient), initial=0.0)), rejected=found.rejected)
