"""The grid's candidate pairs of data association (association.grid.pairs_within) against every pair compared."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from mapjoin.association.grid import pairs_within


def brute_force(left, left_join, right, right_join, radius):
    """Every (i, j) of one join within right j's radius, by two loops, in row order."""
    return [(i, j) for i in range(len(left)) for j in range(len(right))
            if left_join[i] == right_join[j] and abs(left[i] - right[j]) <= radius[j]]


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 100_000), joins=st.integers(1, 4), n=st.integers(0, 300), m=st.integers(0, 120),
       extent=st.sampled_from([0.5, 10.0, 1e4]), spread=st.sampled_from([1e-6, 0.1, 1.0, 50.0]))
def test_pairs_within_equal_every_pair_compared(seed, joins, n, m, extent, spread):
    """Points of several joins (each join's rows together, as the tree's), radii from tiny to wider than the extent,
    some points on cell boundaries and duplicated, few pairs (compared at once) and many (the grid): the same pairs
    in the same order as the brute force."""
    rng = np.random.default_rng(seed)
    left = rng.uniform(-extent, extent, n) + 1j * rng.uniform(-extent, extent, n)
    right = rng.uniform(-extent, extent, m) + 1j * rng.uniform(-extent, extent, m)
    if n and m:  # exact copies and points at a radius' distance (the <= boundary)
        right[: m // 3] = left[rng.integers(0, n, m // 3)]
    radius = rng.exponential(spread, m)
    if n and m > 3:
        right[-1] = left[0] + radius[-1]
    left_join, right_join = np.sort(rng.integers(0, joins, n)), np.sort(rng.integers(0, joins, m))
    i, j = pairs_within(left, left_join, right, right_join, radius, joins)
    assert list(zip(i.tolist(), j.tolist())) == brute_force(left, left_join, right, right_join, radius)


def test_pairs_within_find_far_points_of_a_wide_reach_and_none_across_joins():
    """A right point reaching 100 m finds a left point 99 m away in its join, not one 1 m away in another join."""
    left = np.array([99.0 + 0j, 1.0 + 0j])
    i, j = pairs_within(left, np.array([0, 1]), np.array([0j, 0.5 + 0j]), np.array([0, 1]), np.array([100.0, 0.1]), 2)
    assert i.tolist() == [0] and j.tolist() == [0]
