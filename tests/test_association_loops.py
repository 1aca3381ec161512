"""Loop closures in data association: the drift since each feature's sighting (association.feature_drift) against
the dense sum over the junctions, the two-pair rigid votes (association.loop_votes) against a planted correction,
and the association of a drifted loop closure (association.match_with_drift) against the truth."""

from __future__ import annotations

import math

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from mapjoin.association import loop_votes
from mapjoin.association import LOOP_SUPPORT, match_features, match_with_drift
from mapjoin.association.feature_drift import SightingDrift
from mapjoin.association.loop_votes import DIFFERENT_CELLS, rigid_votes
from mapjoin.se2 import compose


def dead_reckoned(end_poses):
    """Pose m (map m's start) of the chain, by composing the end poses one at a time (se2.compose, not
    ChainDrift's cumulative sums)."""
    poses = [np.zeros(3)]
    for pose in end_poses:
        poses.append(compose(poses[-1], pose))
    return np.array(poses)


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 10_000), n=st.integers(3, 12))
def test_sighting_drift_is_the_dense_sum_over_the_junctions(seed, n):
    """D = sum over the junctions between a sighting and the link of v_i + p_i |f - x_i|^2 / 2, with f and x_i
    dead-reckoned, the junctions' posteriors given in any order and in several batches (as the tree places them),
    and the heading variance the sum of their p_i."""
    rng = np.random.default_rng(seed)
    end_poses = np.column_stack([rng.uniform(1, 5, n), rng.uniform(-1, 1, n), rng.uniform(-0.5, 0.5, n)])
    v, p = rng.uniform(0.001, 0.1, n + 1), rng.uniform(1e-5, 1e-3, n + 1)
    drift = SightingDrift.of(end_poses, 4)
    junctions = rng.permutation(np.arange(1, n))
    for batch in np.array_split(junctions, 3):
        drift.placed(batch, v[batch], p[batch])
    poses = dead_reckoned(end_poses)
    seen_map, first_map = int(rng.integers(0, n)), int(rng.integers(0, n))
    point = complex(rng.normal(), rng.normal())
    drift.seen(np.array([0, 1]), np.array([seen_map, first_map]), np.array([point, point]))
    f_seen = complex(*(compose(poses[seen_map], np.array([point.real, point.imag, 0.0]))[:2]))
    f_first = complex(*(compose(poses[first_map], np.array([point.real, point.imag, 0.0]))[:2]))

    def dense(junction_range, f):
        return sum(v[i] + p[i] * abs(f - complex(*poses[i, :2])) ** 2 / 2 for i in junction_range)

    link_map = int(rng.integers(seen_map, n))  # the left piece ends with this map
    value, heading = drift.before(np.array([0]), np.array([link_map]))
    assert math.isclose(value[0], dense(range(seen_map + 1, link_map + 1), f_seen), rel_tol=1e-9, abs_tol=1e-12)
    assert math.isclose(heading[0], sum(p[seen_map + 1:link_map + 1]), rel_tol=1e-9, abs_tol=1e-15)
    left_end = int(rng.integers(-1, first_map)) if first_map > 0 else -1  # the right piece starts at left_end + 1
    value, heading = drift.after(np.array([1]), np.array([left_end]))
    assert math.isclose(value[0], dense(range(left_end + 2, first_map + 1), f_first), rel_tol=1e-9, abs_tol=1e-12)


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 10_000), n=st.integers(3, 12))
def test_dead_reckoned_drift_adds_each_maps_own_end_pose_variance(seed, n):
    """SightingDrift.dead_reckoned: D over the junctions between a sighting and the link with each junction i carrying,
    besides its posterior (v_i, p_i), the end-pose variance (t, p) of map i - 1, which ends there: the dense sum of
    (v_i + t_{i-1}) + (p_i + p_{i-1}) |f - x_i|^2 / 2; the drift itself unchanged."""
    rng = np.random.default_rng(seed)
    end_poses = np.column_stack([rng.uniform(1, 5, n), rng.uniform(-1, 1, n), rng.uniform(-0.5, 0.5, n)])
    v, p = rng.uniform(0.001, 0.1, n + 1), rng.uniform(1e-5, 1e-3, n + 1)
    own = np.column_stack([rng.uniform(0.001, 0.1, n), rng.uniform(1e-5, 1e-3, n)])
    drift = SightingDrift.of(end_poses, 4, own)
    junctions = np.arange(1, n)
    drift.placed(junctions, v[junctions], p[junctions])
    poses = dead_reckoned(end_poses)
    seen_map = int(rng.integers(0, n))
    point = complex(rng.normal(), rng.normal())
    drift.seen(np.array([0]), np.array([seen_map]), np.array([point]))
    f = complex(*(compose(poses[seen_map], np.array([point.real, point.imag, 0.0]))[:2]))
    link_map = int(rng.integers(seen_map, n))
    span = range(seen_map + 1, link_map + 1)
    value, heading = drift.dead_reckoned().before(np.array([0]), np.array([link_map]))
    expected = sum(v[i] + own[i - 1, 0] + (p[i] + own[i - 1, 1]) * abs(f - complex(*poses[i, :2])) ** 2 / 2
                   for i in span)
    assert math.isclose(value[0], expected, rel_tol=1e-9, abs_tol=1e-12)
    assert math.isclose(heading[0], sum(p[i] + own[i - 1, 1] for i in span), rel_tol=1e-9, abs_tol=1e-15)
    plain = drift.before(np.array([0]), np.array([link_map]))[0]
    assert math.isclose(plain[0], sum(v[i] + p[i] * abs(f - complex(*poses[i, :2])) ** 2 / 2 for i in span),
                        rel_tol=1e-9, abs_tol=1e-12)


def test_sighting_drift_follows_sightings_through_renaming():
    """seen_again moves the last sighting; merged takes another feature's last sighting; copied takes all; grown
    keeps what was there."""
    drift = SightingDrift.of(np.tile([2.0, 0.0, 0.0], (6, 1)), 2)
    drift.seen(np.array([0, 1]), np.array([0, 1]), np.array([0j, 1j]))
    drift.seen_again(np.array([0]), np.array([3]), np.array([1 + 0j]))
    drift = drift.grown(5)
    drift.copied(np.array([4]), np.array([0]))
    drift.merged(np.array([1]), np.array([0]))
    assert drift.first_map.tolist()[:5] == [0, 1, 0, 0, 0] and drift.last_map.tolist()[:5] == [3, 3, 0, 0, 3]
    assert drift.last_point[4] == 7 + 0j and drift.first_point[4] == 0j  # map 3 starts at x = 6


def planted(rng, turn=0.12, offset=3.0 - 2.0j, count=14, clutter=120, noise=0.03):
    """A map so far (``clutter`` random features in a 40 m square) containing ``count`` of a right map's features
    moved by a rigid correction (``turn`` about the right features' centroid, then ``offset``) and noise."""
    right = rng.uniform(-8, 8, count) + 1j * rng.uniform(-8, 8, count)
    centre = right.mean()
    moved = centre + offset + np.exp(1j * turn) * (right - centre)
    left = np.concatenate([moved + rng.normal(scale=noise, size=count) + 1j * rng.normal(scale=noise, size=count),
                           rng.uniform(-20, 20, clutter) + 1j * rng.uniform(-20, 20, clutter)])
    return left, right, centre


def test_rigid_votes_find_the_planted_correction_among_clutter():
    """Every (left, right) pair within 10 m votes; the best cell is the planted correction, supported by every
    planted feature, and the runner-up agrees far less (chance pairs rarely keep their distances)."""
    rng = np.random.default_rng(3)
    left, right, centre = planted(rng)
    a, b = np.nonzero(np.abs(left[:, None] - right[None, :]) <= 10)
    order = np.argsort(b, kind="stable")
    a, b = a[order], b[order]
    noise = np.full(len(a), 2 * 0.03**2)
    votes = rigid_votes(left, right, a, b, np.zeros(len(a), np.intp), np.array([centre]), noise,
                        np.full(len(a), 0.5), np.array([0.02]), np.array([0.2]), 1)
    assert abs(votes.turn[0] - 0.12) < 0.02 and abs(votes.offset[0] - (3 - 2j)) < 0.2
    assert votes.support[0] == 14 and votes.agreement[0] >= 60
    assert votes.agreement[0] >= 5 * votes.runner_up[0]
    # a bound on the turn below the planted one: the planted correction cannot win
    bounded = rigid_votes(left, right, a, b, np.zeros(len(a), np.intp), np.array([centre]), noise,
                          np.full(len(a), 0.05), np.array([0.02]), np.array([0.2]), 1)
    assert bounded.agreement[0] < 10


def test_rigid_votes_of_several_joins_are_those_of_each_alone():
    rng = np.random.default_rng(8)
    cases = [planted(rng, turn=t, offset=o) for t, o in ((0.1, 2 + 1j), (-0.05, -4 + 0j))]
    lefts, rights, joins, a_all, b_all, centres = [], [], [], [], [], []
    singles = []
    for k, (left, right, centre) in enumerate(cases):
        a, b = np.nonzero(np.abs(left[:, None] - right[None, :]) <= 10)
        order = np.argsort(b, kind="stable")
        a, b = a[order], b[order]
        noise = np.full(len(a), 2 * 0.03**2)
        singles.append(rigid_votes(left, right, a, b, np.zeros(len(a), np.intp), np.array([centre]), noise,
                                   np.full(len(a), 0.5), np.array([0.02]), np.array([0.2]), 1))
        a_all.append(a + sum(len(x) for x in lefts))
        b_all.append(b + sum(len(x) for x in rights))
        lefts.append(left)
        rights.append(right)
        joins.append(np.full(len(a), k))
        centres.append(centre)
    a, b = np.concatenate(a_all), np.concatenate(b_all)
    both = rigid_votes(np.concatenate(lefts), np.concatenate(rights), a, b, np.concatenate(joins), np.array(centres),
                       np.full(len(a), 2 * 0.03**2), np.full(len(a), 0.5), np.full(2, 0.02), np.full(2, 0.2), 2)
    for k, single in enumerate(singles):
        assert both.support[k] == single.support[0] and both.agreement[k] == single.agreement[0]
        assert both.runner_up[k] == single.runner_up[0]
        assert math.isclose(both.turn[k], single.turn[0]) and both.offset[k] == single.offset[0]


def loop_closure(rng, drift_offset=4.0 + 3.0j, drift_turn=0.08):
    """A join whose right map (20 features, in its own frame, link at the origin) sees 6 features of the map just
    before (no drift) and 10 last seen long ago, moved by the chain's drift (a rigid correction metres away),
    among 150 other old features: the true pairs, and the drift each left feature is given."""
    right = rng.uniform(-10, 10, 20) + 1j * rng.uniform(-10, 10, 20)
    noise = 0.02
    recent = right[:6] + rng.normal(scale=noise, size=6) + 1j * rng.normal(scale=noise, size=6)
    centre = right[6:16].mean()
    old = centre + drift_offset + np.exp(1j * drift_turn) * (right[6:16] - centre)
    old = old + rng.normal(scale=noise, size=10) + 1j * rng.normal(scale=noise, size=10)
    clutter = rng.uniform(-25, 25, 150) + 1j * rng.uniform(-25, 25, 150)
    left = np.concatenate([recent, old, clutter])
    left_drift = np.concatenate([np.zeros(6), np.full(160, 16.0)])  # sqrt(D) = 4 m: the drift's size
    left_heading = np.concatenate([np.zeros(6), np.full(160, 0.003)])
    truth = set(zip(range(16), range(16)))
    covariance = np.tile([noise**2, 0.0, noise**2], (len(left), 1))
    return left, covariance, right, np.tile([noise**2, 0.0, noise**2], (20, 1)), left_drift, left_heading, truth


def test_a_drifted_loop_closure_is_found_without_false_pairs():
    """The ordinary association pairs the recent features only (the drifted ones are metres outside its gate);
    with the drift, the loop closure's ten pairs are found too, and no pair is false; without drift it is
    match_features."""
    rng = np.random.default_rng(21)
    left, left_cov, right, right_cov, left_drift, left_heading, truth = loop_closure(rng)
    link = (np.zeros(1, complex), np.zeros(1), np.array([[1e-4, 1e-6]]))
    joins_left, joins_right = np.zeros(len(left), np.intp), np.zeros(len(right), np.intp)
    plain = match_features(left, left_cov, joins_left, *link, right, right_cov, joins_right)
    assert set(zip(plain.left.tolist(), plain.right.tolist())) == set(zip(range(6), range(6)))
    no_drift = match_with_drift(left, left_cov, joins_left, *link, right, right_cov, joins_right, None)
    assert np.array_equal(no_drift.left, plain.left) and np.array_equal(no_drift.right, plain.right)
    zeros = np.zeros(len(right))
    found = match_with_drift(left, left_cov, joins_left, *link, right, right_cov, joins_right,
                             (left_drift, left_heading, zeros, zeros))
    assert set(zip(found.left.tolist(), found.right.tolist())) == truth
    assert np.all(np.diff(found.right) > 0)


def test_clutter_alone_makes_no_loop_closure():
    """The same join with the drifted features removed from the map so far: the votes find no clear correction
    (chance pairs do not keep their distances), so the pairs are the ordinary association's, all true."""
    for seed in range(40):
        rng = np.random.default_rng(seed)
        left, left_cov, right, right_cov, left_drift, left_heading, _ = loop_closure(rng)
        keep = np.r_[0:6, 16:len(left)]
        link = (np.zeros(1, complex), np.zeros(1), np.array([[1e-4, 1e-6]]))
        zeros = np.zeros(len(right))
        arguments = (left[keep], left_cov[keep], np.zeros(len(keep), np.intp), *link, right, right_cov,
                     np.zeros(len(right), np.intp))
        plain = match_features(*arguments)
        found = match_with_drift(*arguments, (left_drift[keep], left_heading[keep], zeros, zeros))
        pairs = set(zip(found.left.tolist(), found.right.tolist()))
        assert pairs == set(zip(plain.left.tolist(), plain.right.tolist())) and pairs <= set(zip(range(6), range(6)))
    assert LOOP_SUPPORT >= 4


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 10_000), votes=st.integers(1, 200), spread=st.sampled_from([1, 3, 1 << 21]))
def test_cells_count_their_distinct_right_features_and_pairs_as_a_dictionary(seed, votes, spread):
    """_fullest against a dictionary of cells: each occupied cell in (join, cell) order, its first vote's join and
    coordinates, its distinct pairs of right features and, in the cells with their join's most pairs (where the best
    cell is chosen), its distinct right features (0 elsewhere, and everywhere when not asked for); cells far apart
    (2^21 cells between votes: the key from their spans would pass 2^62, each column is made compact) count alike."""
    from mapjoin.association.loop_votes import _fullest

    rng = np.random.default_rng(seed)
    join = np.sort(rng.integers(0, 3, votes))
    cells = rng.integers(-2, 3, (votes, 3)) * spread
    first = rng.integers(0, 6, votes)
    second = first + 1 + rng.integers(0, 4, votes)
    expected: dict[tuple, list] = {}
    for v in range(votes):
        entry = expected.setdefault((int(join[v]), *cells[v].tolist()), [set(), set()])
        entry[0] |= {int(first[v]), int(second[v])}
        entry[1].add((int(first[v]), int(second[v])))
    owner, coordinates, support, agreement = _fullest(join, cells, first, second)
    keys = sorted(expected)
    most = {j: max(len(expected[k][1]) for k in keys if k[0] == j) for j in {k[0] for k in keys}}
    assert [(int(j), *c) for j, c in zip(owner, coordinates.tolist())] == keys
    assert support.tolist() == [len(expected[k][0]) if len(expected[k][1]) == most[k[0]] else 0 for k in keys]
    assert agreement.tolist() == [len(expected[k][1]) for k in keys]
    assert (_fullest(join, cells, first, second, supported=False)[2] == 0).all()


def test_a_lattice_met_again_closes_no_loop():
    """8240's last join in small (docs/method.md#data-association, limits): features on a 3 m lattice, the right map
    a patch of 27 whose two top rows the map just before saw (no drift) and whose two bottom rows (7 features) meet
    the two rows the chain saw first, drifted by metres. Counted by brute force over the lattice's translations,
    several pair 8 right features with old ones where the true correction pairs 7: the data cannot tell them apart,
    and the association closes no loop (no false pair), the recent features paired as without drift."""
    rng = np.random.default_rng(5)
    spacing, noise, drift_offset = 3.0, 0.02, -4.33 + 2.82j
    right = np.array([complex(x, y) for y in range(0, 19, 3) for x in range(0, 10, 3) if (x, y) != (0, 0)])
    recent = right[right.imag >= 15]
    world_old = np.array([complex(x, y) for y in (0, 3) for x in range(-6, 10, 3)])  # the chain's first rows
    old = world_old + drift_offset

    def paired(correction):  # right features landing on an old one under a correction (brute force)
        return int((np.abs(old[:, None] - (right[None, :] + correction)) < spacing / 4).any(axis=0).sum())

    translations = [drift_offset + spacing * complex(i, j) for i in range(-4, 5) for j in range(-8, 3)]
    assert paired(drift_offset) == 7 and max(paired(t) for t in translations) == 8
    assert sum(paired(t) == 8 for t in translations) >= 3
    left = np.concatenate([recent, old])
    left = left + rng.normal(scale=noise, size=len(left)) + 1j * rng.normal(scale=noise, size=len(left))
    observed = right + rng.normal(scale=noise, size=len(right)) + 1j * rng.normal(scale=noise, size=len(right))
    left_drift = np.concatenate([np.zeros(len(recent)), np.full(len(old), 16.0)])  # sqrt(D) = 4 m
    left_heading = np.concatenate([np.zeros(len(recent)), np.full(len(old), 0.003)])
    covariance = np.tile([noise**2, 0.0, noise**2], (len(left), 1))
    link = (np.zeros(1, complex), np.zeros(1), np.array([[1e-4, 1e-6]]))
    zeros = np.zeros(len(right))
    arguments = (left, covariance, np.zeros(len(left), np.intp), *link, observed,
                 np.tile([noise**2, 0.0, noise**2], (len(right), 1)), np.zeros(len(right), np.intp))
    plain = match_features(*arguments)
    found = match_with_drift(*arguments, (left_drift, left_heading, zeros, zeros))
    recent_pairs = {(k, int(np.flatnonzero(right == f)[0])) for k, f in enumerate(recent)}
    assert set(zip(plain.left.tolist(), plain.right.tolist())) == recent_pairs
    assert set(zip(found.left.tolist(), found.right.tolist())) == recent_pairs


def bent_join(rng, near=6, far=60, clutter=80, near_noise=0.05, far_noise=0.15, turn=0.015, offset=0.3 - 0.4j):
    """A join whose right piece (link at the origin) sees ``near`` features of the map so far close to the link (no
    drift: seen there by both pieces) and ``far`` ones 40-80 m away, last seen long ago and moved since by one rigid
    correction (``turn`` about the link, then ``offset``; drift variance 1 m^2), among ``clutter`` other left
    features at least 2 m from any of them. Bearings are spread so that no two features share a gate. The pairs
    (left row, right row) ``(k, k)`` for the first ``near + far`` rows are the truth."""
    def bearings(n):
        return 2 * np.pi * (np.arange(n) + rng.uniform(-0.2, 0.2, n)) / n

    def noise(sigma, n):
        return sigma * (rng.normal(size=n) + 1j * rng.normal(size=n)) / np.sqrt(2)

    close = rng.uniform(4, 15, near) * np.exp(1j * bearings(near))
    away = rng.uniform(40, 80, far) * np.exp(1j * bearings(far))
    seen = np.concatenate([close + noise(near_noise, near), offset + np.exp(1j * turn) * away + noise(far_noise, far)])
    others = rng.uniform(-30, 30, clutter) + 1j * rng.uniform(-30, 30, clutter)
    others = others[np.abs(others[:, None] - seen[None, :]).min(axis=1) > 2]

    def covariances(sigma, n):
        return np.tile([sigma**2 / 2, 0.0, sigma**2 / 2], (n, 1))

    left = np.concatenate([seen, others])
    left_cov = np.concatenate([covariances(near_noise, near), covariances(far_noise, far),
                               covariances(near_noise, len(others))])
    right_cov = np.concatenate([covariances(near_noise, near), covariances(far_noise, far)])
    left_drift = np.concatenate([np.zeros(near), np.full(far, 1.0), np.zeros(len(others))])
    left_heading = np.concatenate([np.zeros(near), np.full(far, 1e-4), np.zeros(len(others))])
    return left, left_cov, np.concatenate([close, away]), right_cov, left_drift, left_heading


BENT_LINK = (np.zeros(1, complex), np.zeros(1), np.array([[0.1, 1e-4]]))  # sd 0.32 m, 0.01 rad: all in the gate


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 10_000))
def test_undrifted_features_the_correction_moved_are_found_again(seed):
    """The far pairs, many, set the link's correction (0.5 m and 0.015 rad) that moves the near features' predictions
    out of their gate (noise 0.05 m), so match_features pairs the far ones and at most two near ones; the second
    vote of step 6 (their spread: how far the correction moved them) finds the near ones again, with no false pair."""
    rng = np.random.default_rng(seed)
    left, left_cov, right, right_cov, left_drift, left_heading = bent_join(rng)
    arguments = (left, left_cov, np.zeros(len(left), np.intp), *BENT_LINK, right, right_cov,
                 np.zeros(len(right), np.intp))
    plain = match_features(*arguments)
    pairs = set(zip(plain.left.tolist(), plain.right.tolist()))
    assert set(zip(range(6, 66), range(6, 66))) <= pairs <= set(zip(range(66), range(66)))
    assert len(pairs) <= 62  # at least LOOP_SUPPORT near features left for the vote
    zeros = np.zeros(len(right))
    found = match_with_drift(*arguments, (left_drift, left_heading, zeros, zeros))
    assert np.array_equal(found.left, np.arange(66)) and np.array_equal(found.right, np.arange(66))


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 10_000), near=st.integers(0, LOOP_SUPPORT - 1), present=st.booleans())
def test_too_few_moved_features_or_none_in_the_map_make_no_loop_closure(seed, near, present):
    """Fewer than LOOP_SUPPORT near features (a loop closure's support), or six whose partners are missing from the
    map so far (clutter alone near the link): the pairs are match_features' own, all true."""
    rng = np.random.default_rng(seed)
    left, left_cov, right, right_cov, left_drift, left_heading = bent_join(rng, near=near if present else 6)
    keep = np.arange(len(left)) if present else np.arange(6, len(left))
    arguments = (left[keep], left_cov[keep], np.zeros(len(keep), np.intp), *BENT_LINK, right, right_cov,
                 np.zeros(len(right), np.intp))
    plain = match_features(*arguments)
    zeros = np.zeros(len(right))
    found = match_with_drift(*arguments, (left_drift[keep], left_heading[keep], zeros, zeros))
    pairs = set(zip(keep[found.left].tolist(), found.right.tolist()))
    assert pairs == set(zip(keep[plain.left].tolist(), plain.right.tolist()))
    assert all(k == j for k, j in pairs)


@settings(max_examples=40, deadline=None)
@given(st.integers(33, 300), st.integers(0, 2**32 - 1), st.booleans(), st.booleans())
def test_each_right_features_nearest_are_its_nearest(n, seed, lattice, tree):
    """The votes' neighbours (loop_votes._nearest, brute force in blocks or scipy's k-d tree beyond
    BRUTE_FORCE) against a full sort of every distance: the same k smallest distances, never the point itself
    (on a lattice, whose ties may be broken either way, the distances still agree)."""
    rng = np.random.default_rng(seed)
    points = (rng.integers(0, 12, n) + 1j * rng.integers(0, 12, n)) * 3.0 if lattice else \
        rng.normal(size=n) * 20 + 1j * rng.normal(size=n) * 20
    points = points + 1e-9 * np.arange(n)  # no two points alike (a lattice's duplicates apart)
    k = loop_votes.NEIGHBOURS
    saved = loop_votes.BRUTE_FORCE
    loop_votes.BRUTE_FORCE = 0 if tree else saved
    try:
        near = loop_votes._nearest(points, k)
    finally:
        loop_votes.BRUTE_FORCE = saved
    assert near.shape == (n, k) and not (near == np.arange(n)[:, None]).any()
    distances = np.abs(points[:, None] - points[None, :])
    np.fill_diagonal(distances, np.inf)
    expected = np.sort(distances, axis=1)[:, :k]
    assert np.allclose(np.sort(np.take_along_axis(distances, near, axis=1), axis=1), expected, rtol=0, atol=1e-12)


def bent(rng, count=24, bend=0.004, clutter=40, noise=0.03):
    """A map so far holding ``count`` of a right map's features (20 m long) moved by a correction that bends along
    the map: a turn growing by ``bend`` per metre of x (as a piece that drifted along its own chain), then 0.6 m,
    among ``clutter`` random features: the candidate pairs within 1.5 m, sorted by right feature."""
    right = rng.uniform(-10, 10, count) + 1j * rng.uniform(-2, 2, count)
    moved = 0.5 - 0.3j + right * np.exp(1j * bend * (right.real + 10))
    left = np.concatenate([moved + noise * (rng.normal(size=count) + 1j * rng.normal(size=count)),
                           rng.uniform(-12, 12, clutter) + 1j * rng.uniform(-4, 4, clutter)])
    a, b = np.nonzero(np.abs(left[:, None] - right[None, :]) <= 1.5)
    order = np.argsort(b, kind="stable")
    return left, right, a[order], b[order]


def brute_force_votes(left, right, a, b, centre, noise, turning, turn_cell, offset_cell):
    """rigid_votes of one join of at most 32 right features (every pair of them votes) by a loop over the pairs of
    candidate pairs and a dictionary of cells: the best cell (agreement, then support), its voters (the pairs of
    the votes within a cell of its centre) and the runner-up, counted both ways: over every vote, and over the votes
    of two pairs that are not voters (the rival association)."""
    votes = []
    for p in range(len(a)):
        for q in range(len(a)):
            if b[p] >= b[q] or a[p] == a[q]:
                continue
            span_left, span_right = left[a[p]] - left[a[q]], right[b[p]] - right[b[q]]
            if (abs(span_left) - abs(span_right)) ** 2 > 9.0 * (noise[p] + noise[q]):
                continue
            dphi = float(np.angle(span_left / span_right))
            if abs(dphi) > min(turning[p], turning[q]):
                continue
            o = left[a[p]] + np.exp(1j * dphi) * (centre - right[b[p]]) - centre
            votes.append((p, q, np.array([dphi, o.real, o.imag])))
    scale = np.array([turn_cell, offset_cell, offset_cell])

    def cells(chosen):
        found = {}
        for p, q, x in chosen:
            for shift in (0.0, 0.5):
                key = (shift, *np.floor(x / scale + shift).astype(int).tolist())
                found.setdefault(key, set()).add((int(b[p]), int(b[q])))
        return {key: ((np.array(key[1:]) + 0.5 - key[0]) * scale, pairs) for key, pairs in found.items()}

    every = cells(votes)
    rank = {key: (len(pairs), len({f for pair in pairs for f in pair})) for key, (_, pairs) in every.items()}
    best = max(rank.values())
    centres = [every[key][0] for key in rank if rank[key] == best]
    voters = {r for p, q, x in votes if (np.abs(x - centres[0]) <= scale).all() for r in (p, q)}

    def runner_up(chosen):
        return max([len(pairs) for c, pairs in cells(chosen).values()
                    if (np.abs(c - centres[0]) > DIFFERENT_CELLS * scale).any()], default=0)

    rivals = [vote for vote in votes if vote[0] not in voters and vote[1] not in voters]
    claimed = {int(b[r]) for r in voters}
    conflicting = [vote for vote in rivals if b[vote[0]] in claimed or b[vote[1]] in claimed]
    return best, len(centres), voters, runner_up(votes), runner_up(rivals), runner_up(conflicting)


def agree_with_brute_force(left, right, a, b, noise, turning):
    """rigid_votes' best cell, voters and runner-up of one join (centred on the right piece) against
    brute_force_votes'; (the votes, the runner-up over every vote)."""
    centre = right.mean()
    votes = rigid_votes(left, right, a, b, np.zeros(len(a), np.intp), np.array([centre]), noise, turning,
                        np.array([0.01]), np.array([0.15]), 1)
    best, ties, voters, every, rival, _ = brute_force_votes(left, right, a, b, centre, noise, turning, 0.01, 0.15)
    assert (votes.agreement[0], votes.support[0]) == best
    if ties == 1:  # else either is the best
        assert set(votes.voters.tolist()) == voters and votes.runner_up[0] == rival
    return votes, every


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 10_000), bend=st.sampled_from([0.0, 0.002, 0.004, 0.008]))
def test_the_runner_up_is_a_rival_association_as_counted_by_brute_force(seed, bend):
    """rigid_votes' best cell, voters and runner-up against brute_force_votes on planted pieces, rigid or bent: the
    runner-up counts only votes of pairs other than the best's voters. A bent piece's own pairs vote for cells
    beyond the best (the runner-up over every vote is large); no rival association keeps their distances."""
    rng = np.random.default_rng(seed)
    left, right, a, b = bent(rng, bend=bend)
    noise, turning = np.full(len(a), 2 * 0.03**2), np.full(len(a), 0.5)
    votes, every = agree_with_brute_force(left, right, a, b, noise, turning)
    assert votes.runner_up[0] <= every


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 10_000), spread=st.sampled_from([1.0, 4.0, 30.0]))
def test_votes_of_pairs_with_unequal_noise_are_those_counted_by_brute_force(seed, spread):
    """rigid_votes drops the votes whose distances disagree first against the largest noise of the join's pairs, then
    tests the others with their own: with each pair's noise drawn over a factor ``spread``, its best cell, voters and
    runner-up are brute_force_votes' (each vote tested with its own two pairs' noise)."""
    rng = np.random.default_rng(seed)
    left, right, a, b = bent(rng, bend=0.002)
    noise = 2 * 0.03**2 * np.exp(rng.uniform(-np.log(spread), 0.0, len(a)))
    turning = np.full(len(a), 0.5)
    agree_with_brute_force(left, right, a, b, noise, turning)


def test_a_bent_piece_closes_its_loop_where_its_own_pairs_vote_beyond_the_best():
    """A piece bent by 0.004 rad per metre (0.08 rad along it): over every vote, the runner-up agrees more than half
    the best (a rigid correction holds for part of the piece only: the closure would be refused), over the rival
    association's votes far less (taken)."""
    rng = np.random.default_rng(0)
    left, right, a, b = bent(rng, bend=0.004)
    noise, turning = np.full(len(a), 2 * 0.03**2), np.full(len(a), 0.5)
    best, _, _, every, rival, _ = brute_force_votes(left, right, a, b, right.mean(), noise, turning, 0.01, 0.15)
    votes = rigid_votes(left, right, a, b, np.zeros(len(a), np.intp), np.array([right.mean()]), noise, turning,
                        np.array([0.01]), np.array([0.15]), 1)
    assert 2 * every > best[0] and votes.agreement[0] >= 2 * votes.runner_up[0] == 2 * rival


def two_regions(rng, count=24, clutter=40, noise=0.03):
    """A right piece 40 m long whose two halves (``count`` / 2 features each) the chain moved by two different rigid
    corrections (0.05 rad apart and 0.8 m: a piece bent at its middle), among ``clutter`` random features: the
    candidate pairs within 1.5 m, sorted by right feature."""
    half = count // 2
    right = np.concatenate([rng.uniform(-20, -2, half), rng.uniform(2, 20, count - half)]) \
        + 1j * rng.uniform(-2, 2, count)
    moved = np.where(right.real < 0, 0.5 - 0.3j + right * np.exp(0.02j), -0.3 + 0.5j + right * np.exp(-0.03j))
    left = np.concatenate([moved + noise * (rng.normal(size=count) + 1j * rng.normal(size=count)),
                           rng.uniform(-22, 22, clutter) + 1j * rng.uniform(-4, 4, clutter)])
    a, b = np.nonzero(np.abs(left[:, None] - right[None, :]) <= 1.5)
    order = np.argsort(b, kind="stable")
    return left, right, a[order], b[order]


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 10_000), halves=st.booleans())
def test_a_bent_joins_runner_up_counts_only_rivals_of_the_voters_features(seed, halves):
    """rigid_votes with ``bent``: the runner-up counts only the votes of two non-voting pairs one of which pairs a
    right feature of the best cell's voters (brute_force_votes' conflicting rivals); a join not bent keeps every
    rival association's votes."""
    rng = np.random.default_rng(seed)
    left, right, a, b = two_regions(rng) if halves else bent(rng, bend=0.004)
    noise, turning = np.full(len(a), 2 * 0.03**2), np.full(len(a), 0.5)
    centre = right.mean()
    _, ties, _, _, rival, conflicting = brute_force_votes(left, right, a, b, centre, noise, turning, 0.01, 0.15)
    arguments = (left, right, a, b, np.zeros(len(a), np.intp), np.array([centre]), noise, turning, np.array([0.01]),
                 np.array([0.15]), 1)
    if ties == 1:
        assert rigid_votes(*arguments, bent=np.array([True])).runner_up[0] == conflicting
        assert rigid_votes(*arguments, bent=np.array([False])).runner_up[0] == rival


def test_a_piece_bent_at_its_middle_closes_its_loop_only_as_bent():
    """Two halves moved by two corrections: each half's pairs agree on their own; counted as rivals, the other half
    ties the best (the closure refused), as a bent piece's other region it is no rival (taken)."""
    rng = np.random.default_rng(5)
    left, right, a, b = two_regions(rng)
    noise, turning = np.full(len(a), 2 * 0.03**2), np.full(len(a), 0.5)
    arguments = (left, right, a, b, np.zeros(len(a), np.intp), np.array([right.mean()]), noise, turning,
                 np.array([0.01]), np.array([0.15]), 1)
    rigid, bent_piece = rigid_votes(*arguments), rigid_votes(*arguments, bent=np.array([True]))
    assert rigid.agreement[0] < 2 * rigid.runner_up[0]
    assert bent_piece.agreement[0] >= 2 * bent_piece.runner_up[0]
