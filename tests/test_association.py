"""Data association (``join --associate``, mapjoin.association): the chi-square quantiles and the joint
test against dense formulas, local ids, recovery on simulated and real maps, the command's boundary."""

from __future__ import annotations

import csv
import json
import dataclasses
import itertools
import logging
import math

import numpy as np
import pytest
import scipy.stats
from cli_runner import run
from hypothesis import given, settings
from hypothesis import strategies as st

from mapjoin import io as mapio
from mapjoin.association import (correspondence_rows, feature_covariances, inverted, join_associated, link_errors,
                                 local_ids, match_features, rotated, sighting_bits)
from mapjoin.association.gate import _gate
from mapjoin.association.joint import _joint_distances, _joint_terms, _joint_test
from mapjoin.joining import join
from mapjoin.maps import LocalMap
from mapjoin.simulation import simulate



def test_link_errors_count_missed_and_false_links_by_hand():
    """Two maps; true ids: map 1 sees features 10, 11, map 2 sees 10, 11, 12 (two true links)."""
    def local_map(name, start, ids):
        return LocalMap(name=name, start_id=start, end_id=start + 1, end_pose=np.zeros(3), feature_ids=np.array(ids),
                        features=np.zeros((len(ids), 2)), pose_variances=np.ones(2), feature_variances=np.ones(len(ids)))
    local = [local_map("a", 0, [0, 1]), local_map("b", 1, [0, 1, 2])]
    truth = [np.array([10, 11]), np.array([10, 11, 12])]

    class Found:
        def __init__(self, *ids):
            self.global_ids = [np.array(i) for i in ids]
    assert link_errors(local, truth, Found([0, 1], [0, 1, 2])) == (2, 0, 0)    # all right
    assert link_errors(local, truth, Found([0, 1], [0, 5, 2])) == (2, 1, 0)    # 11 seen anew: one missed
    assert link_errors(local, truth, Found([0, 1], [0, 1, 0])) == (2, 0, 1)    # 12 taken for 10: one false


def random_covariances(rng, count, low=0.01, high=1.0):
    """Random 2 x 2 covariances (rows [xx, xy, yy]) and the same as dense matrices."""
    factor = rng.uniform(-1, 1, (count, 2, 2))
    dense = factor @ factor.transpose(0, 2, 1) * rng.uniform(low, high, count)[:, None, None] + low * np.eye(2)
    return np.column_stack([dense[:, 0, 0], dense[:, 0, 1], dense[:, 1, 1]]), dense


def test_joint_distance_equals_the_dense_mahalanobis_distance():
    """The Woodbury form against r^T S^-1 r with S = blockdiag(C_j) + H P H^T formed and inverted densely
    (non-spherical pair covariances C_j)."""
    rng = np.random.default_rng(4)
    k = 6
    r = rng.normal(size=k) + 1j * rng.normal(size=k)
    covariances, dense_c = random_covariances(rng, k, 0.1, 2.0)
    u = rng.normal(size=k) * 5 + 1j * rng.normal(size=k) * 5
    prior = np.diag([0.3, 0.3, 0.01])
    h = np.zeros((2 * k, 3))
    h[0::2, 0] = h[1::2, 1] = 1
    h[0::2, 2], h[1::2, 2] = u.real, u.imag
    masks = ((np.arange(1, 2**k)[:, None] >> np.arange(k)) & 1).astype(float)
    distances, _ = _joint_distances(masks, _joint_terms(r, inverted(covariances), u), np.linalg.inv(prior))
    vector = np.column_stack([r.real, r.imag]).ravel()
    block = np.zeros((2 * k, 2 * k))
    for n in range(k):
        block[2 * n:2 * n + 2, 2 * n:2 * n + 2] = dense_c[n]
    for mask, distance in zip(masks[::7], distances[::7]):
        rows = np.repeat(mask > 0, 2)
        dense = block[np.ix_(rows, rows)] + h[rows] @ prior @ h[rows].T
        assert math.isclose(distance, vector[rows] @ np.linalg.solve(dense, vector[rows]), rel_tol=1e-10)


def test_a_join_whose_link_the_pairs_cannot_fix_keeps_no_pair():
    """Two pairs at the link's origin (lever u = 0) with no prior on the link: ``P_link^-1 + sum H^T W H`` has a zero
    heading row, exactly singular, so no joint distance exists. The other join (levers apart, a prior) is tested as
    usual: its two consistent pairs are kept. numpy must not raise."""
    r = np.array([0.1 + 0.1j, -0.1 + 0.05j, 0.1 + 0.0j, 0.0 - 0.1j])
    u = np.array([0j, 0j, 3 + 1j, -2 + 4j])
    w = inverted(np.tile([0.1, 0.0, 0.1], (4, 1)))
    information = np.stack([np.zeros((3, 3)), np.diag([10.0, 10.0, 100.0])])
    keep, _, _ = _joint_test(_joint_terms(r, w, u), r, w, u, np.array([0, 0, 1, 1]), information, 0.999, 2)
    assert keep.tolist() == [False, False, True, True]


def test_rotated_covariances_equal_the_dense_product():
    rng = np.random.default_rng(6)
    covariances, dense = random_covariances(rng, 5)
    phi = rng.uniform(-4, 4, 5)
    c, s = np.cos(phi), np.sin(phi)
    turn = np.stack([np.stack([c, -s], 1), np.stack([s, c], 1)], 1)
    expected = turn @ dense @ turn.transpose(0, 2, 1)
    assert np.allclose(rotated(covariances, phi), np.column_stack([expected[:, 0, 0], expected[:, 0, 1], expected[:, 1, 1]]))
    assert np.allclose(inverted(covariances)[:, [0, 1, 1, 2]].reshape(-1, 2, 2), np.linalg.inv(dense))


@pytest.mark.parametrize("margin", [0.0, 3.0, math.inf])
@pytest.mark.parametrize("with_sightings", [False, True])
@pytest.mark.parametrize("scale", [1.0, 1.5])
def test_gate_equals_the_dense_pairwise_test(margin, with_sightings, scale):
    """_gate's pairs against each pair's 2x2 innovation covariance (the features' covariances times the variance
    factor ``scale``, plus the link's) built and inverted densely, and the choice made by loops: a pair is taken
    when it is the nearest of both its features and every rival of either (another candidate seen in one map with
    the nearest one, or any other without sightings) is margin farther."""
    rng = np.random.default_rng(5)
    left = rng.uniform(-20, 20, 40) + 1j * rng.uniform(-20, 20, 40)
    left_cov, left_dense = random_covariances(rng, 40)
    predicted = left[:25] + rng.normal(scale=0.5, size=25) + 1j * rng.normal(scale=0.5, size=25)
    lever = rng.normal(scale=10, size=25) + 1j * rng.normal(scale=10, size=25)
    right_cov, right_dense = random_covariances(rng, 25)
    link = np.array([[0.2, 0.05, 0.01], [0.05, 0.3, -0.02], [0.01, -0.02, 0.004]])
    g2 = -2 * math.log(0.001)
    left_maps = [set(rng.choice(6, 2).tolist()) for _ in range(40)]
    right_maps = [set(rng.choice(6, 2).tolist()) for _ in range(25)]
    def bits(maps):
        return np.bitwise_or.reduce(np.stack([sighting_bits(np.full(len(maps), m)) * np.array(
            [[m in s] for s in maps], dtype=np.uint64) for m in range(6)]), axis=0)
    sightings = (bits(left_maps), bits(right_maps)) if with_sightings else (None, None)
    largest = np.array([(left_cov[:, 0] + left_cov[:, 2]).max()])
    i, j, undecided = _gate(left, left_cov, np.zeros(40, np.intp), largest, predicted, lever, right_cov,
                            np.zeros(25, np.intp), link[None], np.array([scale]), g2, margin, *sightings)
    d2 = np.full((40, 25), np.inf)
    for a in range(40):
        for b in range(25):
            h = np.array([[1, 0, lever[b].real], [0, 1, lever[b].imag]])
            s = scale * (left_dense[a] + right_dense[b]) + h @ link @ h.T
            r = np.array([(left[a] - predicted[b]).real, (left[a] - predicted[b]).imag])
            d2[a, b] = r @ np.linalg.solve(s, r) if r @ np.linalg.solve(s, r) <= g2 else np.inf
    def clear(distances, maps):
        """the nearest index when every rival is margin farther, else None"""
        near = int(np.argmin(distances))
        rivals = [distances[n] for n in range(len(distances)) if n != near and np.isfinite(distances[n])
                  and (not with_sightings or maps[n] & maps[near])]
        return near if all(x - distances[near] >= margin for x in rivals) else None
    expected = sorted((a, b) for a in range(40) for b in range(25) if np.isfinite(d2[a, b])
                      and clear(d2[:, b], left_maps) == a and clear(d2[a], right_maps) == b)
    assert sorted(zip(i.tolist(), j.tolist())) == expected
    taken = {b for _, b in expected}
    assert undecided.tolist() == [b for b in range(25) if np.isfinite(d2[:, b]).any() and b not in taken]
    assert len(expected) > (5 if scale == 1 else 2) and len(undecided) > 0  # both kinds occur


def match_one(left, left_variances, link_xy, link_phi, link_variances, right, right_variances):
    """match_features for one join."""
    return match_features(left, left_variances, np.zeros(len(left), np.intp), np.array([link_xy]),
                          np.array([link_phi]), np.array([link_variances]), right, right_variances,
                          np.zeros(len(right), np.intp))


@pytest.mark.parametrize("brute_force", [True, False])
def test_joins_matched_together_match_as_alone(brute_force, monkeypatch):
    """Three joins in one call (as a tree level) give each join's own association, whether the candidates
    come from all pairs or from the grid's cells."""
    monkeypatch.setattr("mapjoin.association.gate.BRUTE_FORCE_PAIRS", 1 << 30 if brute_force else 0)
    monkeypatch.setattr("mapjoin.association.grid.ALL_PAIRS", 1 << 30 if brute_force else 0)
    rng = np.random.default_rng(8)
    problems = []
    for _ in range(3):
        left = rng.uniform(-30, 30, 30) + 1j * rng.uniform(-30, 30, 30)
        phi = rng.uniform(-3, 3)
        link = complex(*rng.uniform(-5, 5, 2))
        right = (left[:12] - link) * np.exp(-1j * phi) + rng.normal(scale=0.05, size=12)
        right = np.concatenate([right, rng.uniform(-30, 30, 5) + 1j * rng.uniform(-30, 30, 5)])
        problems.append((left, np.full(30, 0.01), link, phi, (0.05, 1e-4), right, np.full(17, 0.01)))
    alone = [match_one(*problem) for problem in problems]
    together = match_features(np.concatenate([p[0] for p in problems]), np.full(90, 0.01), np.repeat(np.arange(3), 30),
                              np.array([p[2] for p in problems]), np.array([p[3] for p in problems]),
                              np.array([p[4] for p in problems]), np.concatenate([p[5] for p in problems]),
                              np.full(51, 0.01), np.repeat(np.arange(3), 17))
    expected = [(30 * k + i, 17 * k + j) for k, found in enumerate(alone)
                for i, j in zip(found.left.tolist(), found.right.tolist())]
    assert sorted(zip(together.left.tolist(), together.right.tolist())) == sorted(expected)
    assert together.right.tolist() == sorted(set(together.right.tolist()))
    assert all(len(found.left) >= 11 for found in alone)
    assert together.ambiguous.tolist() == [int(found.ambiguous[0]) for found in alone]


@pytest.mark.parametrize("rounds", [2, 3, 4])
def test_a_tree_level_settles_joins_without_changing_them(rounds, monkeypatch):
    """A tree level's joins whose state repeats (correction, factor, link) stop being associated while the others
    go on: every level's outcome is consistent (each right row paired once, sorted; the ambiguous counts are the
    undecided rows per join, which no pair uses), and the ids are those of the known-id truth's partition
    wherever the tree found them, as with one round less or more (ROUNDS = 2, 3, 4)."""
    monkeypatch.setattr("mapjoin.association.rounds.ROUNDS", rounds)
    from mapjoin.association import associator, drifted

    seen = []
    original = match_features

    def checked(*args, **options):
        found = original(*args, **options)
        right_join = args[8]
        assert found.right.tolist() == sorted(set(found.right.tolist()))
        assert found.undecided.tolist() == sorted(set(found.undecided.tolist()))
        assert not set(found.undecided.tolist()) & set(found.right.tolist())
        assert found.ambiguous.tolist() == np.bincount(right_join[found.undecided], minlength=len(args[3])).tolist()
        seen.append(len(args[3]))
        return found

    for caller in (drifted, associator):  # every call: steps 2-5, the loop closures', the junction rule's
        monkeypatch.setattr(caller, "match_features", checked)
    local, truth = local_ids(simulate(40, seed=4).maps)
    found = join_associated(local, strategy="tree")
    links, missed, _ = link_errors(local, truth, found)
    assert max(seen) > 1 and links > 0 and missed < links


def test_two_candidates_in_the_gate_leave_a_feature_new():
    left = np.array([0.0 + 0j, 0.3 + 0j, 10 + 0j, 0 + 10j])
    right = np.array([0.15 + 0j, 10 + 0j, 0 + 10j])
    found = match_one(left, np.full(4, 0.05), 0j, 0.0, (0.01, 1e-6), right, np.full(3, 0.05))
    assert sorted(zip(found.left.tolist(), found.right.tolist())) == [(2, 1), (3, 2)]
    assert found.ambiguous.tolist() == [1]


def test_the_joint_test_rejects_a_pair_inconsistent_with_the_others():
    """Six features moved by 0.02 m and one by 0.9 m: the last is individually in the wide gate (a large link
    variance) but not jointly with the others, which all agree on the link's error."""
    rng = np.random.default_rng(1)
    left = rng.uniform(-30, 30, 7) + 1j * rng.uniform(-30, 30, 7)
    right = left + 0.5 + rng.normal(scale=0.02, size=7)  # the link is off by 0.5 m
    right[6] += 0.9
    found = match_one(left, np.full(7, 1e-3), 0j, 0.0, (1.0, 1e-8), right, np.full(7, 1e-3))
    assert 6 not in found.right.tolist() and len(found.right) == 6


def test_feature_covariances_are_the_marginal_blocks_in_sorted_id_order():
    rng = np.random.default_rng(9)
    ids = np.array([7, 2, 9, 4])
    factor = rng.normal(size=(11, 11))
    covariance = factor @ factor.T + np.eye(11)
    local_map = LocalMap(name="m", start_id=0, end_id=1, end_pose=np.zeros(3), feature_ids=ids,
                         features=rng.normal(size=(4, 2)), pose_variances=np.ones(2),
                         feature_variances=np.arange(1.0, 5.0), covariance=covariance)
    found = feature_covariances(local_map)
    for row, position in enumerate(np.argsort(ids)):  # file position of the row-th smallest id
        block = covariance[3 + 2 * position:5 + 2 * position, 3 + 2 * position:5 + 2 * position]
        assert np.allclose(found[row], [block[0, 0], block[0, 1], block[1, 1]])
    spherical = feature_covariances(dataclasses.replace(local_map, covariance=None))
    assert spherical.tolist() == [[v, 0.0, v] for v in [2.0, 4.0, 1.0, 3.0]]


def test_a_feature_mapped_twice_is_no_rival_of_itself():
    """Two left features 0.3 m apart in the gate of one right feature: never seen in one map, they may be one feature
    mapped twice and the nearest is taken; seen in one map, they are two features and the choice is left new."""
    left = np.array([0.0 + 0j, 0.3 + 0j, 10 + 0j])
    right = np.array([0.1 + 0j, 10 + 0j])
    args = (left, np.full(3, 0.05), np.zeros(3, np.intp), np.array([0j]), np.array([0.0]), np.array([(0.01, 1e-6)]),
            right, np.full(2, 0.05), np.zeros(2, np.intp))
    apart = match_features(*args, left_sightings=sighting_bits([0, 1, 0]), right_sightings=sighting_bits([2, 2]))
    assert sorted(zip(apart.left.tolist(), apart.right.tolist())) == [(0, 0), (2, 1)]
    together = match_features(*args, left_sightings=sighting_bits([0, 0, 0]), right_sightings=sighting_bits([2, 2]))
    assert sorted(zip(together.left.tolist(), together.right.tolist())) == [(2, 1)]
    assert together.ambiguous.tolist() == [1]
    assert sighting_bits([0, 64, 128, 255]).tolist() == [[1, 0], [0, 1], [1, 0], [0, 1 << 63]]


def test_rounds_find_the_pairs_the_link_error_hid(monkeypatch):
    """The link's heading is off by 0.03 rad, almost four of its prior standard deviations: the first round gates the
    features near the start only; the link corrected by them, the far ones are found too."""
    rng = np.random.default_rng(12)
    right = rng.uniform(1, 40, 20) * np.exp(1j * rng.uniform(-np.pi, np.pi, 20))
    left = right * np.exp(0.03j) + rng.normal(scale=0.003, size=20) + 1j * rng.normal(scale=0.003, size=20)
    args = (left, np.full(20, 1e-4), np.zeros(20, np.intp), np.array([0j]), np.array([0.0]),
            np.array([(1e-6, 6e-5)]), right, np.full(20, 1e-4), np.zeros(20, np.intp))
    found = match_features(*args)
    assert found.left.tolist() == found.right.tolist() == list(range(20))
    monkeypatch.setattr("mapjoin.association.rounds.ROUNDS", 1)
    assert 0 < len(match_features(*args).right) < 20


@pytest.mark.parametrize("strategy", ["sequential", "tree"])
def test_one_map_is_numbered_in_order(strategy):
    local, _ = local_ids(simulate(1, seed=1).maps)
    found = join_associated(local, strategy=strategy)
    assert found.global_map.feature_ids.tolist() == list(range(local[0].size)) and found.report == ()
    assert np.array_equal(found.global_map.features, local[0].features)
    assert found.global_map.provenance.strategy == strategy


@pytest.mark.parametrize("strategy", ["sequential", "tree"])
def test_any_local_labels_give_the_same_association(strategy):
    """Local ids are labels: relabelled with overlapping, unsorted, non-contiguous ids (a front end's), the maps'
    features are grouped into the same global features as with ids 0 .. m-1 (numbered by first sighting, by
    map then local id, so the numbers differ: the two numberings are one-to-one)."""
    local, _ = local_ids(simulate(8, seed=3, noiseless=True).maps)
    rng = np.random.default_rng(0)
    labels = [rng.choice(60, size=m.size, replace=False) for m in local]
    relabelled = [dataclasses.replace(m, feature_ids=label[m.feature_ids]) for m, label in zip(local, labels)]
    plain = join_associated(local, strategy=strategy)
    other = join_associated(relabelled, strategy=strategy)
    pairs = set(zip(np.concatenate(plain.global_ids).tolist(), np.concatenate(other.global_ids).tolist()))
    assert len(pairs) == plain.global_map.features.shape[0] == other.global_map.features.shape[0]
    assert len(pairs) < sum(m.size for m in local)  # features were associated
    assert np.allclose(np.sort(other.global_map.features, axis=0), np.sort(plain.global_map.features, axis=0))


def test_local_ids_round_trip():
    maps = simulate(8, seed=2).maps
    local, truth = local_ids(maps)
    for original, relabelled, ids in zip(maps, local, truth):
        assert sorted(relabelled.feature_ids.tolist()) == list(range(original.size))
        assert np.array_equal(ids[relabelled.feature_ids], original.feature_ids)
        assert np.array_equal(relabelled.features, original.features)
    rows = correspondence_rows(truth)
    assert len(rows) == sum(m.size for m in maps) and rows[0].map == 1


@settings(max_examples=12, deadline=None)
@given(seed=st.integers(0, 10_000), count=st.integers(2, 14), strategy=st.sampled_from(["sequential", "tree"]))
def test_noise_free_simulations_are_associated_without_false_matches(seed, count, strategy):
    """Exact local maps: no false match between features the maps' declared covariances tell apart, and every
    correspondence missed was left new on purpose (ambiguous, rejected or guarded: a true pair is always in the
    gate); when every one is found, the global map is the known-id join's (same features and poses).

    The estimates are exact but their declared covariances are not zero, so two features 0.4-1.2 m apart that no
    piece of a join sees together are one feature to the gate (about 1% of 13-map runs: seeds 22, 81, 119, 183,
    217, 288, 305, 332; benchmarks/README.md, 'Data association'): every false match must be such a pair, within
    twice the gate's radius of their declared variances."""
    sim = simulate(count, seed=seed, noiseless=True)
    maps = sim.maps
    local, truth = local_ids(maps)
    found = join_associated(local, strategy=strategy)
    links, missed, false = link_errors(local, truth, found)
    true = np.concatenate(truth)
    mine = np.concatenate([found.global_ids[k][np.argsort(m.feature_ids)] for k, m in enumerate(local)])
    for feature in np.unique(mine):
        merged = np.unique(true[mine == feature])
        if len(merged) > 1:
            where = sim.truth.features[np.searchsorted(sim.truth.feature_ids, merged)]
            variance = [max(m.feature_variances[m.feature_ids == t].max(initial=0.0) for m in maps) for t in merged]
            radius = math.sqrt(scipy.stats.chi2.ppf(0.999, 2) * (variance[0] + variance[1]))
            assert len(merged) == 2 and abs(complex(*(where[0] - where[1]))) < 2 * radius
    if false:  # a feature seen again beside its merged twin is left new as neither: the count below needs none
        return
    assert missed <= sum(r.ambiguous + r.rejected + r.guarded for r in found.report)
    if missed == 0:
        known = join(maps, strategy=strategy).global_map
        mine = join(found.relabel(local), strategy=strategy).global_map
        assert np.allclose(found.global_map.poses, known.poses, atol=1e-9)
        assert np.allclose(np.sort(found.global_map.features, axis=0), np.sort(known.features, axis=0), atol=1e-9)
        assert np.allclose(mine.features, found.global_map.features, atol=1e-9)


def unmet(name, strategy, measured):
    """A target case not met yet: strict xfail, with what benchmarks/README.md ('Data association') measured."""
    return pytest.param(name, strategy, marks=pytest.mark.xfail(
        strict=True, reason=f"issue 13's target is not met yet here: {measured} (benchmarks/README.md)"))


@pytest.mark.parametrize("name, strategy", [
    ("VicPark_200_local_maps", "sequential"),
    unmet("VicPark_200_local_maps", "tree", "recall 99.0 % (36 missed, 35 allowed), 1 false link (a new feature 2.5 m "
          "from another, no rival)"),
    unmet("DLR_200_local_maps", "sequential", "recall 93.0 %, no false link (its true pairs fail their own joint test "
          "in 89 joins at 0.999, 21 at 1 - 1e-12: the test below)"),
    unmet("DLR_200_local_maps", "tree", "recall 82.6 %, no false link (pieces bent against each other; its true "
          "pairs fail their own joint test in 87 joins at 0.999, 25 at 1 - 1e-12)"),
    unmet("8240_data_50_local_maps", "sequential", "recall 97.4 %, no false link (the last join's 7 links: at most 6 of "
          "its 13 true pairs pass their joint test, the test below; a lattice ties with the true correction)"),
    unmet("8240_data_50_local_maps", "tree", "recall 97.4 %, no false link (the 7 links of the lattice's tie at map 49)"),
    unmet("simulation", "sequential", "recall 83.5 %, no false link (old features met again after the chain drifted "
          "metres, beside other features: docs/method.md#data-association, steps 6 and 9)"),
    unmet("simulation", "tree", "recall 85.9 %, 2 false links (tree joins whose pieces bent by metres: "
          "docs/method.md#data-association, step 6)")])
def test_target_recall_99_percent_without_false_links(data_dir, name, strategy, caplog):
    """Issue 13's target: at least 99 % of the true links recovered, no false one; then the global map equals
    the known-id join (compared numerically)."""
    caplog.set_level(logging.ERROR, logger="mapjoin")  # restored after the test
    maps = simulate(30, seed=11).maps if name == "simulation" else mapio.read_maps(str(data_dir / name))
    local, truth = local_ids(maps)
    found = join_associated(local, strategy=strategy)
    links, missed, false = link_errors(local, truth, found)
    assert false == 0 and missed <= links // 100
    if missed == 0:
        known = join(maps, strategy=strategy).global_map
        assert np.allclose(found.global_map.poses, known.poses, atol=1e-9)


@pytest.mark.parametrize("strategy", ["sequential", "tree"])
def test_dlr_true_pairs_fail_their_own_joint_test_in_more_joins_than_1_percent_of_links(data_dir, strategy, caplog):
    """Why DLR 200 stays short of issue 13's 99 %: joined with its true ids, more of its joins than 1 % of its links
    (14) cost more than the joint test's chi-square quantile on their true pairs (2 x common degrees of freedom) even
    at the level 1 - 1e-12, so that a test at the maps' own covariances must leave a true pair out of each
    (benchmarks/association_truth.py). Checked with scipy's chi-square, not mapjoin's."""
    caplog.set_level(logging.ERROR, logger="mapjoin")
    maps = mapio.read_maps(str(data_dir / "DLR_200_local_maps"))
    ids = np.concatenate([m.feature_ids for m in maps])
    links = len(ids) - len(np.unique(ids))
    report = [r for r in join(maps, strategy=strategy).report if r.common]
    failing = sum(scipy.stats.chi2.sf(r.cost, 2 * r.common) < 1e-12 for r in report)
    assert links == 1400 and failing > links // 100


def test_8240_last_join_keeps_fewer_than_11_of_its_13_true_pairs_in_the_joint_test(data_dir, caplog):
    """Why the 8240 simulation stays at 97.4 %: 99 % of its 273 links would need 11 of its last sequential join's 13
    true pairs, and no 11 or more of them pass the joint test at 0.999 (every such subset tried, the others' ids made
    new; all 13 cost far beyond any stated level). benchmarks/association_truth.py --fewest finds that at most 6
    pass: the association, which misses 7, keeps what the test admits."""
    caplog.set_level(logging.ERROR, logger="mapjoin")
    maps = mapio.read_maps(str(data_dir / "8240_data_50_local_maps"))
    before, last = maps[:-1], maps[-1]
    common = np.intersect1d(last.feature_ids, np.concatenate([m.feature_ids for m in before]))
    assert len(common) == 13
    for size in (11, 12, 13):
        for kept in itertools.combinations(common, size):
            ids = last.feature_ids.copy()
            dropped = np.isin(ids, common) & ~np.isin(ids, kept)
            ids[dropped] = 10**6 + np.arange(dropped.sum())
            record = join(before + [dataclasses.replace(last, feature_ids=ids)]).report[-1]
            assert record.common == size and record.cost > scipy.stats.chi2.ppf(0.999, 2 * size)
            if size == 13:
                assert scipy.stats.chi2.sf(record.cost, 26) < 1e-12


@pytest.mark.parametrize("name, strategy", [
    ("VicPark_200_local_maps", "sequential"),
    unmet("VicPark_200_local_maps", "tree", "1 false link: at level 2 a new tree 2.36 m from an old one, each piece "
          "seeing one of the two; its conditional distance given the join's other pairs, 11.6, is inside the gate"),
    ("DLR_200_local_maps", "sequential"), ("DLR_200_local_maps", "tree"),
    ("8240_data_50_local_maps", "sequential"), ("8240_data_50_local_maps", "tree")])
def test_no_false_link_on_the_datasets(data_dir, name, strategy, caplog):
    """Issue 13's first target alone, against the datasets' true ids: no two different features joined (DLR's last
    three false links were lone drifted pairs, docs/method.md#data-association, step 8)."""
    caplog.set_level(logging.ERROR, logger="mapjoin")
    local, truth = local_ids(mapio.read_maps(str(data_dir / name)))
    assert link_errors(local, truth, join_associated(local, strategy=strategy))[2] == 0


def test_cli_writes_one_association_row_per_feature_and_report_columns(tmp_path):
    folder = tmp_path / "sim"
    assert run("simulate", "-o", str(folder), "--maps", "6", "--seed", "1", "--local-ids").exit_code == 0
    result = run("join", str(folder), "--associate", "--associations", str(tmp_path / "ids.csv"),
                 "--report", str(tmp_path / "joins.csv"), "-o", str(tmp_path / "g.csv"), "--strategy", "tree")
    assert result.exit_code == 0, result.output
    rows = list(csv.DictReader(open(tmp_path / "ids.csv")))
    true = list(csv.DictReader(open(folder / "associations.csv")))
    assert [(r["map"], r["local_id"]) for r in rows] == [(r["map"], r["local_id"]) for r in true]
    maps = mapio.read_maps(str(folder))
    expected = join_associated(maps, strategy="tree").rows(maps)
    assert [(str(e.map), str(e.local_id), str(e.global_id)) for e in expected] == \
        [(r["map"], r["local_id"], r["global_id"]) for r in rows]
    truth = mapio.read_truth(str(folder / "truth.yaml"))
    assert {int(r["global_id"]) for r in true} <= set(truth.feature_ids.tolist())
    header = open(tmp_path / "joins.csv").readline().strip().split(",")
    assert header[-3:] == ["ambiguous", "rejected", "guarded"]


def test_cli_refuses_association_options_without_associate(tmp_path, simulated_folder):
    result = run("join", simulated_folder, "--associations", str(tmp_path / "ids.csv"), "-o", str(tmp_path / "g.csv"))
    assert result.exit_code == 2 and "--associate" in result.output
    assert not (tmp_path / "g.csv").exists() and not (tmp_path / "ids.csv").exists()
    result = run("join", simulated_folder, "--associate", "--gate-association", "1.5", "-o", str(tmp_path / "g.csv"))
    assert result.exit_code == 2 and "--gate-association" in result.output


def test_cli_refuses_an_associations_file_that_is_an_input(tmp_path, simulated_folder):
    target = f"{simulated_folder}/localmap_1.yaml"
    before = open(target).read()
    result = run("join", simulated_folder, "--associate", "--associations", target, "-o", str(tmp_path / "g.csv"))
    assert result.exit_code == 1 and "localmap_1.yaml" in result.output and len(result.output.splitlines()) == 1
    assert open(target).read() == before and not (tmp_path / "g.csv").exists()


@pytest.mark.parametrize("strategy", ["sequential", "tree"])
@pytest.mark.parametrize("seed", [0, 3])
def test_association_counts_match_the_global_ids(strategy, seed, caplog):
    """The summed counts against the written ids, not the report: every match removes one feature from the sum of the
    maps' sizes, and a sequential join sees every feature of maps 2..n once, matched or new."""
    caplog.set_level(logging.ERROR, logger="mapjoin")
    local, _ = local_ids(simulate(12, seed=seed).maps)
    found = join_associated(local, strategy=strategy)
    ids = np.concatenate(found.global_ids)
    counts = found.counts
    assert counts.matched == ids.size - np.unique(ids).size > 0
    if strategy == "sequential":
        assert counts.matched + counts.new == sum(m.size for m in local[1:])
    assert counts.ambiguous + counts.rejected <= counts.new


def test_a_doubtful_association_is_said_once_and_a_clear_one_is_not(caplog):
    """Long local maps (30 steps each) leave most incoming features ambiguous: one warning names the counts. The
    default simulation's association is clear: no such warning."""
    caplog.set_level(logging.WARNING, logger="mapjoin")
    local, _ = local_ids(simulate(6, seed=0, steps_per_map=30).maps)
    counts = join_associated(local).counts
    said = [r.getMessage() for r in caplog.records if "ambiguous" in r.getMessage()]
    assert counts.doubtful and len(said) == 1
    assert f"{counts.ambiguous} incoming features ambiguous" in said[0] and f"{counts.matched} matched" in said[0]
    caplog.clear()
    local, _ = local_ids(simulate(12, seed=0).maps)
    assert not join_associated(local).counts.doubtful
    assert not [r for r in caplog.records if "ambiguous" in r.getMessage()]


def test_cli_summary_states_the_association_counts(tmp_path):
    folder = tmp_path / "sim"
    assert run("simulate", "-o", str(folder), "--maps", "6", "--seed", "1", "--local-ids").exit_code == 0
    result = run("-q", "join", str(folder), "--associate", "--json", "-o", str(tmp_path / "g.csv"),
                 "--associations", str(tmp_path / "ids.csv"))
    assert result.exit_code == 0, result.output
    summary = json.loads(result.stdout)
    rows = list(csv.DictReader(open(tmp_path / "ids.csv")))
    written = [int(r["global_id"]) for r in rows]
    assert summary["associated_matched"] == len(written) - len(set(written))
    result = run("join", str(folder), "--associate", "-o", str(tmp_path / "g2.csv"))
    assert f"{summary['associated_matched']} features matched ({summary['associated_ambiguous']} left ambiguous" \
        in result.stderr
