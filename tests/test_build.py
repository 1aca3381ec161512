"""Local maps from raw data (mapjoin.raw, mapjoin.build, ``mapjoin build``).

The maps are checked against an independent solve written here: the raw SLAM problem's
residuals and analytic Jacobian, solved by ``scipy.optimize.least_squares`` from its own
dead reckoning, the covariance a dense inverse of J^T J; raw Victoria Park rows are read
with ``scipy.io.loadmat``, not with mapjoin's reader. Real data: the shipped 200 local
maps (built by others from the same rows), the known batch optimum chi^2 9012.72.
"""

from __future__ import annotations

import dataclasses
import itertools
import logging
from pathlib import Path

import numpy as np
import pytest
import scipy.io
from cli_runner import run
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.optimize import least_squares

from mapjoin import InputError
from mapjoin import io as mapio
from mapjoin.build import batch, build, cut
from mapjoin.evaluation import compare
from mapjoin.raw import RawData, _positive_definite, read_raw

VICPARK = "VicPark_200_local_maps/VicPark_clean_data.mat"
ISAM = "victoria_park_raw/victoria_park_isam.txt"


# --------------------------------------------------------------------------- independent solve


def wrap(angle):
    return (np.asarray(angle) + np.pi) % (2 * np.pi) - np.pi


def rotation_t(phi):
    """R(phi)^T per angle, (n, 2, 2)."""
    c, s = np.cos(phi), np.sin(phi)
    return np.stack([np.stack([c, s], -1), np.stack([-s, c], -1)], -2)


def solve_independently(odometry, odometry_cov, observer, feature, z, z_cov):
    """Poses 1..n after pose 0 (the origin) and the features: scipy least squares on the raw
    residuals. Returns (chi^2, poses (n, 3), feature ids, features, covariance of [pose n,
    features] from the dense inverse of J^T J)."""
    n = len(odometry)
    ids, which = np.unique(feature, return_inverse=True)
    m = len(ids)
    Wo = np.linalg.inv(np.linalg.cholesky(odometry_cov))
    Wz = np.linalg.inv(np.linalg.cholesky(z_cov)) if len(z) else np.zeros((0, 2, 2))

    def split(x):
        return np.vstack([np.zeros(3), x[:3 * n].reshape(n, 3)]), x[3 * n:].reshape(m, 2)

    def residual(x):
        poses, f = split(x)
        a, b = poses[:-1], poses[1:]
        eo = np.concatenate([np.einsum("kij,kj->ki", rotation_t(a[:, 2]), b[:, :2] - a[:, :2]) - odometry[:, :2],
                             wrap(b[:, 2] - a[:, 2] - odometry[:, 2])[:, None]], axis=1)
        o = poses[observer]
        ez = np.einsum("kij,kj->ki", rotation_t(o[:, 2]), f[which] - o[:, :2]) - z
        return np.concatenate([np.einsum("kij,kj->ki", Wo, eo).ravel(), np.einsum("kij,kj->ki", Wz, ez).ravel()])

    def jacobian(x):
        poses, f = split(x)
        J = np.zeros((3 * n + 2 * len(z), 3 * n + 2 * m))
        for k in range(n):
            a, b = poses[k], poses[k + 1]
            Rt = rotation_t(a[2:])[0]
            dRt = np.array([[-np.sin(a[2]), np.cos(a[2])], [-np.cos(a[2]), -np.sin(a[2])]])
            block = np.zeros((3, 6))                      # columns: pose a, pose b
            block[:2, :2], block[:2, 2] = -Rt, dRt @ (b[:2] - a[:2])
            block[:2, 3:5], block[2, 2], block[2, 5] = Rt, -1.0, 1.0
            rows = slice(3 * k, 3 * k + 3)
            J[rows, 3 * k:3 * k + 3] = Wo[k] @ block[:, 3:]
            if k:
                J[rows, 3 * (k - 1):3 * k] = Wo[k] @ block[:, :3]
        for i, (o, j) in enumerate(zip(observer, which)):
            p = poses[o]
            Rt = rotation_t(p[2:])[0]
            dRt = np.array([[-np.sin(p[2]), np.cos(p[2])], [-np.cos(p[2]), -np.sin(p[2])]])
            rows = slice(3 * n + 2 * i, 3 * n + 2 * i + 2)
            J[rows, 3 * n + 2 * j:3 * n + 2 * j + 2] = Wz[i] @ Rt
            if o:
                J[rows, 3 * (o - 1):3 * o] = Wz[i] @ np.column_stack([-Rt, dRt @ (f[j] - p[:2])])
        return J

    # dead reckoning, then each feature from its first observation
    poses = [np.zeros(3)]
    for d in odometry:
        p = poses[-1]
        poses.append(np.array([*(p[:2] + rotation_t(p[2:])[0].T @ d[:2]), p[2] + d[2]]))
    poses = np.array(poses)
    first = np.array([np.flatnonzero(which == j)[0] for j in range(m)], dtype=int)
    placed = poses[observer[first], :2] + np.einsum("kji,kj->ki", rotation_t(poses[observer[first], 2]), z[first]) \
        if m else np.zeros((0, 2))
    x0 = np.concatenate([poses[1:].ravel(), placed.ravel()])
    solution = least_squares(residual, x0, jac=jacobian, method="lm", xtol=1e-15, ftol=1e-15, gtol=1e-15,
                             max_nfev=2000)
    J = jacobian(solution.x)
    covariance = np.linalg.inv(J.T @ J)
    chosen = np.concatenate([3 * n - 3 + np.arange(3), 3 * n + np.arange(2 * m)])
    poses, features = split(solution.x)
    r = residual(solution.x)
    return float(r @ r), poses[1:], ids, features, covariance[np.ix_(chosen, chosen)]


def segment(raw_arrays, a, b, last):
    """The raw data of the map from chain pose a to b: its odometry, the observations from
    poses a .. b-1 (and b when it is the last pose), observers counted from a."""
    odometry, odometry_cov, observer, feature, z, z_cov = raw_arrays
    keep = (observer >= a) & ((observer < b) | ((observer == b) & last))
    return (odometry[a:b], odometry_cov[a:b], observer[keep] - a, feature[keep], z[keep], z_cov[keep])


def arrays_of(raw: RawData):
    return (raw.odometry, raw.odometry_covariances, raw.observers, raw.feature_ids, raw.observations,
            raw.observation_covariances)


def assert_maps_match_independent_solves(raw_arrays, result, bounds, spans=None):
    """Each map of ``result`` (from chain pose ``bounds[j]`` to ``bounds[j + 1]``, or ``spans[j]``)
    against the independent solve of its own data."""
    steps = len(raw_arrays[0])
    spans = spans or list(itertools.pairwise(bounds))
    for j, (local_map, (a, b)) in enumerate(zip(result.maps, spans)):
        cost, poses, ids, features, covariance = solve_independently(*segment(raw_arrays, a, b, b == steps))
        assert result.costs[j] == pytest.approx(cost, rel=1e-7, abs=1e-9)
        np.testing.assert_allclose(local_map.end_pose[:2], poses[-1, :2], rtol=0, atol=1e-7)
        assert wrap(local_map.end_pose[2] - poses[-1, 2]) == pytest.approx(0, abs=1e-8)
        np.testing.assert_array_equal(local_map.feature_ids, ids)
        np.testing.assert_allclose(local_map.features, features, rtol=0, atol=1e-7)
        np.testing.assert_allclose(local_map.covariance, covariance, rtol=1e-5,
                                   atol=1e-9 * np.abs(covariance).max())


# --------------------------------------------------------------------------- synthetic raw data


def spd(rng, d, scale):
    A = rng.normal(size=(d, d))
    return scale * (A @ A.T / d + 0.2 * np.eye(d))


def synthetic(seed: int, steps: int = 12, features: int = 6, standstill: tuple[int, ...] = (),
              blind: tuple[int, ...] = ()):
    """A random drive among random features, with noisy odometry and observations (full random
    covariances, noise drawn from them). ``standstill``: steps where the robot does not move
    (odometry and its covariance exactly zero); ``blind``: poses that observe nothing."""
    rng = np.random.default_rng(seed)
    truth = [np.zeros(3)]
    for k in range(steps):
        move = np.zeros(3) if k in standstill else np.array([rng.uniform(0.5, 1.5), rng.normal(0, 0.1),
                                                             rng.normal(0, 0.3)])
        p = truth[-1]
        truth.append(np.array([*(p[:2] + rotation_t(p[2:])[0].T @ move[:2]), p[2] + move[2]]))
    truth = np.array(truth)
    world = truth[rng.integers(0, steps + 1, features), :2] + rng.uniform(-4, 4, (features, 2))
    odometry, odometry_cov = [], []
    for k in range(steps):
        a, b = truth[k], truth[k + 1]
        true = np.array([*(rotation_t(a[2:])[0] @ (b[:2] - a[:2])), b[2] - a[2]])
        if k in standstill:
            odometry.append(true)
            odometry_cov.append(np.zeros((3, 3)))
        else:
            C = spd(rng, 3, 1e-3)
            odometry.append(true + rng.multivariate_normal(np.zeros(3), C))
            odometry_cov.append(C)
    observer, feature, z, z_cov = [], [], [], []
    for k in range(steps + 1):
        if k in blind:
            continue
        for j in range(features):
            if rng.random() < 0.6 or k == 0:
                C = spd(rng, 2, 1e-2)
                observer.append(k)
                feature.append(3 * j + 1)                 # ids that skip
                z.append(rotation_t(truth[k, 2:])[0] @ (world[j] - truth[k, :2])
                         + rng.multivariate_normal(np.zeros(2), C))
                z_cov.append(C)
    return (np.array(odometry), np.array(odometry_cov), np.array(observer, dtype=np.int64),
            np.array(feature, dtype=np.int64), np.array(z).reshape(-1, 2), np.array(z_cov).reshape(-1, 2, 2))


def isam_text(arrays, pose_ids=None) -> str:
    """The arrays as iSAM text (covariances, upper triangle by rows), observations after the odometry."""
    odometry, odometry_cov, observer, feature, z, z_cov = arrays
    ids = np.arange(len(odometry) + 1) if pose_ids is None else pose_ids
    lines = [f"ODOMETRY {ids[k]} {ids[k + 1]} {' '.join(map(repr, odometry[k].tolist()))} "
             + " ".join(repr(float(c[i, j])) for i, j in ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2)))
             for k, c in enumerate(odometry_cov)]
    lines += [f"LANDMARK {ids[o]} {f} " + " ".join(map(repr, [*z[i].tolist(), *z_cov[i][[0, 0, 1], [0, 1, 1]].tolist()]))
              for i, (o, f) in enumerate(zip(observer, feature))]
    return "\n".join(lines) + "\n"


def g2o_text(arrays) -> str:
    """The arrays as g2o 2D: vertices, then information matrices (inverse covariances)."""
    odometry, odometry_cov, observer, feature, z, z_cov = arrays
    offset = 10 ** len(str(len(odometry)))             # one id space: landmarks after the poses
    lines = [f"VERTEX_SE2 {k} 0 0 0" for k in range(len(odometry) + 1)]
    lines += [f"VERTEX_XY {offset + f} 0 0" for f in np.unique(feature)]
    lines.append("FIX 0")
    for k, d in enumerate(odometry):
        info = np.linalg.inv(odometry_cov[k])
        lines.append(f"EDGE_SE2 {k} {k + 1} " + " ".join(map(repr, d.tolist())) + " "
                     + " ".join(repr(float(info[i, j])) for i, j in ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))))
    for i, (o, f) in enumerate(zip(observer, feature)):
        info = np.linalg.inv(z_cov[i])
        lines.append(f"EDGE_SE2_XY {o} {offset + f} "
                     + " ".join(map(repr, [*z[i].tolist(), *info[[0, 0, 1], [0, 1, 1]].tolist()])))
    return "\n".join(lines) + "\n"


def write(tmp_path: Path, name: str, text: str) -> str:
    path = tmp_path / name
    path.write_text(text)
    return str(path)


# --------------------------------------------------------------------------- correctness


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 10**6), steps=st.integers(2, 14), count=st.integers(1, 4), by_poses=st.booleans())
def test_built_maps_are_the_independent_least_squares_solutions(tmp_path_factory, seed, steps, count, by_poses):
    arrays = synthetic(seed, steps)
    path = write(tmp_path_factory.mktemp("raw"), "run.txt", isam_text(arrays))
    raw = read_raw(path)
    bounds = cut(steps, poses_per_map=count) if by_poses else cut(steps, maps=min(count, steps))
    result = build(raw, bounds)
    assert result.converged and len(result.maps) == len(bounds) - 1
    assert [(m.start_id, m.end_id) for m in result.maps] == [(j, j + 1) for j in range(len(bounds) - 1)]
    assert_maps_match_independent_solves(arrays, result, bounds)
    assert np.array_equal(result.degrees_of_freedom, result.residuals - result.unknowns)


def test_long_maps_built_from_joined_pieces_equal_direct_solves(tmp_path):
    """The piecewise start (pieces of 3 steps, certified joins, refinement) and dead
    reckoning reach the same maps; the independent solve agrees."""
    arrays = synthetic(5, steps=30, features=10)
    raw = read_raw(write(tmp_path, "run.txt", isam_text(arrays)))
    bounds = cut(30, maps=2)
    direct, pieces = build(raw, bounds), build(raw, bounds, piece_steps=3)
    assert direct.pieces == 0 and pieces.pieces == 10
    np.testing.assert_allclose(pieces.costs, direct.costs, rtol=1e-9)
    for a, b in zip(direct.maps, pieces.maps):
        np.testing.assert_allclose(b.end_pose, a.end_pose, rtol=0, atol=1e-8)
        np.testing.assert_allclose(b.features, a.features, rtol=0, atol=1e-8)
        np.testing.assert_allclose(b.covariance, a.covariance, rtol=1e-6, atol=1e-12)
    assert_maps_match_independent_solves(arrays, pieces, bounds)


def test_batch_is_one_map_with_every_pose(tmp_path):
    arrays = synthetic(9, steps=10)
    raw = read_raw(write(tmp_path, "run.txt", isam_text(arrays)))
    solution = batch(raw)
    cost, poses, ids, features, _ = solve_independently(*arrays)
    assert solution.cost == pytest.approx(cost, rel=1e-9)
    assert solution.degrees_of_freedom == 3 * 10 + 2 * len(arrays[4]) - 3 * 10 - 2 * len(ids)
    np.testing.assert_array_equal(solution.global_map.pose_ids, np.arange(1, 11))
    np.testing.assert_allclose(solution.global_map.poses[:, :2], poses[:, :2], rtol=0, atol=1e-7)
    np.testing.assert_allclose(solution.global_map.features, features, rtol=0, atol=1e-7)
    # at the built maps' end poses, labelled as the maps are
    bounds = cut(10, maps=3)
    ends = batch(raw, bounds, covariances=False).global_map
    np.testing.assert_allclose(ends.poses[:, :2], poses[bounds[1:] - 1, :2], rtol=0, atol=1e-7)
    np.testing.assert_array_equal(ends.pose_ids, [1, 2, 3])


def test_a_blind_stretch_a_standstill_and_the_last_pose(tmp_path, caplog):
    """Poses 4-7 observe nothing (map 2 sees no feature: written with its end pose only, with
    a warning); the robot stands still on step 9 (zero odometry covariance: 1e-6 added to
    its diagonal, with a warning naming the line); the last pose's observations are in the
    last map."""
    arrays = synthetic(3, steps=12, standstill=(9,), blind=(4, 5, 6, 7))
    path = write(tmp_path, "run.txt", isam_text(arrays))
    with caplog.at_level(logging.WARNING, logger="mapjoin"):
        raw = read_raw(path)
        assert "1 odometry covariance with a variance below 1e-06" in caplog.text and "line 10" in caplog.text
        result = build(raw, [0, 4, 8, 12])
    assert "1 local map without a feature" in caplog.text
    assert result.maps[1].size == 0 and result.maps[1].covariance.shape == (3, 3)
    np.testing.assert_allclose(raw.odometry_covariances[9], 1e-6 * np.eye(3))
    stabilised = list(arrays)
    stabilised[1] = raw.odometry_covariances
    assert_maps_match_independent_solves(stabilised, result, [0, 4, 8, 12])
    last = arrays[2] == 12
    assert last.any() and set(arrays[3][last]) <= set(result.maps[-1].feature_ids)


def assert_same_maps(a, b, tolerance=1e-12):
    """Two builds' maps: the same numbering, names and features; estimates to ``tolerance``
    (m, rad), covariances to ``tolerance`` relative to each map's largest entry."""
    assert [(m.name, m.start_id, m.end_id) for m in a.maps] == [(m.name, m.start_id, m.end_id) for m in b.maps]
    for x, y in zip(a.maps, b.maps):
        np.testing.assert_array_equal(x.feature_ids, y.feature_ids)
        np.testing.assert_allclose(y.end_pose, x.end_pose, rtol=0, atol=tolerance)
        np.testing.assert_allclose(y.features, x.features, rtol=0, atol=tolerance)
        np.testing.assert_allclose(y.covariance, x.covariance, rtol=0, atol=tolerance * np.abs(x.covariance).max())
    np.testing.assert_allclose(b.costs, a.costs, rtol=tolerance, atol=tolerance * a.costs.max())
    np.testing.assert_array_equal(b.residuals, a.residuals)
    np.testing.assert_array_equal(b.unknowns, a.unknowns)


@pytest.mark.parametrize("jobs", [2, 9])
def test_jobs_build_the_maps_of_one_process(tmp_path, jobs):
    """Runs of consecutive maps built in worker processes (a blind map, maps long enough to
    be built from pieces, the last pose's observations in the last run): the maps one process
    builds and the independent solve's. Each run's solve stops on its own, so one may skip
    a last step below the step tolerance (1e-10 (1 + max |x|)) that one process takes:
    agreement to 1e-8 here (1e-12 on Victoria Park, below). The batch solution started from
    them is the same optimum."""
    arrays = synthetic(3, steps=16, blind=(4, 5, 6, 7))
    raw = read_raw(write(tmp_path, "run.txt", isam_text(arrays)))
    bounds = [0, 4, 8, 11, 16]
    one = build(raw, bounds, piece_steps=2, with_batch=True)
    several = build(raw, bounds, jobs=jobs, piece_steps=2, with_batch=True)
    assert one.pieces == several.pieces == 9 and several.converged
    assert_same_maps(one, several, 1e-8)
    assert_maps_match_independent_solves(arrays, several, bounds)
    assert several.batch.cost == pytest.approx(one.batch.cost, rel=1e-12)
    np.testing.assert_allclose(several.batch.global_map.poses, one.batch.global_map.poses, rtol=0, atol=1e-9)
    with pytest.raises(ValueError, match="jobs must be at least 1"):
        build(raw, bounds, jobs=0)


def test_noise_free_data_gives_the_true_relative_poses(tmp_path):
    arrays = list(synthetic(4, steps=8))
    odometry, _, observer, feature, z, _ = arrays
    poses = [np.zeros(3)]
    for d in odometry:
        p = poses[-1]
        poses.append(np.array([*(p[:2] + rotation_t(p[2:])[0].T @ d[:2]), p[2] + d[2]]))
    poses = np.array(poses)
    # observations made consistent with the (noisy) odometry as the truth
    first = {f: poses[o, :2] + rotation_t(poses[o, 2:])[0].T @ z[i]
             for i, (o, f) in reversed(list(enumerate(zip(observer, feature))))}
    arrays[4] = np.array([rotation_t(poses[o, 2:])[0] @ (first[f] - poses[o, :2]) for o, f in zip(observer, feature)])
    raw = read_raw(write(tmp_path, "run.txt", isam_text(arrays)))
    result = build(raw, [0, 3, 8])
    assert result.cost == pytest.approx(0, abs=1e-12)
    end = poses[3]
    np.testing.assert_allclose(result.maps[0].end_pose, end, atol=1e-9)
    relative = rotation_t(end[2:])[0] @ (poses[8, :2] - end[:2])
    np.testing.assert_allclose(result.maps[1].end_pose[:2], relative, atol=1e-9)


# --------------------------------------------------------------------------- formats


def test_isam_and_g2o_readers_agree_and_read_the_numbers(tmp_path):
    arrays = synthetic(7, steps=6)
    pose_ids = np.array([0, 1, 2, 4, 7, 8, 9])                  # iSAM pose ids may skip
    isam = read_raw(write(tmp_path, "run.txt", isam_text(arrays, pose_ids)))
    g2o = read_raw(write(tmp_path, "run.g2o", g2o_text(arrays)))
    np.testing.assert_array_equal(isam.pose_ids, pose_ids)
    np.testing.assert_array_equal(g2o.pose_ids, np.arange(7))
    for raw in (isam, g2o):
        np.testing.assert_array_equal(raw.odometry, arrays[0])
        np.testing.assert_array_equal(raw.observers, arrays[2])
        np.testing.assert_allclose(raw.odometry_covariances, arrays[1], rtol=1e-12)
        np.testing.assert_allclose(raw.observation_covariances, arrays[5], rtol=1e-12)
    np.testing.assert_array_equal(isam.feature_ids, arrays[3])
    np.testing.assert_array_equal(g2o.feature_ids, 10 + arrays[3])
    a, b = build(isam, [0, 3, 6]), build(g2o, [0, 3, 6])
    np.testing.assert_allclose(a.costs, b.costs, rtol=1e-9)
    assert a.maps[1].name.endswith("run.txt poses 4-9")


@settings(max_examples=100, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), size=st.integers(1, 4))
def test_positive_definiteness_by_pivots_equals_the_eigenvalues(seed, size):
    """The readers' check of covariance and information matrices (pivots of elimination)
    against the smallest eigenvalue (away from zero, where rounding may decide either way)."""
    rng = np.random.default_rng(seed)
    X = rng.normal(size=(200, size, size))
    S = X + X.transpose(0, 2, 1) + rng.uniform(-1, 4, (200, 1, 1)) * np.eye(size)
    smallest = np.linalg.eigvalsh(S)[:, 0]
    clear = np.abs(smallest) > 1e-9
    np.testing.assert_array_equal(_positive_definite(S)[clear], (smallest > 0)[clear])
    assert not _positive_definite(np.full((1, size, size), np.nan)).any()


def test_vicpark_rows_are_read_as_documented(data_dir):
    rows = scipy.io.loadmat(data_dir / VICPARK)["VicPark_clean_data"]
    raw = read_raw(str(data_dir / VICPARK))
    odometry, observation = rows[rows[:, 0] == 1], rows[rows[:, 0] == 0]
    assert raw.steps == len(odometry) == 6898 and len(raw.observations) == len(observation) == 45390
    np.testing.assert_array_equal(raw.pose_ids, np.arange(6899))
    np.testing.assert_array_equal(raw.odometry, odometry[:, 3:6])
    np.testing.assert_array_equal(raw.odometry_covariances[:, 0, 2], odometry[:, 8])
    np.testing.assert_array_equal(raw.odometry_covariances[:, 2, 1], odometry[:, 10])
    np.testing.assert_array_equal(raw.observation_covariances[:, 1, 0], observation[:, 6])
    np.testing.assert_array_equal(raw.feature_ids, observation[:, 2])
    assert raw.where(raw.observation_lines[0]) == "VicPark_clean_data row 1"


def vicpark_subset(data_dir, steps):
    """The first ``steps`` odometry steps of Victoria Park and the observations from their poses,
    as read by scipy.io.loadmat (arrays) and as mapjoin's RawData (sliced)."""
    rows = scipy.io.loadmat(data_dir / VICPARK)["VicPark_clean_data"]
    odometry, observation = rows[rows[:, 0] == 1][:steps], rows[rows[:, 0] == 0]
    observation = observation[observation[:, 1] <= steps]
    upper = lambda r, entries: np.array([[[r[c] for c in row] for row in entries] for r in r])
    arrays = (odometry[:, 3:6], upper(odometry[:, 6:12], [[0, 1, 2], [1, 3, 4], [2, 4, 5]]),
              observation[:, 1].astype(np.int64), observation[:, 2].astype(np.int64), observation[:, 3:5],
              upper(observation[:, 5:8], [[0, 1], [1, 2]]))
    raw = read_raw(str(data_dir / VICPARK))
    keep = raw.observers <= steps
    sub = dataclasses.replace(raw, pose_ids=raw.pose_ids[:steps + 1], odometry=raw.odometry[:steps],
                              odometry_covariances=raw.odometry_covariances[:steps],
                              odometry_lines=raw.odometry_lines[:steps], observers=raw.observers[keep],
                              feature_ids=raw.feature_ids[keep], observations=raw.observations[keep],
                              observation_covariances=raw.observation_covariances[keep],
                              observation_lines=raw.observation_lines[keep])
    return arrays, sub


def test_vicpark_subset_against_scipy_and_as_g2o(data_dir, tmp_path):
    """The first 60 steps (about 400 observations) in 2 maps, against the independent solve;
    the same rows written as g2o (information matrices) give the same maps."""
    arrays, raw = vicpark_subset(data_dir, 60)
    assert len(raw.observations) > 350
    bounds = cut(60, maps=2)
    result = build(raw, bounds)
    assert_maps_match_independent_solves(arrays, result, bounds)
    again = build(read_raw(write(tmp_path, "vp.g2o", g2o_text(arrays))), bounds)
    np.testing.assert_allclose(again.costs, result.costs, rtol=1e-8)
    for a, b in zip(result.maps, again.maps):
        np.testing.assert_allclose(b.features, a.features, rtol=0, atol=1e-8)
        np.testing.assert_allclose(b.covariance, a.covariance, rtol=1e-6, atol=1e-14)


def test_vicpark_200_maps_are_the_shipped_ones(data_dir):
    """The shipped 200 local maps were cut and solved from the same rows by I-SLSJF's code:
    the same cut points, and, for all but a couple of maps, the same estimates and
    covariances to rounding. Where a shipped map differs (maps 50 and 51: by 0.5 m), the
    independent solve sides with the built one."""
    raw = read_raw(str(data_dir / VICPARK))
    bounds = cut(raw.steps, maps=200)
    built = build(raw, bounds)
    shipped = mapio.read_maps([str(data_dir / "VicPark_200_local_maps")])
    differing = []
    for j, (b, s) in enumerate(zip(built.maps, shipped)):
        order = np.argsort(s.feature_ids)                       # shipped: in order of first sighting
        state = np.concatenate([np.arange(3), (3 + 2 * order[:, None] + np.arange(2)).ravel()])
        covariance = s.covariance[np.ix_(state, state)]
        deviation = np.sqrt(np.diag(covariance))
        if (np.array_equal(b.feature_ids, s.feature_ids[order]) and np.allclose(b.end_pose, s.end_pose, atol=1e-5)
                and np.allclose(b.features, s.features[order], atol=1e-4)):
            assert np.abs(b.covariance - covariance).max() / np.outer(deviation, deviation).max() < 1e-4
        else:
            differing.append(j)
    assert len(differing) <= 2, differing
    one = dataclasses.replace(built, maps=[built.maps[j] for j in differing], costs=built.costs[differing])
    assert_maps_match_independent_solves(arrays_of(raw), one, None, [(bounds[j], bounds[j + 1]) for j in differing])


def test_vicpark_200_maps_with_two_jobs(data_dir):
    """Two worker processes, 100 maps each, build the maps one process builds (to rounding)."""
    raw = read_raw(str(data_dir / VICPARK))
    bounds = cut(raw.steps, maps=200)
    assert_same_maps(build(raw, bounds), build(raw, bounds, jobs=2))


def test_vicpark_batch_is_the_global_optimum(data_dir):
    """The batch solution (from the 200 built maps, and --maps 1 from pieces of 50 steps):
    chi^2 9012.72, the optimum I-SLSJF and the independent oracle reach for the exact join
    of the 6898 one-step maps (README), which is this problem. The exact join of the 200
    built maps lands close to it (the paper's metric)."""
    raw = read_raw(str(data_dir / VICPARK))
    built = build(raw, cut(raw.steps, maps=200), with_batch=True)
    solution = built.batch
    assert solution.converged and solution.cost == pytest.approx(9012.72, abs=0.005)
    assert solution.degrees_of_freedom == 3 * 6898 + 2 * 45390 - 3 * 6898 - 2 * 299
    one = build(raw, cut(raw.steps, maps=1))
    assert one.pieces > 1 and one.cost == pytest.approx(solution.cost, rel=1e-9)
    np.testing.assert_allclose(one.maps[0].end_pose[:2], solution.global_map.poses[-1, :2], atol=1e-7)
    np.testing.assert_allclose(one.maps[0].features, solution.global_map.features, atol=1e-7)
    from mapjoin.refine import refine

    joined = refine(built.maps, covariances=False).global_map
    difference = compare(solution.global_map, joined)
    assert difference.poses == 200 and difference.mean_abs_x < 0.05 and difference.mean_abs_phi < 0.001


# --------------------------------------------------------------------------- bad input


BAD_TEXT = [
    ("ODOMETRY 0 1 1 0 0 1 0 0 1 0 1\nFOO 1 2\n", "line 2: unknown tag 'FOO'"),
    ("ODOMETRY 0 1 1 0 0 1 0 0 1 0\n", "line 1: expected 11 numbers after ODOMETRY, got 10"),
    ("ODOMETRY 0 1 1 0 x 1 0 0 1 0 1\n", "line 1: expected a number, got 'x'"),
    ("ODOMETRY 0 1 1 0 0 1 0 0 1 0 1\nODOMETRY 2 3 1 0 0 1 0 0 1 0 1\n",
     "line 2: odometry from pose 2 to pose 3: expected it to start at pose 1"),
    ("ODOMETRY 0 1 1 0 0 1 0 0 1 0 1\nODOMETRY 1 0 1 0 0 1 0 0 1 0 1\n",
     "line 2: odometry to pose 0, which is already a pose of the chain"),
    ("ODOMETRY 0 1 1 0 0 1 0 0 1 0 1\nLANDMARK 5 9 1 1 1 0 1\n",
     "line 2: observation of feature 9 from pose 5, which is not a pose of the odometry chain"),
    ("ODOMETRY 0 1 1 0 0 1 0 0 1 0 1\nLANDMARK 1 9 1 1 1 0 1\nLANDMARK 1 9 1 1 1 0 1\n",
     "line 3: feature 9 is observed from pose 1 twice (also line 2)"),
    ("ODOMETRY 0 1 1 0 0 1 2 0 1 0 1\n", "line 1: odometry covariance is not positive definite"),
    ("ODOMETRY 0 1 1 0 0 1 0 0 1 0 1\nLANDMARK 1 9 1 1 -1 0 1\n",
     "line 2: observation covariance is not positive definite"),
    ("ODOMETRY 0 1.5 1 0 0 1 0 0 1 0 1\n", "line 1: expected a non-negative integer pose id, got 1.5"),
    ("ODOMETRY 0 1 nan 0 0 1 0 0 1 0 1\n", "line 1: expected a finite odometry"),
    ("LANDMARK 0 9 1 1 1 0 1\n", "no odometry"),
    ("# nothing\n", "cannot tell the raw format"),
]
BAD_G2O = [
    ("VERTEX_SE2 0 0 0 0\nEDGE_SE2 0 1 1 0 0 1 0 0 1 0 1\n", "line 2: vertex 1 is not declared by a VERTEX_SE2 line"),
    ("VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 0 0 0\nEDGE_SE2 0 1 1 0 0 1 0 0 0 0 1\n",
     "line 3: EDGE_SE2 information matrix is not positive definite"),
    ("VERTEX_SE2 0 0 0 0\nVERTEX_XY 0 0 0\n", "line 2: vertex 0 is declared twice"),
    ("VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 0 0 0\nEDGE_SE2 0 1 1 0 0 1 0 0 1 0 1\nEDGE_SE2_XY 1 7 1 1 1 0 1\n",
     "line 4: vertex 7 is not declared by a VERTEX_XY line"),
    ("VERTEX_SE2 0 0 0 0\nEDGE_SE3:QUAT 0 1\n", "line 2: unknown tag 'EDGE_SE3:QUAT'"),
]


@pytest.mark.parametrize(("text", "message"), BAD_TEXT + [(t, m) for t, m in BAD_G2O])
def test_bad_raw_input_is_one_line_naming_file_and_line(tmp_path, text, message):
    name = "bad.g2o" if (text, message) in BAD_G2O else "bad.txt"
    path = write(tmp_path, name, text)
    with pytest.raises(InputError, match="^" + str(tmp_path).replace("\\", "\\\\")) as error:
        read_raw(path)
    assert message in str(error.value)
    result = run("build", path, "-o", str(tmp_path / "out"))
    assert result.exit_code == 1 and message in result.stderr and "Traceback" not in result.output
    assert len(result.stderr.strip().splitlines()) == 1


def test_bad_mat_files(tmp_path, data_dir):
    data = (data_dir / VICPARK).read_bytes()
    cases = {"cut.mat": data[:1000], "other.mat": (data_dir / "VicPark_200_local_maps/localmap_1.mat").read_bytes(),
             "flipped.mat": data[:200] + bytes([data[200] ^ 0x40]) + data[201:]}
    messages = {"cut.mat": "truncated .mat file", "other.mat": "missing; expected the variable VicPark_clean_data",
                "flipped.mat": ""}
    for name, content in cases.items():
        path = tmp_path / name
        path.write_bytes(content)
        result = run("build", str(path), "-o", str(tmp_path / "out"))
        assert result.exit_code == 1 and "Traceback" not in result.output, result.output
        assert str(path) in result.stderr and messages[name] in result.stderr


def test_impossible_cuts(tmp_path):
    path = write(tmp_path, "run.txt", isam_text(synthetic(1, steps=5)))
    result = run("build", path, "-o", str(tmp_path / "out"), "--maps", "6")
    assert result.exit_code == 1 and "cannot cut 5 odometry steps into 6 local maps" in result.stderr
    result = run("build", path, "-o", str(tmp_path / "out"), "--maps", "2", "--poses-per-map", "2")
    assert result.exit_code == 2 and "not both" in result.output


# --------------------------------------------------------------------------- command line


def test_cli_builds_a_folder_that_joins(tmp_path):
    arrays = synthetic(11, steps=20, features=8)
    path = write(tmp_path, "run.g2o", g2o_text(arrays))
    out = tmp_path / "maps"
    result = run("-v", "build", path, "-o", str(out), "--poses-per-map", "5", "--global-map", str(tmp_path / "b.csv"))
    assert result.exit_code == 0, result.output
    assert "iteration 0: chi^2 = " in result.stderr and "built 4 local maps from" in result.stderr
    assert "batch solution: chi^2 " in result.stderr
    assert sorted(p.name for p in out.iterdir()) == [f"localmap_{k}.yaml" for k in (1, 2, 3, 4)]
    maps = mapio.read_maps([str(out)])
    assert all(m.covariance is not None for m in maps)
    joined = run("join", str(out), "--refine", "-o", str(tmp_path / "j.csv"))
    assert joined.exit_code == 0, joined.output
    difference = compare(mapio.read_global_map(str(tmp_path / "b.csv")),
                         mapio.read_global_map(str(tmp_path / "j.csv")))
    assert difference.poses == 4 and difference.mean_abs_x < 0.05
    # a stale map of another cut is refused; the same cut again is fine
    assert run("build", path, "-o", str(out), "--poses-per-map", "10").exit_code == 1
    assert run("build", path, "-o", str(out), "--poses-per-map", "5").exit_code == 0
    csv = run("build", path, "-o", "-", "--maps", "2", "--format", "csv")
    assert csv.exit_code == 0 and csv.stdout.startswith("map,start_id,end_id,kind")
    parallel = run("build", path, "-o", str(tmp_path / "two.csv"), "--maps", "2", "-j", "2")
    assert parallel.exit_code == 0, parallel.output
    assert run("build", path, "-o", str(tmp_path / "one.csv"), "--maps", "2").exit_code == 0
    for a, b in zip(mapio.read_maps([str(tmp_path / "one.csv")]), mapio.read_maps([str(tmp_path / "two.csv")])):
        assert (a.start_id, a.end_id) == (b.start_id, b.end_id)
        np.testing.assert_allclose(b.features, a.features, rtol=0, atol=1e-8)
    assert run("build", path, "-o", "-", "-j", "0").exit_code == 2
