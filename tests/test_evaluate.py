"""Comparing global maps, evaluating them against ground truth (errors, NEES), the truth of the
I-SLSJF simulation folders, and the compare/evaluate commands."""

from __future__ import annotations

import json
import math
import shutil

import numpy as np
import pytest
import scipy.io
from cli_runner import run
from click.testing import CliRunner
from scipy.stats import chi2

from mapjoin import io as mapio
from mapjoin.cli import main
from mapjoin.errors import InputError
from mapjoin.evaluation import CHI2_LEVEL, chi2_interval, chi2_verdict, compare, evaluate, nees_bounds
from mapjoin.io.matfile import variables as mat_variables
from mapjoin.joining import join_sequential
from mapjoin.maps import GlobalMap, GroundTruth
from mapjoin.se2 import wrap
from mapjoin.simulation import simulate

SIMULATIONS = ("535_data_5_local_maps", "8240_data_50_local_maps")


def global_map(feature_ids, features, pose_ids, poses, feature_variances=None, pose_variances=None,
               feature_covariances=None, pose_covariances=None, name="map") -> GlobalMap:
    features, poses = np.asarray(features, float).reshape(-1, 2), np.asarray(poses, float).reshape(-1, 3)
    return GlobalMap(
        np.asarray(feature_ids), features,
        np.ones(len(features)) if feature_variances is None else feature_variances,
        np.asarray(pose_ids), poses, np.ones((len(poses), 2)) if pose_variances is None else pose_variances,
        feature_covariances=feature_covariances, pose_covariances=pose_covariances, name=name)


# ---------------------------------------------------------------------------------------
# compare


A = global_map([1, 2], [[1, 0], [0, 2]], [1], [[2, 2, 0.5]], name="a")


def test_compare_identical_maps_gives_zeros():
    difference = compare(A, A)
    assert (difference.features, difference.poses) == (2, 1)
    for name in ("mean_abs_x", "mean_abs_y", "mean_abs_phi", "rms_xy", "max_xy", "rms_phi", "max_phi"):
        assert getattr(difference, name) == 0.0, name


def test_compare_a_rotated_and_shifted_map_by_hand():
    # B = A rotated by +90 degrees about the origin, then moved by (1, 0):
    # (1,0) -> (0,1) -> (1,1); (0,2) -> (-2,0) -> (-1,0); pose (2,2) -> (-2,2) -> (-1,2), phi + pi/2
    b = global_map([1, 2], [[1, 1], [-1, 0]], [1], [[-1, 2, 0.5 + math.pi / 2]], name="b")
    d = compare(A, b)
    # differences B - A: (0, 1), (-1, -2), (-3, 0); distances 1, sqrt 5, 3
    assert d.mean_abs_x == pytest.approx(4 / 3)
    assert d.mean_abs_y == pytest.approx(1.0)
    assert d.mean_abs_phi == pytest.approx(math.pi / 2)
    assert d.rms_xy == pytest.approx(math.sqrt((1 + 5 + 9) / 3))
    assert d.max_xy == pytest.approx(3.0)
    assert d.rms_phi == pytest.approx(math.pi / 2) and d.max_phi == pytest.approx(math.pi / 2)
    assert compare(b, A) == d  # symmetric in absolute values


def test_compare_wraps_angles_across_plus_minus_pi():
    a = global_map([], [], [1, 2], [[0, 0, math.pi - 0.01], [0, 0, -math.pi + 0.005]])
    b = global_map([], [], [1, 2], [[0, 0, -math.pi + 0.02], [0, 0, math.pi - 0.015]])
    d = compare(a, b)
    assert d.mean_abs_phi == pytest.approx(0.025)
    assert d.max_phi == pytest.approx(0.03)
    assert d.rms_phi == pytest.approx(math.sqrt((0.03 ** 2 + 0.02 ** 2) / 2))
    assert d.features == 0 and d.mean_abs_x == 0.0


def test_compare_counts_only_shared_ids():
    a = global_map([1, 2, 3], [[0, 0], [1, 1], [2, 2]], [1, 2], [[0, 0, 0], [5, 5, 1]])
    b = global_map([4, 3, 2], [[100, 100], [2, 3], [1, 1]], [3, 2], [[-50, 9, 2], [5, 5, 1.5]])
    d = compare(a, b)
    assert (d.features, d.poses) == (2, 1)
    # feature 3: (0, 1); feature 2: (0, 0); pose 2: (0, 0, 0.5)
    assert d.mean_abs_x == 0.0 and d.mean_abs_y == pytest.approx(1 / 3)
    assert d.max_xy == pytest.approx(1.0) and d.mean_abs_phi == pytest.approx(0.5)


def test_compare_without_a_shared_id_is_an_error():
    a = global_map([1], [[0, 0]], [1], [[0, 0, 0]], name="a.csv")
    b = global_map([2], [[0, 0]], [2], [[0, 0, 0]], name="b.csv")
    with pytest.raises(InputError, match="a.csv: shares no feature or pose id with b.csv"):
        compare(a, b)


# ---------------------------------------------------------------------------------------
# evaluate


def test_evaluate_a_noiseless_joined_simulation_is_exact():
    simulation = simulate(20, seed=4, noiseless=True)
    result = evaluate(join_sequential(simulation.maps).global_map, simulation.truth)
    assert result.alignment.startswith("none")
    assert result.features == len(simulation.truth.feature_ids) and result.poses == 20
    for name in ("feature_rms", "feature_max", "pose_rms_xy", "pose_max_xy", "pose_rms_phi", "pose_max_phi"):
        assert getattr(result, name) < 1e-9, name


def _random_covariances(rng, count: int, size: int, scale: float) -> np.ndarray:
    """Random SPD blocks with correlations and uneven axes."""
    factors = rng.normal(size=(count, size, size)) * scale
    return factors @ factors.transpose(0, 2, 1) + np.eye(size) * scale ** 2 * 0.1


def _noisy_map(truth: GroundTruth, seed: int, full: bool) -> tuple[GlobalMap, dict]:
    """The truth plus errors drawn from known covariances (full blocks, or spherical variances)."""
    rng = np.random.default_rng(seed)
    n, p = len(truth.feature_ids), len(truth.pose_ids)
    if full:
        feature_cov = _random_covariances(rng, n, 2, 0.1)
        pose_cov = _random_covariances(rng, p, 3, 0.05)
    else:
        feature_var = rng.uniform(0.001, 0.05, n)
        pose_var = np.column_stack([rng.uniform(0.001, 0.05, p), rng.uniform(1e-4, 1e-2, p)])
        feature_cov = feature_var[:, None, None] * np.eye(2)
        pose_cov = np.zeros((p, 3, 3))
        pose_cov[:, 0, 0] = pose_cov[:, 1, 1] = pose_var[:, 0]
        pose_cov[:, 2, 2] = pose_var[:, 1]
    feature_error = np.einsum("nij,nj->ni", np.linalg.cholesky(feature_cov), rng.standard_normal((n, 2)))
    pose_error = np.einsum("nij,nj->ni", np.linalg.cholesky(pose_cov), rng.standard_normal((p, 3)))
    poses = truth.poses + pose_error
    poses[:, 2] = wrap(poses[:, 2])
    covariances = (dict(feature_covariances=feature_cov, pose_covariances=pose_cov) if full else
                   dict(feature_variances=feature_var, pose_variances=pose_var))

    def make(scale: float) -> GlobalMap:
        scaled = {key: value * scale for key, value in covariances.items()}
        if full:
            scaled |= dict(feature_variances=np.ones(n), pose_variances=np.ones((p, 2)))
        return GlobalMap(truth.feature_ids, truth.features + feature_error, pose_ids=truth.pose_ids, poses=poses,
                         **scaled)

    return make(1.0), {"scaled": make(0.1), "inflated": make(10.0)}


@pytest.fixture(scope="module")
def sim_truth() -> GroundTruth:
    return simulate(40, seed=0).truth      # 216 features, 41 poses (some near phi = +-pi)


@pytest.mark.parametrize("full", [False, True], ids=["spherical", "full-blocks"])
def test_nees_passes_with_the_true_covariances_and_fails_when_they_are_scaled(sim_truth, full):
    inside = {"features": 0, "poses": 0}
    draws = 200
    for seed in range(draws):
        correct, wrong = _noisy_map(sim_truth, seed, full)
        result = evaluate(correct, sim_truth)
        low, high = result.nees_bounds_features
        features_pass = low < result.nees_features < high
        low, high = result.nees_bounds_poses
        poses_pass = low < result.nees_poses < high
        assert result.consistent == (features_pass and poses_pass)
        inside["features"] += features_pass
        inside["poses"] += poses_pass
        overconfident = evaluate(wrong["scaled"], sim_truth)
        assert overconfident.nees_features == pytest.approx(10 * result.nees_features)
        assert overconfident.nees_features > overconfident.nees_bounds_features[1]
        assert overconfident.nees_poses > overconfident.nees_bounds_poses[1]
        assert overconfident.consistent is False
        conservative = evaluate(wrong["inflated"], sim_truth)
        assert conservative.nees_features < conservative.nees_bounds_features[0]
        assert conservative.consistent is False
    # two-sided 95% bounds: about 95% of the draws with the true covariances pass (binomial sd 1.5%)
    assert 0.90 <= inside["features"] / draws <= 0.99 and 0.90 <= inside["poses"] / draws <= 0.99
    result = evaluate(_noisy_map(sim_truth, 0, full)[0], sim_truth)
    assert result.consistent is True and 1.8 < result.nees_features < 2.2 and 2.5 < result.nees_poses < 3.5


def test_nees_uses_full_blocks_when_present_else_spherical_variances():
    truth = GroundTruth([7], [[0.0, 0.0]], [0, 1], [[0, 0, 0], [1, 0, 0]])
    block = np.array([[4.0, 0.0], [0.0, 0.25]])
    spherical = global_map([7], [[0.0, 1.0]], [1], [[1, 0, 0.1]], feature_variances=[0.5],
                           pose_variances=[[1.0, 0.01]])
    full = global_map([7], [[0.0, 1.0]], [1], [[1, 0, 0.1]], feature_variances=[0.5],
                      pose_variances=[[1.0, 0.01]], feature_covariances=block[None],
                      pose_covariances=np.diag([1.0, 1.0, 0.04])[None])
    assert evaluate(spherical, truth).nees_features == pytest.approx(1 / 0.5)
    assert evaluate(spherical, truth).nees_poses == pytest.approx(0.01 / 0.01)
    assert evaluate(full, truth).nees_features == pytest.approx(1 / 0.25)
    assert evaluate(full, truth).nees_poses == pytest.approx(0.01 / 0.04)


def test_nees_bounds_are_chi_square_quantiles_of_the_average():
    assert nees_bounds(2, 50) == (pytest.approx(chi2.ppf(0.025, 100) / 50), pytest.approx(chi2.ppf(0.975, 100) / 50))
    truth = simulate(10, seed=1).truth
    result = evaluate(_noisy_map(truth, 1, False)[0], truth)
    n, p = len(truth.feature_ids), len(truth.pose_ids)
    assert result.nees_bounds_features == nees_bounds(2, n)
    assert result.nees_bounds_poses == pytest.approx((chi2.ppf(0.025, 3 * p) / p, chi2.ppf(0.975, 3 * p) / p))


def test_chi2_verdict_places_each_value_against_its_interval_and_skips_no_degrees_of_freedom():
    low, high = chi2_interval(100, CHI2_LEVEL)
    assert (low, high) == (pytest.approx(chi2.ppf(0.0005, 100)), pytest.approx(chi2.ppf(0.9995, 100)))
    verdict = chi2_verdict([low / 2, 100.0, 2 * high, 5.0], [100, 100, 100, 0])
    assert verdict.too_small.tolist() == [True, False, False, False]
    assert verdict.too_large.tolist() == [False, False, True, False]
    assert verdict.outside.tolist() == [0, 2] and math.isnan(verdict.low[3]) and verdict.level == CHI2_LEVEL
    assert verdict.low[0] == low and verdict.high[0] == high


def test_evaluate_only_features_gives_no_pose_nees():
    truth = GroundTruth([1, 2], [[0, 0], [1, 1]], [0], [[0, 0, 0]])
    result = evaluate(global_map([2], [[1, 1.5]], [5], [[0, 0, 0]]), truth)
    assert (result.features, result.poses) == (1, 0)
    assert result.feature_rms == pytest.approx(0.5) and math.isnan(result.pose_rms_xy)
    assert result.nees_poses is None and result.nees_bounds_poses is None
    assert result.nees_features == pytest.approx(0.25)
    assert result.consistent is True  # 0.25 lies within chi2(2)'s 2.5% and 97.5% quantiles, 0.051 and 7.38


def test_evaluate_rigid_alignment_recovers_a_moved_map():
    simulation = simulate(10, seed=2, noiseless=True)
    exact = join_sequential(simulation.maps).global_map
    angle, shift = 0.3, np.array([2.0, -1.0])
    rotation = np.array([[math.cos(angle), -math.sin(angle)], [math.sin(angle), math.cos(angle)]])
    moved = global_map(exact.feature_ids, exact.features @ rotation.T + shift, exact.pose_ids,
                       np.column_stack([exact.poses[:, :2] @ rotation.T + shift, wrap(exact.poses[:, 2] + angle)]))
    assert evaluate(moved, simulation.truth).feature_rms > 1.0
    aligned = evaluate(moved, simulation.truth, align="rigid")
    assert aligned.feature_rms < 1e-9 and aligned.pose_rms_phi < 1e-9
    assert aligned.alignment.startswith("rigid") and "-0.300000 rad" in aligned.alignment
    with pytest.raises(ValueError, match="unknown alignment"):
        evaluate(moved, simulation.truth, align="similarity")


def test_evaluate_without_a_shared_id_is_an_error():
    truth = GroundTruth([1], [[0, 0]], [0], [[0, 0, 0]], name="truth.yaml")
    with pytest.raises(InputError, match="g.csv: shares no feature or pose id with the ground truth"):
        evaluate(global_map([9], [[0, 0]], [4], [[0, 0, 0]], name="g.csv"), truth)


# ---------------------------------------------------------------------------------------
# ground truth of the I-SLSJF simulation folders


def _relative(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Pose(s) ``b`` in the frame of pose(s) ``a``."""
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    dx, dy = b[..., 0] - a[..., 0], b[..., 1] - a[..., 1]
    return np.stack([c * dx + s * dy, -s * dx + c * dy, wrap(b[..., 2] - a[..., 2])], axis=-1)


def _robot(folder) -> np.ndarray:
    return mat_variables((folder / "store_robotTrue.mat").read_bytes(), "robot")["store_robotTrue"]


def _state_nees_per_dof(local_map, start: np.ndarray, end: np.ndarray, beacons: GroundTruth) -> float:
    """NEES per degree of freedom of a local map's whole state against the truth between two true poses."""
    c, s = math.cos(start[2]), math.sin(start[2])
    features = beacons.features[np.searchsorted(beacons.feature_ids, local_map.feature_ids)] - start[:2]
    true_state = np.concatenate([_relative(start, end), (features @ np.array([[c, -s], [s, c]])).ravel()])
    error = np.concatenate([local_map.end_pose, local_map.features.ravel()]) - true_state
    error[2] = wrap(error[2])
    return float(error @ np.linalg.solve(local_map.covariance, error)) / len(error)


@pytest.mark.parametrize("name, steps, maps, end_tolerance, phi_tolerance",
                         [("535_data_5_local_maps", 535, 5, 0.7, 0.25),
                          ("8240_data_50_local_maps", 8240, 50, 0.4, 0.06)])
def test_truth_folder_step_rule_matches_the_local_maps(data_dir, name, steps, maps, end_tolerance,
                                                       phi_tolerance):
    folder = data_dir / name
    truth = mapio.read_truth_folder(folder)
    local_maps = mapio.read_maps([str(folder)])
    robot = _robot(folder)
    assert robot.shape == (3, steps + 1) and len(local_maps) == maps
    rule = [round(k * steps / maps) for k in range(maps + 1)]   # no .5 ties in these two folders
    assert truth.pose_ids.tolist() == list(range(maps + 1))
    np.testing.assert_array_equal(truth.poses[:, :2], robot[:2, rule].T)  # both folders start at the origin
    np.testing.assert_allclose(wrap(truth.poses[:, 2] - robot[2, rule]), 0, atol=1e-12)
    assert set(np.concatenate([m.feature_ids for m in local_maps])) <= set(truth.feature_ids.tolist())

    # truth pose k-1 composed with local map k's end pose lands on truth pose k
    relative = _relative(truth.poses[:-1], truth.poses[1:])
    ends = np.array([m.end_pose for m in local_maps])
    assert np.hypot(*(ends[:, :2] - relative[:, :2]).T).max() < end_tolerance
    assert np.abs(wrap(ends[:, 2] - relative[:, 2])).max() < phi_tolerance

    # the maps' whole states fit the truth at the rule's steps (NEES/dof ~ 1), worse one step off
    def mean_nees(shift: int) -> float:
        return float(np.mean([_state_nees_per_dof(m, robot[:, rule[k]], robot[:, min(rule[k + 1] + shift, steps)],
                                                  truth) for k, m in enumerate(local_maps)]))
    at_rule = mean_nees(0)
    assert 0.5 < at_rule < 1.5
    assert mean_nees(-1) > 1.5 * at_rule and mean_nees(1) > 1.5 * at_rule


def test_truth_folder_ids_are_the_beacon_ids(data_dir):
    folder = data_dir / "8240_data_50_local_maps"
    beacons = mat_variables((folder / "store_beaconsTrue.mat").read_bytes(), "b")["store_beaconsTrue"]
    truth = mapio.read_truth_folder(folder)
    np.testing.assert_array_equal(truth.feature_ids, beacons[:, 0])
    np.testing.assert_array_equal(truth.features, beacons[:, 1:])


@pytest.mark.parametrize("name, feature_rms, pose_phi_rms", [("535_data_5_local_maps", 3.0, 0.2),
                                                              ("8240_data_50_local_maps", 6.0, 0.05)])
def test_joining_then_evaluating_the_simulations_gives_plausible_errors(data_dir, name, feature_rms,
                                                                        pose_phi_rms):
    # measured (default fast join, 'information' covariances): 535 features RMS 1.64 m, poses 1.86 m /
    # 0.130 rad; 8240 features 4.08 m, poses 3.53 m / 0.023 rad; the joined variances are far too small
    # (average NEES in the thousands), the errors being mostly drift the sequential join never corrects.
    folder = data_dir / name
    result = evaluate(join_sequential(mapio.read_maps([str(folder)])).global_map,
                      mapio.read_truth_folder(folder))
    assert result.features == len(np.unique(np.concatenate([m.feature_ids for m in
                                                             mapio.read_maps([str(folder)])])))
    assert 0.01 < result.feature_rms < feature_rms and 0.01 < result.pose_rms_xy < feature_rms
    assert result.pose_rms_phi < pose_phi_rms


def _synthetic_folder(tmp_path, robot: np.ndarray, beacons: np.ndarray, maps: int):
    folder = tmp_path / "sim"
    folder.mkdir()
    scipy.io.savemat(folder / "store_robotTrue.mat", {"store_robotTrue": robot})
    scipy.io.savemat(folder / "store_beaconsTrue.mat", {"store_beaconsTrue": beacons})
    for k in range(1, maps + 1):
        (folder / f"localmap_{k}.mat").write_bytes(b"")   # only the names count
    return folder


def test_truth_folder_rounds_halves_up_and_uses_the_frame_of_step_0(tmp_path):
    rng = np.random.default_rng(0)
    start = np.array([5.0, -3.0, 1.0])
    local = np.column_stack([rng.normal(size=(11, 2)) * 4, wrap(rng.normal(size=11))])
    local[0] = 0
    c, s = math.cos(start[2]), math.sin(start[2])
    robot = np.column_stack([local[:, :2] @ np.array([[c, s], [-s, c]]) + start[:2], wrap(local[:, 2] + start[2])]).T
    beacon_local = np.array([[1.0, 2.0], [-3.0, 0.5]])
    beacons = np.column_stack([[4, 9], beacon_local @ np.array([[c, s], [-s, c]]) + start[:2]])
    truth = mapio.read_truth_folder(_synthetic_folder(tmp_path, robot, beacons, 4))
    # 10 steps, 4 maps: round(2.5 k) with halves up = 0, 3, 5, 8, 10 (MATLAB's round)
    np.testing.assert_allclose(truth.poses, local[[0, 3, 5, 8, 10]], atol=1e-12)
    np.testing.assert_allclose(truth.features, beacon_local, atol=1e-12)
    assert truth.feature_ids.tolist() == [4, 9] and truth.pose_ids.tolist() == [0, 1, 2, 3, 4]
    assert mapio.read_truth_folder(tmp_path / "sim", maps=5).poses.shape == (6, 3)


def test_truth_folder_errors_name_the_file(tmp_path, data_dir):
    folder = tmp_path / "copy"
    folder.mkdir()
    shutil.copy(data_dir / "535_data_5_local_maps" / "store_robotTrue.mat", folder)
    with pytest.raises(InputError, match="no localmap_<k> files"):
        mapio.read_truth_folder(folder)
    with pytest.raises(InputError, match=r"store_beaconsTrue\.mat: missing"):
        mapio.read_truth_folder(folder, maps=5)
    (folder / "store_beaconsTrue.mat").write_bytes(b"not a mat file")
    with pytest.raises(InputError, match=r"store_beaconsTrue\.mat: expected a MATLAB v5"):
        mapio.read_truth_folder(folder, maps=5)
    scipy.io.savemat(folder / "store_beaconsTrue.mat", {"other": np.zeros((2, 3))})
    with pytest.raises(InputError, match="store_beaconsTrue: expected a numeric matrix variable"):
        mapio.read_truth_folder(folder, maps=5)
    scipy.io.savemat(folder / "store_beaconsTrue.mat", {"store_beaconsTrue": np.zeros((2, 4))})
    with pytest.raises(InputError, match=r"expected rows \[integer id, x, y\]"):
        mapio.read_truth_folder(folder, maps=5)
    scipy.io.savemat(folder / "store_beaconsTrue.mat", {"store_beaconsTrue": np.zeros((2, 3))})
    with pytest.raises(InputError, match="with at least 600 steps for 600 local maps"):
        mapio.read_truth_folder(folder, maps=600)
    (folder / "localmap_1.mat").write_bytes(b"")
    (folder / "localmap_3.mat").write_bytes(b"")
    with pytest.raises(InputError, match=r"expected local maps numbered 1\.\.2"):
        mapio.read_truth_folder(folder)
    with pytest.raises(InputError, match="expected a simulation folder"):
        mapio.read_truth_folder(tmp_path / "absent")


# ---------------------------------------------------------------------------------------
# the commands


@pytest.fixture(scope="module")
def simulated(tmp_path_factory):
    folder = tmp_path_factory.mktemp("evaluate") / "sim"
    assert run("-q", "simulate", "-o", str(folder), "--maps", "12", "--seed", "5").exit_code == 0
    assert run("-q", "join", str(folder), "-o", str(folder / "global.csv")).exit_code == 0
    assert run("-q", "join", str(folder), "-o", str(folder / "identity.yaml"),
               "--covariance", "identity").exit_code == 0
    return folder


def test_help_has_examples():
    for command in ("compare", "evaluate"):
        result = run(command, "--help")
        assert result.exit_code == 0 and "Examples:" in result.output, command


def test_compare_command_table_and_json(simulated):
    a, b = str(simulated / "global.csv"), str(simulated / "identity.yaml")
    expected = compare(mapio.read_global_map(a), mapio.read_global_map(b))
    table = run("compare", a, b)
    assert table.exit_code == 0
    assert f"shared ids: {expected.features} features, 12 poses" in table.output
    assert "mean |B-A|" in table.output and f"{expected.mean_abs_x:.6g}" in table.output
    document = json.loads(run("compare", a, b, "--json").output)
    assert document["features"] == expected.features and document["a"] == a
    assert document["mean_abs_phi"] == pytest.approx(expected.mean_abs_phi)
    with open(a) as file:
        assert json.loads(run("compare", "-", b, "--json", input=file.read()).output)["rms_xy"] == \
            pytest.approx(expected.rms_xy)


def test_compare_command_errors_are_one_line(simulated, tmp_path):
    other = tmp_path / "other.csv"
    mapio.write_global_map(global_map([10**6], [[0, 0]], [10**6], [[0, 0, 0]]), other)
    result = CliRunner().invoke(main, ["compare", str(simulated / "global.csv"), str(other)])
    assert result.exit_code == 1
    assert result.output.strip().startswith("Error: ") and "shares no feature or pose id" in result.output
    assert len(result.output.strip().splitlines()) == 1
    assert CliRunner().invoke(main, ["compare", "-", "-"]).exit_code == 2


@pytest.mark.parametrize("truth", ["truth.yaml", "."])
def test_evaluate_command_with_a_simulate_truth(simulated, truth):
    global_path = str(simulated / "global.csv")
    result = run("evaluate", global_path, "--truth", str(simulated / truth))
    assert result.exit_code == 0
    expected = evaluate(mapio.read_global_map(global_path), mapio.read_truth(simulated / "truth.yaml"))
    assert "alignment: none: map and truth both in the frame of pose 0" in result.output
    assert f"{expected.feature_rms:.6g}" in result.output and "spherical weights (not covariances" in result.output
    assert "bounds [" in result.output and "verdict: " in result.output


def test_evaluate_command_json_on_a_real_simulation_folder(data_dir, tmp_path):
    folder = data_dir / "535_data_5_local_maps"
    out = tmp_path / "g.yaml"
    assert run("-q", "join", str(folder), "-o", str(out)).exit_code == 0
    document = json.loads(run("evaluate", str(out), "--truth", str(folder), "--json", "--align", "rigid").output)
    assert document["features"] == 28 and document["poses"] == 5
    assert document["alignment"].startswith("rigid")
    assert len(document["nees_bounds_features"]) == 2 and isinstance(document["consistent"], bool)
    assert document["nees_covariances"].startswith("spherical weights (not covariances")


def test_evaluate_command_errors_are_one_line(simulated, data_dir):
    result = CliRunner().invoke(main, ["evaluate", str(simulated / "global.csv"), "--truth",
                                       str(data_dir / "VicPark_200_local_maps")])
    assert result.exit_code == 1 and "VicPark_200_local_maps: holds no ground truth; expected truth.yaml" in \
        result.output
    assert len(result.output.strip().splitlines()) == 1
    assert CliRunner().invoke(main, ["evaluate", "-", "--truth", "-"]).exit_code == 2
    result = CliRunner().invoke(main, ["evaluate", str(simulated / "global.csv")])
    assert result.exit_code == 2 and "--truth" in result.output
