"""Lone drifted pairs in data association (docs/method.md#data-association, step 8): association.lone.lone_drifted
against a brute-force count, and a DLR-like join (a marker met again after drift lands beside an old marker mapped
twice, the copies never seen together) against the truth."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from mapjoin.association import match_with_drift, sighting_bits
from mapjoin.association.lone import CHECKED, LONE_DRIFT, lone_drifted


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 10_000))
def test_lone_drifted_equals_a_brute_force_count(seed):
    rng = np.random.default_rng(seed)
    k, joins = int(rng.integers(0, 12)), int(rng.integers(1, 4))
    pair_join = np.sort(rng.integers(0, joins, k))
    noise = rng.uniform(0.001, 0.05, k)
    drift = np.where(rng.random(k) < 0.5, noise * rng.uniform(0, 30, k), 0.0)
    got = lone_drifted(pair_join, noise, drift, joins)
    for pair in range(k):
        drifted = [q for q in range(k) if pair_join[q] == pair_join[pair] and drift[q] > 0
                   and drift[q] >= LONE_DRIFT * noise[q]]
        assert got[pair] == (pair in drifted and len(drifted) < CHECKED)


NOISE = 0.015


def strained_join(rng, drifted=1, duplicate=True, spacing=0.7):
    """A DLR-like join: markers on a lattice ``spacing`` m apart (jittered), all seen by map 1. The right map (map 9)
    sees 8 of them with no drift and ``drifted`` old markers through 0.3 m^2 of drift, each landing 0.02 m from a
    *different* marker ``wrong`` (one lattice step away); with ``duplicate``, each ``wrong`` was also mapped a second
    time 0.25 m away, by map 2 alone (never seen with it). Returns the join's arrays, the left rows of the true recent
    markers, the wrong ones, and the left drift."""
    steps = np.arange(-8, 9)
    grid = spacing * np.array([complex(x, y) for x in steps for y in steps])
    grid = grid + rng.normal(scale=0.05, size=len(grid)) + 1j * rng.normal(scale=0.05, size=len(grid))
    recent = rng.choice(np.flatnonzero(np.abs(grid) < 4 * spacing), 8, replace=False)
    ring = (np.abs(grid) > 5 * spacing) & (np.abs(grid) < 6.5 * spacing)
    old = np.setdiff1d(np.flatnonzero(ring), recent)[::3][:drifted]
    wrong = np.array([np.argmin(np.abs(grid - (grid[p] + spacing))) for p in old], dtype=np.intp)
    right = np.concatenate([grid[recent], grid[wrong] + 0.02])
    right = right + rng.normal(scale=NOISE / 3, size=len(right)) + 1j * rng.normal(scale=NOISE / 3, size=len(right))
    left = np.concatenate([grid, grid[wrong] + 0.25j]) if duplicate else grid
    maps = np.concatenate([np.ones(len(grid), np.intp), np.full(len(left) - len(grid), 2)])
    left_drift = np.full(len(left), 0.3)
    left_drift[recent] = 0.0
    return left, right, maps, recent, wrong, left_drift


def covariance(count):
    return np.tile([NOISE**2, 0.0, NOISE**2], (count, 1))


def associate(left, right, maps, left_drift):
    link = (np.zeros(1, complex), np.zeros(1), np.array([[1e-4, 1e-6]]))
    zeros = np.zeros(len(right))
    return match_with_drift(left, covariance(len(left)), np.zeros(len(left), np.intp), *link, right,
                            covariance(len(right)), np.zeros(len(right), np.intp),
                            (left_drift, np.zeros(len(left)), zeros, zeros), left_sightings=sighting_bits(maps),
                            right_sightings=sighting_bits(np.full(len(right), 9)),
                            pair_drift=lambda i, j, noise: left_drift[i])


def test_a_lone_drifted_pair_beside_a_duplicate_is_left_new():
    """The drifted sighting lands 0.02 m from a different marker whose second copy (never seen with it, so no rival of
    step 7) is 0.25 m away, inside half the drift, and whose neighbours seen with it (0.7 m away: 1.6 in squared
    distance over the drift) are within step 3's margin: step 8 leaves it new, counted ambiguous; the recent pairs (all
    true) are kept. Without the copy, or with the neighbours 3 m away (30 over the drift, so the nearest is clear), the
    lone pair is kept (a false pair: what is left of it is for steps 3 and 7 to see)."""
    for seed in range(10):
        left, right, maps, recent, wrong, left_drift = strained_join(np.random.default_rng(seed))
        found = associate(left, right, maps, left_drift)
        assert set(zip(found.left.tolist(), found.right.tolist())) == set(zip(recent.tolist(), range(8)))
        assert 8 in found.undecided.tolist() and found.ambiguous[0] >= 1
        for case in ({"duplicate": False}, {"spacing": 3.0}):
            left, right, maps, recent, wrong, left_drift = strained_join(np.random.default_rng(seed), **case)
            found = associate(left, right, maps, left_drift)
            assert (int(wrong[0]), 8) in set(zip(found.left.tolist(), found.right.tolist())), case


def test_drifted_pairs_that_confirm_one_another_are_kept():
    """Three drifted pairs moved by one common offset are not lone: step 8 keeps them (steps 6-7 judge them)."""
    for seed in range(10):
        left, right, maps, _, wrong, left_drift = strained_join(np.random.default_rng(seed), drifted=CHECKED)
        assert len(wrong) == CHECKED
        found = associate(left, right, maps, left_drift)
        pairs = set(zip(found.left.tolist(), found.right.tolist()))
        assert {(int(w), 8 + n) for n, w in enumerate(wrong)} <= pairs
