"""The factorisation backends of the exact join (mapjoin.refine.factor) and the selected inversion that uses a
factor up: each backend against dense linear algebra, and the two backends against each other.

CHOLMOD is the optional extra ``fast`` (scikit-sparse): its tests are skipped without it, and SuperLU, the
fallback, is tested everywhere.
"""

from __future__ import annotations

import importlib.util

import numpy as np
import pytest
import scipy.sparse as sp

from mapjoin import io as mapio
from mapjoin.joining import join
from mapjoin.refine import factor as factor_module, sparse
from mapjoin.refine.factor import BACKENDS, Factoriser, default_backend
from mapjoin.refine.problem import ExactProblem
from mapjoin.refine.solver import minimise
from mapjoin.simulation import simulate

HAS_CHOLMOD = importlib.util.find_spec("sksparse") is not None
AVAILABLE = [b for b in BACKENDS if b == "superlu" or HAS_CHOLMOD]


def _problem(maps, backend: str) -> tuple[ExactProblem, np.ndarray]:
    problem = ExactProblem(maps)
    problem.factoriser = Factoriser(backend)
    return problem, problem.pack(join(maps).global_map)


@pytest.fixture(scope="module")
def simulated():
    return simulate(12, seed=5).maps


@pytest.mark.parametrize("backend", AVAILABLE)
def test_the_triangle_and_pivots_rebuild_the_matrix(simulated, backend):
    """L D L^T (the factor's own triangle, unit diagonal) is the normal matrix, dense, in the factor's order."""
    problem, x = _problem(simulated, backend)
    data = problem.linearise(x)[0]
    A = problem.normal_matrix(data).toarray()
    factor = problem.factorise(data)
    L, D = factor.triangle()
    L = L.toarray()
    assert np.allclose(np.diag(L), 1.0)
    q = factor.perm
    np.testing.assert_allclose((L * D) @ L.T, A[np.ix_(q, q)], rtol=1e-9, atol=1e-9 * np.abs(A).max())
    with pytest.raises(IndexError):
        factor.triangle()   # used up: its storage was handed over


@pytest.mark.parametrize("backend", AVAILABLE)
def test_solve_equals_the_dense_solve(simulated, backend):
    problem, x = _problem(simulated, backend)
    data, gradient, _ = problem.linearise(x)
    J = problem.jacobian(x).toarray()
    np.testing.assert_allclose(problem.solve(problem.factorise(data), gradient),
                               np.linalg.solve(J.T @ J, gradient), rtol=1e-7, atol=1e-9)


@pytest.mark.parametrize("chunk", [5, 1 << 21])
def test_marginals_placed_a_chunk_of_columns_at_a_time_equal_the_dense_inverse(simulated, chunk, monkeypatch):
    """The triangle goes into the supernodal blocks a chunk of columns at a time (the index arrays' memory
    bounded) and only the wanted entries of each inverse block are kept: the dense inverse's diagonal blocks."""
    monkeypatch.setattr(sparse, "_CHUNK", chunk)
    problem, x = _problem(simulated, "superlu")
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


@pytest.mark.skipif(not HAS_CHOLMOD, reason="scikit-sparse (the extra 'fast') is not installed")
def test_both_backends_reach_the_same_optimum_and_covariances(data_dir):
    """VicPark 200 solved with each backend: the same chi^2, iterations, estimate and marginal covariances."""
    maps = mapio.read_maps(str(data_dir / "VicPark_200_local_maps"))
    results = []
    for backend in ("superlu", "cholmod"):
        problem, x = _problem(maps, backend)
        found = minimise(problem, x)
        results.append((found, problem.marginals(found.final_factor(problem))))
    (a, (pa, fa)), (b, (pb, fb)) = results
    assert a.converged and b.converged and a.iterations == b.iterations
    assert abs(a.cost - b.cost) <= 1e-12 * a.cost
    np.testing.assert_allclose(a.x, b.x, rtol=0, atol=1e-7)
    np.testing.assert_allclose(pa, pb, rtol=1e-7, atol=1e-12)
    np.testing.assert_allclose(fa, fb, rtol=1e-7, atol=1e-12)


@pytest.mark.skipif(not HAS_CHOLMOD, reason="scikit-sparse (the extra 'fast') is not installed")
def test_cholmod_refuses_an_indefinite_matrix_as_singular_where_superlu_factorises_it():
    """A Newton matrix need not be positive definite: CHOLMOD's refusal is the RuntimeError the solver takes
    for 'no Newton step'; SuperLU's L D L^T has a negative pivot."""
    A = sp.csc_matrix(np.array([[2.0, 1.0, 0.0], [1.0, -3.0, 1.0], [0.0, 1.0, 2.0]]))
    with pytest.raises(RuntimeError):
        Factoriser("cholmod")(A)
    L, D = Factoriser("superlu")(A).triangle()
    assert (D < 0).any()
    np.testing.assert_allclose((L.toarray() * D) @ L.toarray().T, A.toarray(), atol=1e-12)


def test_the_default_backend_is_superlu_for_small_problems_and_without_scikit_sparse(monkeypatch):
    assert default_backend(factor_module.CHOLMOD_FROM - 1) == "superlu"
    assert default_backend(factor_module.CHOLMOD_FROM) == ("cholmod" if HAS_CHOLMOD else "superlu")
    monkeypatch.setattr(factor_module.importlib.util, "find_spec", lambda name: None)
    assert default_backend(10 ** 7) == "superlu"
    with pytest.raises(ValueError, match="backend"):
        Factoriser("mumps")
