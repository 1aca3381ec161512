"""The scalar CSC pattern of the normal matrix (mapjoin.refine.sparse.BlockPattern) and its mirror, made in
place: against a dense symmetric matrix of node blocks built entry by entry, for random node patterns, node
sizes, orders and chunk sizes."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mapjoin.refine import sparse
from mapjoin.refine.sparse import BlockPattern


@st.composite
def node_patterns(draw):
    """(node sizes, symmetric node adjacency with its diagonal, node order, chunk size)."""
    n_nodes = draw(st.integers(1, 7))
    sizes = np.array(draw(st.lists(st.sampled_from([2, 3]), min_size=n_nodes, max_size=n_nodes)))
    upper = np.array(draw(st.lists(st.booleans(), min_size=n_nodes * n_nodes, max_size=n_nodes * n_nodes)))
    coupled = np.triu(upper.reshape(n_nodes, n_nodes), 1)
    coupled = coupled | coupled.T | np.eye(n_nodes, dtype=bool)
    order = np.array(draw(st.permutations(range(n_nodes))))
    return sizes, coupled, order, draw(st.integers(1, 9))


@settings(max_examples=60, deadline=None)
@given(node_patterns(), st.integers(0, 2 ** 31))
def test_the_mirrored_lower_triangle_is_the_dense_symmetric_matrix(pattern, seed):
    """The lower triangle written into the CSC slots, the slots above it filled with rubbish: the mirror (in
    place, a chunk at a time) gives exactly the dense symmetric matrix, on the node blocks' pattern, and
    leaves the lower triangle as it was."""
    sizes, coupled, order, chunk = pattern
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(sparse, "_CHUNK", chunk)
        _check_mirror(sizes, coupled, order, seed)


def _check_mirror(sizes: np.ndarray, coupled: np.ndarray, order: np.ndarray, seed: int) -> None:
    row, col = np.nonzero(coupled)
    blocks = BlockPattern(col, row, order, sizes)
    rng = np.random.default_rng(seed)
    n = int(sizes.sum())
    # the dense symmetric matrix, in unknowns numbered node by node, non-zero on the coupled nodes' blocks
    node = np.repeat(np.arange(len(sizes)), sizes)
    A = rng.normal(size=(n, n)) * coupled[node[:, None], node[None, :]]
    A = np.tril(A) + np.tril(A, -1).T
    # ... in the factor's order: entry (position[i], position[j]) is A[i, j]
    inverse = np.argsort(blocks.position)
    permuted = A[np.ix_(inverse, inverse)]
    indptr, indices = blocks.indptr, blocks.indices
    data = np.empty(blocks.nnz)
    for column in range(n):
        for slot in range(indptr[column], indptr[column + 1]):
            r = indices[slot]
            data[slot] = permuted[r, column] if r >= column else np.nan     # above the diagonal: not read
    lower = data.copy()
    mirrored = blocks.mirror(data)
    assert mirrored is data
    full = blocks.matrix(data).toarray()
    np.testing.assert_array_equal(full, permuted)
    assert not np.isnan(data).any()
    below = np.repeat(np.arange(n), np.diff(indptr)) <= indices
    np.testing.assert_array_equal(data[below], lower[below])
    # the pattern: every entry of the coupled nodes' blocks, no other
    expected = coupled[node[:, None], node[None, :]][np.ix_(inverse, inverse)]
    structure = np.zeros((n, n), dtype=bool)
    structure[indices, np.repeat(np.arange(n), np.diff(indptr))] = True
    np.testing.assert_array_equal(structure, expected)
    np.testing.assert_array_equal(blocks.mirror(data), full[indices, np.repeat(np.arange(n), np.diff(indptr))])
