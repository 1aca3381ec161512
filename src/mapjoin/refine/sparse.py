"""Sparse symmetric factorisation of the normal equations and selected inversion.

The normal matrix ``J^T J`` of the exact join (docs/method.md#exact-joining) is a matrix of
node blocks: a node is a pose (3 unknowns) or a feature (2), and two nodes are coupled
when one local map sees both. Its pattern is fixed, so the work that depends only on it
is done once:

* :func:`fill_reducing_order`: multiple minimum degree (SuperLU's) on the node graph,
  re-postordered so that supernodes chain, with the closed symbolic pattern of the factor;
* :class:`BlockPattern`: the scalar CSC pattern of the node-block matrix in that order, and
  where each scalar entry, its mirror and each diagonal entry live;
* the factorisation ``J^T J = L D L^T`` in that order is :mod:`.factor`'s (SuperLU).

Marginal covariances (:func:`diagonal_blocks`): the diagonal blocks of ``(J^T J)^-1`` by
supernodal selected inversion (Takahashi's recursion, :func:`selected_inverse`) on the
factor: only the entries of the inverse on the pattern of L (closed under elimination)
are computed, top-down along the supernodal elimination tree, never the whole inverse.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from .factor import SYMMETRIC_MODE

if TYPE_CHECKING:
    import scipy.sparse as sp

    from .factor import Factor

# scipy is imported by the functions that use it: BlockPattern's arithmetic is numpy's, and the dense
# backend (.dense) of a small problem uses it without scipy

__all__ = ["BlockPattern", "Supernodes", "closed_pattern", "diagonal_blocks", "fill_reducing_order",
           "selected_inverse"]

_SUPERNODE_OVERHEAD = 5e4  # flops worth one supernode's Python overhead in the selected inversion


def fill_reducing_order(row: np.ndarray, col: np.ndarray, n_nodes: int) -> tuple[np.ndarray, np.ndarray]:
    """``(order, closed)`` for the symmetric node pattern ``(row, col)`` (both triangles and
    the diagonal): ``order[node]`` its position, by minimum degree then a postorder of the
    same elimination tree (same fill) putting each node's heaviest child right before it, so
    that supernodes can be merged; ``closed``: the strictly lower pattern of the factor in
    positions (keys ``col * n_nodes + row``, sorted, closed under elimination, see
    :func:`closed_pattern`), for the selected inversion."""
    # The values make the matrix a weighted Laplacian plus 1e-3 I: an M-matrix, so its factor
    # has no cancellation (nor, as the shift is small, decay to underflow), and its pattern is
    # the symbolic one.
    import scipy.sparse as sp
    from scipy.sparse.linalg import splu

    off = row != col
    graph = sp.csc_matrix((np.where(off, -1.0, 1e-3 + np.bincount(col[off], minlength=n_nodes)[col]),
                           (row, col)), shape=(n_nodes, n_nodes))
    lu = splu(graph, permc_spec="MMD_AT_PLUS_A", **SYMMETRIC_MODE)
    if not np.array_equal(lu.perm_r, lu.perm_c):
        raise np.linalg.LinAlgError("SuperLU pivoted on the node graph")
    order = np.asarray(lu.perm_c, dtype=np.int64)   # node -> position
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
    pattern = closed_pattern(pattern, n_nodes)
    relabel = _heavy_last_postorder(pattern, n_nodes)
    pattern = np.sort(relabel[pattern // n_nodes] * n_nodes + relabel[pattern % n_nodes])
    return relabel[order], pattern


# entries handled at a time where whole index arrays would be large temporaries: a chunk's 64-bit temporaries
# (2 MB) are reused from the heap, below numpy's huge-page requests (4 MB) and the sizes glibc maps afresh for
# each (at 10^4 maps, against 2^21: 6 % fewer page faults in the refine, its peak 1.52 -> 1.43 GB)
_CHUNK = 1 << 18


def _chunks(indptr: np.ndarray, size: int) -> list[tuple[int, int]]:
    """Runs ``(a, b)`` of the columns of a CSC ``indptr`` holding about ``size`` entries each (at least a column)."""
    n = len(indptr) - 1
    runs, a = [], 0
    while a < n:
        b = min(max(int(np.searchsorted(indptr, indptr[a] + size, side="right")) - 1, a + 1), n)
        runs.append((a, b))
        a = b
    return runs


class BlockPattern:
    """The scalar CSC pattern of a symmetric matrix of node blocks in a node order.

    Built from the node pattern ``(col, row)`` (natural node ids, both triangles), the
    node order ``order[node] = position`` and each node's scalar size. Scalar unknowns are
    numbered node by node in natural order; ``position[i]`` is unknown i's row/column. Only
    the lower triangle is accumulated (see :meth:`mirror`). Node entry t (column node C,
    row node at or below it) holds scalar (i, j) at ``column_start[C] + j * col_length[C] +
    row_offset[t] + i``; ``rank[e]`` is the node entry of the e-th given pair.
    """

    def __init__(self, col: np.ndarray, row: np.ndarray, order: np.ndarray, node_size: np.ndarray):
        n_nodes = len(node_size)
        self.size = size = np.empty(n_nodes, dtype=np.int64)
        size[order] = node_size                           # node size by position
        start = np.concatenate([[0], np.cumsum(size)])
        unknown_node = np.repeat(np.arange(n_nodes), node_size)
        unknown_offset = np.arange(len(unknown_node)) - np.repeat(np.cumsum(node_size) - node_size, node_size)
        self.n = len(unknown_node)
        self.position = start[order[unknown_node]] + unknown_offset
        # node CSC pattern in positions
        pkeys = order[col] * n_nodes + order[row]
        sort = np.argsort(pkeys)
        self.rank = np.empty(len(sort), dtype=np.int64)
        self.rank[sort] = np.arange(len(sort))
        pkeys = pkeys[sort]
        ncol, nrow = pkeys // n_nodes, pkeys % n_nodes
        nptr = np.searchsorted(ncol, np.arange(n_nodes + 1))
        row_size = size[nrow]
        cum = np.concatenate([[0], np.cumsum(row_size)])
        self.row_offset = cum[:-1] - cum[nptr[ncol]]           # scalar rows above node entry t in its column
        self.col_length = col_length = cum[nptr[1:]] - cum[nptr[:-1]]       # scalar rows of each node column
        # scalar CSC: every scalar column of node column c holds the rows of c's node entries, in order
        # (a "template" per node column: node entry t and row offset i of each of its scalar rows)
        column_length = np.repeat(col_length, size)
        indptr = np.concatenate([[0], np.cumsum(column_length)])
        self.nnz = nnz = int(indptr[-1])
        template_entry = np.repeat(np.arange(len(pkeys)), row_size)
        template_row = start[nrow][template_entry] + np.arange(len(template_entry)) - cum[:-1][template_entry]
        # the lower triangle is accumulated; an entry above the diagonal takes its mirror's value
        transposed_slot = np.searchsorted(pkeys, nrow * n_nodes + ncol)
        template_mirror = self.row_offset[transposed_slot][template_entry]
        scalar_node = np.repeat(np.arange(n_nodes), size)
        template_start = indptr[:-1] - cum[nptr[scalar_node]]     # each scalar column's first template entry
        within = np.arange(len(scalar_node)) - start[scalar_node]   # its offset j in its node
        # the scalar entries a chunk of columns at a time, in 32-bit indices: at 10^4 maps (10^7 entries)
        # the whole arrays' temporaries took 0.9 GB. The slots above the diagonal and their mirrors below it
        # (:meth:`mirror`): half the pattern less the diagonal, as the pattern is symmetric
        index = np.int32 if nnz < 2 ** 31 - 1 else np.int64
        self.indices = np.empty(nnz, dtype=np.int32)
        self.upper, self.twin = np.empty((2, (nnz - self.n) // 2), dtype=index)
        filled = 0
        for a, b in _chunks(indptr, _CHUNK):
            e0, e1 = indptr[a], indptr[b]
            lengths = column_length[a:b]
            column = np.repeat(np.arange(a, b), lengths)
            entry = np.arange(e0, e1)
            template = entry - np.repeat(template_start[a:b], lengths)
            indices = template_row[template]
            self.indices[e0:e1] = indices
            above = np.flatnonzero(indices < column)
            self.upper[filled:filled + above.size] = entry[above]
            self.twin[filled:filled + above.size] = (indptr[indices[above]] + template_mirror[template[above]]
                                                     + np.repeat(within[a:b], lengths)[above])
            filled += above.size
        if filled != self.upper.size:
            raise AssertionError("the node pattern is not symmetric")
        self.indptr = indptr.astype(np.int32)
        self.column_start = indptr[start[:-1]]
        diagonal_slot = np.searchsorted(pkeys, np.arange(n_nodes) * (n_nodes + 1))
        self.diagonal = (indptr[self.position] + self.row_offset[diagonal_slot[order[unknown_node]]]
                         + unknown_offset)                # CSC index of A[i, i], natural order

    def placed(self) -> None:
        """Drop what only placing the blocks needs (``rank``, ``row_offset``, ``col_length``,
        ``column_start``): at 10^4 maps 50 MB otherwise held through every factorisation."""
        del self.rank, self.row_offset, self.col_length, self.column_start

    def mirror(self, data: np.ndarray) -> np.ndarray:
        """``data`` holding the lower triangle (its slots above the diagonal ignored) made the whole symmetric
        CSC data in place: each slot above the diagonal takes its mirror's value, a chunk at a time (numpy makes
        a 64-bit copy of 32-bit indices; ``take`` and ``put`` took 34 ms where indexing took 42 at 10^4 maps).
        Returns ``data``. In place, as every reader of the lower triangle ignores the slots above it: no second
        array of the matrix's size (a fresh 84 MB at 10^4 maps), and half the entries copied."""
        for a in range(0, self.upper.size, _CHUNK):
            data.put(self.upper[a:a + _CHUNK], data.take(self.twin[a:a + _CHUNK]))
        return data

    def matrix(self, data: np.ndarray) -> sp.csc_matrix:
        """The matrix of CSC ``data``: entry (position[i], position[j]) is (i, j)."""
        import scipy.sparse as sp

        return sp.csc_matrix((data, self.indices, self.indptr), shape=(self.n, self.n))


def diagonal_blocks(factor: Factor, pattern: BlockPattern, closed: np.ndarray, blocks: list[np.ndarray]
                    ) -> list[np.ndarray]:
    """Diagonal blocks of the inverse of the matrix ``factor`` (a :class:`.factor.Factor` of the
    matrix of ``pattern``) factorises: for each (k, s) array of unknowns in ``blocks``, the (k, s, s)
    blocks of the inverse over each row's unknowns, by selected inversion on ``closed``, the
    closed node pattern of :func:`fill_reducing_order` (or, when the factor is in another order
    after all, on the factor's own pattern closed). Uses the factor up (:meth:`.Factor.triangle`):
    its storage is freed before the inversion's, and the triangle's once it is in the supernodal
    blocks."""
    nv = pattern.n
    perm = np.asarray(factor.perm)
    natural = np.array_equal(perm, np.arange(nv))
    where = pattern.position if natural else perm[pattern.position]
    placed = [(where[b], b.shape[1]) for b in blocks]
    rows = np.concatenate([np.repeat(b, size, axis=1).ravel() for b, size in placed])
    cols = np.concatenate([np.tile(b, (1, size)).ravel() for b, size in placed])
    wanted = (np.maximum(rows, cols), np.minimum(rows, cols))
    L, D = factor.triangle()            # the factor's own storage freed
    values = None
    if natural:   # the factor is in node order: use the symbolic node pattern
        structure = Supernodes(closed, pattern.size)
        flat = _scatter(structure, L)
        if flat is not None:
            del L
            values = _invert(structure, flat, D, *wanted)
    if values is None:   # general: close the factor's own pattern (with that of the matrix)
        Lrow, Lcol, Lval = _strictly_lower(L)
        A = pattern.matrix(np.ones(pattern.nnz)).tocoo()
        ar, ac = perm[A.row], perm[A.col]
        keep = ar > ac
        keys = closed_pattern(np.concatenate([Lcol, ac[keep]]) * nv + np.concatenate([Lrow, ar[keep]]), nv)
        values = selected_inverse(Supernodes(keys, np.ones(nv, dtype=np.int64)), Lrow, Lcol, Lval, D, *wanted)
        if values is None:
            raise np.linalg.LinAlgError("the factor's pattern is not closed")
    ends = np.cumsum([b.size * b.shape[1] for b in blocks])[:-1]
    return [v.reshape(len(b), b.shape[1], b.shape[1]) for v, b in zip(np.split(values, ends), blocks)]


def _strictly_lower(L: sp.csc_matrix, first: int = 0, last: int | None = None
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(rows, columns, values)`` (int64, int64, float) of the non-zero entries of ``L`` below its diagonal, in
    the columns ``first`` to ``last`` (default: all)."""
    last = L.shape[1] if last is None else last
    lo, hi = L.indptr[first], L.indptr[last]
    col = np.repeat(np.arange(first, last, dtype=np.int64), np.diff(L.indptr[first:last + 1]))
    row = L.indices[lo:hi].astype(np.int64)
    value = L.data[lo:hi]
    keep = (row > col) & (value != 0)   # an explicit zero needs no place
    return row[keep], col[keep], value[keep]


def _scatter(structure: Supernodes, L: sp.csc_matrix) -> np.ndarray | None:
    """The strictly lower entries of the unit triangle ``L`` in the supernodal blocks of ``structure`` (see
    :func:`_invert`), a chunk of columns at a time; None if an entry does not fit the structure."""
    flat = np.zeros(structure.block_offset[-1])
    for first, last in _chunks(L.indptr, _CHUNK):
        if not _place(structure, flat, *_strictly_lower(L, first, last)):
            return None
    return flat


def _place(structure: Supernodes, flat: np.ndarray, Lrow: np.ndarray, Lcol: np.ndarray, Lval: np.ndarray) -> bool:
    """Put entries of L into ``flat``, per supernode J the b x (b + s) array whose row jc is column jc of
    ``[L_JJ; L_SJ]``; False if one does not fit the structure."""
    st = structure
    J = st.super_of[Lcol]
    at = st.locate(J, Lrow)
    if at is None:
        return False
    flat[st.block_offset[J] + (Lcol - st.start[J]) * (st.size[J] + st.below[J]) + at] = Lval
    return True


def closed_pattern(keys: np.ndarray, n: int) -> np.ndarray:
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


class Supernodes:
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


def selected_inverse(structure: Supernodes, Lrow: np.ndarray, Lcol: np.ndarray, Lval: np.ndarray,
                      D: np.ndarray, rows: np.ndarray, cols: np.ndarray) -> np.ndarray | None:
    """Entries ``(rows, cols)`` (rows >= cols, factor order) of ``A^-1`` for ``A = L D L^T``
    (unit lower L given by its strictly lower entries), by supernodal selected inversion
    (Takahashi's recursion, :func:`_invert`); None if L does not fit the structure."""
    flat = np.zeros(structure.block_offset[-1])
    if not _place(structure, flat, Lrow, Lcol, Lval):
        return None
    return _invert(structure, flat, D, rows, cols)


def _invert(structure: Supernodes, flat: np.ndarray, D: np.ndarray, rows: np.ndarray, cols: np.ndarray
            ) -> np.ndarray:
    """Entries ``(rows, cols)`` (rows >= cols, factor order) of ``A^-1`` for ``A = L D L^T``, the
    strictly lower entries of the unit L in ``flat``: per supernode J (from ``block_offset[J]``)
    the b x (b + s) array whose row jc is column jc of ``[L_JJ; L_SJ]``.

    Supernodes are visited from the last to the first. Supernode J needs ``Z[S, S]`` (S: the
    rows below it), a submatrix of the block ``Z[P+S_P, P+S_P]`` of its parent P, which is
    kept until P's last child is done. Per supernode: ``U = L_SJ L_JJ^-1``,
    ``Z_SJ = -Z_SS U``, ``Z_JJ = (L_JJ D_J L_JJ^T)^-1 - U^T Z_SJ``. Only these blocks of
    the inverse are formed, never the whole inverse, and of them only the wanted entries
    are kept, as each supernode is done.
    """
    st = structure
    J = st.super_of[cols]
    at = st.locate(J, rows)
    if at is None:
        raise np.linalg.LinAlgError("a wanted entry of the inverse is outside the factor's pattern")
    by = np.argsort(J, kind="stable")            # the wanted entries supernode by supernode
    local = ((cols - st.start[J]) * (st.size[J] + st.below[J]) + at)[by]
    bounds = np.searchsorted(J[by], np.arange(st.count + 1)).tolist()
    values = np.empty(len(rows))
    frontal: dict[int, np.ndarray] = {}
    children = st.children.copy()
    import scipy.linalg

    dtrtri = scipy.linalg.lapack.get_lapack_funcs("trtri", (D,))
    for J in range(st.count - 1, -1, -1):
        j0, b, s = st.start[J], st.size[J], st.below[J]
        o0, o1 = st.block_offset[J], st.block_offset[J + 1]
        block = flat[o0:o1].reshape(b, b + s)
        Linv, info = dtrtri(block[:, :b].T + np.eye(b), lower=1, unitdiag=1)
        if info:
            raise np.linalg.LinAlgError("singular diagonal block in the factor")
        Zjj = Linv.T @ (Linv / D[j0:j0 + b, None])
        out = np.empty((b, b + s))
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
        lo, hi = bounds[J], bounds[J + 1]
        if hi > lo:
            values[by[lo:hi]] = out.ravel()[local[lo:hi]]
        if children[J]:
            F = np.empty((b + s, b + s))
            F[:b, :b] = Zjj
            if s:
                F[b:, :b] = Zsj
                F[:b, b:] = Zsj.T
                F[b:, b:] = Zss
            frontal[J] = F
    return values
