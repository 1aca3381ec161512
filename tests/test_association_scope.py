"""Step 6's scope (mapjoin.association.loop_scope): the drift between two sightings against the dense sums over each way
along the chain and through its ties, the least over a join's voters against a loop over them, the votes' voters
against a planted correction, a loop closure whose far part the correction does not hold against the truth, a
bent piece's closures held only near their voters against the default simulation's tree, and the link's own map's
sighting of a closure's pair against the next map's, composed by hand."""

from __future__ import annotations

import logging
import math

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from mapjoin.association import (
    drifted,
    join_associated,
    link_errors,
    local_ids,
    match_with_drift,
)
from mapjoin.association.feature_drift import SightingDrift
from mapjoin.association.loop_scope import beyond_voters, chain_drift, voter_drift
from mapjoin.association.loop_votes import rigid_votes
from mapjoin.se2 import compose
from mapjoin.simulation import simulate


def dead_reckoned(end_poses):
    """Pose m (map m's start) of the chain by composing the end poses one at a time (se2.compose)."""
    poses = [np.zeros(3)]
    for pose in end_poses:
        poses.append(compose(poses[-1], pose))
    return np.array(poses)


def random_chain(rng, n, ties):
    """A chain of ``n`` maps, every junction placed, ``ties`` random ties: the drift, its junctions' posteriors
    (v, p) and its poses dead-reckoned by composition."""
    end_poses = np.column_stack([rng.uniform(1, 5, n), rng.uniform(-1, 1, n), rng.uniform(-0.5, 0.5, n)])
    v, p = rng.uniform(0.001, 0.1, n + 1), rng.uniform(1e-5, 1e-3, n + 1)
    drift = SightingDrift.of(end_poses, 4)
    drift.placed(np.arange(1, n), v[1:n], p[1:n])
    for _ in range(ties):
        old = int(rng.integers(0, n - 1))
        drift.tie(old, int(rng.integers(old + 1, n)), float(rng.uniform(0, 0.5)))
    return drift, v, p, dead_reckoned(end_poses)


def dense(v, p, poses, first, second, f):
    """D over the junctions between maps ``first`` and ``second`` (either order) at point ``f``, term by term."""
    low, high = min(first, second), max(first, second)
    return sum(v[i] + p[i] * abs(f - complex(*poses[i, :2])) ** 2 / 2 for i in range(low + 1, high + 1))


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 10_000), n=st.integers(2, 12))
def test_drift_between_two_maps_is_the_dense_sum_either_way_and_broadcasts(seed, n):
    """SightingDrift.between (the piece of every way: the direct one and those through a tie) against the sum term
    by term, for every (map, other map) of a grid at once, each row at its own point; 0 between a map and itself."""
    rng = np.random.default_rng(seed)
    drift, v, p, poses = random_chain(rng, n, 0)
    maps, others = rng.integers(0, n, 5), rng.integers(0, n, 4)
    points = rng.normal(size=5) * 5 + 1j * rng.normal(size=5) * 5
    found = drift.between(maps[:, None], others[None, :], points[:, None])
    assert found.shape == (5, 4)
    for k in range(5):
        for u in range(4):
            assert math.isclose(found[k, u], dense(v, p, poses, maps[k], others[u], points[k]), rel_tol=1e-9,
                                abs_tol=1e-12)
    assert np.array_equal(drift.between(others[None, :], maps[:, None], points[:, None]), found)
    assert not drift.between(maps, maps, points).any()


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 10_000), n=st.integers(3, 12), ties=st.integers(0, 4))
def test_chain_drift_is_the_least_dense_sum_over_the_ways(seed, n, ties):
    """D between two sightings is the least of the direct way and, per tie (m, c, s), the junctions from the
    sighting to one end, s, and those from the other end to the other sighting at the point moved by x_end - x_start
    (each sum term by term at dead-reckoned poses)."""
    rng = np.random.default_rng(seed)
    drift, v, p, poses = random_chain(rng, n, ties)
    maps, others = rng.integers(0, n, 6), rng.integers(0, n, 6)
    points = rng.normal(size=6) * 5 + 1j * rng.normal(size=6) * 5
    found = chain_drift(drift, maps, others, points)
    for k in range(6):
        ways = [dense(v, p, poses, maps[k], others[k], points[k])]
        for old, junction, strain in drift.ties:
            for near, far in ((old, junction), (junction, old)):
                moved = points[k] - complex(*poses[near, :2]) + complex(*poses[far, :2])
                ways.append(dense(v, p, poses, maps[k], near, points[k]) + strain
                            + dense(v, p, poses, far, others[k], moved))
        assert math.isclose(found[k], min(ways), rel_tol=1e-9, abs_tol=1e-12)


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 10_000), joins=st.integers(1, 4), voters=st.integers(0, 12))
def test_voter_drift_is_the_least_over_the_join_s_voters(seed, joins, voters):
    """Each feature against every voter of its join, one at a time: the least chain_drift, infinite without one."""
    rng = np.random.default_rng(seed)
    n = 10
    drift, *_ = random_chain(rng, n, 2)
    maps, join = rng.integers(0, n, 8), rng.integers(0, joins, 8)
    points = rng.normal(size=8) * 5 + 1j * rng.normal(size=8) * 5
    voter_maps, voter_join = rng.integers(0, n, voters), rng.integers(0, joins, voters)
    found = voter_drift(drift, maps, points, join, voter_maps, voter_join)
    for k in range(8):
        mine = [float(chain_drift(drift, maps[k:k + 1], voter_maps[u:u + 1], points[k:k + 1])[0])
                for u in range(voters) if voter_join[u] == join[k]]
        assert found[k] == (min(mine) if mine else math.inf)


def test_the_voters_are_the_planted_pairs():
    """A correction planted on 14 of a right map's features among 120 clutter features: the pairs whose votes made
    it are planted pairs (left row = right row), all 14 features among them."""
    rng = np.random.default_rng(3)
    right = rng.uniform(-8, 8, 14) + 1j * rng.uniform(-8, 8, 14)
    centre = right.mean()
    moved = centre + 3 - 2j + np.exp(0.12j) * (right - centre)
    left = np.concatenate([moved + rng.normal(scale=0.03, size=14) + 1j * rng.normal(scale=0.03, size=14),
                           rng.uniform(-20, 20, 120) + 1j * rng.uniform(-20, 20, 120)])
    a, b = np.nonzero(np.abs(left[:, None] - right[None, :]) <= 10)
    order = np.argsort(b, kind="stable")
    a, b = a[order], b[order]
    votes = rigid_votes(left, right, a, b, np.zeros(len(a), np.intp), np.array([centre]), np.full(len(a), 0.0018),
                        np.full(len(a), 0.5), np.array([0.02]), np.array([0.2]), 1)
    assert np.array_equal(a[votes.voters], b[votes.voters]) and set(b[votes.voters].tolist()) == set(range(14))
    assert np.all(votes.voter_join == 0)


def test_a_pair_is_left_new_only_when_unclear_under_every_reference():
    """Left features at 0 and 0.5 m: a pair at 0 with drift 1 (> noise) has a rival within it (0.25 < 0 + 1.01); with
    drift 0.01 (< noise 0.02) it is not flagged. Unclear under one reference and clear under the other: kept."""
    left = np.array([0j, 0.5 + 0j])
    join = np.zeros(2, np.intp)
    at = np.array([0j])
    unclear = (at, np.array([0.02]), np.array([1.0]))
    clear = (at, np.array([0.02]), np.array([0.01]))
    assert beyond_voters(left, join, np.array([0]), None, unclear).tolist() == [True]
    assert beyond_voters(left, join, np.array([0]), None, clear).tolist() == [False]
    assert beyond_voters(left, join, np.array([0]), None, unclear, clear).tolist() == [False]
    assert beyond_voters(left, join, np.array([0]), None, unclear, unclear).tolist() == [True]



def test_near_voters_the_correction_holds_only_a_pair_whose_drift_is_below_its_noise():
    """``near_voters``: a pair drifted from the voters (drift 1 against noise 0.02) with no rival (the other left
    feature 5 m away) is clear under the correction without it, not with it, whatever its offset; a pair within its
    noise of the voters (drift 0.01) is held either way; the link's reference (the second) still holds the first;
    a pair not marked is as before."""
    left = np.array([0j, 5.0 + 0j])
    join = np.zeros(2, np.intp)
    for offset in (0.0, 0.05, 0.3):
        drifted = (np.array([offset + 0j]), np.array([0.02]), np.array([1.0]))
        near = (np.array([offset + 0j]), np.array([0.02]), np.array([0.01]))
        pair = np.array([0])
        assert beyond_voters(left, join, pair, None, drifted).tolist() == [False]
        assert beyond_voters(left, join, pair, None, drifted, near_voters=np.array([True])).tolist() == [True]
        assert beyond_voters(left, join, pair, None, drifted, near_voters=np.array([False])).tolist() == [False]
        assert beyond_voters(left, join, pair, None, near, near_voters=np.array([True])).tolist() == [False]
        assert beyond_voters(left, join, pair, None, drifted, near, near_voters=np.array([True])).tolist() == [False]


def test_a_reference_holds_a_pair_only_within_its_bound():
    """``within``: a pair whose drift is below its noise (0.01 < 0.02) but whose reference predicts it 1 m away is
    held there without a bound (the drift alone decides), not with the gate's bound (1 > 13.8 * 0.03); within 0.5 m
    it is (0.25 < 0.41); an infinite bound is none."""
    left = np.array([0j, 5.0 + 0j])
    join = np.zeros(2, np.intp)
    far = (np.array([1.0 + 0j]), np.array([0.02]), np.array([0.01]))
    near = (np.array([0.5 + 0j]), np.array([0.02]), np.array([0.01]))
    gate = np.array([-2 * np.log(0.001)])
    assert beyond_voters(left, join, np.array([0]), None, far).tolist() == [False]
    assert beyond_voters(left, join, np.array([0]), None, far, within=gate).tolist() == [True]
    assert beyond_voters(left, join, np.array([0]), None, near, within=gate).tolist() == [False]
    assert beyond_voters(left, join, np.array([0]), None, far, near, within=gate).tolist() == [False]
    assert beyond_voters(left, join, np.array([0]), None, far, within=np.array([np.inf])).tolist() == [False]

def far_loop(rng):
    """A join whose right map (24 features, link at the origin) sees 6 features of the map before, 12 last seen long
    ago moved by one rigid correction (the voters'), and 6 whose own features drifted otherwise (a far part of the
    loop: moved by another correction, out of reach). Where the voters' correction puts those 6, the map so far has
    other features, each with a neighbour 0.7 m away, among 150 clutter features. The true pairs, the arguments of
    match_with_drift and which right rows are the far part. The right features lie on a jittered 3.5 m grid, in a
    random order (so that no two of them are confused with each other's partners)."""
    grid = (np.arange(24) % 6 - 2.5) * 3.5 + 1j * (np.arange(24) // 6 - 1.5) * 3.5
    right = rng.permutation(grid) + rng.uniform(-0.5, 0.5, 24) + 1j * rng.uniform(-0.5, 0.5, 24)
    noise = 0.02

    def noisy(points):
        return points + rng.normal(scale=noise, size=len(points)) + 1j * rng.normal(scale=noise, size=len(points))

    centre = right[6:18].mean()
    old = noisy(centre + 4 + 3j + np.exp(0.08j) * (right[6:18] - centre))
    far = noisy(centre - 9 + 6j + np.exp(-0.1j) * (right[18:] - centre))
    decoys = noisy(centre + 4 + 3j + np.exp(0.08j) * (right[18:] - centre))
    left = np.concatenate([noisy(right[:6]), old, far, decoys, decoys + 0.7,
                           rng.uniform(-25, 25, 150) + 1j * rng.uniform(-25, 25, 150)])
    left_drift = np.concatenate([np.zeros(6), np.full(len(left) - 6, 16.0)])
    left_heading = np.concatenate([np.zeros(6), np.full(len(left) - 6, 0.003)])
    zeros = np.zeros(len(right))
    arguments = (left, np.tile([noise**2, 0.0, noise**2], (len(left), 1)), np.zeros(len(left), np.intp),
                 np.zeros(1, complex), np.zeros(1), np.array([[1e-4, 1e-6]]), right,
                 np.tile([noise**2, 0.0, noise**2], (24, 1)), np.zeros(24, np.intp),
                 (left_drift, left_heading, zeros, zeros))
    return arguments, set(zip(range(24), range(24))), np.arange(24) >= 18


def test_a_loop_closure_takes_no_pair_beyond_its_voters_drift():
    """Without a scope the voters' correction pairs the far part's right features with the features it puts them
    on, all false; with each pair's drift relative to the voters (4 m for the far part, none elsewhere) those pairs
    are left new (counted rejected) and the pairs taken are exactly the true ones found before; a scope of no drift
    changes nothing."""
    for seed in range(5):
        arguments, truth, far = far_loop(np.random.default_rng(seed))

        def scope(drift_of_far, far=far):
            return lambda pair_left, pair_right, join, *voters: np.where(far[pair_right], drift_of_far, 0.0)

        unscoped = match_with_drift(*arguments)
        pairs = set(zip(unscoped.left.tolist(), unscoped.right.tolist()))
        assert len(pairs & truth) >= 16 and {j for i, j in pairs - truth} == set(range(18, 24))
        none = match_with_drift(*arguments, scope=scope(0.0))
        assert np.array_equal(none.left, unscoped.left) and np.array_equal(none.right, unscoped.right)
        scoped = match_with_drift(*arguments, scope=scope(16.0))
        assert set(zip(scoped.left.tolist(), scoped.right.tolist())) == pairs & truth
        assert scoped.rejected[0] == unscoped.rejected[0] + 6


def test_the_trees_bent_closures_keep_no_pair_beyond_their_voters_on_the_default_simulation(monkeypatch, caplog):
    """The default simulation's tree (50 maps, seeds 0-3), whose upper joins' right pieces bent by metres: their loop
    closures' pairs beyond their voters (drift relative to them at least their noise) land by different features, with
    no rival seen with them (21 false links with them, 7 without; docs/method.md#data-association, step 6): at least
    twice fewer false links with the correction held only near its voters."""
    caplog.set_level(logging.ERROR, logger="mapjoin")
    runs = [local_ids(simulate(50, seed=seed).maps) for seed in range(4)]

    def false_links() -> int:
        return sum(link_errors(local, truth, join_associated(local, strategy="tree"))[2] for local, truth in runs)

    near = false_links()
    held = drifted.beyond_voters
    monkeypatch.setattr(drifted, "beyond_voters", lambda *args, near_voters=None, **bounds: held(*args, **bounds))
    assert 2 * near <= false_links()


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 10_000), n=st.integers(2, 10))
def test_across_link_compares_the_link_map_s_own_sighting_with_the_next_map_s(seed, n):
    """SightingDrift.across_link against se2.compose: a feature map m saw at z_m (its frame) and a right feature map
    m + 1 sees at z (its frame) lie |compose(P_m, z_m) - compose(P_m+1, z)|^2 apart, P the end poses composed one at
    a time; the variance is map m's own end-pose variance at the point, v_m + p_m |x - x_m+1|^2 / 2, whatever the
    junctions' posteriors; a feature another map saw last gets an infinite variance."""
    rng = np.random.default_rng(seed)
    end_poses = np.column_stack([rng.uniform(1, 5, n), rng.uniform(-1, 1, n), rng.uniform(-0.5, 0.5, n)])
    own = np.column_stack([rng.uniform(0.001, 0.1, n), rng.uniform(1e-5, 1e-3, n)])
    drift = SightingDrift.of(end_poses, 6, own)
    drift.placed(np.arange(1, n), rng.uniform(0.001, 0.1, n - 1), rng.uniform(1e-5, 1e-3, n - 1))
    poses = dead_reckoned(end_poses)
    link = int(rng.integers(0, n - 1))
    seen_by = np.array([link, link, link, (link + 1) % n, 0, link])
    seen_at = rng.normal(size=6) * 4 + 1j * rng.normal(size=6) * 4
    for feature in range(6):
        drift.seen(np.array([feature]), int(seen_by[feature]), seen_at[feature:feature + 1])
    points = rng.normal(size=6) * 4 + 1j * rng.normal(size=6) * 4
    offset2, variance = drift.across_link(np.arange(6), link, points)
    for feature in range(6):
        last = compose(poses[seen_by[feature]], np.array([seen_at[feature].real, seen_at[feature].imag, 0.0]))
        here = compose(poses[link + 1], np.array([points[feature].real, points[feature].imag, 0.0]))
        assert math.isclose(offset2[feature], (last[0] - here[0]) ** 2 + (last[1] - here[1]) ** 2, rel_tol=1e-9,
                            abs_tol=1e-12)
        lever = (here[0] - poses[link + 1, 0]) ** 2 + (here[1] - poses[link + 1, 1]) ** 2
        expected = own[link, 0] + own[link, 1] * lever / 2 if seen_by[feature] == link else math.inf
        assert math.isclose(variance[feature], expected, rel_tol=1e-9, abs_tol=1e-12)


def test_a_loop_closure_takes_no_pair_the_link_s_map_saw_elsewhere():
    """The far loop's false pairs (right rows 18-23, each put on a decoy by the voters' correction), their left features
    said to be seen last by the link's own map 2 m from where the right map sees them (4 m^2 against the gate of the
    noise 0.0008 and a variance of 0.01: 13.8 * 0.0108 = 0.15) are left new, counted rejected, and every other pair is
    the same; at 0.1 m (0.01 m^2, inside that gate), or for features another map saw last (infinite variance),
    nothing changes (each with a scope of no drift: the sequential join passes both)."""
    for seed in range(5):
        arguments, truth, far = far_loop(np.random.default_rng(seed))

        def across(offset2, variance, far=far):
            return lambda pair_left, pair_right: (np.where(far[pair_right], offset2, 0.0),
                                                  np.where(far[pair_right], variance, np.inf))

        def scope(pair_left, pair_right, join, *voters):  # no drift relative to the voters: holds every pair
            return np.zeros(len(pair_left))

        before = match_with_drift(*arguments, scope=scope)
        pairs = set(zip(before.left.tolist(), before.right.tolist()))
        assert {j for i, j in pairs - truth} == set(range(18, 24))
        for kept in (across(0.01, 0.01), across(4.0, np.inf)):
            same = match_with_drift(*arguments, scope=scope, across=kept)
            assert np.array_equal(same.left, before.left) and np.array_equal(same.right, before.right)
        refused = match_with_drift(*arguments, scope=scope, across=across(4.0, 0.01))
        assert set(zip(refused.left.tolist(), refused.right.tolist())) == pairs & truth
        assert refused.rejected[0] == before.rejected[0] + 6
