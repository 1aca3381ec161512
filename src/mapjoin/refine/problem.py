"""The exact least-squares joining problem (the problem I-SLSJF solves): residuals, Jacobian
and normal equations.

Problem (docs/method.md#exact-joining)::

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

Maps are evaluated in groups of nearby sizes (:mod:`.groups`); the blocks of ``J^T J``
they give go into the fixed sparse pattern of ``J^T J`` (:mod:`.sparse`) with one
``bincount``, in a fill-reducing order computed once; a small problem's linear algebra is
dense (:mod:`.dense`, the natural order), on the same assembled data.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, NamedTuple

import numpy as np

from ..covariance import state_covariance
from ..errors import JoinError
from ..maps import GlobalMap, LocalMap, locate
from ..se2 import to_frame, wrap
from . import dense
from . import groups as grouping
from .dense import Backend, backend_for
from .groups import Group
from .factor import Factor, factorise
from .sparse import BlockPattern, diagonal_blocks, fill_reducing_order

if TYPE_CHECKING:
    import scipy.sparse as sp

__all__ = ["Blocks", "ExactProblem"]


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
            return np.stack([state_covariance(maps[k]) for k in ks])

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
    different origins make independent problems, solved together. ``backend``: the linear
    algebra of the normal equations, ``sparse`` (SuperLU, selected inversion: :mod:`.sparse`)
    or ``dense`` (numpy: :mod:`.dense`); ``auto`` takes dense for small problems
    (:func:`.dense.backend_for`), where importing scipy would cost more than the solve.
    """

    def __init__(self, measurements: Sequence[LocalMap] | Blocks, origins: Sequence[int] | None = None,
                 backend: Backend = "auto"):
        blocks = _as_blocks(measurements)
        self.n_maps = N = len(blocks.end_ids)
        if not N:
            raise JoinError("no local maps to join")
        self.pose_ids = np.asarray(blocks.end_ids, dtype=np.int64)
        base = self._base_poses(blocks, origins)
        sizes = np.asarray(blocks.sizes, dtype=np.int64)
        self.feature_ids, compact = np.unique(blocks.feature_ids, return_inverse=True)
        self.n_features = n = len(self.feature_ids)
        self.n_unknowns = 3 * N + 2 * n
        self.row0 = np.concatenate([[0], np.cumsum(3 + 2 * sizes)])
        self.n_residuals = int(self.row0[-1])
        chain = _Chain(base, compact.ravel(), np.concatenate([[0], np.cumsum(sizes)]), sizes)
        self.backend, self._partition = backend_for(backend, self.n_unknowns, lambda: dense.Partition.of(
            np.repeat(np.arange(N), sizes), chain.compact, base, n))
        measurement = self._measurement(blocks, chain)
        covariances, independent = _covariances_by_size(blocks, sizes)
        self.groups: list[Group] = [self._group(ks, chain, measurement, covariances, bool(independent[ks[0]]))
                                    for ks in grouping.size_classes(sizes, independent)]
        self._pattern: BlockPattern | None = None
        self._evaluated: tuple[np.ndarray, list] | None = None

    # ---- set-up -------------------------------------------------------------------------

    def _base_poses(self, blocks: Blocks, origins: Sequence[int] | None) -> np.ndarray:
        """Each map's base pose: the index of the map ending where it starts, -1 for a map
        starting at a fixed origin; a pose ending two maps, an origin that ends one, or a
        start that is neither are errors."""
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
        return np.where(at_origin, -1, base)

    def _measurement(self, blocks: Blocks, chain: _Chain) -> np.ndarray:
        """All maps' states ``s_k`` in residual order, and a spare last row for the groups' padding."""
        N = self.n_maps
        measurement = np.zeros(self.n_residuals + 1)
        measurement[self.row0[:-1, None] + np.arange(3)] = blocks.end_poses
        owner = np.repeat(np.arange(N), chain.sizes)
        first_row = self.row0[owner] + 3 + 2 * (np.arange(len(owner)) - chain.feature0[owner])
        measurement[first_row[:, None] + np.arange(2)] = blocks.features
        return measurement

    def _group(self, ks: np.ndarray, chain: _Chain, measurement: np.ndarray,
               covariances: dict[int, tuple[np.ndarray, np.ndarray]], independent: bool) -> Group:
        """The group of maps ``ks``: their whitening, the parts of their information that the
        evaluation rotates, and where their residuals, columns and nodes are."""
        N = self.n_maps
        G, real, m = len(ks), chain.sizes[ks], int(chain.sizes[ks].max())
        p = m + 1
        point = np.arange(p) <= real[:, None]                   # real points (the rest is padding)
        entry = np.concatenate([point, point, np.ones((G, 1), dtype=bool)], axis=1)
        stacks = []                                             # (which maps, their covariances) by size
        for r in np.flatnonzero(np.bincount(real)).tolist():   # the sizes present (np.unique imports numpy.ma)
            members, stack = covariances[r]
            mine = real == r
            stacks.append((mine, stack[np.searchsorted(members, ks[mine])]))
        layout = grouping.piece_layout(p, independent)
        whitening, information = grouping.whitening(stacks, point, independent)
        has_base = chain.base[ks] >= 0
        b = np.where(has_base, chain.base[ks], ks)
        feature = point[:, 1:]
        fidx = np.where(feature, chain.compact[np.where(feature, chain.feature0[ks][:, None] + np.arange(m), 0)], 0)
        fx = np.where(feature, 3 * N + 2 * fidx, self.n_unknowns)     # padding: a spare unknown
        fy = np.where(feature, fx + 1, fx)
        pose = 3 * ks[:, None]
        columns = np.concatenate([pose, fx, pose + 1, fy, pose + 2, 3 * b[:, None] + np.arange(3)], axis=1)
        nodes = np.concatenate([ks[:, None], N + fidx, b[:, None]], axis=1)
        rows = np.where(entry, self.row0[ks][:, None] + grouping.state_order(m), self.n_residuals)
        coupled = grouping.coupled_nodes(information, point, independent)
        coupled[~has_base, -1, :] = coupled[~has_base, :, -1] = False    # no base: its columns are zero
        return Group(ks, b, has_base, fidx, whitening, measurement[rows], rows, columns, nodes, coupled, layout,
                     grouping.rotated_information(information, layout))

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

    def variances(self, global_map: GlobalMap) -> tuple[np.ndarray, np.ndarray]:
        """The spherical variances ``(poses (N, 2), features (n,))`` ``global_map`` holds for the
        unknowns (it must hold every pose and feature)."""
        return (_lookup(global_map.pose_ids, global_map.pose_variances, self.pose_ids, "pose", global_map.name),
                _lookup(global_map.feature_ids, global_map.feature_variances, self.feature_ids, "feature",
                        global_map.name))

    # ---- evaluation ---------------------------------------------------------------------

    def _geometry(self, group: Group, x: np.ndarray):
        """Base pose's rotation (cos, sin: (G, 1)) and the map's measurements predicted at ``x``: the
        points (end pose position, features) seen from the base pose (``se2.to_frame``), x's and y's,
        and the end pose's orientation relative to the base's, unwrapped."""
        N = self.n_maps
        poses = x[:3 * N].reshape(N, 3)
        features = x[3 * N:].reshape(-1, 2)
        bp = poses[group.base] * group.has_base[:, None]
        points = np.concatenate([poses[group.maps, None, :2], features[group.features]], axis=1)
        local = to_frame(bp[:, None, :], points)
        return np.cos(bp[:, 2:]), np.sin(bp[:, 2:]), local[..., 0], local[..., 1], poses[group.maps, 2] - bp[:, 2]

    def _residual(self, group: Group, geometry) -> np.ndarray:
        _, _, lx, ly, phi = geometry
        e = group.measurement - np.concatenate([lx, ly, phi[:, None]], axis=1)
        e[:, -1] = wrap(e[:, -1])
        return np.matmul(group.whitening, e[:, :, None])[:, :, 0]

    def _jacobian(self, group: Group, geometry) -> np.ndarray:
        """(G, d, w): d r / d (the group's columns) for every map of the group."""
        c, s, lx, ly, _ = geometry
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
        import scipy.sparse as sp

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
        """Once: the fill-reducing node order (the natural one for the dense backend, which factorises in
        its own order, :class:`.dense.Partition`), the CSC
        pattern of J^T J in it (with the closed node pattern for the sparse marginal
        covariances), and where each map block's entries go."""
        if self._pattern is not None:
            return
        N, n = self.n_maps, self.n_features
        n_nodes = N + n
        keys = self._node_pairs(n_nodes)
        pairs = np.concatenate(keys)
        # the distinct pairs and where each pair is among them: a sort and a search (np.unique's inverse takes an
        # argsort and a scatter: 0.65 s against 0.46 s for the 4.7 million pairs of 10^4 maps)
        natural = np.sort(pairs)
        natural = natural[np.concatenate([[True], natural[1:] != natural[:-1]])]
        inverse = np.searchsorted(natural, pairs)
        del pairs
        col, row = natural // n_nodes, natural % n_nodes
        if self.backend == "dense":
            order, self._closed = np.arange(n_nodes), None
        else:
            order, self._closed = fill_reducing_order(row, col, n_nodes)
        self._pattern = BlockPattern(col, row, order, np.concatenate([np.full(N, 3), np.full(n, 2)]))
        slots = np.split(self._pattern.rank[inverse], np.cumsum([k.size for k in keys])[:-1])
        self._place_blocks(order, slots)
        self._pattern.placed()

    def _node_pairs(self, n_nodes: int) -> list[np.ndarray]:
        """Per group, the node pairs (keys ``column * n_nodes + row``) its maps' information
        couples (a clique for a full covariance)."""
        keys = []
        for group in self.groups:
            nodes = group.nodes
            w = nodes.shape[1]
            pairs = np.repeat(nodes, w, axis=1) * n_nodes + np.tile(nodes, (1, w))
            keys.append(pairs[group.coupled.reshape(len(nodes), -1)])
        return keys

    def _place_blocks(self, order: np.ndarray, slots: list[np.ndarray]) -> None:
        """Where each evaluated entry of each map's J_k^T J_k (see :func:`.groups.piece_layout`),
        its J_k^T r_k and its base angle's row of the second-order term go: entry (i, j) of
        J_k^T J_k is row columns[i], column columns[j] of J^T J, on or below the diagonal.
        ``slots``: per group, the node entry of each of its coupled node pairs."""
        pattern = self._pattern
        csc = pattern.column_start, pattern.col_length, pattern.row_offset, pattern.nnz   # see groups.entries
        gradient_columns, angle_targets = [], []
        block_offset = gradient_offset = 0
        # where each block entry goes, filled group by group (a list of the pieces and its concatenation
        # would hold them twice: 2 x 88 MB at 10^4 maps)
        # in numpy's index integer: np.bincount copies any other into a new array at every linearisation (at 10^4
        # maps 92 MB: 0.035 s of page faults each time, 0.5 s a solve, against the 46 MB that 32 bits would save)
        self._targets = np.empty(sum(len(g.maps) * len(g.layout.rows) for g in self.groups), dtype=np.intp)
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
            pieces = grouping.entries(layout.rows, layout.cols, node_of, offset_of, placed, full, csc)
            group.block_offset, group.gradient_offset = block_offset, gradient_offset
            gradient_offset += group.columns.size
            bounds = np.cumsum([0] + [math.prod(shape) for shape in layout.shapes])
            for lo, hi in itertools.pairwise(bounds):   # piece by piece (see groups.pieces)
                self._targets[block_offset:block_offset + G * (hi - lo)] = pieces[:, lo:hi].ravel()
                block_offset += G * (hi - lo)
            gradient_columns.append(group.columns.ravel())
            w = group.columns.shape[1]
            angle_targets.append(grouping.entries(np.full(w, w - 1), np.arange(w), node_of, offset_of, placed,
                                                  full, csc).ravel())
        self._gradient_columns = np.concatenate(gradient_columns)
        # the second-order term's own slots (its base angles' rows: 0.5 M at 10^4 maps), not all of J^T J's
        # (a fresh 84 MB array and a second for J^T J plus it, at each Newton step); the padding's last
        self._curvature_slots, self._curvature_index = np.unique(np.concatenate(angle_targets), return_inverse=True)
        self._curvature_count = int(np.searchsorted(self._curvature_slots, self._pattern.nnz))
        # the blocks' buffer is made by each linearisation (its 88 MB at 10^4 maps not held through the
        # factorisations); the gradient's is small
        self._buffer_size, self._gradient_buffer = block_offset, np.empty(gradient_offset)

    @property
    def position(self) -> np.ndarray:
        """Row/column of each unknown in the factorised J^T J (a fill-reducing order)."""
        self._prepare()
        return self._pattern.position

    def linearise(self, x: np.ndarray, curvature: bool = False):
        """``(data, gradient, chi^2[, curvature data])`` at ``x``: the lower triangle of J^T J in its CSC
        layout (the slots above the diagonal hold zeros until :meth:`normal_matrix` mirrors it), J^T r
        (natural order), and with ``curvature`` the second-order term ``sum_i r_i d^2 r_i / dx^2`` (J^T J plus
        it is half the Hessian of chi^2) in its own slots of that layout only (:attr:`curvature_slots`;
        :meth:`factorise` adds it).

        Per map, with ``Lambda = P_k^-1``: the own columns' block is ``B^T Lambda B``, B the
        rotation by the base angle (:func:`.groups.own_blocks`); the base pose's columns are
        combinations of the own columns (:func:`.groups.base_blocks`); so a map costs one
        matrix-vector product and O(d^2) elementwise work. Only the lower triangle is
        accumulated (one ``bincount``), and mirrored only when factorised (:meth:`normal_matrix`, in place).
        """
        self._prepare()
        x = np.asarray(x, dtype=float)
        extra = [] if curvature else None
        cost = 0.0
        buffer = np.empty(self._buffer_size)
        for group, (geometry, r) in zip(self.groups, self._evaluate(x)):
            c, s, lx, ly, *_ = geometry
            cost += float(np.einsum("gi,gi->", r, r))
            mu = np.matmul(r[:, None, :], group.whitening)[:, 0, :]      # W^T r = P^-1 e
            views = grouping.pieces(buffer, group)
            grouping.own_blocks(group, c, s, views)
            v = grouping.base_blocks(group, c, s, lx, ly, views)
            size = group.columns.size
            g = self._gradient_buffer[group.gradient_offset:group.gradient_offset + size]
            grouping.gradient(group, c, s, mu, v, g.reshape(group.columns.shape))
            if curvature:
                extra.append(grouping.curvature(group, c, s, lx, ly, mu).ravel())
        pattern = self._pattern
        data = np.bincount(self._targets, buffer, minlength=pattern.nnz + 1)[:-1]
        del buffer
        gradient = np.bincount(self._gradient_columns, self._gradient_buffer, minlength=self.n_unknowns + 1)[:-1]
        if not curvature:
            return data, gradient, cost
        second = np.bincount(self._curvature_index, np.concatenate(extra),
                             minlength=len(self._curvature_slots))[:self._curvature_count]
        return data, gradient, cost, second

    @property
    def curvature_slots(self) -> np.ndarray:
        """The slots of J^T J's CSC data (lower triangle) that the second-order term of :meth:`linearise` fills,
        one per value, ascending."""
        self._prepare()
        return self._curvature_slots[:self._curvature_count]

    def normal_matrix(self, data: np.ndarray) -> sp.csc_matrix:
        """J^T J (from its lower triangle ``data``, see :meth:`linearise`) as a symmetric CSC matrix in the
        factor's order: entry (position[i], position[j]) is (i, j). Its data is ``data`` itself, whose slots
        above the diagonal take their mirrors' values (:meth:`.sparse.BlockPattern.mirror`; every reader of
        ``data`` reads only the lower triangle)."""
        return self._pattern.matrix(self._pattern.mirror(data))

    def factorise(self, data: np.ndarray, damping: float = 0.0, second: np.ndarray | None = None
                  ) -> Factor | dense.DenseFactor:
        """The factor of ``J^T J + damping diag(J^T J)``: SuperLU's (:mod:`.factor`, in the fill-reducing
        order), or the dense backend's (:func:`.dense.factorise`); raises RuntimeError if singular. With
        ``second`` (the second-order term of :meth:`linearise`), of Newton's matrix J^T J plus it: added into
        ``data``'s own slots for the factorisation and their values put back after it, the same numbers as
        ``data + second`` in full without a second copy of J^T J (the slots above the diagonal, which no
        reader of ``data`` reads, are left holding Newton's)."""
        if second is None:
            return self._factorise(data, damping)
        slots = self.curvature_slots
        kept = data[slots]
        data[slots] += second
        try:
            return self._factorise(data, damping)
        finally:
            data[slots] = kept

    def _factorise(self, data: np.ndarray, damping: float) -> Factor | dense.DenseFactor:
        """The factor of ``data`` (J^T J's layout) damped by ``damping diag``, by the problem's backend."""
        if damping:
            data = data.copy()
            data[self._pattern.diagonal] *= 1.0 + damping
        if self.backend == "dense":
            return dense.factorise(self._pattern, self._partition, data)
        return factorise(self.normal_matrix(data))

    def solve(self, factor: Factor, rhs: np.ndarray) -> np.ndarray:
        """``(J^T J)^-1 rhs`` (natural order; ``rhs`` a vector or a matrix of columns) with a
        factor from :meth:`factorise`."""
        position = self._pattern.position
        permuted = np.empty(np.shape(rhs))
        permuted[position] = rhs
        return factor.solve(permuted)[position]

    def diagonal(self, data: np.ndarray) -> np.ndarray:
        """diag(J^T J) in natural order."""
        return data[self._pattern.diagonal]

    def marginals(self, factor: Factor) -> tuple[np.ndarray, np.ndarray]:
        """Marginal covariances ``(poses (N, 3, 3), features (n, 2, 2))``, the diagonal blocks
        of ``(J^T J)^-1``, by selected inversion of an undamped factor from :meth:`factorise`,
        which it uses up (:func:`.sparse.diagonal_blocks`; the dense backend: from the inverse of its Cholesky
        factor, :func:`.dense.diagonal_blocks`)."""
        N, n = self.n_maps, self.n_features
        poses = np.arange(3 * N).reshape(N, 3)
        features = 3 * N + np.arange(2 * n).reshape(n, 2)
        if self.backend == "dense":
            pose_covariances, feature_covariances = dense.diagonal_blocks(factor, [poses, features])
        else:
            pose_covariances, feature_covariances = diagonal_blocks(factor, self._pattern, self._closed,
                                                                    [poses, features])
        return pose_covariances, feature_covariances


class _Chain(NamedTuple):
    """How the maps link and what they saw: each map's base pose (-1: the origin), the
    compact index of every feature observation, where each map's observations start
    (``feature0``, with the total last), and each map's size."""

    base: np.ndarray
    compact: np.ndarray
    feature0: np.ndarray
    sizes: np.ndarray


def _as_blocks(measurements: Sequence[LocalMap] | Blocks) -> Blocks:
    """``measurements`` as :class:`Blocks` (local maps: one block each)."""
    if isinstance(measurements, Blocks):
        return measurements
    maps = list(measurements)
    if not maps:
        raise JoinError("no local maps to join")
    return Blocks.of_maps(maps)


def _covariances_by_size(blocks: Blocks, sizes: np.ndarray) -> tuple[dict[int, tuple[np.ndarray, np.ndarray]],
                                                                      np.ndarray]:
    """The blocks' covariances by size m, ``{m: (blocks of that size, their covariances)}``,
    and which blocks' points are independent (:func:`.groups.independent_points`)."""
    covariances, independent = {}, np.zeros(len(sizes), dtype=bool)
    for m in np.flatnonzero(np.bincount(sizes)).tolist():   # the sizes present (np.unique imports numpy.ma)
        ks = np.flatnonzero(sizes == m)
        covariances[m] = ks, np.asarray(blocks.covariances(ks), dtype=float)
        independent[ks] = grouping.independent_points(covariances[m][1])
    return covariances, independent


def _lookup(ids: np.ndarray, values: np.ndarray, wanted: np.ndarray, what: str, source: str) -> np.ndarray:
    """The rows of ``values`` (one per id of the initial map ``source``) for the ids ``wanted``."""
    index, found = locate(ids, wanted, np.argsort(ids, kind="stable"))
    missing = ~found
    if missing.any():
        raise JoinError(f"the initial map {source} has no {what} {int(wanted[missing][0])} "
                        f"({int(missing.sum())} {what}s missing)")
    return np.asarray(values, dtype=float)[index]
