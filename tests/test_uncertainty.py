"""Uncertainty columns mean what they say (issue 14, part 3; docs/method.md#uncertainty-columns).

A column called ``var*``/``cov*`` must be a covariance: only maps carrying marginal covariance
blocks (the exact join) write them; the fast join writes its spherical weights as ``weight*``,
and ``evaluate`` and ``plot --ellipses`` say so. Independent references: the NEES of the
exact join is recomputed here from the dense inverse of ``J^T J`` (numpy's ``inv`` of the
Jacobian built by finite-difference-checked code, not the selected inversion the CLI uses),
and compared with what ``mapjoin evaluate`` reports for the file ``join --refine`` writes.
"""

from __future__ import annotations

import io
import json

import numpy as np
import pytest
from cli_runner import run

from mapjoin import io as mapio
from mapjoin.joining import join_sequential
from mapjoin.refine import refine
from mapjoin.refine.problem import ExactProblem
from mapjoin.se2 import wrap
from mapjoin.simulation import simulate

SIMULATIONS = ("535_data_5_local_maps", "8240_data_50_local_maps")


def dense_nees(maps, global_map, truth) -> tuple[float, float]:
    """Average feature and pose NEES of ``global_map`` against ``truth`` with the covariance
    ``(J^T J)^-1`` of the exact problem at its estimate, inverted densely."""
    problem = ExactProblem(maps)
    J = problem.jacobian(problem.pack(global_map)).toarray()
    Z = np.linalg.inv(J.T @ J)
    N = problem.n_maps
    pose_error = problem.unpack(problem.pack(global_map))[0] - truth.poses[np.searchsorted(truth.pose_ids,
                                                                                         problem.pose_ids)]
    pose_error[:, 2] = wrap(pose_error[:, 2])
    feature_error = (problem.unpack(problem.pack(global_map))[1]
                     - truth.features[np.searchsorted(truth.feature_ids, problem.feature_ids)])
    pose = [e @ np.linalg.solve(Z[3 * k:3 * k + 3, 3 * k:3 * k + 3], e) for k, e in enumerate(pose_error)]
    feature = [e @ np.linalg.solve(Z[3 * N + 2 * j:3 * N + 2 * j + 2, 3 * N + 2 * j:3 * N + 2 * j + 2], e)
               for j, e in enumerate(feature_error)]
    return float(np.mean(feature)), float(np.mean(pose))


def evaluated(map_path, truth_path) -> dict:
    result = run("evaluate", str(map_path), "--truth", str(truth_path), "--json")
    assert result.exit_code == 0, result.output
    return json.loads(result.output)


def check_nees_targets(tmp_path, inputs, truth_path, maps, truth) -> None:
    """``join --refine``'s var/cov columns: evaluate's NEES within 2x of the dense-inverse NEES of
    the exact join; the fast join's file names weights, and evaluate labels them so."""
    exact_file, fast_file = tmp_path / "exact.csv", tmp_path / "fast.csv"
    assert run("join", *inputs, "--refine", "-o", str(exact_file)).exit_code == 0
    assert run("join", *inputs, "-o", str(fast_file)).exit_code == 0
    assert exact_file.read_text().splitlines()[0].split(",")[5:8] == ["var_xy", "var_phi", "cov_xx"]
    assert fast_file.read_text().splitlines()[0].split(",")[5:] == ["weight_xy", "weight_phi"]
    reported = evaluated(exact_file, truth_path)
    assert reported["nees_covariances"] == "full marginal blocks"
    features, poses = dense_nees(maps, mapio.read_global_map(str(exact_file)), truth)
    assert 0.5 <= reported["nees_features"] / features <= 2 and 0.5 <= reported["nees_poses"] / poses <= 2
    fast = evaluated(fast_file, truth_path)
    assert fast["nees_covariances"].startswith("spherical weights (not covariances")


@pytest.mark.parametrize("name", SIMULATIONS)
def test_nees_of_covariance_columns_on_the_simulations(data_dir, tmp_path, name):
    folder = data_dir / name
    maps = mapio.read_maps(folder)
    check_nees_targets(tmp_path, [str(folder)], folder, maps, mapio.read_truth_folder(folder, maps=len(maps)))


def test_nees_of_covariance_columns_on_a_simulate_run(tmp_path):
    folder = tmp_path / "sim"
    assert run("simulate", "-o", str(folder), "--maps", "60", "--seed", "5").exit_code == 0
    maps = mapio.read_maps(str(folder / "localmap_*.yaml"))
    check_nees_targets(tmp_path, [str(folder / "localmap_*.yaml")], folder / "truth.yaml", maps,
                       mapio.read_truth(str(folder / "truth.yaml")))


def test_fast_weights_are_not_covariances(data_dir):
    """Why the fast join's columns are not called variances: against ground truth their NEES is
    orders of magnitude above 2 on the 8240-step simulation (measured 6.4e4, exact join 1.6)."""
    from mapjoin.evaluation import evaluate

    folder = data_dir / "8240_data_50_local_maps"
    maps = mapio.read_maps(folder)
    truth = mapio.read_truth_folder(folder, maps=len(maps))
    fast = join_sequential(maps).global_map
    assert not fast.has_covariances and evaluate(fast, truth).nees_features > 100
    exact = refine(maps, fast).global_map
    assert exact.has_covariances and evaluate(exact, truth).nees_features < 4


@pytest.mark.parametrize("fmt", ["csv", "yaml"])
def test_weights_and_older_var_files_read_alike(fmt):
    """A fast join written now (weight names) and as older versions wrote it (var names, no cov)
    read back to the same map, without covariances; an exact join keeps var and cov names."""
    run_ = simulate(6, seed=2)
    fast = join_sequential(run_.maps).global_map
    buffer = io.StringIO()
    mapio.write_global_map(fast, buffer, fmt)
    text = buffer.getvalue()
    assert "weight_xy" in text and "var_xy" not in text and "var:" not in text
    older = text.replace("weight_xy", "var_xy").replace("weight_phi", "var_phi").replace("weight:", "var:")
    for version in (text, older):
        back = mapio.read_global_map(io.StringIO(version), fmt)
        assert not back.has_covariances
        np.testing.assert_array_equal(back.feature_variances, fast.feature_variances)
        np.testing.assert_array_equal(back.pose_variances, fast.pose_variances)
    exact = refine(run_.maps, fast).global_map
    buffer = io.StringIO()
    mapio.write_global_map(exact, buffer, fmt)
    assert "weight" not in buffer.getvalue() and "var_xy" in buffer.getvalue() and "cov" in buffer.getvalue()
    assert mapio.read_global_map(io.StringIO(buffer.getvalue()), fmt).has_covariances


def test_a_list_mixing_var_and_weight_names_is_one_error(tmp_path):
    text = ("format: mapjoin/global-map\nversion: 1\nfeatures: []\nposes:\n"
            "- {id: 1, x: 1, y: 2, phi: 0, weight_xy: 1, weight_phi: 1}\n"
            "- {id: 2, x: 1, y: 2, phi: 0, var_xy: 1, var_phi: 1}\n")
    path = tmp_path / "g.yaml"
    path.write_text(text)
    result = run("evaluate", str(path), "--truth", str(path))
    assert result.exit_code == 1
    assert "g.yaml" in result.output and "poses[1]" in result.output and "var_xy" in result.output


def test_plot_and_evaluate_label_weights(tmp_path):
    """``plot --ellipses`` does not call weight circles 95% regions; evaluate's table says weights."""
    from mapjoin.plot import map_figure

    run_ = simulate(5, seed=1)
    fast = join_sequential(run_.maps).global_map
    legend = "\n".join(t.get_text() for t in map_figure([fast], ["fast"], ellipses=True).legends[0].get_texts())
    assert "not uncertainty regions" in legend and "95% circles" not in legend
    path, truth = tmp_path / "fast.csv", tmp_path / "truth.csv"
    mapio.write_global_map(fast, str(path))
    mapio.write_truth(run_.truth, str(truth))
    result = run("evaluate", str(path), "--truth", str(truth))
    assert result.exit_code == 0 and "against the map's spherical weights (not covariances" in result.output
    assert "verdict: none: weights are not covariances" in result.output


@pytest.mark.parametrize("seed", [0, 4])
def test_marginals_linearised_at_the_fast_join_equal_the_dense_inverse(seed):
    """The benchmark's "linearised" column (benchmarks/uncertainty.py): the selected inversion of
    the factor of J^T J at a point that is not the optimum (the fast join) gives the diagonal
    blocks of the dense inverse there."""
    run_ = simulate(8, seed=seed)
    fast = join_sequential(run_.maps).global_map
    problem = ExactProblem(run_.maps)
    x = problem.pack(fast)
    data, _, _ = problem.linearise(x)
    poses, features = problem.marginals(problem.factorise(data))
    J = problem.jacobian(x).toarray()
    Z = np.linalg.inv(J.T @ J)
    N = problem.n_maps
    for k in range(N):
        np.testing.assert_allclose(poses[k], Z[3 * k:3 * k + 3, 3 * k:3 * k + 3], rtol=1e-7, atol=1e-12)
    for j in range(problem.n_features):
        at = 3 * N + 2 * j
        np.testing.assert_allclose(features[j], Z[at:at + 2, at:at + 2], rtol=1e-7, atol=1e-12)
