"""Exact joining (mapjoin.refine): derivatives, optimality, the known optima, the oracle,
covariances by selected inversion, warm starts, and the ``refine`` command."""

from __future__ import annotations

import csv
import dataclasses
import io
import itertools
import math
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import scipy.linalg
import scipy.sparse as sp
from cli_runner import run
from click.testing import CliRunner
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.optimize import least_squares
from scipy.sparse.linalg import splu, spsolve

from mapjoin import GlobalMap, JoinError, LocalMap
from mapjoin import io as mapio
from mapjoin.cli import main
from mapjoin.joining import join, join_sequential
from mapjoin.refine import (
    DEFAULT_START,
    RefineResult,
    default_start,
    exact_cost,
    join_and_refine,
    refine,
)
from mapjoin.refine import dense, solver
from mapjoin.refine.groups import (
    _GROUP_OVERHEAD,
    _block_whitening,
    independent_points,
    size_classes,
)
from mapjoin.refine.problem import ExactProblem
from mapjoin.refine.solver import TOLERANCE, minimise
from mapjoin.refine.factor import factorise
from mapjoin.refine.sparse import Supernodes, closed_pattern, selected_inverse
from mapjoin.refine.triangular import lower_inverses
from mapjoin.simulation import simulate

KNOWN_OPTIMA = {  # chi^2 at the exact optimum
    "VicPark_200_local_maps": 3643.435,
    "DLR_200_local_maps": 11163.64,
    "8240_data_50_local_maps": 458.15,
}


@pytest.fixture(autouse=True)
def sparse_backend(monkeypatch):
    """These tests are of the sparse backend (SuperLU, selected inversion), which the exact solve would leave
    for the dense one on most of their small problems (refine/dense.py); tests/test_startup.py checks the dense
    backend against the sparse one."""
    monkeypatch.setattr(dense, "DENSE_UNKNOWNS", -1)


@pytest.fixture(scope="module")
def real(data_dir):
    """Local maps of the real datasets, read once."""
    cache: dict[str, list[LocalMap]] = {}

    def load(name: str) -> list[LocalMap]:
        if name not in cache:
            cache[name] = mapio.read_maps([str(data_dir / name)])
        return cache[name]

    return load


@pytest.fixture(scope="module")
def solved(real):
    """refine() of the real datasets, solved once."""
    cache: dict[str, RefineResult] = {}

    def get(name: str) -> RefineResult:
        if name not in cache:
            cache[name] = refine(real(name))
        return cache[name]

    return get


def sim_maps(count: int = 10, **options) -> list[LocalMap]:
    return list(simulate(count, seed=options.pop("seed", 4), **options).maps)


def spherical(maps):
    """The same maps without their full covariances (their spherical variances only)."""
    return [dataclasses.replace(m, covariance=None) for m in maps]


def as_oracle_maps(maps):
    """LocalMaps as the oracle's ``(localmap_st, localmap_P)`` pairs."""
    pairs = []
    for m in maps:
        ids = np.concatenate([[0, 0, 0], np.repeat(m.feature_ids, 2)])
        values = np.concatenate([m.end_pose, m.features.ravel()])
        pairs.append((np.column_stack([ids, values]).astype(float), np.array(m.covariance)))
    return pairs


def decreasing(costs) -> bool:
    """chi^2 after each accepted step decreases; the last step, of negligible predicted decrease, is
    taken however chi^2 compares (at that level it is rounding), so it may rise by rounding only."""
    costs = list(costs)
    return costs[:-1] == sorted(costs[:-1], reverse=True) and costs[-1] <= costs[-2] * (1 + 1e-13)


def numeric_jacobian(problem: ExactProblem, x: np.ndarray, h: float = 1e-6) -> np.ndarray:
    columns = []
    for i in range(len(x)):
        e = np.zeros_like(x)
        e[i] = h
        columns.append((problem.residual(x + e) - problem.residual(x - e)) / (2 * h))
    return np.column_stack(columns)


def relative_gradient(problem: ExactProblem, global_map: GlobalMap) -> float:
    """|J^T r|_inf / (max column norm of J * |r|): ~1e-16 at a stationary point, O(1) elsewhere."""
    x = problem.pack(global_map)
    J, r = problem.jacobian(x), problem.residual(x)
    column_norms = np.sqrt(np.asarray(J.multiply(J).sum(axis=0))).ravel()
    return float(np.max(np.abs(J.T @ r)) / (column_norms.max() * np.linalg.norm(r)))


def dense_marginals(problem: ExactProblem, x: np.ndarray):
    J = problem.jacobian(x).toarray()
    Z = np.linalg.inv(J.T @ J)
    N, n = problem.n_maps, problem.n_features
    poses = np.stack([Z[3 * k:3 * k + 3, 3 * k:3 * k + 3] for k in range(N)])
    features = np.stack([Z[3 * N + 2 * j:3 * N + 2 * j + 2, 3 * N + 2 * j:3 * N + 2 * j + 2] for j in range(n)])
    return poses, features


# --------------------------------------------------------------------------- derivatives


@pytest.mark.parametrize("case", ["vicpark5", "sim", "sim-spherical"])
def test_jacobian_equals_central_differences_at_random_points(case, request):
    maps = {"vicpark5": lambda: request.getfixturevalue("real")("VicPark_200_local_maps")[:5],
            "sim": lambda: sim_maps(6), "sim-spherical": lambda: spherical(sim_maps(6))}[case]()
    problem = ExactProblem(maps)
    rng = np.random.default_rng(1)
    x0 = problem.pack(join_sequential(maps).global_map)
    for _ in range(2):
        x = x0 + rng.normal(0, 0.3, x0.size)
        J = problem.jacobian(x).toarray()
        numeric = numeric_jacobian(problem, x)
        assert np.max(np.abs(J - numeric)) <= 1e-6 * max(1.0, np.max(np.abs(J)))


def test_normal_equations_and_newton_term_equal_dense_references(real):
    maps = real("DLR_200_local_maps")[:8]
    problem = ExactProblem(maps)
    x = problem.pack(join_sequential(maps).global_map) + np.random.default_rng(2).normal(0, 0.1, problem.n_unknowns)
    data, gradient, cost, second = problem.linearise(x, curvature=True)
    J, r = problem.jacobian(x).toarray(), problem.residual(x)
    order = problem.position
    A = problem.normal_matrix(data).toarray()[np.ix_(order, order)]
    full = np.zeros_like(data)
    full[problem.curvature_slots] = second
    S = problem.normal_matrix(full).toarray()[np.ix_(order, order)]
    np.testing.assert_allclose(A, J.T @ J, rtol=0, atol=1e-12 * np.abs(A).max())
    np.testing.assert_allclose(gradient, J.T @ r, rtol=0, atol=1e-12 * np.abs(gradient).max())
    assert cost == pytest.approx(r @ r, rel=1e-13) == pytest.approx(problem.cost(x), rel=1e-13)
    # J^T J + S is half the Hessian of chi^2: the derivative of the gradient J^T r
    h = 1e-6
    hessian = np.column_stack([(problem.linearise(x + h * e)[1] - problem.linearise(x - h * e)[1]) / (2 * h)
                               for e in np.eye(problem.n_unknowns)])
    np.testing.assert_allclose(A + S, hessian, rtol=0, atol=1e-7 * np.abs(hessian).max())


@pytest.mark.parametrize("backend", ["sparse", "dense"])
def test_newtons_factor_is_that_of_the_whole_sum_and_leaves_the_normal_matrix_as_it_was(real, backend):
    """factorise(data, second=...) adds the second-order term into its own slots and puts them back: its steps are
    bit for bit those of the factor of ``data`` plus the term spread over the whole layout (zeros elsewhere), and
    ``data``'s lower triangle is unchanged after it (the solver reads it again when a Newton step fails)."""
    maps = real("DLR_200_local_maps")[:8]
    problem = ExactProblem(maps, backend=backend)
    x = problem.pack(join_sequential(maps).global_map) + np.random.default_rng(4).normal(0, 0.01, problem.n_unknowns)
    data, gradient, _, second = problem.linearise(x, curvature=True)
    full = np.zeros_like(data)
    full[problem.curvature_slots] = second
    assert np.count_nonzero(second) and len(second) < len(data)
    whole = data + full
    before = data.copy()
    for damping in (0.0, 1e-3):
        expected = problem.solve(problem.factorise(whole.copy(), damping), -gradient)
        found = problem.solve(problem.factorise(data, damping, second), -gradient)
        assert np.array_equal(found, expected)
        lower = problem.normal_matrix(data.copy()).toarray()   # from data's lower triangle
        assert np.array_equal(lower, problem.normal_matrix(before.copy()).toarray())
        assert not np.array_equal(found, problem.solve(problem.factorise(data, damping), -gradient))


def test_uncoupled_features_leave_the_normal_matrix_sparser_and_still_exact():
    """Maps without a full covariance (independent features) couple no two of their features:
    those pairs are left out of J^T J's pattern, which still equals the dense J^T J."""
    full, diagonal = sim_maps(6), spherical(sim_maps(6))
    sizes = []
    for maps in (full, diagonal):
        problem = ExactProblem(maps)
        x = problem.pack(join_sequential(maps).global_map) + np.random.default_rng(3).normal(0, 0.1,
                                                                                           problem.n_unknowns)
        data = problem.linearise(x)[0]
        J = problem.jacobian(x).toarray()
        order = problem.position
        A = problem.normal_matrix(data).toarray()[np.ix_(order, order)]
        np.testing.assert_allclose(A, J.T @ J, rtol=0, atol=1e-12 * np.abs(A).max())
        sizes.append(problem.normal_matrix(data).nnz)
    assert sizes[1] < sizes[0]


def test_cost_is_chi2_of_each_maps_full_covariance_and_spherical_without():
    maps = sim_maps(5)
    guess = join_sequential(maps).global_map
    problem = ExactProblem(maps)
    x = problem.pack(guess)
    poses, features = problem.unpack(x)
    expected = {True: 0.0, False: 0.0}
    for k, m in enumerate(maps):
        base = np.zeros(3) if k == 0 else poses[k - 1]
        c, s = math.cos(base[2]), math.sin(base[2])
        Rt = np.array([[c, s], [-s, c]])
        predicted = [Rt @ (poses[k, :2] - base[:2]), [poses[k, 2] - base[2]]]
        predicted += [Rt @ (features[np.searchsorted(problem.feature_ids, i)] - base[:2]) for i in m.feature_ids]
        e = np.concatenate([m.end_pose, m.features.ravel()]) - np.concatenate(predicted)
        e[2] = (e[2] + math.pi) % (2 * math.pi) - math.pi
        expected[True] += e @ np.linalg.solve(m.covariance, e)
        diagonal = np.concatenate([m.pose_variances[[0, 0, 1]], np.repeat(m.feature_variances, 2)])
        expected[False] += e @ (e / diagonal)
    assert exact_cost(maps, guess) == pytest.approx(expected[True], rel=1e-12)
    assert exact_cost(spherical(maps), guess) == pytest.approx(expected[False], rel=1e-12)


@settings(max_examples=40, deadline=None)
@given(count=st.integers(1, 40), d=st.integers(1, 100), seed=st.integers(0, 2**32 - 1), split=st.integers(0, 100))
def test_triangular_inverse_equals_the_dense_inverse(count, d, seed, split):
    """Every way (one by one for few small matrices, row by row for many small ones, large ones by halves,
    down to either) against numpy's LU inverse of L itself; the off-diagonal entries are scaled so that L is
    well conditioned (a random unit-scaled triangle's condition grows exponentially with d: the two ways'
    roundings then differ by more than 1e-12). A zero block of L below the diagonal (``split``) gives an
    exactly zero block of the inverse."""
    rng = np.random.default_rng(seed)
    L = (np.tril(rng.normal(size=(count, d, d)), -1) / np.sqrt(d)
         + np.eye(d) * (1 + rng.random((count, 1, d))) * np.sign(rng.normal(size=(count, 1, 1))))
    W, expected = lower_inverses(L), np.linalg.inv(L)
    np.testing.assert_allclose(W, expected, rtol=1e-12, atol=1e-12 * np.abs(expected).max())
    assert not np.triu(W, 1).any()
    h = split % d
    L[:, h:, :h] = 0.0
    W = lower_inverses(L)
    assert not W[:, h:, :h].any() and not np.triu(W, 1).any()
    np.testing.assert_allclose(W, np.linalg.inv(L), rtol=1e-12, atol=1e-12 * np.abs(W).max())


@settings(max_examples=40, deadline=None)
@given(count=st.integers(1, 12), m=st.integers(0, 5), seed=st.integers(0, 2**32 - 1))
def test_independent_points_are_found_as_looking_at_every_entry_finds_them(count, m, seed):
    """Which blocks' covariances correlate no two of their points, against a look at every entry across two
    points, map by map (brute force): block-diagonal ones, and ones with a single non-zero entry across
    two points anywhere (the end pose's x with a feature, which the first look takes, or elsewhere)."""
    rng = np.random.default_rng(seed)
    d = 3 + 2 * m
    owner = [0, 0, 0] + [1 + i // 2 for i in range(2 * m)]
    covariances = np.zeros((count, d, d))
    for k in range(count):
        for point in range(m + 1):
            where = [i for i in range(d) if owner[i] == point]
            block = rng.normal(size=(len(where), len(where)))
            covariances[k][np.ix_(where, where)] = block @ block.T + np.eye(len(where))
        if m and rng.random() < 0.6:
            i, j = rng.integers(0, d, 2)
            if owner[i] != owner[j]:
                covariances[k, i, j] = covariances[k, j, i] = rng.choice([1e-300, 0.5])
    expected = [not any(covariances[k, i, j] != 0 for i in range(d) for j in range(d) if owner[i] != owner[j])
                for k in range(count)]
    assert independent_points(covariances).tolist() == expected


@settings(max_examples=25, deadline=None)
@given(sizes=st.lists(st.integers(0, 4), min_size=1, max_size=4), seed=st.integers(0, 2**32 - 1))
def test_block_whitening_equals_the_factor_of_the_whole_covariance(sizes, seed):
    """Independent points (block-diagonal covariances of several sizes, padded to the largest):
    W and W^T W block by block equal the inverse Cholesky factor of each whole covariance in
    the order [x's, y's, phi] (as the dense path computes it) and its inverse, padding zero."""
    rng = np.random.default_rng(seed)
    m = max(sizes)
    p = m + 1
    stacks, point = [], np.arange(p) <= np.array(sizes)[:, None]
    for k, r in enumerate(sizes):
        blocks = [rng.normal(size=(3, 3))] + [rng.normal(size=(2, 2)) for _ in range(r)]
        covariance = scipy.linalg.block_diag(*[b @ b.T + 0.1 * np.eye(len(b)) for b in blocks])
        stacks.append((np.arange(len(sizes)) == k, covariance[None]))
    whitening, information = _block_whitening(stacks, point)
    for k, (_, covariance) in enumerate(stacks):
        r = sizes[k]
        local = np.concatenate([[0], 3 + 2 * np.arange(r), [1], 4 + 2 * np.arange(r), [2]])
        real = np.concatenate([np.arange(r + 1), p + np.arange(r + 1), [2 * p]])
        expected = np.linalg.inv(np.linalg.cholesky(covariance[0][np.ix_(local, local)]))
        np.testing.assert_allclose(whitening[k][np.ix_(real, real)], expected, rtol=0, atol=1e-10)
        np.testing.assert_allclose(information[k][np.ix_(real, real)],
                                   np.linalg.inv(covariance[0][np.ix_(local, local)]), rtol=1e-9, atol=1e-9)
        padding = np.setdiff1d(np.arange(2 * p + 1), real)
        assert not whitening[k][padding].any() and not whitening[k][:, padding].any()


@settings(max_examples=50, deadline=None)
@given(sizes=st.lists(st.integers(0, 60), min_size=1, max_size=40), independent=st.lists(st.booleans(), max_size=40))
def test_size_classes_are_the_cheapest_runs_of_sizes(sizes, independent):
    """The maps' groups: each kind's maps split into runs of consecutive sizes, padded to the
    largest; their cost (fixed cost per group + maps x padded work) is the brute-force minimum
    over every way to cut the kind's distinct sizes into runs (up to 10 distinct sizes)."""
    sizes = np.array(sizes)
    kinds = np.resize(np.array(independent + [False], dtype=bool), len(sizes))
    classes = size_classes(sizes, kinds)
    assert np.array_equal(np.sort(np.concatenate(classes)), np.arange(len(sizes)))

    def cost(groups):
        return sum(_GROUP_OVERHEAD + len(g) * (2.0 * sizes[g].max() + 6) ** 2 for g in groups)

    for kind in np.unique(kinds):
        mine = [g for g in classes if kinds[g[0]] == kind]
        for g in mine:                          # a run: every map of the kind with a size in its range
            inside = (kinds == kind) & (sizes >= sizes[g].min()) & (sizes <= sizes[g].max())
            assert np.array_equal(np.sort(g), np.flatnonzero(inside))
        distinct = np.unique(sizes[kinds == kind])
        if len(distinct) > 10:
            continue
        best = min(cost([np.flatnonzero((kinds == kind) & np.isin(sizes, distinct[a:b]))
                         for a, b in itertools.pairwise([0, *(i + 1 for i, c in enumerate(cuts) if c), len(distinct)])])
                   for cuts in itertools.product((False, True), repeat=len(distinct) - 1))
        assert cost(mine) == pytest.approx(best, rel=1e-12)


# --------------------------------------------------------------------------- the optimum


@pytest.mark.parametrize("name", sorted(KNOWN_OPTIMA))
def test_reaches_the_known_optimum_with_zero_gradient(name, real, solved):
    result = solved(name)
    assert result.converged, result.reason
    digits = len(str(KNOWN_OPTIMA[name]).split(".")[1])
    assert round(result.cost, digits) == KNOWN_OPTIMA[name]
    assert result.costs[-1] == result.cost and result.costs[0] > result.cost
    assert decreasing(result.costs)
    assert result.cost == pytest.approx(exact_cost(real(name), result.global_map), rel=1e-12)
    assert relative_gradient(ExactProblem(real(name)), result.global_map) < 1e-10
    assert result.degrees_of_freedom == result.residuals - result.unknowns > 0


@pytest.mark.parametrize("name", sorted(KNOWN_OPTIMA))
def test_stops_at_the_optimum_not_one_step_short(name, real, solved):
    """Where the solver stops does not hang on rounding: the last step, predicted to lower chi^2
    by less than the tolerance (chi^2 then compares by rounding only), is taken, so a further
    Gauss-Newton step (scipy's sparse solve of the normal equations of the analytic Jacobian)
    moves nothing by more than 1e-10 (on 8240 the solver used to stop 2e-7 short)."""
    problem = ExactProblem(real(name))
    x = problem.pack(solved(name).global_map)
    J, r = problem.jacobian(x), problem.residual(x)
    step = spsolve((J.T @ J).tocsc(), -(J.T @ r))
    assert np.abs(step).max() < 1e-10


@pytest.mark.parametrize("name, count, chord", [("VicPark_200_local_maps", 200, "settles"),
                                                ("DLR_200_local_maps", 200, "settles"),
                                                ("535_data_5_local_maps", 5, "unsettled"),
                                                ("DLR_200_local_maps", 181, "not taken")])
@pytest.mark.parametrize("backend", ["dense", "sparse"])
def test_the_step_that_confirms_convergence_costs_a_solve_not_a_factorisation(name, count, chord, backend, real,
                                                                              monkeypatch):
    """Near the optimum the last step is the chord step of the previous point's factor: one factorisation
    fewer than steps where the step after it would move by at most the tolerance (VicPark 200, DLR 200); as
    many, and one step more, where it would move more (535: the solver goes on with a factorisation); not
    taken where its length times the last step's exceeds the tolerance (DLR 200's first 181 maps, the piece
    its join's confirmation solves: the same steps as without it). Where it is taken the solve stops where a
    further Gauss-Newton step (scipy's sparse solve of the normal equations of the analytic Jacobian) moves
    nothing by more than 1e-10; always at the chi^2 the solve without the chord reaches."""
    maps = real(name)[:count]
    problem = ExactProblem(maps, backend=backend)
    x0 = problem.pack(join(maps, strategy="tree").global_map)
    factorisations = []
    plain = ExactProblem.factorise
    monkeypatch.setattr(ExactProblem, "factorise", lambda *a: factorisations.append(1) or plain(*a))
    found = minimise(problem, x0)
    assert found.converged and found.reason == "relative cost change below tolerance"
    monkeypatch.setattr(ExactProblem, "factorise", plain)
    monkeypatch.setattr(solver, "_chord", lambda *a: None)      # every step factorised, as before the chord
    without = minimise(ExactProblem(maps, backend=backend), x0)
    assert len(factorisations) == without.iterations - (chord == "settles")
    assert found.iterations == without.iterations + (chord == "unsettled")
    assert found.cost == pytest.approx(without.cost, rel=1e-13)
    if chord == "not taken":                                   # the very same steps
        assert np.array_equal(found.x, without.x)
    else:
        J, r = problem.jacobian(found.x), problem.residual(found.x)
        assert np.abs(spsolve((J.T @ J).tocsc(), -(J.T @ r))).max() < 1e-10


@pytest.mark.parametrize("name, count", [("535_data_5_local_maps", 5), ("VicPark_200_local_maps", 20)])
def test_positions_equal_the_oracles(name, count, real, data_dir):
    oracles = pytest.importorskip("oracles")
    maps = real(name)[:count]
    reference = oracles.exact_join(oracles.load_folder(data_dir / name)[:count], dec_tol=1e-18, max_rounds=60)
    result = refine(maps)
    g = result.global_map
    np.testing.assert_array_equal(g.feature_ids, reference.feature_ids)
    np.testing.assert_array_equal(g.pose_ids, reference.pose_ids)
    np.testing.assert_allclose(g.features, reference.features, rtol=0, atol=1e-6)
    np.testing.assert_allclose(g.poses[:, :2], reference.poses[:, :2], rtol=0, atol=1e-6)
    np.testing.assert_allclose(np.angle(np.exp(1j * (g.poses[:, 2] - reference.poses[:, 2]))), 0, atol=1e-7)
    assert result.cost == pytest.approx(reference.cost, rel=1e-9)


def test_positions_equal_scipy_least_squares_on_a_simulation():
    oracles = pytest.importorskip("oracles")
    maps = sim_maps(10, seed=9)
    problem = oracles.ExactProblem(as_oracle_maps(maps))   # an independent residual and Jacobian
    start = ExactProblem(maps).pack(join_sequential(maps).global_map)
    reference = least_squares(problem.residual, start, jac=lambda x: problem.jacobian(x).toarray(), method="lm",
                              xtol=1e-15, ftol=1e-15, gtol=1e-15)
    poses, features = problem.split(reference.x)
    result = refine(maps)
    np.testing.assert_allclose(result.global_map.features, features, rtol=0, atol=1e-6)
    np.testing.assert_allclose(result.global_map.poses[:, :2], poses[:, :2], rtol=0, atol=1e-6)
    assert result.cost == pytest.approx(2 * reference.cost, rel=1e-9)


@pytest.mark.parametrize("full_covariance", [True, False])
def test_noise_free_maps_give_zero_cost_and_the_truth(full_covariance):
    run = simulate(12, seed=5, noiseless=True, full_covariance=full_covariance)
    guess = join_sequential(run.maps).global_map
    start = dataclasses.replace(guess, features=guess.features + 0.05, poses=guess.poses + [0.1, -0.1, 0.01])
    result = refine(run.maps, start)
    assert result.converged and result.cost < 1e-16
    order = np.searchsorted(run.truth.feature_ids, result.global_map.feature_ids)
    np.testing.assert_allclose(result.global_map.features, run.truth.features[order], rtol=0, atol=1e-9)
    truth = run.truth.poses[1:]
    np.testing.assert_allclose(result.global_map.poses[:, :2], truth[:, :2], rtol=0, atol=1e-9)
    np.testing.assert_allclose(np.angle(np.exp(1j * (result.global_map.poses[:, 2] - truth[:, 2]))), 0, atol=1e-9)


# --------------------------------------------------------------------------- covariances


@pytest.mark.parametrize("case", ["vicpark30", "dlr25", "sim-spherical"])
def test_marginal_covariances_equal_the_dense_inverse(case, request):
    real = request.getfixturevalue("real") if case != "sim-spherical" else None
    maps = {"vicpark30": lambda: real("VicPark_200_local_maps")[:30],
            "dlr25": lambda: real("DLR_200_local_maps")[:25],
            "sim-spherical": lambda: spherical(sim_maps(20))}[case]()
    result = refine(maps)
    g = result.global_map
    problem = ExactProblem(maps)
    poses, features = dense_marginals(problem, problem.pack(g))
    np.testing.assert_allclose(g.pose_covariances, poses, rtol=1e-8, atol=1e-10 * np.abs(poses).max())
    np.testing.assert_allclose(g.feature_covariances, features, rtol=1e-8, atol=1e-10 * np.abs(features).max())
    # spherical summaries: half the trace of the x/y block, the orientation variance as is
    np.testing.assert_allclose(g.feature_variances, np.trace(features, axis1=1, axis2=2) / 2, rtol=1e-8)
    np.testing.assert_allclose(g.pose_variances[:, 0], (poses[:, 0, 0] + poses[:, 1, 1]) / 2, rtol=1e-8)
    np.testing.assert_allclose(g.pose_variances[:, 1], poses[:, 2, 2], rtol=1e-8)
    assert np.all(np.linalg.eigvalsh(g.pose_covariances) > 0) and np.all(np.linalg.eigvalsh(g.feature_covariances) > 0)


def test_selected_inversion_of_a_sparse_matrix_with_structural_zeros():
    """The general path: a closed pattern made from SuperLU's own factor (which drops the
    entries that come out zero), scalar supernodes, against the dense inverse."""
    rng = np.random.default_rng(3)
    n = 120
    B = sp.random(n, n, density=0.03, random_state=rng, format="csr")
    A = (B @ B.T + sp.diags(rng.uniform(1, 2, n))).tocsc()
    A = (A + sp.csc_matrix((np.zeros(40), (rng.integers(0, n, 40), rng.integers(0, n, 40))), shape=A.shape)).tocsc()
    A = (A + A.T) / 2
    factor = splu(A, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0, options={"SymmetricMode": True})
    q = np.asarray(factor.perm_c)
    assert np.array_equal(factor.perm_r, q)
    L = factor.L.tocoo()
    lower = L.row > L.col
    Lrow, Lcol = L.row[lower].astype(np.int64), L.col[lower].astype(np.int64)
    Acoo = A.tocoo()
    ar, ac = q[Acoo.row], q[Acoo.col]
    keys = closed_pattern(np.concatenate([Lcol, ac[ar > ac]]) * n + np.concatenate([Lrow, ar[ar > ac]]), n)
    structure = Supernodes(keys, np.ones(n, dtype=np.int64))
    rows, cols = np.maximum(ar, ac), np.minimum(ar, ac)
    values = selected_inverse(structure, Lrow, Lcol, L.data[lower], factor.U.diagonal(), rows, cols)
    Z = np.linalg.inv(A.toarray())
    np.testing.assert_allclose(values, Z[Acoo.row, Acoo.col], rtol=1e-9, atol=1e-12 * np.abs(Z).max())


def test_marginals_of_a_factor_in_another_order_take_the_general_path(real):
    """A factor whose own ordering is not the problem's node order: the pattern is closed
    from the factor itself (scalar supernodes); same blocks as the fast path."""
    maps = real("VicPark_200_local_maps")[:25]
    problem = ExactProblem(maps)
    data = problem.linearise(problem.pack(join_sequential(maps).global_map))[0]
    other = factorise(problem.normal_matrix(data), permc_spec="COLAMD")
    assert not np.array_equal(other.perm, np.arange(problem.n_unknowns))
    fast, general = problem.marginals(problem.factorise(data)), problem.marginals(other)
    for a, b in zip(fast, general):
        np.testing.assert_allclose(a, b, rtol=1e-9, atol=1e-12 * np.abs(a).max())


def test_a_map_without_features_and_a_single_map():
    maps = sim_maps(6, seed=2)
    m = maps[3]
    bare = LocalMap(m.name, m.start_id, m.end_id, m.end_pose, np.zeros(0, int), np.zeros((0, 2)), np.zeros(0),
                    m.pose_variances, m.covariance[:3, :3])
    result = refine(maps[:3] + [bare] + maps[4:])
    assert result.converged
    problem = ExactProblem(maps[:3] + [bare] + maps[4:])
    poses, _ = dense_marginals(problem, problem.pack(result.global_map))
    np.testing.assert_allclose(result.global_map.pose_covariances, poses, rtol=1e-8, atol=1e-14)
    single = refine(maps[:1])   # one map: the optimum is the map itself, its covariance the map's
    assert single.cost == pytest.approx(0, abs=1e-20) and single.iterations == 0
    np.testing.assert_allclose(single.global_map.poses[0, :2], maps[0].end_pose[:2], rtol=0, atol=1e-12)
    np.testing.assert_allclose(single.global_map.pose_covariances[0], maps[0].covariance[:3, :3], rtol=1e-9)


# --------------------------------------------------------------------------- starting points


def test_refining_the_optimum_takes_no_iteration(solved, real):
    first = solved("VicPark_200_local_maps")
    again = refine(real("VicPark_200_local_maps"), first.global_map)
    assert again.converged and again.iterations == 0 and again.initial_seconds == 0
    assert again.cost == pytest.approx(first.cost, rel=1e-12)
    np.testing.assert_allclose(again.global_map.features, first.global_map.features, rtol=0, atol=1e-9)


def test_a_perturbed_start_converges_to_the_same_optimum(solved, real):
    maps = real("DLR_200_local_maps")
    best = solved("DLR_200_local_maps").global_map
    rng = np.random.default_rng(7)
    start = dataclasses.replace(best, features=best.features + rng.normal(0, 0.3, best.features.shape),
                                poses=best.poses + rng.normal(0, [0.3, 0.3, 0.03], best.poses.shape))
    result = refine(maps, start, covariances=False)
    assert result.converged and result.costs[0] > 10 * result.cost
    np.testing.assert_allclose(result.global_map.features, best.features, rtol=0, atol=1e-6)
    np.testing.assert_allclose(result.global_map.poses[:, :2], best.poses[:, :2], rtol=0, atol=1e-6)
    assert result.global_map.feature_covariances is None and result.global_map.pose_covariances is None
    np.testing.assert_array_equal(result.global_map.feature_variances, best.feature_variances)


def test_levenberg_marquardt_recovers_from_a_far_start():
    """Far starts (poses off by ~2 m and ~2.4 rad, features by ~2 m) reach the same optimum,
    with the damping refusing steps on the way (checked over several starts, so that no
    single random path decides whether the safeguard is exercised)."""
    maps = sim_maps(8, seed=11)
    guess = join_sequential(maps).global_map
    near = refine(maps, guess)
    assert near.rejected == 0
    rejected = 0
    for seed in (3, 4, 5, 6):
        rng = np.random.default_rng(seed)
        start = dataclasses.replace(guess, poses=guess.poses + rng.normal(0, [2.0, 2.0, 2.4], guess.poses.shape),
                                    features=guess.features + rng.normal(0, 2.0, guess.features.shape))
        far = refine(maps, start, max_iterations=200)
        assert far.converged
        assert far.costs[0] > 1e3 * far.cost and decreasing(far.costs)
        assert far.cost == pytest.approx(near.cost, rel=1e-9)
        np.testing.assert_allclose(far.global_map.features, near.global_map.features, rtol=0, atol=1e-6)
        rejected += far.rejected
    assert rejected >= 1  # steps were refused on the way


def refined_from_the_truth(run):
    """The exact solve of a simulation's maps started at its ground truth (the reference optimum)."""
    problem = ExactProblem(run.maps)
    where = np.searchsorted(run.truth.feature_ids, problem.feature_ids)
    truth = GlobalMap(feature_ids=problem.feature_ids, features=run.truth.features[where],
                      feature_variances=np.ones(problem.n_features), pose_ids=problem.pose_ids,
                      poses=run.truth.poses[problem.pose_ids], pose_variances=np.ones((problem.n_maps, 2)))
    return refine(run.maps, truth, covariances=False)


def test_an_overshooting_gauss_newton_step_is_shortened_not_damped():
    """Two laps of a simulated run (400 maps) from the sequential join: early Gauss-Newton
    steps overshoot; halved (a line search; the damping stays zero) the solver reaches, in 11
    iterations, the optimum the ground truth leads to (Marquardt damping instead took 18; on
    10^4 maps from the tree's join it crept for 100 without converging)."""
    run = simulate(400, seed=3)
    result = join_and_refine(run.maps, start="sequential", covariances=False)
    reference = refined_from_the_truth(run)
    assert result.converged and reference.converged and result.rejected >= 1 and result.iterations <= 12
    assert result.cost == pytest.approx(reference.cost, rel=1e-9)
    np.testing.assert_allclose(result.global_map.features, reference.global_map.features, rtol=0, atol=1e-5)


class ArctangentProblem:
    """A constructed one-unknown problem in :func:`minimise`'s interface: residuals ``(atan x, b)``, so
    chi^2 = atan(x)^2 + b^2, its optimum x = 0 with chi^2 = b^2 (by hand). Gauss-Newton's step
    ``-atan(x) (1 + x^2)`` overshoots for |x| > 1.39 (Newton's method on atan diverges there), and the
    constant ``b`` makes the gain of a shortened step tiny relative to chi^2."""

    n_residuals = 2

    def __init__(self, b: float):
        self.b = b

    def cost(self, x):
        return float(np.arctan(x[0]) ** 2 + self.b ** 2)

    def linearise(self, x, curvature=False):
        r, j = np.arctan(x[0]), 1.0 / (1.0 + x[0] ** 2)         # residual and its derivative
        found = (np.array([j * j]), np.array([j * r]), self.cost(x))
        return found + (np.array([r * -2.0 * x[0] * j * j]),) if curvature else found   # r * r''

    def factorise(self, data, damping=0.0, second=None):
        return (data if second is None else data + second) * (1.0 + damping)

    def solve(self, factor, rhs):
        return rhs / factor

    def diagonal(self, data):
        return data


def test_a_shortened_step_does_not_stop_the_solver_far_from_the_optimum():
    """From x = 10 Gauss-Newton's step lands at -139 (chi^2 up); its eighth lowers chi^2 by 0.047, under
    the tolerance's 1e-12 * chi^2 = 0.1 though the optimum is 2.2 lower: the solver used to stop there
    (x = -8.57) as converged, on the cost change of a step shortened because the full one was rejected.
    The cost change counts only for full undamped steps, so it goes on to the optimum."""
    problem = ArctangentProblem(10 ** 5.5)
    found = minimise(problem, np.array([10.0]))
    optimum = problem.b ** 2
    assert found.rejected >= 1                     # the shortened step was taken on the way
    assert found.converged and found.reason == "relative cost change below tolerance"
    assert found.cost - optimum <= TOLERANCE * optimum
    assert abs(found.x[0]) < 0.33                  # atan(x)^2 <= 0.1: the optimum to the tolerance


class ScaledArctangentProblem(ArctangentProblem):
    """:class:`ArctangentProblem` with its first residual scaled, ``(c atan x, b)``: Gauss-Newton's step is the
    same, its gain c^2 times as large. ``curvatures`` records, per linearisation, whether Newton's term was
    asked for."""

    def __init__(self, b: float, c: float):
        super().__init__(b)
        self.c = c
        self.curvatures: list[bool] = []

    def cost(self, x):
        return float((self.c * np.arctan(x[0])) ** 2 + self.b ** 2)

    def linearise(self, x, curvature=False):
        self.curvatures.append(curvature)
        r, j = self.c * np.arctan(x[0]), self.c / (1.0 + x[0] ** 2)
        found = (np.array([j * j]), np.array([j * r]), self.cost(x))
        return found + (np.array([r * -2.0 * x[0] * self.c / (1.0 + x[0] ** 2) ** 2]),) if curvature else found


@pytest.mark.parametrize("scale, newton", [(2.0, True), (10.0, False)])
def test_a_newton_step_follows_only_a_step_of_at_most_three_standard_deviations(scale, newton):
    """From x = 0.5 Gauss-Newton's step lands at x = 0.5 - 1.25 atan(0.5) = -0.0795 and lowers chi^2 by
    c^2 (atan(0.5)^2 - atan(0.0795)^2) = 0.2087 c^2 (by hand), a part in 10^7 of chi^2 (b^2 = 10^8) or
    less: near the optimum by the relative test. With c = 2 (0.83) Newton's step follows; with c = 10 (20.9,
    a step of 4.6 standard deviations) Gauss-Newton's does (docs/method.md#solver)."""
    problem = ScaledArctangentProblem(1e4, scale)
    found = minimise(problem, np.array([0.5]))
    assert found.converged and abs(found.x[0]) < 1e-3
    assert problem.curvatures[0] is False and problem.curvatures[1] is newton   # after the first step


@pytest.mark.parametrize("scale, stops_at_once", [(1e-3, True), (1e-1, False)])
def test_a_full_step_the_data_do_not_resolve_stops_the_solver(scale, stops_at_once):
    """Residuals ``(c atan x, 10)`` from x = 3 (by hand): Gauss-Newton's step -atan(3) (1 + 9) = -12.49 lands at
    x = -9.49, where atan(x)^2 = 2.149 exceeds atan(3)^2 = 1.560, and is predicted to lower chi^2 (about 100) by
    c^2 atan(3)^2. With c = 1e-3 that is 1.6e-6: the optimum x = 0, whose standard deviation is 1 / c = 1000, is
    0.003 of it away, and chi^2 is 1.6e-6 above its optimum (1.6e-8 relative): the solver stops at once, converged,
    instead of creeping on halved steps (it did, for 21 iterations, at the optimum of 10^5 simulated maps). With
    c = 0.1 (a predicted 0.016) the data resolve the difference and the solver goes on to the optimum."""
    problem = ScaledArctangentProblem(10.0, scale)
    found = minimise(problem, np.array([3.0]))
    optimum = problem.b ** 2
    assert found.converged
    if stops_at_once:
        assert found.reason == "predicted decrease below the data's resolution" and found.iterations == 0
        assert found.x[0] == 3.0 and abs(found.x[0]) <= 0.01 / scale          # within 0.01 standard deviations
        assert 0 < found.cost - optimum <= 1e-4 and found.cost - optimum <= 1e-6 * optimum
    else:
        assert found.reason != "predicted decrease below the data's resolution" and abs(found.x[0]) < 1e-3
        assert found.cost - optimum <= TOLERANCE * optimum


@pytest.mark.parametrize("seed", [0, 6])
def test_the_default_start_reaches_the_optimum_a_start_at_the_truth_reaches(seed):
    """1000-map simulations (two laps): the default start (the tree join) reaches the chi^2 and the map
    that the solve started at the ground truth reaches, with a vanishing gradient. From the sequential
    join the solver crept for 100 iterations (seed 0: chi^2 31856, exit 3); on seed 6 Newton's steps
    taken far from the optimum led it from the tree's start into a local minimum 10 % above it."""
    run = simulate(1000, seed=seed)
    result = join_and_refine(run.maps, covariances=False)
    reference = refined_from_the_truth(run)
    assert result.start == DEFAULT_START == "tree" and result.converged and reference.converged, result.reason
    assert result.cost == pytest.approx(reference.cost, rel=1e-9)
    np.testing.assert_allclose(result.global_map.features, reference.global_map.features, rtol=0, atol=1e-6)
    assert relative_gradient(ExactProblem(run.maps), result.global_map) < 1e-10


def test_the_cli_names_its_start_and_skips_with_the_sequential_one(simulated_folder, tmp_path):
    """refine's default start is the library's (the CLI does not import it), the summary names it, and
    --on-inconsistent skip, which re-joins map by map, starts from the sequential join unless told."""
    from mapjoin.cli import common

    assert common.REFINE_START == DEFAULT_START == default_start() and default_start("skip") == "sequential"
    result = run("refine", simulated_folder, "--no-covariances", "-o", str(tmp_path / "a.csv"))
    assert result.exit_code == 0 and "), from the tree join, " in result.stderr, result.stderr
    result = run("refine", simulated_folder, "--on-inconsistent", "skip", "-o", str(tmp_path / "b.csv"))
    assert result.exit_code == 0 and "), from the sequential join, " in result.stderr, result.stderr
    result = run("join", simulated_folder, "--refine", "--json", "-o", str(tmp_path / "c.csv"))
    assert result.exit_code == 0 and '"strategy": "tree"' in result.stdout, result.stderr
    result = run("join", simulated_folder, "--json", "-o", str(tmp_path / "d.csv"))
    assert result.exit_code == 0 and '"strategy": "sequential"' in result.stdout, result.stderr


def test_max_iterations_stops_early_and_says_so(real):
    result = refine(real("DLR_200_local_maps"), max_iterations=1, covariances=False)
    assert not result.converged and result.reason == "max iterations reached"
    assert result.iterations == 1 and len(result.costs) == 2


def test_join_and_refine_is_the_fast_join_then_refine_from_it(real):
    """The pipeline both commands run: the fast join it made is kept, and refine's default start is it."""
    maps = real("8240_data_50_local_maps")
    for start in ("sequential", "tree"):
        piped = join_and_refine(maps, start=start, covariances=False)
        fast = join(maps, strategy=start)
        assert piped.fast_join.report == fast.report and piped.initial_seconds > 0
        direct = refine(maps, fast.global_map, covariances=False)
        assert direct.fast_join is None and direct.initial_seconds == 0
        np.testing.assert_array_equal(piped.global_map.features, direct.global_map.features)
        assert piped.costs == direct.costs
    assert refine(maps, covariances=False).costs == join_and_refine(maps, covariances=False).costs


def test_bad_chains_and_starts_are_join_errors():
    maps = sim_maps(4)
    with pytest.raises(JoinError, match="neither the origin"):
        ExactProblem([maps[0], maps[2]])
    with pytest.raises(JoinError, match="does not connect"):
        refine([maps[0], maps[2]])         # the fast join, the default start, needs a chain
    with pytest.raises(JoinError, match="more than one map"):
        ExactProblem([maps[0], maps[1], dataclasses.replace(maps[3], start_id=2, end_id=1)])
    guess = join_sequential(maps).global_map
    short = dataclasses.replace(guess, feature_ids=guess.feature_ids[1:], features=guess.features[1:],
                                feature_variances=guess.feature_variances[1:])
    with pytest.raises(JoinError, match="has no feature"):
        refine(maps, short)
    with pytest.raises(JoinError, match="no local maps"):
        refine([])


# --------------------------------------------------------------------------- command line


def test_cli_writes_the_exact_map_with_covariances(simulated_folder, tmp_path):
    result = run("-v", "refine", simulated_folder, "-o", str(tmp_path / "g.csv"))
    assert result.exit_code == 0, result.output
    table = list(csv.DictReader(io.StringIO((tmp_path / "g.csv").read_text())))
    assert {"cov_xx", "cov_xy", "cov_yy", "cov_phiphi"} <= set(table[0])
    assert all(r["cov_xx"] for r in table) and all(r["cov_phiphi"] for r in table if r["kind"] == "pose")
    assert "iteration 0: chi^2 = " in result.stderr and "iteration 1: chi^2 = " in result.stderr
    assert "refined 12 maps:" in result.stderr and "from the tree join, 4 iterations, chi^2 " in result.stderr
    written = mapio.read_global_map(tmp_path / "g.csv")
    expected = refine(mapio.read_maps([simulated_folder]))
    # each step's line also gives chi^2's change, the difference of the library's costs (3 digits)
    changes = [float(c) for c in re.findall(r"^iteration \d+: chi\^2 = \S+ \(change (\S+)\)$", result.stderr, re.M)]
    np.testing.assert_allclose(changes, np.diff(expected.costs), rtol=5e-3)
    assert len(changes) == expected.iterations and "iteration 0: chi^2 = " + f"{expected.costs[0]:.10g}\n" in result.stderr
    np.testing.assert_array_equal(written.features, expected.global_map.features)
    np.testing.assert_array_equal(written.pose_covariances, expected.global_map.pose_covariances)


def test_cli_yaml_stdin_and_no_covariances(simulated_folder, tmp_path):
    piped = run("simulate", "-o", "-", "--maps", "6", "--seed", "2")
    result = run("-q", "refine", "-", "--format", "yaml", "--no-covariances", input=piped.stdout)
    assert result.exit_code == 0, result.output
    assert result.stdout.startswith("format: mapjoin/global-map") and "cov:" not in result.stdout
    assert result.stderr == ""
    result = run("-q", "refine", simulated_folder, "-o", str(tmp_path / "g.yaml"))
    assert "cov:" in (tmp_path / "g.yaml").read_text()


def test_cli_warns_when_chi2_is_far_from_its_degrees_of_freedom(data_dir):
    result = run("refine", str(data_dir / "VicPark_200_local_maps"), "--no-covariances")
    assert result.exit_code == 0
    assert "warning: final chi^2 = 3643.43 is outside the 99.9% interval [6792.23, 7580.88]" in result.stderr
    assert "7180 degrees of freedom (8378 residuals - 1198 unknowns" in result.stderr and "pessimistic" in result.stderr
    quiet = run("refine", str(data_dir / "535_data_5_local_maps"))
    assert "warning" not in quiet.stderr   # chi^2 7.83 with 85 - 62 = 23 degrees of freedom: plausible


def test_join_refine_warns_as_refine_does_and_quiet_runs_skip_the_chi2_interval(data_dir, tmp_path):
    folder = str(data_dir / "VicPark_200_local_maps")
    result = run("join", folder, "--refine", "-o", str(tmp_path / "g.csv"))
    assert result.exit_code == 0
    assert "warning: final chi^2 = 3643.43 is outside the 99.9% interval [6792.23, 7580.88]" in result.stderr
    # -q silences warnings, so the interval is not computed at all
    code = ("import mapjoin.evaluation as evaluation\nfrom mapjoin.cli import main\n"
            "evaluation.chi2_verdict = None  # asked for, it would fail\n"
            f"main(['-q', 'refine', {folder!r}, '--no-covariances', '-o', {str(tmp_path / 'q.csv')!r}], "
            "standalone_mode=False)\nprint('done')")
    quiet = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert quiet.stdout.split() == ["done"] and quiet.stderr == ""


def test_cli_reports_non_convergence_refuses_to_overwrite_and_has_examples(simulated_folder, tmp_path):
    result = run("refine", simulated_folder, "--max-iterations", "0", "-o", str(tmp_path / "g.csv"))
    assert result.exit_code == 3 and "did not converge (max iterations reached after 0 iterations, chi^2" in result.stderr
    # the default start's solve did not converge: the hierarchical start was tried too, and said so
    assert "), from the hierarchical join (the tree join's solve did not converge), 0 iterations" in result.stderr
    assert "try --start" not in result.stderr
    again = run("refine", simulated_folder, "--max-iterations", "0", "--start", "tree", "-o", str(tmp_path / "h.csv"))
    assert again.exit_code == 3 and again.stderr.rstrip().endswith("; try --start hierarchical"), again.stderr
    assert "), from the tree join, 0 iterations" in again.stderr   # a start given is not replaced
    target = Path(simulated_folder) / "localmap_1.yaml"
    before = target.read_text()
    result = CliRunner().invoke(main, ["refine", simulated_folder, "-o", str(target)])
    assert result.exit_code == 1 and "is an input file" in result.output and target.read_text() == before
    assert "Examples:" in run("refine", "--help").output


def test_cli_start_from_the_tree_reaches_the_same_optimum(data_dir, tmp_path):
    """DLR 200 from the tree's start (chi^2 2.8e6 against 7.4e4 from the sequential one): the same optimum."""
    folder = str(data_dir / "DLR_200_local_maps")
    outputs = {}
    for start in ("sequential", "tree"):
        out = tmp_path / f"{start}.csv"
        result = run("refine", folder, "--start", start, "--no-covariances", "-o", str(out))
        assert result.exit_code == 0, result.output
        assert "chi^2" in result.stderr and "-> 11163.643" in result.stderr
        outputs[start] = mapio.read_global_map(out)
    np.testing.assert_allclose(outputs["tree"].features, outputs["sequential"].features, atol=1e-6)
    np.testing.assert_allclose(outputs["tree"].poses, outputs["sequential"].poses, atol=1e-6)


def test_cli_tolerance_default_is_the_library_default():
    from mapjoin.refine import TOLERANCE

    for command in ("refine", "join"):
        assert f"[default: ({TOLERANCE:g}); 0.0<=x<=1.0]" in " ".join(run(command, "--help").output.split())


def test_tolerance_zero_means_to_rounding_and_converges(simulated_folder, data_dir, tmp_path):
    """A zero tolerance stops where chi^2's rounding hides any further decrease, reported as
    converged, at the same optimum as the default tolerance (it used to damp on to the damping
    limit and warn that the solve had not converged)."""
    result = run("refine", simulated_folder, "--tolerance", "0", "-o", str(tmp_path / "g.csv"))
    assert result.exit_code == 0 and "did not converge" not in result.stderr, result.stderr
    for maps in (mapio.read_maps([simulated_folder]), mapio.read_maps([str(data_dir / "DLR_200_local_maps")])):
        default, zero = refine(maps), refine(maps, tolerance=0)
        assert zero.converged, zero.reason
        assert zero.cost <= default.cost * (1 + 1e-12)
        assert np.max(np.abs(zero.global_map.features - default.global_map.features)) < 1e-8
        assert np.max(np.abs(zero.global_map.poses - default.global_map.poses)) < 1e-8


def test_a_refine_that_does_not_converge_exits_3_and_says_so_in_one_line(tmp_path):
    """Not converging must not look like success, under -q too; the last iterate is still written."""
    from cli_runner import run as cli

    example = str(Path(__file__).resolve().parents[1] / "examples" / "sim20")
    for args in (["refine", example, "-o", str(tmp_path / "r.csv"), "--max-iterations", "1"],
                 ["refine", example, "-o", str(tmp_path / "c.csv")]):
        result = cli("-q", *args)
        converged = "--max-iterations" not in args
        assert result.exit_code == (0 if converged else 3), result.stderr
        assert (tmp_path / args[3].rsplit("/", 1)[-1]).is_file()
        if not converged:
            assert result.stderr.count("\n") == 1 and "did not converge" in result.stderr
            assert "holds the last iterate" in result.stderr
