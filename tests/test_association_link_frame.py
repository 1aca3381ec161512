"""The link's own map's features in the link's frame (mapjoin.association.link_frame, link_pairs;
docs/method.md#data-association, step 2's link rule): their end-relative covariances against a dense finite-difference
Jacobian, and the pairs a long map's end leaves ambiguous otherwise."""

from __future__ import annotations

import logging

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from mapjoin.association import (end_relative, feature_covariances, join_associated, link_errors, local_ids,
                                 match_features)
from mapjoin.association.link_frame import LinkFrame
import mapjoin.association.associated_join as associated_join
from mapjoin.maps import LocalMap
from mapjoin.simulation import simulate


def _relative(state: np.ndarray, feature: int) -> np.ndarray:
    """One feature of ``state`` = [x, y, phi, f1x, f1y, ...] relative to the end pose, in its frame (by hand)."""
    x, y, phi = state[:3]
    fx, fy = state[3 + 2 * feature: 5 + 2 * feature]
    return np.array([np.cos(phi) * (fx - x) + np.sin(phi) * (fy - y), -np.sin(phi) * (fx - x) + np.cos(phi) * (fy - y)])


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(1, 6))
def test_end_relative_covariance_is_the_dense_jacobian_product(seed, count):
    """Each feature's block equals ``J Sigma J^T`` with ``J`` the finite-difference Jacobian of the relative position
    over the whole state (one feature at a time), and the position the relative one computed by hand; ids shuffled."""
    rng = np.random.default_rng(seed)
    size = 3 + 2 * count
    root = rng.normal(size=(size, size))
    covariance = root @ root.T / size + 0.01 * np.eye(size)
    state = np.concatenate([rng.normal(size=2) * 5, rng.uniform(-np.pi, np.pi, 1), rng.normal(size=2 * count) * 5])
    ids = rng.permutation(count) * 7 + 3
    local = LocalMap("m", 0, 1, state[:3], ids, state[3:].reshape(-1, 2), np.ones(count), np.ones(2), covariance)
    points, blocks = end_relative(local)
    for n, feature in enumerate(np.argsort(ids, kind="stable")):
        step = 1e-6
        jacobian = np.column_stack([(_relative(state + step * e, feature) - _relative(state - step * e, feature))
                                    / (2 * step) for e in np.eye(size)])
        dense = jacobian @ covariance @ jacobian.T
        assert np.allclose(blocks[n], [dense[0, 0], dense[0, 1], dense[1, 1]], rtol=1e-6, atol=1e-9)
        assert np.allclose([points[n].real, points[n].imag], _relative(state, feature))


def test_end_relative_is_none_without_a_full_covariance():
    local = simulate(2, seed=0, full_covariance=False).maps[0]
    assert end_relative(local) is None


def test_a_long_maps_end_features_are_known_to_its_end_not_to_its_start():
    """Why the rule: 30 steps a map (the default run of 30 maps, seed 0), the features the first map and the second
    share are known relative to the first map's end (the second map's start) to a fraction of what steps 2-5 count
    without it: their marginal (start-relative) covariance plus the end pose's translation variance."""
    first, second = simulate(30, seed=0, steps_per_map=30).maps[:2]
    shared = np.isin(np.sort(first.feature_ids), second.feature_ids)
    _, blocks = end_relative(first)
    marginal = feature_covariances(first)
    counted = marginal[:, 0] + marginal[:, 2] + 2 * first.pose_variances[0]
    assert np.median((blocks[:, 0] + blocks[:, 2])[shared] / counted[shared]) < 0.2


def test_the_link_rule_pairs_what_a_long_maps_end_left_ambiguous(monkeypatch, caplog):
    """Sequential joins of 30-step maps (seed 0, 10 maps): with the link rule, more true links and no false one more
    than without it (without it, ``end_relative`` gives None: the maps' start-relative treatment alone)."""
    caplog.set_level(logging.ERROR, logger="mapjoin")
    local, truth = local_ids(simulate(10, seed=0, steps_per_map=30).maps)
    links, missed, false = link_errors(local, truth, join_associated(local))
    monkeypatch.setattr(associated_join, "end_relative", lambda local_map: None)
    _, missed_without, false_without = link_errors(local, truth, join_associated(local))
    assert missed < missed_without and false <= false_without


def test_a_pair_in_the_links_frame_is_gated_without_the_link_and_gives_it_no_correction():
    """Two left features 0.5 m apart, the link's variance 1 m^2 (0.1 rad^2): under ``C0 + C1 + H P H^T`` the right
    feature's two candidates lie within the margin of each other and it is left ambiguous; in the link's frame
    (``C_end`` 0.001 m^2) the nearer one, ``d^2`` 0.45 against its rival's 1.1 m^2 / 0.002, is taken, and the link
    keeps no correction (the pair does not see its error) though its offset is 3 cm."""
    link_xy, link_phi = np.array([2.0 + 1.0j]), np.array([0.3])
    turn = np.exp(1j * link_phi[0])
    points = np.array([1.0 + 0.0j, 1.5 + 0.0j])  # relative to the link
    left = link_xy[0] + turn * points
    tiny = np.array([[0.001, 0.0, 0.001]] * 2)
    right, right_covariances = np.array([1.03 + 0.0j]), np.array([[0.001, 0.0, 0.001]])
    arguments = (left, np.array([[0.01, 0.0, 0.01]] * 2), np.zeros(2, np.intp), link_xy, link_phi,
                 np.array([[1.0, 0.1]]), right, right_covariances, np.zeros(1, np.intp))
    without = match_features(*arguments)
    assert len(without.right) == 0 and without.ambiguous[0] == 1
    within = match_features(*arguments, link_frame=LinkFrame(np.arange(2), points, tiny))
    assert within.left.tolist() == [0] and within.right.tolist() == [0]
    assert np.allclose(within.correction, 0.0)


def test_the_trees_first_level_pairs_what_a_long_maps_end_left_ambiguous(monkeypatch, caplog):
    """The tree's first level joins single maps, each left piece's end pose the link: two 20-step maps (seed 0) have
    22 true links; without the link rule (``end_relative`` None) the tree misses 7 of them, with it fewer, and no
    false link either way."""
    caplog.set_level(logging.ERROR, logger="mapjoin")
    local, truth = local_ids(simulate(2, seed=0, steps_per_map=20).maps)
    links, missed, false = link_errors(local, truth, join_associated(local, strategy="tree"))
    monkeypatch.setattr(associated_join, "end_relative", lambda local_map: None)
    _, missed_without, false_without = link_errors(local, truth, join_associated(local, strategy="tree"))
    assert links == 22 and missed_without == 7
    assert missed < missed_without and false == false_without == 0


@settings(max_examples=20, deadline=None)
@given(st.integers(0, 2**16), st.sampled_from([10, 20, 30]))
def test_two_maps_join_alike_by_the_tree_and_sequentially(seed, steps):
    """Two maps are one join either way, its link the first map's end pose: the tree's first level compares the first
    map's features in the link's frame as a sequential join does (the link rule, both), so every feature gets the same
    global id."""
    local, _ = local_ids(simulate(2, seed=seed, steps_per_map=steps).maps)
    tree, sequential = join_associated(local, strategy="tree"), join_associated(local)
    for by_tree, in_sequence in zip(tree.global_ids, sequential.global_ids):
        assert np.array_equal(by_tree, in_sequence)
