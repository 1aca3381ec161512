"""Tests of the seeded ground-truth simulator (``mapjoin.simulation``)."""

from __future__ import annotations

import re

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.stats import chi2

from mapjoin.maps import LocalMap
from mapjoin.simulation import Simulation, simulate

MIN_SHARED = 3  # the default guarantee


# --- independent helpers (method.md conventions) ----------------------------------------

def wrap(angle):
    return (np.asarray(angle) + np.pi) % (2 * np.pi) - np.pi


def rot(phi: float) -> np.ndarray:
    return np.array([[np.cos(phi), -np.sin(phi)], [np.sin(phi), np.cos(phi)]])


def compose(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Pose ``b`` (expressed in the frame of ``a``) in the frame ``a`` is expressed in."""
    return np.r_[a[:2] + rot(a[2]) @ b[:2], wrap(a[2] + b[2])]


def true_local_state(sim: Simulation, k: int) -> np.ndarray:
    """Map k's true state ``[x, y, phi, f1x, f1y, ...]`` from the truth: x_local = R^T (x - t)."""
    local_map = sim.maps[k - 1]
    start, end = sim.truth.poses[k - 1], sim.truth.poses[k]
    inverse = rot(start[2]).T
    lookup = {int(i): j for j, i in enumerate(sim.truth.feature_ids)}
    features = sim.truth.features[[lookup[int(i)] for i in local_map.feature_ids]]
    return np.r_[inverse @ (end[:2] - start[:2]), wrap(end[2] - start[2]),
                 ((features - start[:2]) @ inverse.T).ravel()]


def state(local_map: LocalMap) -> np.ndarray:
    return np.r_[local_map.end_pose, local_map.features.ravel()]


def errors(sim: Simulation):
    """(error, covariance) per map, the angle difference wrapped."""
    for k, local_map in enumerate(sim.maps, start=1):
        error = state(local_map) - true_local_state(sim, k)
        error[2] = wrap(error[2])
        yield error, local_map.covariance


def shared(a: LocalMap, b: LocalMap) -> int:
    return len(np.intersect1d(a.feature_ids, b.feature_ids))


def assert_same(a: Simulation, b: Simulation) -> None:
    assert len(a.maps) == len(b.maps)
    for x, y in zip(a.maps, b.maps):
        assert (x.name, x.start_id, x.end_id) == (y.name, y.start_id, y.end_id)
        for field in ("end_pose", "feature_ids", "features", "feature_variances", "pose_variances", "covariance"):
            assert np.array_equal(getattr(x, field), getattr(y, field)), field
    for field in ("feature_ids", "features", "pose_ids", "poses"):
        assert np.array_equal(getattr(a.truth, field), getattr(b.truth, field)), field


# --- reproducibility and structure (hypothesis over maps, seed, steps) ---------------------

runs = dict(maps=st.integers(1, 25), seed=st.integers(0, 2**32 - 1), steps_per_map=st.integers(1, 12))


@settings(max_examples=25, deadline=None)
@given(**runs)
def test_same_seed_same_output(maps, seed, steps_per_map):
    assert_same(simulate(maps, seed=seed, steps_per_map=steps_per_map),
                simulate(maps, seed=seed, steps_per_map=steps_per_map))


@settings(max_examples=15, deadline=None)
@given(maps=st.integers(1, 25), seed=st.integers(0, 2**32 - 2))
def test_different_seed_different_output(maps, seed):
    a, b = simulate(maps, seed=seed), simulate(maps, seed=seed + 1)
    assert not np.array_equal(a.truth.features[:5], b.truth.features[:5])
    assert not np.array_equal(a.maps[0].end_pose, b.maps[0].end_pose)


@settings(max_examples=40, deadline=None)
@given(**runs)
def test_chain_structure_and_shared_features(maps, seed, steps_per_map):
    sim = simulate(maps, seed=seed, steps_per_map=steps_per_map)
    assert len(sim.maps) == maps
    assert [(m.name, m.start_id, m.end_id) for m in sim.maps] == [
        (f"sim-{k}", k - 1, k) for k in range(1, maps + 1)]
    assert np.array_equal(sim.truth.pose_ids, np.arange(maps + 1))
    assert np.array_equal(sim.truth.poses[0], [0.0, 0.0, 0.0])
    # truth features are exactly the features the maps saw, ids 0..n-1
    seen = np.unique(np.concatenate([m.feature_ids for m in sim.maps]))
    assert np.array_equal(seen, np.arange(len(sim.truth.feature_ids)))
    assert np.array_equal(sim.truth.feature_ids, seen)
    for m in sim.maps:
        assert m.size >= MIN_SHARED
        assert np.all(np.diff(m.feature_ids) > 0)
        assert m.covariance.shape == (3 + 2 * m.size,) * 2
    for a, b in zip(sim.maps, sim.maps[1:]):
        assert shared(a, b) >= MIN_SHARED


@pytest.mark.parametrize("kwargs", [dict(min_shared=8, density=0.03), dict(features=0), dict(features=0, min_shared=1)],
                         ids=["sparse-world-8-shared", "no-random-features", "no-random-features-1-shared"])
def test_shared_feature_guarantee_is_enforced(kwargs):
    sim = simulate(40, seed=5, **kwargs)
    need = kwargs.get("min_shared", MIN_SHARED)
    assert min(m.size for m in sim.maps) >= need
    assert min(shared(a, b) for a, b in zip(sim.maps, sim.maps[1:])) >= need


def test_default_run_shares_several_features_and_has_about_20_per_map():
    sim = simulate(200, seed=1)
    sizes = np.array([m.size for m in sim.maps])
    common = np.array([shared(a, b) for a, b in zip(sim.maps, sim.maps[1:])])
    assert 15 <= sizes.mean() <= 25
    assert common.mean() >= 6


@pytest.mark.parametrize("maps,laps", [(20, 2.0), (30, 3.0), (100, 2.0)], ids=["20x2", "30x3", "100x2"])
def test_loop_closure_reobserves_early_features(maps, laps):
    sim = simulate(maps, seed=2, laps=laps)
    late = [(k, j) for k in range(maps) for j in range(k + 3, maps) if shared(sim.maps[k], sim.maps[j])]
    assert late, "no map re-observes features of a map 3 or more maps earlier"
    # the second lap re-observes the first map
    lap_maps = round(maps / laps)
    assert shared(sim.maps[0], sim.maps[lap_maps]) >= MIN_SHARED


def test_no_loop_closure_within_less_than_a_lap():
    # sanity check of the loop test: one lap of a large figure-eight closes only at its end
    sim = simulate(40, seed=2, laps=1.0)
    late = {j - k for k in range(40) for j in range(k + 3, 40) if shared(sim.maps[k], sim.maps[j])}
    assert late and min(late) > 5   # only the crossing at the origin and the lap's end


# --- the truth: frames and the chain --------------------------------------------------------

@pytest.mark.parametrize("kwargs", [dict(), dict(steps_per_map=1), dict(steps_per_map=7, laps=3.5, step_length=0.5,
                                                                         sensor_range=3.0, min_range=0.2)],
                         ids=["default", "one-step-maps", "odd-sizes"])
def test_noiseless_maps_compose_to_the_truth(kwargs):
    maps = 45
    sim = simulate(maps, seed=11, noiseless=True, **kwargs)
    pose = np.zeros(3)
    lookup = {int(i): j for j, i in enumerate(sim.truth.feature_ids)}
    for k, local_map in enumerate(sim.maps, start=1):
        # map k's features, placed from the true start pose, are the true global features
        placed = pose[:2] + local_map.features @ rot(pose[2]).T
        expected = sim.truth.features[[lookup[int(i)] for i in local_map.feature_ids]]
        np.testing.assert_allclose(placed, expected, atol=1e-9)
        pose = compose(pose, local_map.end_pose)
        np.testing.assert_allclose(pose[:2], sim.truth.poses[k, :2], atol=1e-9)
        assert abs(wrap(pose[2] - sim.truth.poses[k, 2])) < 1e-9
        assert -np.pi <= local_map.end_pose[2] < np.pi


def test_noiseless_is_the_true_local_state_and_keeps_world_and_covariances():
    noisy, exact = simulate(30, seed=4), simulate(30, seed=4, noiseless=True)
    for field in ("feature_ids", "features", "poses"):
        assert np.array_equal(getattr(noisy.truth, field), getattr(exact.truth, field))
    for k, (a, b) in enumerate(zip(noisy.maps, exact.maps), start=1):
        assert np.array_equal(a.feature_ids, b.feature_ids)
        assert np.array_equal(a.covariance, b.covariance)
        np.testing.assert_allclose(state(b), true_local_state(exact, k), atol=1e-9)
        assert not np.allclose(state(a), state(b), atol=1e-6)


@pytest.mark.parametrize("maps,n,laps,rmin,rmax",
                         [(30, 6, 2.0, 0.5, 4.0), (3, 10, 2.0, 0.5, 5.0), (25, 7, 3.5, 0.2, 3.0)],
                         ids=["default-like", "tiny-lap-whole-circle-visible", "odd-lap"])
def test_maps_hold_exactly_the_features_in_sensor_range(maps, n, laps, rmin, rmax):
    """Brute-force oracle: a map sees the features within [min_range, range] of its scan poses."""
    kwargs = dict(seed=8, sensor_range=rmax, min_range=rmin, laps=laps, noiseless=True, min_shared=0)
    sim = simulate(maps, steps_per_map=n, **kwargs)
    # the same run (same number of steps, hence the same figure-eight and world; no
    # features added for the guarantee) with one step per map gives every scan pose
    steps = simulate(maps * n, steps_per_map=1, **kwargs)
    assert np.array_equal(steps.truth.features, sim.truth.features)
    scan_poses = steps.truth.poses[:-1, :2]
    assert sum(m.size for m in sim.maps) > 0
    for k, local_map in enumerate(sim.maps):
        poses = scan_poses[k * n:(k + 1) * n]
        distance = np.linalg.norm(sim.truth.features[:, None, :] - poses[None], axis=2)
        expected = sim.truth.feature_ids[((distance >= rmin - 1e-9) & (distance <= rmax + 1e-9)).any(axis=1)]
        assert np.array_equal(local_map.feature_ids, expected)


# --- the declared covariance --------------------------------------------------------------

def test_covariances_are_symmetric_positive_definite_and_correlated():
    sim = simulate(60, seed=9)
    for m in sim.maps:
        p = m.covariance
        assert np.array_equal(p, p.T)
        assert np.linalg.eigvalsh(p).min() > 0
        sigma = np.sqrt(np.diag(p))
        corr = p / np.outer(sigma, sigma)
        # end pose <-> features, and feature <-> feature (other blocks) are correlated
        assert np.abs(corr[:3, 3:]).max() > 0.3
        off_block = corr[3:, 3:].copy()
        for j in range(m.size):
            off_block[2 * j:2 * j + 2, 2 * j:2 * j + 2] = 0
        assert np.abs(off_block).max() > 0.3
        # the marginal spherical variances are the documented summary
        np.testing.assert_allclose(m.feature_variances, np.diag(p)[3:].reshape(-1, 2).mean(axis=1))


def test_covariance_grows_with_odometry_noise():
    quiet = simulate(10, seed=3, odometry_noise=(0.01, 0.01, 0.002))
    loud = simulate(10, seed=3, odometry_noise=(0.1, 0.1, 0.02))
    for a, b in zip(quiet.maps, loud.maps):
        # features seen only from the start pose carry no odometry error: equal there
        assert np.all(np.diag(b.covariance) >= np.diag(a.covariance))
        assert np.all(np.diag(b.covariance)[:3] > np.diag(a.covariance)[:3])


def test_declared_covariance_is_the_linearised_estimator_covariance():
    """Oracle for the noise model: the covariance of the nonlinear estimator (dead reckoning
    with noisy odometry, mean of the points placed from noisy range/bearing observations),
    linearised by central finite differences, is the declared covariance."""
    n, rmin, rmax = 5, 0.5, 5.0
    sig_odo, sig_obs = (0.05, 0.02, 0.01), (0.05, 0.01)
    kwargs = dict(seed=21, min_shared=0, noiseless=True, odometry_noise=sig_odo, sensor_noise=sig_obs,
                  sensor_range=rmax, min_range=rmin)
    sim = simulate(6, steps_per_map=n, **kwargs)
    steps = simulate(6 * n, steps_per_map=1, **kwargs)          # every true pose of the run
    lookup = {int(i): j for j, i in enumerate(sim.truth.feature_ids)}

    def relative(a, b):                                         # b in the frame of a, unwrapped
        return np.r_[rot(a[2]).T @ (b[:2] - a[:2]), b[2] - a[2]]

    for k in (1, 4, 6):
        local_map = sim.maps[k - 1]
        start = steps.truth.poses[(k - 1) * n]
        poses = [relative(start, steps.truth.poses[(k - 1) * n + i]) for i in range(n + 1)]
        increments = [relative(poses[i], poses[i + 1]) for i in range(n)]
        features = (sim.truth.features[[lookup[int(i)] for i in local_map.feature_ids]] - start[:2]) @ rot(start[2])
        observations = [(j, i) for i in range(n) for j in range(local_map.size)
                        if rmin <= np.linalg.norm(features[j] - poses[i][:2]) <= rmax]
        assert {j for j, _ in observations} == set(range(local_map.size))
        measured = [(np.linalg.norm(features[j] - poses[i][:2]),
                     np.arctan2(*(features[j] - poses[i][:2])[::-1]) - poses[i][2]) for j, i in observations]

        def estimate(noise: np.ndarray) -> np.ndarray:
            du, dz = noise[:3 * n].reshape(n, 3), noise[3 * n:].reshape(-1, 2)
            pose, dead_reckoned = np.zeros(3), [np.zeros(3)]
            for i in range(n):
                step = increments[i] + du[i]
                pose = np.r_[pose[:2] + rot(pose[2]) @ step[:2], pose[2] + step[2]]
                dead_reckoned.append(pose)
            total = np.zeros((local_map.size, 2))
            count = np.zeros(local_map.size)
            for (j, i), (r, b), (dr, db) in zip(observations, measured, dz):
                x = dead_reckoned[i]
                total[j] += x[:2] + (r + dr) * np.array([np.cos(x[2] + b + db), np.sin(x[2] + b + db)])
                count[j] += 1
            return np.r_[dead_reckoned[n], (total / count[:, None]).ravel()]

        sigmas = np.r_[np.tile(sig_odo, n), np.tile(sig_obs, len(observations))]
        np.testing.assert_allclose(estimate(np.zeros(len(sigmas)))[3:], features.ravel(), atol=1e-9)
        h = 1e-6
        jacobian = np.stack([(estimate(h * e) - estimate(-h * e)) / (2 * h) for e in np.eye(len(sigmas))], 1)
        expected = (jacobian * sigmas) @ (jacobian * sigmas).T
        np.testing.assert_allclose(local_map.covariance, expected, rtol=1e-5, atol=1e-9)


def chi2_interval(dof: int, alpha: float = 1e-3) -> tuple[float, float]:
    return chi2.ppf(alpha / 2, dof), chi2.ppf(1 - alpha / 2, dof)


def test_nees_matches_the_declared_covariance():
    """(est - true)^T P^-1 (est - true), summed over independent maps, is chi-square(dim)."""
    sim = simulate(400, seed=12)
    pairs = list(errors(sim))
    dof = sum(len(e) for e, _ in pairs)
    lo, hi = chi2_interval(dof)

    def total(transform) -> float:
        return sum(float(e @ np.linalg.solve(transform(p), e)) for e, p in pairs)

    assert lo <= total(lambda p: p) <= hi
    # a wrong covariance fails the same bound: 10% too large or too small
    assert not lo <= total(lambda p: 1.1 * p) <= hi
    assert not lo <= total(lambda p: p / 1.1) <= hi
    # ... or the odometry correlations dropped (keeping only the 3x3 and 2x2 diagonal blocks)
    def block_diagonal(p: np.ndarray) -> np.ndarray:
        q = np.zeros_like(p)
        q[:3, :3] = p[:3, :3]
        for j in range(3, len(p), 2):
            q[j:j + 2, j:j + 2] = p[j:j + 2, j:j + 2]
        return q
    assert not lo <= total(block_diagonal) <= hi

    # the end-pose marginal alone (3 dof per map)
    pose_nees = sum(float(e[:3] @ np.linalg.solve(p[:3, :3], e[:3])) for e, p in pairs)
    assert chi2_interval(3 * len(pairs))[0] <= pose_nees <= chi2_interval(3 * len(pairs))[1]
    # the errors are centred: mean whitened error per map is ~N(0, 1) per coordinate
    whitened = np.concatenate([np.linalg.solve(np.linalg.cholesky(p), e) for e, p in pairs])
    assert abs(whitened.mean()) < 4 / np.sqrt(len(whitened))


def test_spherical_only_maps_carry_the_same_estimates_and_marginals():
    full = simulate(25, seed=6)
    light = simulate(25, seed=6, full_covariance=False)
    for a, b in zip(full.maps, light.maps):
        assert b.covariance is None
        assert np.array_equal(a.end_pose, b.end_pose)
        assert np.array_equal(a.features, b.features)
        np.testing.assert_allclose(b.feature_variances, a.feature_variances, rtol=1e-12)
        np.testing.assert_allclose(b.pose_variances, a.pose_variances, rtol=1e-12)


def test_features_argument_sets_the_random_world_size():
    sim = simulate(12, seed=0, features=40)
    assert len(sim.truth.feature_ids) <= 40 + 3 * 12
    denser = simulate(12, seed=0, features=120)
    assert np.mean([m.size for m in denser.maps]) > 2 * np.mean([m.size for m in sim.maps])


# --- argument validation ----------------------------------------------------------------------

INVALID = [
    (dict(maps=0), "maps must be >= 1"),
    (dict(maps=-3), "maps must be >= 1"),
    (dict(maps=2.5), "maps must be an integer"),
    (dict(maps=True), "maps must be an integer"),
    (dict(seed=-1), "seed must be >= 0"),
    (dict(seed="x"), "seed must be an integer"),
    (dict(steps_per_map=0), "steps_per_map must be >= 1"),
    (dict(features=-1), "features must be >= 0"),
    (dict(laps=0), "laps must be a positive"),
    (dict(laps=0.4), "laps must be >= 0.5"),
    (dict(step_length=-1.0), "step_length must be a positive"),
    (dict(sensor_range=float("inf")), "sensor_range must be a positive"),
    (dict(min_range=0.0), "min_range must be a positive"),
    (dict(density=float("nan")), "density must be a positive"),
    (dict(sensor_range=1.4, min_range=0.5), "sensor_range must exceed min_range + step_length"),
    (dict(odometry_noise=(0.1, 0.0, 0.01)), "odometry_noise must be 3 positive"),
    (dict(odometry_noise=(0.1, 0.1)), "odometry_noise must be 3 positive"),
    (dict(sensor_noise=(-0.1, 0.01)), "sensor_noise must be 2 positive"),
    (dict(sensor_noise=None), "sensor_noise must be 2 standard deviations"),
    (dict(min_shared=-1), "min_shared must be >= 0"),
]


@pytest.mark.parametrize("kwargs,fragment", INVALID,
                         ids=[",".join(f"{k}={v!r}" for k, v in kwargs.items()) for kwargs, _ in INVALID])
def test_invalid_arguments_raise_value_error(kwargs, fragment):
    with pytest.raises(ValueError, match=re.escape(fragment)):
        simulate(**kwargs)


def test_single_map():
    sim = simulate(1, seed=0)
    assert len(sim.maps) == 1 and sim.maps[0].size >= MIN_SHARED
    assert sim.truth.poses.shape == (2, 3)


def test_empty_world_without_guarantee_gives_featureless_maps():
    sim = simulate(3, seed=0, features=0, min_shared=0)
    assert [m.size for m in sim.maps] == [0, 0, 0]
    assert len(sim.truth.feature_ids) == 0
    assert sim.maps[0].covariance.shape == (3, 3)


def test_output_does_not_depend_on_the_internal_chunk_size(monkeypatch):
    import mapjoin.simulation as module

    reference = simulate(40, seed=13)
    monkeypatch.setattr(module, "_CHUNK", 7)
    assert_same(simulate(40, seed=13), reference)
