"""The factor of the exact join's normal matrix (mapjoin.refine.factor), the lower triangle linearise returns,
and the selected inversion that uses the factor up: each against dense linear algebra."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

from mapjoin.joining import join
from mapjoin.refine import sparse
from mapjoin.refine.factor import factorise
from mapjoin.refine.problem import ExactProblem
from mapjoin.refine.solver import minimise
from mapjoin.simulation import simulate


@pytest.fixture(scope="module")
def simulated():
    maps = simulate(12, seed=5).maps
    problem = ExactProblem(maps, backend="sparse")   # SuperLU's factor: 12 maps would be solved densely
    return problem, problem.pack(join(maps).global_map)


def test_linearise_gives_the_lower_triangle_and_normal_matrix_the_whole_dense_matrix(simulated):
    problem, x = simulated
    data = problem.linearise(x)[0]
    J = problem.jacobian(x).toarray()
    q = np.argsort(problem.position)                     # factor order -> unknown
    A = (J.T @ J)[np.ix_(q, q)]
    lower = problem._pattern.matrix(data).toarray()
    np.testing.assert_allclose(lower, np.tril(A), rtol=1e-10, atol=1e-10 * np.abs(A).max())
    assert not np.triu(lower, 1).any()
    np.testing.assert_allclose(problem.normal_matrix(data).toarray(), A, rtol=1e-10, atol=1e-10 * np.abs(A).max())


def test_the_triangle_and_pivots_rebuild_the_matrix_and_free_the_factor(simulated):
    """L D L^T (the factor's own triangle, unit diagonal) is the normal matrix, dense; after handing it over
    the factor neither solves nor gives it again."""
    problem, x = simulated
    data = problem.linearise(x)[0]
    A = problem.normal_matrix(data).toarray()
    factor = problem.factorise(data)
    L, D = factor.triangle()
    L = L.toarray()
    assert np.allclose(np.diag(L), 1.0) and np.array_equal(factor.perm, np.arange(len(A)))
    np.testing.assert_allclose((L * D) @ L.T, A, rtol=1e-9, atol=1e-9 * np.abs(A).max())
    with pytest.raises(ValueError, match="handed over"):
        factor.triangle()
    with pytest.raises(ValueError, match="handed over"):
        factor.solve(np.ones(len(A)))


def test_solve_equals_the_dense_solve(simulated):
    problem, x = simulated
    data, gradient, _ = problem.linearise(x)
    J = problem.jacobian(x).toarray()
    np.testing.assert_allclose(problem.solve(problem.factorise(data), gradient),
                               np.linalg.solve(J.T @ J, gradient), rtol=1e-7, atol=1e-9)


@pytest.mark.parametrize("chunk", [5, 1 << 21])
def test_marginals_placed_a_chunk_of_columns_at_a_time_equal_the_dense_inverse(simulated, chunk, monkeypatch):
    """The triangle goes into the supernodal blocks a chunk of columns at a time (the index arrays' memory
    bounded; so are the CSC pattern and its mirror built) and only the wanted entries of each inverse block
    are kept: the dense inverse's diagonal blocks."""
    monkeypatch.setattr(sparse, "_CHUNK", chunk)
    _, x = simulated
    problem = ExactProblem(simulate(12, seed=5).maps, backend="sparse")      # its pattern built under this chunk
    found = minimise(problem, x)
    poses, features = problem.marginals(found.final_factor(problem))
    J = problem.jacobian(found.x).toarray()
    Z = np.linalg.inv(J.T @ J)
    N = problem.n_maps
    for k in range(N):
        np.testing.assert_allclose(poses[k], Z[3 * k:3 * k + 3, 3 * k:3 * k + 3], rtol=1e-8, atol=1e-14)
    for i in range(problem.n_features):
        at = 3 * N + 2 * i
        np.testing.assert_allclose(features[i], Z[at:at + 2, at:at + 2], rtol=1e-8, atol=1e-14)


def test_an_indefinite_matrix_has_a_negative_pivot():
    """A Newton matrix need not be positive definite: SuperLU's L D L^T (no pivoting) still factorises it."""
    A = sp.csc_matrix(np.array([[2.0, 1.0, 0.0], [1.0, -3.0, 1.0], [0.0, 1.0, 2.0]]))
    L, D = factorise(A).triangle()
    assert (D < 0).sum() == 1
    np.testing.assert_allclose((L.toarray() * D) @ L.toarray().T, A.toarray(), atol=1e-12)
