"""Outputs other tools load: the trajectory (TUM read by evo's own reader, CSV, JSON), the JSON global map,
the summary as JSON (--json), the g2o export."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest
from cli_runner import run

import mapjoin
from mapjoin.se2 import wrap


def _joined(tmp_path, data_dir, *extra):
    """``join`` of the 535 simulation to a CSV global map, with ``extra`` options; the global map read back."""
    output = tmp_path / "global.csv"
    result = run("join", str(data_dir / "535_data_5_local_maps"), "-o", str(output), *extra)
    assert result.exit_code == 0, result.output
    return mapjoin.read_global_map(str(output))


def test_tum_trajectory_is_read_by_evo_with_the_origin_and_every_end_pose(tmp_path, data_dir):
    from evo.tools import file_interface  # the reader evo_traj and evo_ape use

    path = tmp_path / "path.tum"
    global_map = _joined(tmp_path, data_dir, "--trajectory", str(path))
    trajectory = file_interface.read_tum_trajectory_file(str(path))
    assert trajectory.num_poses == len(global_map.pose_ids) + 1
    assert trajectory.timestamps.tolist() == [0, *global_map.pose_ids.tolist()]
    se3 = np.array(trajectory.poses_se3)
    expected_xy = np.vstack([[0, 0], global_map.poses[:, :2]])
    assert np.allclose(se3[:, :2, 3], expected_xy, rtol=1e-12, atol=1e-12)
    assert np.allclose(se3[:, 2, 3], 0) and np.allclose(se3[:, 2, 2], 1)  # planar: no z, rotation about z only
    headings = np.concatenate([[0.0], global_map.poses[:, 2]])
    rotation = np.stack([np.cos(headings), -np.sin(headings), np.sin(headings), np.cos(headings)], axis=1)
    assert np.allclose(se3[:, :2, :2].reshape(-1, 4), rotation, atol=1e-12)


def test_refine_trajectory_csv_and_json_hold_the_refined_poses(tmp_path, data_dir):
    output, table, document = tmp_path / "exact.csv", tmp_path / "path.csv", tmp_path / "path.json"
    maps = str(data_dir / "535_data_5_local_maps")
    for path in (table, document):
        result = run("refine", maps, "-o", str(output), "--trajectory", str(path))
        assert result.exit_code == 0, result.output
    exact = mapjoin.read_global_map(str(output))
    with open(table, newline="") as stream:
        rows = list(csv.DictReader(stream))
    assert [int(row["id"]) for row in rows] == [0, 1, 2, 3, 4, 5]
    assert np.array_equal([[float(row[key]) for key in ("x", "y", "phi")] for row in rows],
                          np.vstack([[0, 0, 0], exact.poses]))
    poses = json.loads(document.read_text())
    assert poses["format"] == "mapjoin/trajectory"
    assert [[pose["id"], pose["x"], pose["y"], pose["phi"]] for pose in poses["poses"]] == [
        [int(i), *values] for i, values in zip([0, *exact.pose_ids.tolist()], np.vstack([[0, 0, 0], exact.poses]).tolist())]


def test_trajectory_origin_is_the_first_maps_start_pose():
    """Maps from pose 10 on: the trajectory starts at pose 10 at the origin, then their end poses chain
    (a brute-force composition of the maps' end poses, as the maps are odometry here: no features)."""
    from mapjoin.io.trajectory import Trajectory
    from mapjoin.se2 import compose

    steps = [(1.0, 0.0, np.pi / 2), (2.0, 0.5, -0.3), (0.5, -1.0, 0.1)]
    pose = np.zeros(3)
    chained = [pose]
    for step in steps:
        pose = np.asarray(compose(pose, np.array(step)))
        chained.append(pose)
    maps = [mapjoin.LocalMap(f"m{k}", 10 + k, 11 + k, step, np.zeros(0, int), np.zeros((0, 2)), np.zeros(0),
                             [0.01, 0.001]) for k, step in enumerate(steps)]
    global_map = mapjoin.join(maps).global_map
    trajectory = Trajectory.of(global_map, maps[0].start_id)
    assert trajectory.ids.tolist() == [10, 11, 12, 13]
    assert np.allclose(trajectory.poses[:, :2], np.array(chained)[:, :2])
    assert np.allclose(wrap(trajectory.poses[:, 2] - np.array(chained)[:, 2]), 0)


def test_json_global_map_round_trips_exactly_and_is_plain_json(tmp_path, data_dir):
    maps = str(data_dir / "535_data_5_local_maps")
    assert run("refine", maps, "-o", str(tmp_path / "g.csv")).exit_code == 0
    result = run("refine", maps, "-o", str(tmp_path / "g.json"))
    assert result.exit_code == 0, result.output
    document = json.loads((tmp_path / "g.json").read_text())  # the standard library's reader
    assert document["format"] == "mapjoin/global-map" and len(document["poses"]) == 5
    from_json, from_csv = (mapjoin.read_global_map(str(tmp_path / name)) for name in ("g.json", "g.csv"))
    for key in ("feature_ids", "features", "feature_variances", "pose_ids", "poses", "pose_variances",
                "feature_covariances", "pose_covariances"):
        assert np.array_equal(getattr(from_json, key), getattr(from_csv, key)), key
    assert len(from_json.provenance.maps) == 5


def test_bad_json_global_map_names_file_line_and_field(tmp_path, data_dir):
    assert run("join", str(data_dir / "535_data_5_local_maps"), "-o", str(tmp_path / "g.json")).exit_code == 0
    text = (tmp_path / "g.json").read_text()
    bad = tmp_path / "bad.json"
    bad.write_text(text.replace('"weight": ', '"weight": -', 1))
    with pytest.raises(mapjoin.InputError, match=r"bad\.json, line \d+, field features\[0\]\.weight: expected a positive"):
        mapjoin.read_global_map(str(bad))


def test_json_summary_on_stdout_or_on_stderr_when_stdout_holds_the_data(tmp_path, data_dir):
    maps = str(data_dir / "535_data_5_local_maps")
    result = run("join", maps, "-o", str(tmp_path / "g.csv"), "--json")
    assert result.exit_code == 0, result.output
    summary = json.loads(result.stdout)
    global_map = mapjoin.read_global_map(str(tmp_path / "g.csv"))
    assert summary["command"] == "join" and summary["maps"] == 5
    assert summary["features"] == len(global_map.feature_ids) and summary["poses"] == len(global_map.pose_ids)
    assert "joined" not in result.stderr  # the human line is replaced, not repeated

    result = run("-q", "refine", maps, "-o", "-", "--json")
    assert result.exit_code == 0
    summary = json.loads(result.stderr.strip().splitlines()[-1])
    assert summary["command"] == "refine" and summary["converged"] is True
    assert summary["chi2"] == pytest.approx(7.83, abs=0.01)  # the 535 simulation's exact chi^2
    assert result.stdout.startswith("kind,id,")  # stdout is the data only


def test_trajectory_and_global_map_cannot_both_go_to_stdout(tmp_path, data_dir):
    result = run("join", str(data_dir / "535_data_5_local_maps"), "-o", "-", "--trajectory", "-")
    assert result.exit_code == 1 and "both write to stdout" in result.stderr and result.stdout == ""


def test_trajectory_in_an_unknown_format_writes_nothing(tmp_path, data_dir):
    result = run("join", str(data_dir / "535_data_5_local_maps"), "-o", str(tmp_path / "g.csv"),
                 "--trajectory", str(tmp_path / "path.yaml"))
    assert result.exit_code == 1 and "cannot write a trajectory as yaml" in result.stderr
    assert list(tmp_path.iterdir()) == []


def test_every_command_but_datasets_takes_json():
    """``datasets`` prints data on stdout (the list, the fetched folders); every other command prints a summary or a
    result that --json gives as JSON."""
    from mapjoin.cli import main

    lacking = [name for name, command in main.commands.items()
               if not any("--json" in parameter.opts for parameter in command.params)]
    assert lacking == ["datasets"]


@pytest.mark.parametrize(("command", "fields"), [
    (["simulate", "-o", "{tmp}/s.yaml", "--maps", "3"], {"maps": 3, "seed": 0}),
    (["convert", "{tmp}/maps.yaml", "-o", "{tmp}/c.csv"], {"maps": 4, "format": "csv"}),
    (["join", "{tmp}/maps.yaml", "-o", "{tmp}/g.csv", "--refine"], {"maps": 4, "joins": 3, "converged": True}),
    (["refine", "{tmp}/maps.yaml", "-o", "{tmp}/g.csv"], {"maps": 4, "joins": 3, "converged": True}),
    (["plot-join", "{tmp}/maps.yaml", "--join", "2", "-o", "{tmp}/j.svg"], {"join": 2}),
])
def test_json_summary_of_each_command_is_one_object(tmp_path, command, fields):
    simulation = mapjoin.simulate(4, seed=5)
    mapjoin.write_maps(simulation.maps, str(tmp_path / "maps.yaml"), "yaml")
    result = run("-q", *[part.format(tmp=tmp_path) for part in command], "--json")
    assert result.exit_code == 0, result.output
    [line] = result.stdout.splitlines()
    summary = json.loads(line)
    assert summary["command"] == command[0] and fields.items() <= summary.items()


def test_json_global_map_is_recognised_on_stdin(tmp_path, data_dir):
    assert run("join", str(data_dir / "535_data_5_local_maps"), "-o", str(tmp_path / "g.json")).exit_code == 0
    assert run("join", str(data_dir / "535_data_5_local_maps"), "-o", str(tmp_path / "g.csv")).exit_code == 0
    result = run("compare", "-", str(tmp_path / "g.csv"), "--json", input=(tmp_path / "g.json").read_text())
    assert result.exit_code == 0, result.output
    comparison = json.loads(result.stdout)
    assert comparison["features"] == 28 and comparison["max_xy"] == 0.0 and comparison["max_phi"] == 0.0
