"""Tests of ``mapjoin.sightings``: which scans of the figure-eight see which features, against brute force
(every scan's distance to every feature)."""

from __future__ import annotations

import math

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from mapjoin.sightings import Sightings


def figure_eight(lap: int, step_length: float) -> tuple[np.ndarray, float]:
    """The scan poses of one lap, written from the model (two circles touching at the origin, lobe A's
    centre (0, +rho) driven anticlockwise first, then lobe B's clockwise), and the radius."""
    lobe = lap // 2
    radius = step_length / (2 * math.sin(math.pi / lobe))
    angle = 2 * math.pi * np.arange(lobe) / lobe
    a = np.stack([radius * np.sin(angle), radius - radius * np.cos(angle), angle], axis=1)
    b = np.stack([radius * np.sin(angle), -radius + radius * np.cos(angle), -angle], axis=1)
    return np.concatenate([a, b]), radius


def brute_force(world: np.ndarray, poses: np.ndarray, min_range: float, max_range: float) -> np.ndarray:
    """phases x features: whether the scan sees the feature."""
    distance = np.hypot(world[None, :, 0] - poses[:, None, 0], world[None, :, 1] - poses[:, None, 1])
    return (distance >= min_range) & (distance <= max_range)


def world_near(rng: np.random.Generator, radius: float, band: float, count: int) -> np.ndarray:
    """Points around both circles (and some far away, seen by no scan)."""
    angle = rng.uniform(0, 2 * np.pi, count)
    distance = radius + rng.uniform(-1.5 * band, 1.5 * band, count)
    centre = np.where(rng.random(count) < 0.5, radius, -radius)
    return np.stack([distance * np.cos(angle), centre + distance * np.sin(angle)], axis=1)


cases = dict(lap=st.integers(16, 400).map(lambda k: 2 * k), step=st.floats(0.3, 2.0),
             band=st.floats(1.0, 8.0), inner=st.floats(0.05, 0.9), scanned=st.floats(0.2, 1.0),
             seed=st.integers(0, 2**32 - 1))


def setup(lap, step, band, inner, scanned, seed):
    poses, radius = figure_eight(lap, step)
    poses = poses[:max(1, int(scanned * lap))]
    max_range = max(band, step * 1.01)
    rng = np.random.default_rng(seed)
    world = world_near(rng, radius, max_range, int(rng.integers(0, 300)))
    return rng, world, poses, radius, inner * max_range, max_range


@settings(max_examples=60, deadline=None)
@given(**cases)
def test_the_scans_asked_for_see_exactly_the_features_in_range(lap, step, band, inner, scanned, seed):
    rng, world, poses, radius, min_range, max_range = setup(lap, step, band, inner, scanned, seed)
    sees = brute_force(world, poses, min_range, max_range)
    sightings = Sightings(world, poses, lap, radius, min_range, max_range)
    start = int(rng.integers(0, len(poses)))
    asked = (start + np.arange(int(rng.integers(1, 3 * len(poses))))) % len(poses)   # a run, wrapping
    asked = np.concatenate([asked, rng.integers(0, len(poses), 5)])                  # and a few anywhere
    owner, feature = sightings.at(asked).expand(asked)
    expected = [(i, f) for i, phase in enumerate(asked.tolist()) for f in np.flatnonzero(sees[phase]).tolist()]
    assert list(zip(owner.tolist(), feature.tolist())) == expected


@settings(max_examples=40, deadline=None)
@given(**cases)
def test_first_seen_is_the_first_scan_in_range(lap, step, band, inner, scanned, seed):
    _, world, poses, radius, min_range, max_range = setup(lap, step, band, inner, scanned, seed)
    sees = brute_force(world, poses, min_range, max_range)
    expected = np.where(sees.any(axis=0), sees.argmax(axis=0), len(poses))
    first = Sightings(world, poses, lap, radius, min_range, max_range).first_seen()
    np.testing.assert_array_equal(first, expected)


@settings(max_examples=40, deadline=None)
@given(**cases)
def test_sees_tells_the_pairs_in_range(lap, step, band, inner, scanned, seed):
    rng, world, poses, radius, min_range, max_range = setup(lap, step, band, inner, scanned, seed)
    sees = brute_force(world, poses, min_range, max_range)
    phases = rng.integers(0, len(poses), 50)
    features = rng.integers(0, max(len(world), 1), 50)
    seen = Sightings(world, poses, lap, radius, min_range, max_range).at(phases)
    expected = sees[phases, features] if len(world) else np.zeros(50, dtype=bool)
    np.testing.assert_array_equal(seen.sees(phases, features), expected)


def test_renumbered_features_are_reported_by_their_new_ids():
    poses, radius = figure_eight(64, 1.0)
    world = world_near(np.random.default_rng(1), radius, 5.0, 200)
    sightings = Sightings(world, poses, 64, radius, 0.5, 5.0)
    ids = np.random.default_rng(2).permutation(len(world))
    phases = np.arange(len(poses))
    owner, feature = sightings.at(phases).expand(phases)
    owner_new, feature_new = sightings.renumbered(ids).at(phases).expand(phases)
    assert sorted(zip(owner.tolist(), ids[feature].tolist())) == list(zip(owner_new.tolist(), feature_new.tolist()))


def test_a_long_run_sets_up_without_building_every_pair():
    """simulate_stream's set-up and first chunk at 10^5 maps: ~600 000 features, ~5 million (scan, feature)
    pairs. Building every pair first (7a05a2a) peaked at 878 bytes a feature (tracemalloc); the windows
    cost about 200."""
    import tracemalloc

    from mapjoin.simulation import simulate_stream

    tracemalloc.start()
    try:
        run = simulate_stream(100_000, seed=1, full_covariance=False)
        next(run.chunks)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak / len(run.truth.feature_ids) < 400
