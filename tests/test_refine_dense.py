"""The dense backend's linear algebra (mapjoin.refine.dense, mapjoin.refine.triangular) against numpy's general
LU solve and inverse of the whole matrix, built from the Jacobian (not from the assembled normal equations)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mapjoin import io as mapio
from mapjoin.joining import join
from mapjoin.refine import dense
from mapjoin.refine.problem import ExactProblem
from mapjoin.refine.solver import minimise
from mapjoin.refine.triangular import BLOCK, Triangle, block_inverses
from mapjoin.simulation import simulate


def lower_triangular(n: int, seed: int, spread: float) -> np.ndarray:
    """A random lower triangular matrix whose diagonal spans ``spread`` decades (condition grows with it)."""
    rng = np.random.default_rng(seed)
    L = np.tril(rng.normal(size=(n, n))) / np.sqrt(n)
    L[np.diag_indices(n)] = rng.choice([-1.0, 1.0], n) * 10.0 ** rng.uniform(0, spread, n)
    return L


@settings(max_examples=40, deadline=None)
@given(n=st.one_of(st.integers(0, 2 * BLOCK + 3), st.integers(2 * BLOCK, 6 * BLOCK + 5)), seed=st.integers(0, 10**6),
       spread=st.floats(0.0, 3.0), columns=st.sampled_from([None, 1, 3]), first=st.floats(0.0, 1.0))
def test_triangular_solves_and_inverse_equal_numpys_general_ones(n, seed, spread, columns, first):
    """Across block boundaries (none, one block, a last block cut short), one right-hand side or several: L^-1 b,
    L^-T b and L^-1 equal numpy's LU solve and inverse; the inverse is exactly zero above the diagonal. A
    right-hand side given from its row ``first`` on (the rows before zero) gives the same rows of L^-1 b."""
    L = lower_triangular(n, seed, spread)
    b = np.random.default_rng(seed + 1).normal(size=n if columns is None else (n, columns))
    [triangle] = Triangle.all_of([L])
    scale = np.linalg.cond(L) if n else 1.0
    def assert_close(got, expected):
        assert got.shape == expected.shape
        np.testing.assert_allclose(got, expected, rtol=0, atol=1e-13 * scale * np.abs(expected).max(initial=1.0))
    assert_close(triangle.solve(b), np.linalg.solve(L, b) if n else b)
    assert_close(triangle.solve_transposed(b), np.linalg.solve(L.T, b) if n else b)
    k = int(first * n)
    tail = b.copy()
    tail[:k] = 0.0
    got = triangle.solve(b[k:], k)
    assert_close(got, (np.linalg.solve(L, tail) if n else tail)[k:])
    inverse = triangle.inverse()
    expected = np.linalg.inv(L) if n else L
    assert_close(inverse, expected)
    assert not np.triu(inverse, 1).any()


def random_spd(n: int, rng: np.random.Generator) -> np.ndarray:
    """A random symmetric positive definite matrix (n, n), its eigenvalues spread over about two decades."""
    Q = np.linalg.qr(rng.normal(size=(n, n)))[0] if n else np.zeros((0, 0))
    return (Q * 10.0 ** rng.uniform(-1, 1, n)) @ Q.T


@settings(max_examples=30, deadline=None)
@given(sizes=st.lists(st.one_of(st.integers(0, BLOCK + 2), st.integers(BLOCK, 4 * BLOCK + 7)), max_size=5),
       seed=st.integers(0, 10**6))
def test_block_inverses_of_several_interiors_equal_the_loop_over_each_block(sizes, seed):
    """The batched routine against the straightforward loop: the Cholesky factors of random SPD blocks of mixed
    sizes (as a dense factor's interiors are), their diagonal blocks inverted in one stacked call, equal each
    block inverted on its own by numpy (a last block cut short completed by the identity); and per interior the
    Cholesky solve by those blocks, L^-T L^-1 b, equals numpy's LU solve of the SPD block itself."""
    rng = np.random.default_rng(seed)
    matrices = [random_spd(n, rng) for n in sizes]
    factors = [np.linalg.cholesky(A) for A in matrices]
    batched = block_inverses(factors)
    assert len(batched) == len(factors)
    for L, inverses in zip(factors, batched):
        n = len(L)
        assert inverses.shape == (-(-n // BLOCK), BLOCK, BLOCK)
        for j, j0 in enumerate(range(0, n, BLOCK)):
            j1 = min(j0 + BLOCK, n)
            expected = np.eye(BLOCK)
            expected[:j1 - j0, :j1 - j0] = np.linalg.inv(L[j0:j1, j0:j1])
            np.testing.assert_allclose(inverses[j], expected, rtol=0, atol=1e-12 * np.abs(expected).max())
            assert not np.triu(inverses[j], 1).any()
    for A, triangle in zip(matrices, Triangle.all_of(factors)):
        b = rng.normal(size=len(A))
        expected = np.linalg.solve(A, b) if len(A) else b
        got = triangle.solve_transposed(triangle.solve(b))
        np.testing.assert_allclose(got, expected, rtol=0, atol=1e-10 * np.abs(expected).max(initial=1.0))


def test_a_triangle_refuses_block_inverses_of_another_size():
    """A triangle and its block inverses are made together: a count that does not fit the matrix is refused."""
    L = np.eye(BLOCK + 1)
    with pytest.raises(ValueError, match="needs 2 block inverses"):
        Triangle(L, block_inverses([np.eye(BLOCK)])[0])


@pytest.fixture(scope="module")
def vicpark_optimum(data_dir):
    """VicPark 200 at its optimum, dense backend: the problem, x, and J^T J from the Jacobian."""
    maps = mapio.read_maps([str(data_dir / "VicPark_200_local_maps")])
    problem = ExactProblem(maps, backend="dense")
    found = minimise(problem, problem.pack(join(maps, strategy="tree").global_map))
    J = problem.jacobian(found.x).toarray()
    return problem, found, J.T @ J


def assert_blocks_of(inverse, problem, poses, features, rtol):
    N, n = problem.n_maps, problem.n_features
    for got, first, count, size in ((poses, 0, N, 3), (features, 3 * N, n, 2)):
        index = first + np.arange(count * size).reshape(count, size)
        expected = inverse[index[:, :, None], index[:, None, :]]
        np.testing.assert_allclose(got, expected, rtol=0, atol=rtol * np.abs(expected).max())
        assert np.array_equal(got, got.transpose(0, 2, 1))


def test_the_dense_factor_solves_and_inverts_as_numpys_lu_of_the_jacobians_normal_matrix(vicpark_optimum):
    """Brute force on real data (1198 unknowns): the Cholesky solve equals numpy's LU solve of J^T J (J from
    problem.jacobian), the marginal blocks the blocks of its whole inverse."""
    problem, found, A = vicpark_optimum
    factor = problem.factorise(found.data)
    assert factor.cholesky and factor.partition.segments > 1      # the blockwise factor, not the whole one
    rhs = np.random.default_rng(0).normal(size=problem.n_unknowns)
    expected = np.linalg.solve(A, rhs)
    np.testing.assert_allclose(problem.solve(factor, rhs), expected, rtol=0, atol=1e-9 * np.abs(expected).max())
    poses, features = problem.marginals(factor)
    assert_blocks_of(np.linalg.inv(A), problem, poses, features, 1e-9)


def test_an_indefinite_matrix_is_solved_and_inverted_by_lu(vicpark_optimum):
    """Cholesky refuses a matrix that is not positive definite (a Newton step's may not be): the factor solves
    it by LU and inverts it whole, as numpy does."""
    problem, found, A = vicpark_optimum
    data = found.data.copy()
    data[problem._pattern.diagonal[:3]] *= -1.0           # the first pose's diagonal negated: indefinite
    factor = problem.factorise(data)
    assert not factor.cholesky
    B = A.copy()
    B[np.arange(3), np.arange(3)] *= -1.0
    rhs = np.arange(problem.n_unknowns, dtype=float)
    expected = np.linalg.solve(B, rhs)
    np.testing.assert_allclose(problem.solve(factor, rhs), expected, rtol=0, atol=1e-9 * np.abs(expected).max())
    poses, features = problem.marginals(factor)
    assert_blocks_of(np.linalg.inv(B), problem, poses, features, 1e-9)


def test_a_factor_outlives_the_next_factorisation(vicpark_optimum):
    """The partition fills one dense matrix anew at every factorisation: a factor made before (a Cholesky one,
    as the solver's chord step uses, and an LU one of an indefinite matrix) still solves its own matrix, as
    numpy's LU of it from the Jacobian does, after another matrix has been factorised."""
    problem, found, A = vicpark_optimum
    indefinite = found.data.copy()
    indefinite[problem._pattern.diagonal[:3]] *= -1.0
    B = A.copy()
    B[np.arange(3), np.arange(3)] *= -1.0
    first, lu = problem.factorise(found.data), problem.factorise(indefinite)
    assert first.cholesky and not lu.cholesky
    problem.factorise(found.data, 5.0)                     # another matrix through the same buffer
    rhs = np.random.default_rng(1).normal(size=problem.n_unknowns)
    for factor, matrix in ((first, A), (lu, B)):
        expected = np.linalg.solve(matrix, rhs)
        np.testing.assert_allclose(problem.solve(factor, rhs), expected, rtol=0, atol=1e-9 * np.abs(expected).max())


def test_the_dense_factor_reads_the_lower_triangle_only():
    """The slots above the diagonal (zeros from linearise) are not read: values put there change nothing."""
    maps = list(simulate(6, seed=3).maps)
    problem = ExactProblem(maps, backend="dense")
    data = problem.linearise(problem.pack(join(maps).global_map))[0]
    pattern = problem._pattern
    columns = np.repeat(np.arange(pattern.n), np.diff(pattern.indptr))
    above = pattern.indices < columns
    assert above.any() and not data[above].any()
    noisy = data.copy()
    noisy[above] = 1e6
    rhs = np.ones(problem.n_unknowns)
    assert np.array_equal(problem.solve(problem.factorise(noisy), rhs), problem.solve(problem.factorise(data), rhs))


def test_damping_scales_the_diagonal_the_dense_factor_solves(vicpark_optimum):
    """A Levenberg-Marquardt factor: (A + lambda diag A)^-1 g, against numpy's LU of that matrix."""
    problem, found, A = vicpark_optimum
    damped = A + 0.3 * np.diag(np.diag(A))
    expected = np.linalg.solve(damped, found.gradient)
    got = problem.solve(problem.factorise(found.data, 0.3), found.gradient)
    np.testing.assert_allclose(got, expected, rtol=0, atol=1e-9 * np.abs(expected).max())



@pytest.mark.parametrize("name", ["VicPark_200_local_maps", "DLR_200_local_maps", "8240_data_50_local_maps"])
def test_interiors_of_different_segments_do_not_couple(name, data_dir):
    """The partition's premise, on J^T J from the Jacobian: no entry couples two different interiors, the
    separator meets only each interior's trailing unknowns, and each node's unknowns are together in one
    part; the real datasets are cut (the least work is not the whole)."""
    maps = mapio.read_maps([str(data_dir / name)])
    problem = ExactProblem(maps, backend="dense")
    x = problem.pack(join(maps, strategy="tree").global_map)
    problem.factorise(problem.linearise(x)[0])
    partition = problem._partition
    segments = partition.segments
    assert segments > 1
    J = problem.jacobian(x).toarray()
    A = (J.T @ J)[np.ix_(partition.order, partition.order)]
    bounds = partition.bounds
    for i in range(segments):
        for j in range(segments):
            if i != j:
                assert not A[bounds[i]:bounds[i + 1], bounds[j]:bounds[j + 1]].any()
        # only the interior's last unknowns (coupled[i] of them) meet the separator's rows
        assert not A[bounds[-2]:, bounds[i]:bounds[i + 1] - partition.coupled[i]].any()
        # ... and of those rows only the ones its segment's maps touch (rows[i])
        others = np.ones(A.shape[0] - bounds[-2], dtype=bool)
        others[partition.rows[i]] = False
        assert not A[bounds[-2]:][others, bounds[i]:bounds[i + 1]].any()
    assert partition.coupled.sum() < bounds[-2]        # some interior unknowns never meet the separator
    if segments > 2:                                    # DLR 200 (4), 8240 (6): no interior meets all its rows
        assert all(len(rows) < A.shape[0] - bounds[-2] for rows in partition.rows)
    part = np.searchsorted(bounds, partition.position, side="right") - 1
    N = problem.n_maps
    assert (part[:3 * N].reshape(N, 3) == part[:3 * N:3, None]).all()
    assert (part[3 * N:].reshape(-1, 2) == part[3 * N::2, None]).all()


def test_a_single_map_and_a_map_without_features_take_the_whole_matrix():
    """One segment (no separator) and tiny problems: the dense solve equals numpy's LU of J^T J."""
    for maps in (list(simulate(1, seed=2).maps), list(simulate(2, seed=4).maps)):
        problem = ExactProblem(maps, backend="dense")
        x = problem.pack(join(maps).global_map)
        data, gradient, _ = problem.linearise(x)
        factor = problem.factorise(data)
        J = problem.jacobian(x).toarray()
        expected = np.linalg.solve(J.T @ J, gradient)
        np.testing.assert_allclose(problem.solve(factor, gradient), expected, rtol=0,
                                   atol=1e-9 * np.abs(expected).max())
        poses, features = problem.marginals(factor)
        assert_blocks_of(np.linalg.inv(J.T @ J), problem, poses, features, 1e-9)


@settings(max_examples=25, deadline=None)
@given(count=st.integers(2, 12), seed=st.integers(0, 10_000), full=st.booleans(), noise=st.floats(0.0, 0.3),
       segments=st.integers(2, 12))
def test_the_segmented_solve_equals_the_sparse_one_on_small_simulations(count, seed, full, noise, segments):
    """Small chains cut into a given number of segments (the work model would keep them whole), full or
    spherical covariances, started off the fast join by noise: the same steps, chi^2 after each (1e-9), the
    same optimum and marginal covariances (1e-9) as SuperLU's."""
    maps = list(simulate(count, seed=seed, full_covariance=full).maps)
    start = join(maps).global_map
    solved = {}
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(dense, "_SEGMENT_COUNTS", (min(segments, count),))
        patch.setattr(dense, "_SEGMENT_WORK", -1e12)         # a segment's "gain" outweighs any work: the most
        for backend in ("dense", "sparse"):
            problem = ExactProblem(maps, backend=backend)
            x = problem.pack(start)
            found = minimise(problem, x + np.random.default_rng(seed).normal(0, noise, x.size))
            solved[backend] = problem, found, problem.marginals(found.final_factor(problem))
    (problem, a, (pa, fa)), (_, b, (pb, fb)) = solved["dense"], solved["sparse"]
    assert problem._partition.segments == min(segments, count)
    assert a.iterations == b.iterations and a.converged and b.converged
    np.testing.assert_allclose(a.costs, b.costs, rtol=1e-9, atol=1e-14 * b.costs[0])
    np.testing.assert_allclose(a.x, b.x, rtol=0, atol=1e-9 * (1.0 + np.max(np.abs(b.x))))
    for got, expected in ((pa, pb), (fa, fb)):
        np.testing.assert_allclose(got, expected, rtol=0, atol=1e-9 * np.abs(expected).max())


@pytest.mark.parametrize("name", ["VicPark_200_local_maps", "DLR_200_local_maps", "8240_data_50_local_maps"])
def test_the_partition_is_the_least_work_of_its_segment_counts(name, data_dir, monkeypatch):
    """The work a partition states is the flops of its factorisation counted from what it holds (each interior's
    Cholesky, its trailing block's solve against and update of only the separator's rows it meets, the
    separator's Cholesky, the allowance per segment), and no other segment count gives less."""
    maps = mapio.read_maps([str(data_dir / name)])
    chosen = ExactProblem(maps, backend="dense")._partition

    def counted(partition):
        bounds, n = partition.bounds, partition.bounds[-1]
        s = n - bounds[-2]
        r = np.array([s if isinstance(rows, slice) else len(rows) for rows in partition.rows])
        inner, t = np.diff(bounds[:-1]), partition.coupled
        return float(np.sum(inner ** 3 / 3 + t ** 2 * r + t * r ** 2) + s ** 3 / 3) + dense._SEGMENT_WORK * len(r)

    assert chosen.work == pytest.approx(counted(chosen), rel=1e-12)
    for K in dense._SEGMENT_COUNTS:
        monkeypatch.setattr(dense, "_SEGMENT_COUNTS", (K,))
        other = ExactProblem(maps, backend="dense")._partition
        assert other.work == pytest.approx(counted(other), rel=1e-12)
        assert chosen.work <= other.work


def test_the_schur_updates_index_each_segments_rows_block(vicpark_optimum):
    """Each segment's flat indices address exactly the (rows, rows) block of the separator's Schur complement, as
    numpy's own multi-index does; they are made once (VicPark 200's are small enough to keep)."""
    problem, _, _ = vicpark_optimum
    partition = problem._partition
    s = partition.bounds[-1] - partition.bounds[-2]
    updates = partition.updates()
    assert len(updates) == partition.segments and any(update is not None for update in updates)
    for rows, update in zip(partition.rows, updates):
        if update is None:
            assert isinstance(rows, slice)
        else:
            assert np.array_equal(update, np.ravel_multi_index(np.ix_(rows, rows), (s, s)).ravel())
    assert partition.updates() is updates
