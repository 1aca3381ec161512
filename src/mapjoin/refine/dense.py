"""Dense linear algebra for the normal equations of a small exact join: numpy's LAPACK, not scipy's sparse solvers.

A whole ``mapjoin refine`` of a few hundred unknowns spends more on importing scipy.sparse
than on its arithmetic; numpy, already loaded, solves such a system densely in
milliseconds. :data:`DENSE_WORK` (flops of the partitioned factorisation) is the crossover, measured on whole
commands (benchmarks/README.md, "Start-up"), :data:`DENSE_UNKNOWNS` a cap on the dense matrix's size;
:func:`backend_for` chooses by them.

The structure used (docs/method.md#exact-joining): a local map's information couples its end
pose, its base pose and all its features (a full covariance couples every pair of them), and
nothing else. So the chain of maps cut into K runs ("segments", :class:`Partition`), the
unknowns that only maps of one segment touch (its interior) couple with nothing of another
segment: they couple only with the separator, the unknowns that maps of several segments touch
(the poses at the cuts, features seen on both sides of one). In the order [interior 1, ...,
interior K, separator] the normal matrix is a block arrow,

    A = [[A_1, 0, ..., C_1^T], ..., [C_1, ..., C_K, A_S]]   (C_i: separator rows, interior i columns),

and its Cholesky factor keeps that pattern: ``A_i = L_i L_i^T``, ``B_i = C_i L_i^-T``, and the
separator's Schur complement ``S = A_S - sum_i B_i B_i^T = L_S L_S^T`` (the interiors
eliminated). The feature block is not block-diagonal (a map's full covariance couples its
features: VicPark 200's features couple with 51 others on average, DLR 200's with 18), so
features are eliminated a segment at a time, not one by one. Within an interior, the unknowns
that a map touching the separator also touches come last: ``C_i`` is zero before them, and so is
``B_i``, so only they enter the Schur complement; and ``C_i``'s rows are zero but for the separator's unknowns
that maps of segment i touch (``Partition.rows``: DLR 200's six segments meet 69-197 of its 397), so
``B_i`` has only those rows and updates only their block of ``S`` (a factorisation 17 % less CPU there, with four
segments). K is chosen once per problem by the dense work it leaves, those rows counted per segment
(:meth:`Partition.of`: K = 1 is the whole matrix); VicPark 200 takes K = 3 (separator 406 of 1198
unknowns, 628 of the 792 interior ones coupled to it; 195 MFlop a factorisation with the per-segment
allowance, against the whole Cholesky's 573), DLR 200 K = 6 (397 of 1698, 740 of 1301; 136 against
1632), 8240 K = 6 (141 of 1374; 91 against 865). Counting the separator's whole size per segment instead
chose K = 2 for VicPark 200 and K = 4 for DLR 200: measured in fresh processes as the command runs
(2026-11-26, load 2-3), DLR 200's factorisation 12-13 ms against 10-11 and its marginals 25-27 against 17
ms now (with :mod:`.triangular`'s block solves), VicPark 200's 11-15 against 10-14 and 20 against 17.5.

A step solves ``A x = b`` by the triangular solves of that factor (:mod:`.triangular`: numpy
has none, so they are matrix products by blocks, the blocks' inverses made once per factor, all interiors' in one
numpy call). The marginal covariances
(docs/method.md#marginal-covariances) are the diagonal blocks of ``A^-1 = L^-T L^-1``: the
column blocks of ``L^-1`` multiplied with themselves, where ``L^-1``'s columns of interior i
are ``L_i^-1`` over ``-L_S^-1 B_i L_i^-1`` and the separator's ``L_S^-1``; never the whole
inverse. A matrix Cholesky refuses (a Newton step's, which may be indefinite) is solved by LU
with partial pivoting (``numpy.linalg.solve``) and inverted whole.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable
from typing import TYPE_CHECKING, Literal

import numpy as np

from .triangular import Triangle

if TYPE_CHECKING:
    from .sparse import BlockPattern

__all__ = ["BACKENDS", "DENSE_UNKNOWNS", "DENSE_WORK", "Backend", "DenseFactor", "Partition", "backend_for",
           "diagonal_blocks", "factorise"]

Backend = Literal["auto", "dense", "sparse"]
BACKENDS: tuple[str, ...] = ("auto", "dense", "sparse")

#: no problem of more unknowns is solved densely under ``auto`` (its dense matrix, 8 n^2 bytes, is not even
#: partitioned): 4000 unknowns, 128 MB
DENSE_UNKNOWNS = 4000
#: under ``auto``, problems whose factorisation in their :class:`Partition` costs at most this many flops
#: (:attr:`Partition.work`) are solved densely. Measured on whole refines of the first maps of VicPark 200 and
#: DLR 200 and of 8240 (benchmarks/startup.py --crossover, 2026-11-26, load 3, OpenBLAS on one thread as the
#: command runs it): dense took 0.33-0.63 of the sparse backend's wall time up to 163 MFlop and 0.69-0.80 at
#: DLR 200's 214 (1698 unknowns) and VicPark 200's 217 (1198), the largest measured; a first partition without
#: the interiors' trailing blocks reached parity at 1.3 times that work. (Those works counted the separator's
#: whole size per segment; counting each segment's rows, these problems take 136 and 195 MFlop, and the bound was
#: kept: the crossover's own problems stay dense, larger ones are unmeasured.) A confirmation's solves take the
#: whole chain's backend (:func:`mapjoin.confirmation.chain_backend`).
DENSE_WORK = 2.5e8


def backend_for(backend: Backend, unknowns: int, partition: Callable[[], Partition]
                ) -> tuple[Literal["dense", "sparse"], Partition | None]:
    """The linear algebra of a problem of ``unknowns`` unknowns, and for the dense backend its
    :class:`Partition` (``partition()`` makes it): ``backend`` itself, or under ``auto`` dense if it has at
    most :data:`DENSE_UNKNOWNS` unknowns and its partition's work is at most :data:`DENSE_WORK` flops."""
    if backend not in BACKENDS:
        raise ValueError(f"backend must be one of {', '.join(BACKENDS)}, got {backend!r}")
    if backend == "sparse" or (backend == "auto" and unknowns > DENSE_UNKNOWNS):
        return "sparse", None
    found = partition()
    if backend == "auto" and found.work > DENSE_WORK:
        return "sparse", None
    return "dense", found


class Partition:
    """The dense backend's order of the unknowns: the interiors of K segments of the chain, then the
    separator (see the module docstring). ``order``: the unknowns in that order; ``position[u]``: where
    unknown u is; ``bounds``: where each interior starts, the separator's start last but one and the end
    last (K + 2 entries); ``segments``: K; ``coupled[i]``: how many unknowns at the end of interior i a map
    touching the separator touches (the others' rows of the separator are zero); ``rows[i]``: the separator's
    unknowns (from its start) that maps of segment i touch, the only rows of the separator that interior i
    meets (a slice when they are all of them); ``work``: the flops of one factorisation in this order (with
    :data:`_SEGMENT_WORK` per segment)."""

    def __init__(self, order: np.ndarray, bounds: np.ndarray, coupled: np.ndarray, work: float,
                 rows: list[np.ndarray | slice] | None = None):
        self.order, self.bounds, self.coupled, self.work = order, bounds, coupled, work
        self.rows = rows if rows is not None else [slice(None)] * (len(bounds) - 2)
        self.position = np.empty_like(order)
        self.position[order] = np.arange(len(order))
        self.segments = len(bounds) - 2
        self._lower: np.ndarray | None = None       # which CSC entries are on or below the diagonal
        self._targets: np.ndarray | None = None     # where they go in the dense matrix (flat)
        self._matrix: np.ndarray | None = None      # the dense matrix, filled anew by each scatter
        self._updates: list[np.ndarray | None] | None = None    # see updates

    @classmethod
    def of(cls, owner: np.ndarray, compact: np.ndarray, base: np.ndarray, n_features: int) -> Partition:
        """The partition of the least dense work for a chain of ``len(base)`` maps: map ``owner[o]`` saw
        feature ``compact[o]`` (observation o), map k's base pose is that of map ``base[k]`` (-1: the fixed
        origin). A map touches its own pose, its base pose and the features it saw; an unknown belongs to
        the interior of segment ``k * K // maps`` if every map k touching it lies there, else to the
        separator. Within an interior, the unknowns a map touching the separator also touches come last:
        only their columns of the separator's rows are non-zero, so only they enter its Schur complement; and of
        the separator's rows, only those of the unknowns that maps of its segment touch (``rows``: with more
        than two segments, a separator's unknown is seldom touched by all)."""
        n_maps = len(base)
        n_nodes = n_maps + n_features
        maps = np.arange(n_maps)
        based = base >= 0
        touching = np.concatenate([maps, base[based], n_maps + compact])        # node of each (map, node) pair
        toucher = np.concatenate([maps, maps[based], owner])
        first, last = np.full(n_nodes, n_maps), np.full(n_nodes, -1)
        np.minimum.at(first, touching, toucher)
        np.maximum.at(last, touching, toucher)
        size = np.where(np.arange(n_nodes) < n_maps, 3, 2)
        best = None
        for K in sorted({k for k in _SEGMENT_COUNTS if k <= n_maps} | {1}):
            segment = first * K // n_maps
            part = np.where(segment == last * K // n_maps, segment, K)
            separator = part == K
            at_separator = np.bincount(toucher[separator[touching]], minlength=n_maps) > 0     # per map
            near = (np.bincount(touching[at_separator[toucher]], minlength=n_nodes) > 0) & ~separator
            sizes = np.bincount(part, weights=size, minlength=K + 1)
            t = np.bincount(part[near], weights=size[near], minlength=K + 1)[:K]
            inner, s = sizes[:K], sizes[K]
            at = separator[touching]                    # the separator's rows each segment's maps touch (rows)
            seen = np.zeros((K, n_nodes), dtype=bool)
            seen[toucher[at] * K // n_maps, touching[at]] = True
            r = seen @ size
            work = float(np.sum(inner ** 3 / 3 + t ** 2 * r + t * r ** 2) + s ** 3 / 3) + _SEGMENT_WORK * K
            if best is None or work < best[0]:
                best = work, 2 * part + near, sizes, t, K, separator
        work, key, sizes, t, K, separator = best
        nodes = np.argsort(key, kind="stable")
        start = np.where(nodes < n_maps, 3 * nodes, 3 * n_maps + 2 * (nodes - n_maps))
        order = np.repeat(start, size[nodes]) + (np.arange(int(size.sum())) - np.repeat(
            np.cumsum(size[nodes]) - size[nodes], size[nodes]))
        return cls(order, np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64), t.astype(np.int64), work,
                   _separator_rows(touching, toucher, separator, size, K, n_maps))

    def updates(self) -> list[np.ndarray | None]:
        """Per segment, where the block of its ``rows`` lies in the separator's Schur complement (s, s), as flat
        (row-major) indices; None where its rows are all of them. Made once, for every factorisation's update
        ``S[rows, rows] -= B_i B_i^T``: index arrays made anew each time (``numpy.ix_``) took 2.2 ms of VicPark
        200's 10 ms factorisation, these 0.8 (in-process, 2026-11-26, load 4). Kept only while their bytes are no
        more than the dense matrix's the partition holds (:meth:`scatter`; VicPark 200: 2.8 MB against 11.5): with
        many segments each meeting much of a large separator they are made anew each time, as ``numpy.ix_`` was.
        In numpy's index integer: numpy converts any other at every use (32 bits took 0.78 ms for VicPark 200's
        largest block against 0.31)."""
        if self._updates is not None:
            return self._updates
        s = len(self.order) - int(self.bounds[-2])
        updates = [None if isinstance(rows, slice) else (rows[:, None] * s + rows).ravel().astype(np.intp, copy=False)
                   for rows in self.rows]
        if sum(update.nbytes for update in updates if update is not None) <= 8 * len(self.order) ** 2:
            self._updates = updates
        return updates

    def scatter(self, pattern: BlockPattern, data: np.ndarray) -> np.ndarray:
        """The dense matrix, in this order, holding on and below its diagonal the symmetric matrix whose lower
        triangle is the CSC ``data`` of ``pattern`` (natural order; the slots above its diagonal are not
        read): what the blockwise Cholesky reads. The same array each time, its other entries zero: a fresh one
        of VicPark 200's 11 MB took 2-25 ms of page faults in each factorisation, against 1 ms of filling.
        The matrix a scatter returns is thus the next one's: :class:`DenseFactor` keeps none of it (a copy
        where Cholesky refused)."""
        n = pattern.n
        if self._targets is None:
            columns = np.repeat(np.arange(n), np.diff(pattern.indptr))
            self._lower = pattern.indices >= columns
            row, col = self.position[pattern.indices[self._lower]], self.position[columns[self._lower]]
            self._targets = np.maximum(row, col) * n + np.minimum(row, col)
            self._matrix = np.zeros(n * n)
        self._matrix[self._targets] = data[self._lower]
        return self._matrix.reshape(n, n)


def _separator_rows(touching: np.ndarray, toucher: np.ndarray, separator: np.ndarray, size: np.ndarray,
                    K: int, n_maps: int) -> list[np.ndarray | slice]:
    """Per segment of K, the separator's unknowns (from its start, in node order as :meth:`Partition.of` puts
    them) that a map of the segment touches (map ``toucher[o]`` touches node ``touching[o]``); a slice when
    that is all of them."""
    rank = np.cumsum(separator) - 1                      # each separator node's place among them
    at = separator[touching]
    seen = np.zeros((K, int(separator.sum())), dtype=bool)
    seen[toucher[at] * K // n_maps, rank[touching[at]]] = True
    sizes = size[separator]
    return [slice(None) if mine.all() else np.flatnonzero(np.repeat(mine, sizes)) for mine in seen]


#: the segment counts :meth:`Partition.of` weighs (each no more than the maps)
_SEGMENT_COUNTS = (1, 2, 3, 4, 6, 8, 12, 16, 24, 32, 48, 64)
#: flops worth one segment's numpy calls (a few dozen, ~0.3 ms at this machine's ~25 GFlop/s)
_SEGMENT_WORK = 1e7


class DenseFactor:
    """The blockwise Cholesky factor of a normal matrix ``A`` in a :class:`Partition`'s order (see the module
    docstring): per interior ``L_i`` (a :class:`.triangular.Triangle`, the interiors' block inverses made by one
    numpy call) and the non-zero trailing columns of ``B_i``, and the separator's ``L_S``; or, where Cholesky refused
    (``A`` not positive definite, as a Newton step's may be), ``cholesky`` False and :meth:`solve` takes LU
    with partial pivoting of the whole matrix instead. ``matrix``: ``A`` in that order, lower triangle, kept (a
    copy: ``matrix`` is the partition's buffer, :meth:`Partition.scatter`) only where Cholesky refused."""

    def __init__(self, matrix: np.ndarray, partition: Partition):
        self.matrix: np.ndarray | None = None
        self.partition = partition
        bounds = partition.bounds
        s0 = bounds[-2]
        self.interiors: list[tuple[Triangle, np.ndarray]] = []
        schur = matrix[s0:, s0:].copy()
        entries = schur.reshape(-1)                             # a view: the copy is contiguous
        try:
            spans = list(itertools.pairwise(bounds[:-1]))
            triangles = Triangle.all_of([np.linalg.cholesky(matrix[a:b, a:b]) for a, b in spans])
            for L, (a, b), t, rows, update in zip(triangles, spans, partition.coupled, partition.rows,
                                                  partition.updates()):
                c = b - a - t                                   # the interior's first unknown a map at the
                # separator touches: C_i L_i^-T's columns from there (before it they are zero), its rows those
                # of the separator's unknowns the segment's maps touch (the others are zero)
                B = L.solve(matrix[s0:, a + c:b][rows].T, c).T
                if update is None:
                    schur -= B @ B.T
                else:
                    entries[update] -= (B @ B.T).ravel()
                self.interiors.append((L, B))
            self.separator = Triangle.all_of([np.linalg.cholesky(schur)])[0]
            self.cholesky = True
        except np.linalg.LinAlgError:
            self.interiors, self.cholesky, self.matrix = [], False, matrix.copy()

    def solve(self, rhs: np.ndarray) -> np.ndarray:
        """``A^-1 rhs`` (``rhs`` and the result in the natural order); RuntimeError if ``A`` is exactly
        singular (as SuperLU's factor raises)."""
        partition = self.partition
        b = rhs[partition.order]
        if not self.cholesky:
            try:
                x = np.linalg.solve(_mirrored(self.matrix), b)
            except np.linalg.LinAlgError:
                raise RuntimeError("the normal matrix is exactly singular") from None
        else:
            bounds = partition.bounds
            s0 = bounds[-2]
            y = [L.solve(b[a:c]) for (L, _), a, c in zip(self.interiors, bounds[:-2], bounds[1:-1])]
            ys = b[s0:].copy()
            for (_, B), yi, rows in zip(self.interiors, y, partition.rows):
                ys[rows] -= B @ yi[len(yi) - B.shape[1]:]
            xs = self.separator.solve_transposed(self.separator.solve(ys))
            for (_, B), yi, rows in zip(self.interiors, y, partition.rows):
                yi[len(yi) - B.shape[1]:] -= B.T @ xs[rows]
            x = np.concatenate([L.solve_transposed(yi) for (L, _), yi in zip(self.interiors, y)] + [xs])
        return x[partition.position]

    def inverse_columns(self) -> list[tuple[int, np.ndarray]]:
        """``L^-1`` by column blocks: ``(first, Z)`` per interior and the separator, Z holding the non-zero rows
        (the interior's, then the separator's) of the columns ``first ..`` (in the partition's order)."""
        bounds = self.partition.bounds
        separator_inverse = self.separator.inverse()
        blocks = []
        for (L, B), a, rows in zip(self.interiors, bounds[:-2], self.partition.rows):
            W = L.inverse()
            # (L_S^-1 B_i) L_i^-1's trailing rows: B_i's columns are the fewer
            blocks.append((int(a), np.concatenate([W, -(separator_inverse[:, rows] @ B) @ W[len(W) - B.shape[1]:]])))
        blocks.append((int(bounds[-2]), separator_inverse))
        return blocks


def _mirrored(lower: np.ndarray) -> np.ndarray:
    """The symmetric matrix whose lower triangle is ``lower``'s."""
    return np.tril(lower) + np.tril(lower, -1).T


def factorise(pattern: BlockPattern, partition: Partition, data: np.ndarray) -> DenseFactor:
    """The dense factor, in ``partition``'s order, of the symmetric matrix whose lower triangle is the CSC
    ``data`` of ``pattern`` (built in the natural node order; the slots above the diagonal are not read)."""
    return DenseFactor(partition.scatter(pattern, data), partition)


def diagonal_blocks(factor: DenseFactor, blocks: list[np.ndarray]) -> list[np.ndarray]:
    """Diagonal blocks of ``A^-1`` for each (k, s) array of unknowns (natural order) in ``blocks``: (k, s, s)
    each, a node's unknowns (a pose's, a feature's) per row. With the Cholesky factor, block ``b`` is
    ``L^-1[:, b]^T L^-1[:, b]`` (``A^-1 = L^-T L^-1``), its columns taken from the part holding the node
    (:meth:`DenseFactor.inverse_columns`); else (``A`` not positive definite) from the whole inverse.
    Symmetrised: a covariance written as its upper triangle (CSV) must read back equal to one written
    whole (JSON, YAML)."""
    position = factor.partition.position
    if not factor.cholesky:
        inverse = np.linalg.inv(_mirrored(factor.matrix))
        found = [inverse[position[b][:, :, None], position[b][:, None, :]] for b in blocks]
    else:
        parts = factor.inverse_columns()
        found = [np.empty((len(b), b.shape[1], b.shape[1])) for b in blocks]
        for b, out in zip(blocks, found):
            at = position[b]                                         # (k, s): a node's unknowns stay together
            part = np.searchsorted(factor.partition.bounds, at[:, 0], side="right") - 1
            for p, (first, Z) in enumerate(parts):
                mine = part == p
                if mine.any():
                    columns = Z[:, at[mine] - first]                 # (rows, k', s)
                    out[mine] = np.einsum("rki,rkj->kij", columns, columns)
    return [(f + f.transpose(0, 2, 1)) / 2 for f in found]
