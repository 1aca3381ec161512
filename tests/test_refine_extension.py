"""A chain's exact optimum extended by one map (mapjoin.refine.extension), against the union's own exact problem:
its cost and gradient (ExactProblem), finite differences, and the union solved whole (minimise)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mapjoin.joining import join
from mapjoin.maps import LocalMap
from mapjoin.refine.extension import SharedTerm, extend
from mapjoin.refine.problem import ExactProblem
from mapjoin.refine.solver import minimise
from mapjoin.se2 import compose, transform
from mapjoin.simulation import simulate


def _union_unknowns(union: ExactProblem, problem: ExactProblem, x: np.ndarray, added: LocalMap, end_pose: np.ndarray,
                    feature_ids: np.ndarray, features: np.ndarray) -> np.ndarray:
    """The unknowns of ``union`` (the chain of ``problem`` and ``added``): the chain's at ``x``, the added map's
    end pose and new features as given; looked up by id, one by one."""
    poses, points = problem.unpack(x)
    pose_of = dict(zip(problem.pose_ids.tolist(), poses))
    pose_of[added.end_id] = end_pose
    point_of = dict(zip(problem.feature_ids.tolist(), points))
    point_of.update(zip(feature_ids.tolist(), features))
    assert sorted(point_of) == union.feature_ids.tolist()
    return np.concatenate([np.concatenate([pose_of[i] for i in union.pose_ids.tolist()]),
                           np.concatenate([point_of[i] for i in union.feature_ids.tolist()])])


def _chain(seed: int, full_covariance: bool = True) -> list[LocalMap]:
    return list(simulate(10, seed=seed, laps=1.0, steps_per_map=4, full_covariance=full_covariance).maps)


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 40), k=st.integers(1, 9), spread=st.floats(0.0, 0.3), draw=st.integers(0, 2**32 - 1),
       full=st.booleans())
def test_the_shared_term_is_the_added_maps_term_at_its_own_unknowns_best(seed, k, spread, draw, full):
    """At any point of the chain's unknowns, the union's chi^2 with the added map's end pose and new features
    where :meth:`SharedTerm.placed` puts them is the chain's chi^2 plus the shared term, and there the union's
    gradient in those unknowns is zero (they minimise it): the Schur complement, checked on the union's own
    problem; with full covariances or spherical variances (a diagonal P)."""
    maps = _chain(seed, full)
    chain, added = maps[:k], maps[k]
    problem, union = ExactProblem(chain), ExactProblem(maps[:k + 1])
    rng = np.random.default_rng(draw)
    x = problem.pack(join(chain).global_map) + rng.normal(scale=spread, size=problem.n_unknowns)
    term = SharedTerm(problem, added)
    end_pose, feature_ids, features = term.placed(x)
    u = _union_unknowns(union, problem, x, added, end_pose, feature_ids, features)
    assert union.cost(u) == pytest.approx(problem.cost(x) + term.cost(x), rel=1e-10)
    _, gradient, _ = union.linearise(u)
    own = np.concatenate([3 * (len(union.pose_ids) - 1) + np.arange(3),
                          (3 * union.n_maps + 2 * np.searchsorted(union.feature_ids, feature_ids)[:, None]
                           + np.arange(2)).ravel()])
    scale = np.max(np.abs(gradient)) + 1.0
    np.testing.assert_allclose(gradient[own], 0.0, atol=1e-9 * scale)
    # and no other placement does better: the added map moved a little raises the union's chi^2
    moved = u.copy()
    moved[own] += rng.normal(scale=1e-3, size=len(own))
    assert union.cost(moved) >= union.cost(u) * (1 - 1e-12)


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 40), k=st.integers(2, 9), spread=st.floats(0.0, 0.3), draw=st.integers(0, 2**32 - 1))
def test_the_shared_terms_jacobian_is_its_residuals_finite_differences(seed, k, spread, draw):
    """``J^T J`` and ``J^T r`` of the shared term against the Jacobian of its residual by central differences."""
    maps = _chain(seed)
    problem = ExactProblem(maps[:k])
    rng = np.random.default_rng(draw)
    x = problem.pack(join(maps[:k]).global_map) + rng.normal(scale=spread, size=problem.n_unknowns)
    term = SharedTerm(problem, maps[k])
    h = 1e-6
    columns = []
    for c in term.columns:
        e = np.zeros_like(x)
        e[c] = h
        columns.append((term.residual(x + e) - term.residual(x - e)) / (2 * h))
    J = np.stack(columns, axis=1)
    r = term.residual(x)
    matrix, gradient, cost = term.linearise(x)
    assert cost == pytest.approx(r @ r, rel=1e-12)
    np.testing.assert_allclose(gradient, J.T @ r, rtol=1e-6, atol=1e-6 * np.max(np.abs(J.T @ r)))
    np.testing.assert_allclose(matrix, J.T @ J, rtol=1e-6, atol=1e-6 * np.max(np.abs(J.T @ J)))


@pytest.mark.parametrize("seed", [0, 1])
def test_the_extended_optimum_is_the_union_solved_whole(seed):
    """At the joins the fast statistic flags in simulations with loop closures (the union's optimum moves the
    map), :func:`extend` from the chain's optimum ends where the union's exact problem, solved whole from the
    chain's optimum and the added map, does: the same chi^2 (1e-9; measured 1e-13) and unknowns (1e-4 m or rad;
    measured 1e-5: its steps converge linearly and stop, as the solver's, on chi^2's change). Where it gives up it
    says so (None): at the loop closures that move the map by metres."""
    maps = list(simulate(120, seed=seed, laps=2.0).maps)
    flagged = [r.join for r in join(maps).report if r.flag][:6]
    served = 0
    for k in flagged:
        chain, added = maps[:k], maps[k]
        problem, union = ExactProblem(chain), ExactProblem(maps[:k + 1])
        tree = join(chain, strategy="tree").global_map
        optimum = minimise(problem, problem.pack(tree))
        assert optimum.converged
        found = extend(problem, optimum.x, added)
        if found is None:
            continue
        served += 1
        x = optimum.x   # the whole solve's start: the chain's optimum, the added map at its end
        poses, _ = problem.unpack(x)
        base = poses[np.flatnonzero(problem.pose_ids == added.start_id)[0]]
        fresh = ~np.isin(added.feature_ids, problem.feature_ids)
        start = _union_unknowns(union, problem, x, added, compose(base, added.end_pose),
                                added.feature_ids[fresh], transform(base, added.features[fresh]))
        whole = minimise(union, start)
        assert whole.converged
        assert found.cost == pytest.approx(whole.cost, rel=1e-9)
        at = _union_unknowns(union, problem, found.x, added, found.end_pose, found.feature_ids, found.features)
        difference = at - whole.x
        difference[2:3 * union.n_maps:3] = (difference[2:3 * union.n_maps:3] + np.pi) % (2 * np.pi) - np.pi
        np.testing.assert_allclose(difference, 0.0, atol=1e-4)
        assert found.shared == np.isin(added.feature_ids, problem.feature_ids).sum()
    assert served >= 3


def test_far_from_the_chains_optimum_it_gives_up_without_solving_by_lu():
    """From a point far from the chain's optimum (its features scattered by metres), the Newton matrix there is not
    positive definite (the dense backend would solve by LU of the whole matrix): Gauss-Newton's is factorised
    instead, every solve is by its Cholesky factor, and the chord steps do not lower chi^2 or do not settle: None,
    and the caller solves the union whole."""
    maps = list(simulate(40, seed=5, laps=1.0).maps)
    problem = ExactProblem(maps[:30])
    x = problem.pack(join(maps[:30]).global_map)
    x[3 * problem.n_maps:] += np.random.default_rng(0).normal(scale=3.0, size=2 * problem.n_features)
    data, _, _, second = problem.linearise(x, curvature=True)
    assert problem.backend == "dense" and not problem.factorise(data, second=second).cholesky
    solved_by = []
    solve = problem.solve
    problem.solve = lambda factor, rhs: solved_by.append(factor.cholesky) or solve(factor, rhs)
    assert extend(problem, x, maps[30]) is None
    assert solved_by and all(solved_by)


def test_a_singular_update_gives_up_as_a_singular_factor_does(monkeypatch):
    """I + W C singular to rounding (the outside fuzz met it in `join` of a chain with coordinates near 1e9 m and
    variances from 1e-30 to 1e30: numpy's LinAlgError, a traceback, from a flagged join's confirmation) is a
    give-up (None, the caller solves the union whole), as a singular factor of the chain's Hessian is. The
    fuzz's chain depends on every digit of its 13 x 13 covariances, so numpy's solve is made to fail as it did."""
    maps = _chain(3)
    problem = ExactProblem(maps[:9])
    optimum = minimise(problem, problem.pack(join(maps[:9]).global_map))
    assert extend(problem, optimum.x, maps[9]) is not None

    def singular(matrix, rhs):
        raise np.linalg.LinAlgError("Singular matrix")

    monkeypatch.setattr(np.linalg, "solve", singular)
    assert extend(problem, optimum.x, maps[9]) is None
