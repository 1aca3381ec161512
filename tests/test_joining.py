"""Joining (sequential and tree): exactness on noise-free chains, the pose chain, the real datasets."""

from __future__ import annotations

import logging
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mapjoin import COVARIANCE_MODES, JoinError, LocalMap
from mapjoin.joining import STRATEGIES, certify_pair, join, join_sequential, join_tree
from mapjoin.maps import locate


def _rotation(phi: float) -> np.ndarray:
    return np.array([[math.cos(phi), -math.sin(phi)], [math.sin(phi), math.cos(phi)]])


def noise_free_chain(seed: int, count: int = 6, per_map: int = 8, with_covariance: bool = False):
    """Truth and exact local maps of a random walk; consecutive maps share features."""
    rng = np.random.default_rng(seed)
    poses = [np.zeros(3)]
    for _ in range(count):
        step = np.array([rng.uniform(2, 6), rng.uniform(-1, 1), rng.uniform(-0.8, 0.8)])
        x, y, phi = poses[-1]
        poses.append(np.array([*(np.array([x, y]) + _rotation(phi) @ step[:2]), phi + step[2]]))
    features = {}
    maps = []
    next_id = int(rng.integers(0, 1000))
    for k in range(1, count + 1):
        start, end = poses[k - 1], poses[k]
        old = [i for i in features if np.linalg.norm(features[i] - start[:2]) < 12]
        ids = list(rng.permutation(old)[: per_map // 2])
        while len(ids) < per_map:
            features[next_id] = start[:2] + rng.uniform(-8, 8, 2)
            ids.append(next_id)
            next_id += int(rng.integers(1, 50))
        inverse = _rotation(start[2]).T
        local = np.array([inverse @ (features[i] - start[:2]) for i in ids])
        end_local = np.array([*(inverse @ (end[:2] - start[:2])), (end[2] - start[2] + np.pi) % (2 * np.pi) - np.pi])
        variances = rng.uniform(0.1, 2.0, len(ids))
        covariance = None
        if with_covariance:
            basis = rng.normal(size=(3 + 2 * len(ids),) * 2)
            covariance = basis @ basis.T + np.eye(len(basis))
        maps.append(LocalMap(f"m{k}", k - 1, k, end_local, ids, local, variances,
                             rng.uniform(0.1, 1.0, 2), covariance))
    return maps, features, np.array(poses[1:])


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), mode=st.sampled_from(COVARIANCE_MODES),
       solver=st.sampled_from(["bisection", "golden"]), strategy=st.sampled_from(STRATEGIES),
       count=st.integers(1, 11))
def test_noise_free_maps_are_joined_exactly(seed, mode, solver, strategy, count):
    maps, features, poses = noise_free_chain(seed, count=count, with_covariance=True)
    result = join(maps, mode, solver, strategy)
    g = result.global_map
    truth = np.array([features[i] for i in g.feature_ids])
    tolerance = 1e-9 if solver == "bisection" else 1e-6
    np.testing.assert_allclose(g.features, truth, atol=tolerance * 100)
    np.testing.assert_allclose(g.poses[:, :2], poses[:, :2], atol=tolerance * 100)
    np.testing.assert_allclose(np.angle(np.exp(1j * (g.poses[:, 2] - poses[:, 2]))), 0, atol=tolerance)
    assert all(r.minima == 1 for r in result.report) and len(result.report) == count - 1
    assert all(r.cost < 1e-9 * max(1.0, r.a) for r in result.report if solver == "bisection")


def test_report_counts_common_and_new_features():
    maps, _, _ = noise_free_chain(3)
    result = join_sequential(maps)
    seen = set(maps[0].feature_ids.tolist())
    for record, local_map in zip(result.report, maps[1:]):
        ids = set(local_map.feature_ids.tolist())
        assert record.common == len(ids & seen)
        assert record.new == len(ids - seen)
        assert (record.start_id, record.end_id, record.map) == (local_map.start_id, local_map.end_id,
                                                                local_map.name)
        seen |= ids
    assert [r.join for r in result.report] == list(range(1, len(maps)))


def test_feature_order_within_maps_does_not_matter():
    maps, _, _ = noise_free_chain(5)
    rng = np.random.default_rng(0)
    noisy = [LocalMap(m.name, m.start_id, m.end_id, m.end_pose + rng.normal(0, 0.05, 3), m.feature_ids,
                      m.features + rng.normal(0, 0.1, m.features.shape), m.feature_variances,
                      m.pose_variances) for m in maps]
    shuffled = []
    for m in noisy:
        order = rng.permutation(m.size)
        shuffled.append(LocalMap(m.name, m.start_id, m.end_id, m.end_pose, m.feature_ids[order],
                                 m.features[order], m.feature_variances[order], m.pose_variances))
    a, b = join_sequential(noisy).global_map, join_sequential(shuffled).global_map
    np.testing.assert_array_equal(a.feature_ids, b.feature_ids)
    np.testing.assert_allclose(a.features, b.features, atol=1e-9)
    np.testing.assert_allclose(a.poses, b.poses, atol=1e-9)


def test_variances_stay_positive_and_fused_features_gain_precision():
    maps, _, _ = noise_free_chain(11)
    g = join_sequential(maps, "marginal").global_map
    assert (g.feature_variances > 0).all() and (g.pose_variances > 0).all()
    first = dict(zip(maps[0].feature_ids.tolist(), maps[0].feature_variances))
    both = set(first) & set(maps[1].feature_ids.tolist())
    index = {int(i): n for n, i in enumerate(g.feature_ids)}
    # a feature seen by maps 1 and 2 and never again: fused variance below each input variance
    later = set().union(*(m.feature_ids.tolist() for m in maps[2:]))
    for i in both - later:
        assert g.feature_variances[index[i]] < first[i]


def test_unconnected_chain_is_an_error():
    maps, _, _ = noise_free_chain(1)
    broken = [maps[0], maps[2]]
    with pytest.raises(JoinError, match=r"does not connect: m3 starts at pose 2.*m1\) ends at pose 1"):
        join_sequential(broken)
    with pytest.raises(JoinError, match="no local maps"):
        join_sequential([])


def test_pose_revisited_in_chain_is_an_error():
    maps, _, _ = noise_free_chain(1, count=2)
    loop = LocalMap("back", 2, 0, np.zeros(3), [], np.zeros((0, 2)), [], [1.0, 1.0])
    with pytest.raises(JoinError, match="pose 0 appears twice"):
        join_sequential(maps + [loop])


def test_a_join_asked_not_to_warn_says_nothing_and_leaves_the_logger_alone(caplog):
    """build joins internal pieces with warn=False instead of raising the logger's level."""
    maps, _, _ = noise_free_chain(2, count=2)
    second = maps[1]
    disjoint = LocalMap("disjoint", 1, 2, second.end_pose, second.feature_ids + 10**6, second.features,
                        second.feature_variances, second.pose_variances)
    level = logging.getLogger("mapjoin").level
    with caplog.at_level(logging.WARNING, logger="mapjoin"):
        quiet = join_sequential([maps[0], disjoint], warn=False)
    assert caplog.text == "" and logging.getLogger("mapjoin").level == level
    loud = join_sequential([maps[0], disjoint])
    np.testing.assert_array_equal(quiet.global_map.poses, loud.global_map.poses)


def test_map_sharing_no_feature_is_placed_by_its_start_pose(caplog):
    maps, _, _ = noise_free_chain(2, count=2)
    second = maps[1]
    disjoint = LocalMap("disjoint", 1, 2, second.end_pose, second.feature_ids + 10**6, second.features,
                        second.feature_variances, second.pose_variances)
    result = join_sequential([maps[0], disjoint])
    assert "disjoint shares no feature" in caplog.text
    record = result.report[0]
    assert record.common == 0 and record.minima == 1
    # placed by dead reckoning: the end pose of map 1 composed with map 2's end pose
    x, y, phi = maps[0].end_pose
    expected = np.array([x, y]) + _rotation(phi) @ second.end_pose[:2]
    np.testing.assert_allclose(result.global_map.poses[1, :2], expected, atol=1e-12)
    with pytest.raises(JoinError, match="share no feature"):
        certify_pair(maps[0], disjoint)


def test_certify_pair_matches_first_join():
    maps, _, _ = noise_free_chain(4)
    assert certify_pair(maps[0], maps[1]) == join_sequential(maps).report[0]


def test_first_vicpark_join_with_identity_covariances_matches_the_dense_formulas(data_dir):
    """a and C_phi of join 1, from the raw .mat files and the paper's dense Theorem 1."""
    from scipy.io import loadmat
    from theorem_oracles import Dense

    from mapjoin import io as mapio
    from mapjoin.onestep import OneStepProblem

    folder = data_dir / "VicPark_200_local_maps"
    first, second = (loadmat(folder / f"localmap_{k}.mat")["localmap_st"] for k in (1, 2))
    ids0, ids1 = first[3::2, 0], second[3::2, 0]
    xy0, xy1 = first[3:, 1].reshape(-1, 2), second[3:, 1].reshape(-1, 2)
    common = np.intersect1d(ids0, ids1)
    z0 = xy0[np.searchsorted(ids0, common)] if (np.diff(ids0) > 0).all() else \
        np.array([xy0[list(ids0).index(i)] for i in common])
    z1 = np.array([xy1[list(ids1).index(i)] for i in common])
    ones = np.ones(len(common))
    dense = Dense(OneStepProblem(z0, ones, z1, ones, first[:3, 1], np.ones(2)))
    _, a0, phi0 = dense.constants()
    expected_c = (first[2, 1] - phi0 + np.pi) % (2 * np.pi) - np.pi

    maps = mapio.read_maps([str(folder / "localmap_1.mat"), str(folder / "localmap_2.mat")])
    record = join_sequential(maps, "identity").report[0]
    assert record.common == len(common)
    assert record.a == pytest.approx(a0 * 1.0, rel=1e-12)
    assert record.c_phi == pytest.approx(expected_c, abs=1e-12)


def test_default_join_is_close_to_the_exact_join_on_vicpark(data_dir):
    """The paper's metric against the independent exact solver: better than the paper's
    0.5281 m in y and 0.0080 rad in phi (README, 'Covariance modes'); x measured at 0.50 m."""
    from oracles import exact_join

    from mapjoin import io as mapio
    from mapjoin.evaluation import compare

    folder = data_dir / "VicPark_200_local_maps"
    exact = exact_join(str(folder))
    assert exact.cost == pytest.approx(3643.435, abs=5e-4)
    fast = join_sequential(mapio.read_maps([str(folder)])).global_map
    reference = type(fast)(exact.feature_ids, exact.features, np.ones(len(exact.feature_ids)),
                           exact.pose_ids, exact.poses, np.ones((len(exact.pose_ids), 2)))
    difference = compare(reference, fast)
    assert difference.features == 299 and difference.poses == 200
    assert difference.mean_abs_x < 0.55
    assert difference.mean_abs_y < 0.5281
    assert difference.mean_abs_phi < 0.0080
    # the tree leaves more uncorrected (README, "Strategies"): measured 0.819 m, 0.476 m, 0.0083 rad
    tree = compare(reference, join_tree(mapio.read_maps([str(folder)])).global_map)
    assert tree.mean_abs_x < 0.85 and tree.mean_abs_y < 0.5 and tree.mean_abs_phi < 0.0085


def noisy_chain(seed: int, count: int) -> list[LocalMap]:
    """A noise-free chain with noise added to every estimate (so that joins disagree)."""
    maps, _, _ = noise_free_chain(seed, count=count)
    rng = np.random.default_rng(seed)
    return [LocalMap(m.name, m.start_id, m.end_id, m.end_pose + rng.normal(0, 0.05, 3), m.feature_ids,
                     m.features + rng.normal(0, 0.1, m.features.shape), m.feature_variances,
                     m.pose_variances) for m in maps]


def test_a_deep_tree_of_noiseless_maps_is_the_ground_truth():
    """2^11 + 3 noiseless simulated maps (two laps of a figure-eight: the loops close only in the top levels'
    joins): composed through 12 levels, the tree's joins put every pose and feature at the simulation's ground
    truth to rounding (measured 1.4e-7 m over 1.6 km, 1.7e-10 rad). So the tree start's chi^2 of 9e13 on 10^4
    noisy maps (docs/method.md#solver) is the drift its rigid joins leave, not a pose composed wrongly deep in
    the tree or an angle wrapped wrongly."""
    from mapjoin.simulation import simulate

    run = simulate(2 ** 11 + 3, seed=1, noiseless=True)
    g = join_tree(run.maps).global_map
    poses = dict(zip(run.truth.pose_ids.tolist(), run.truth.poses))
    features = dict(zip(run.truth.feature_ids.tolist(), run.truth.features))
    truth = np.array([poses[int(i)] for i in g.pose_ids])
    np.testing.assert_allclose(g.poses[:, :2], truth[:, :2], rtol=0, atol=1e-6)
    np.testing.assert_allclose(np.angle(np.exp(1j * (g.poses[:, 2] - truth[:, 2]))), 0, atol=1e-9)
    np.testing.assert_allclose(g.features, [features[int(i)] for i in g.feature_ids], rtol=0, atol=1e-6)


@pytest.mark.parametrize("count", [2, 5, 11, 16])
def test_tree_levels_pair_neighbours(count):
    """Level l joins pieces 2i and 2i+1 of level l-1 (an odd last piece waits): counted independently."""
    result = join_tree(noisy_chain(count, count))
    pieces, expected = count, []
    while pieces > 1:
        expected.append(pieces // 2)
        pieces -= pieces // 2
    levels = [r.level for r in result.report]
    assert [levels.count(level) for level in range(1, len(expected) + 1)] == expected
    assert [r.join for r in result.report] == list(range(1, count))
    first_level = [r for r in result.report if r.level == 1]
    maps = noisy_chain(count, count)
    for i, record in enumerate(first_level):  # level 1 joins single maps, as a two-map join does
        single = join_sequential(maps[2 * i:2 * i + 2]).report[0]
        assert (record.map, record.start_id, record.end_id) == (single.map, single.start_id, single.end_id)
        assert (record.common, record.new, record.minima) == (single.common, single.new, single.minima)
        assert record.a == pytest.approx(single.a, rel=1e-12) and record.phi == pytest.approx(single.phi, abs=1e-12)
    # the last join: the first 2^(L-1) maps (a full subtree) on the left, all the rest on the right
    split = 2 ** (len(expected) - 1)
    rest = maps[split].name if split == count - 1 else f"{maps[split].name} to {maps[-1].name}"
    last = result.report[-1]
    assert (last.map, last.start_id, last.end_id) == (rest, maps[split].start_id, maps[-1].end_id)


def test_tree_of_two_maps_is_the_sequential_join():
    """The same join, computed as arrays (tree) and on Python numbers (sequential): equal to rounding."""
    maps = noisy_chain(7, 2)
    tree, sequential = join_tree(maps), join_sequential(maps)
    for field in ("features", "feature_variances", "poses", "pose_variances"):
        np.testing.assert_allclose(getattr(tree.global_map, field), getattr(sequential.global_map, field),
                                   rtol=1e-13, atol=1e-13)
    (a,), (b,) = tree.report, sequential.report
    assert (a.map, a.common, a.new, a.minima, a.iterations) == (b.map, b.common, b.new, b.minima, b.iterations)
    for field in ("a", "c_phi", "phi", "cost"):
        assert getattr(a, field) == pytest.approx(getattr(b, field), rel=1e-12, abs=1e-12)
    assert tree.global_map.provenance.strategy == "tree"


@pytest.mark.parametrize("solver", ["bisection", "golden"])
def test_each_sequential_join_is_the_one_step_problem_of_the_map_so_far(solver):
    """Join k, rebuilt from the documented per-join API: the global map of maps 1..k-1 (common
    features, their variances, the last pose as odometry) and map k go into ``onestep.solve``."""
    from mapjoin.covariance import spherical_variances
    from mapjoin.onestep import OneStepProblem, solve

    maps = noisy_chain(3, 7)
    records = join_sequential(maps, "information", solver).report
    for k in range(1, len(maps)):
        so_far = join_sequential(maps[:k], "information", solver).global_map
        incoming = maps[k]
        row = {int(i): n for n, i in enumerate(so_far.feature_ids)}
        common = np.array([int(i) in row for i in incoming.feature_ids])
        rows = [row[int(i)] for i in incoming.feature_ids[common]]
        problem = OneStepProblem(so_far.features[rows], so_far.feature_variances[rows], incoming.features[common],
                                 spherical_variances(incoming, "information")[0][common], so_far.poses[-1],
                                 so_far.pose_variances[-1])
        expected, record = solve(problem, solver), records[k - 1]
        assert record.common == common.sum() and record.minima == expected.minima.count
        assert record.a == pytest.approx(expected.minima.a, rel=1e-12)
        assert record.c_phi == pytest.approx(expected.minima.c_phi, abs=1e-12)
        assert record.phi == pytest.approx(expected.phi, abs=1e-12 if solver == "bisection" else 1e-7)
        assert record.cost == pytest.approx(expected.cost, rel=1e-9, abs=1e-9)


@pytest.mark.parametrize("count, jobs", [(37, 2), (16, 4), (9, 3), (64, 2)])
def test_tree_result_does_not_depend_on_jobs(count, jobs):
    maps = noisy_chain(count, count)
    one, many = join_tree(maps), join_tree(maps, jobs=jobs)
    for field in ("feature_ids", "features", "feature_variances", "pose_ids", "poses", "pose_variances"):
        np.testing.assert_array_equal(getattr(one.global_map, field), getattr(many.global_map, field))
    assert one.report == many.report


def test_tree_and_sequential_agree_on_maps_sharing_no_feature(caplog):
    maps, _, _ = noise_free_chain(2, count=4)
    disjoint = [maps[0], maps[1]] + [LocalMap(m.name, m.start_id, m.end_id, m.end_pose, m.feature_ids + 10**6 * k,
                                              m.features, m.feature_variances, m.pose_variances)
                                     for k, m in enumerate(maps[2:], start=1)]
    tree = join_tree(disjoint)
    assert "shares no feature" in caplog.text
    np.testing.assert_allclose(tree.global_map.poses, join_sequential(disjoint).global_map.poses, atol=1e-9)


# --------------------------------------------------------------------------- information-mode summary


def _random_spd(rng, size: int, condition: float) -> np.ndarray:
    """A random symmetric positive definite matrix with eigenvalues spread over ``condition``."""
    basis, _ = np.linalg.qr(rng.normal(size=(size, size)))
    return (basis * np.logspace(0, np.log10(condition), size)) @ basis.T


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), sizes=st.lists(st.integers(0, 40), min_size=1, max_size=12),
       log_condition=st.floats(0, 8))
def test_information_variances_are_those_of_the_dense_inverse(seed, sizes, log_condition):
    """``information`` mode (maps of one size summarised as one stack) against each map's own dense inverse:
    sigma^2 = 2 / trace of each 2x2 block of P^-1, 1 / Lambda_phiphi for the pose orientation."""
    from mapjoin.covariance import batch_spherical_variances

    rng = np.random.default_rng(seed)
    maps = []
    for k, m in enumerate(sizes):
        covariance = _random_spd(rng, 3 + 2 * m, 10**log_condition) * 10 ** rng.uniform(-4, 2)
        maps.append(LocalMap(f"m{k}", k, k + 1, np.zeros(3), np.arange(m), np.zeros((m, 2)), np.ones(m),
                             np.ones(2), (covariance + covariance.T) / 2))
    features, poses = batch_spherical_variances(maps, "information")
    start = 0
    for k, local_map in enumerate(maps):
        inverse = np.linalg.inv(local_map.covariance)
        information = np.diagonal(inverse)
        # the rounding errors of an inverse scale with its norm: compare 1 / sigma^2 on that scale
        scale, tolerance = np.abs(inverse).max(), 1e-14 * 10**log_condition * len(inverse)
        expected = np.concatenate([information[3:].reshape(-1, 2).mean(axis=1), [information[:2].mean()],
                                   information[2:3]])
        found = 1 / np.concatenate([features[start:start + local_map.size], poses[k]])
        np.testing.assert_allclose(found / scale, expected / scale, rtol=0, atol=tolerance)
        start += local_map.size


@settings(max_examples=300, deadline=None)
@given(st.lists(st.integers(-50, 50), unique=True, max_size=30), st.lists(st.integers(-60, 60), max_size=30),
       st.booleans())
def test_locate_agrees_with_a_dictionary(keys, wanted, sorted_keys):
    """maps.locate, the sorted lookup joining, refine, raw and simulate share, against a dict."""
    ids = np.array(sorted(keys) if sorted_keys else keys, dtype=np.int64)
    where = {key: i for i, key in enumerate(ids.tolist())}
    index, found = locate(ids, np.array(wanted, dtype=np.int64), None if sorted_keys else np.argsort(ids))
    assert found.tolist() == [w in where for w in wanted]
    assert [i for i, f in zip(index.tolist(), found.tolist()) if f] == [where[w] for w in wanted if w in where]
    assert all(0 <= i < max(len(ids), 1) for i in index.tolist())


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), count=st.integers(1, 6), solver=st.sampled_from(["bisection", "golden"]))
def test_joins_of_a_level_are_each_join_alone(seed, count, solver):
    """The tree's joins of a level (arrays) and each of them as the sequential strategy solves it (Python
    numbers): the same report rows, bit for bit; the joined pose r1 and its variances to rounding (the
    complex products of t = m0 - R(phi) m1 round differently in numpy and in Python)."""
    from mapjoin.joining import _solve_joins

    rng = np.random.default_rng(seed)
    sizes = rng.integers(0, 6, count)  # a join may have no common feature
    pair = np.repeat(np.arange(count), sizes)
    order = rng.permutation(len(pair))
    scale = 10.0 ** rng.uniform(-1, 2)
    z1 = scale * (rng.normal(size=len(pair)) + 1j * rng.normal(size=len(pair)))
    turn = np.exp(1j * rng.uniform(-np.pi, np.pi, count))
    z0 = turn[pair] * z1 + scale * rng.normal(size=count)[pair] + 0.1 * scale * rng.normal(size=len(pair))
    var0, var1 = 10 ** rng.uniform(-2, 1, len(pair)), 10 ** rng.uniform(-2, 1, len(pair))
    xy = scale * (rng.normal(size=count) + 1j * rng.normal(size=count))
    phi = np.angle(turn) + rng.choice([0.0, 2.5], count) + 0.01 * rng.normal(size=count)  # some contradict
    var_o, p_phi = 10 ** rng.uniform(-2, 1, count), 10 ** rng.uniform(-3, 0, count)
    labels = [(f"m{i}", i, i + 1, int(sizes[i]) + 2) for i in range(count)]
    pair, z0, var0, z1, var1 = pair[order], z0[order], var0[order], z1[order], var1[order]
    batch = _solve_joins(pair, count, z0, var0, z1, var1, xy, phi, var_o, p_phi, solver, labels, 1, warn=False)
    for i in range(count):
        mine = pair == i
        alone = _solve_joins(None, 1, z0[mine], var0[mine], z1[mine], var1[mine], complex(xy[i]), float(phi[i]),
                             float(var_o[i]), float(p_phi[i]), solver, labels[i:i + 1], 1, warn=False)
        assert alone.rows == batch.rows[i:i + 1]
        assert alone.phi == batch.phi[i] and alone.phi_variance == batch.phi_variance[i]
        assert alone.turn == batch.turn[i]
        assert abs(alone.t - batch.t[i]) <= 1e-14 * (abs(alone.t) + scale)
        assert alone.t_variance == pytest.approx(batch.t_variance[i], rel=1e-14)
