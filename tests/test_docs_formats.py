"""Every example of the format specification (docs/formats.md) is written to a file and read by mapjoin.

Each example follows a line ``<!-- example: FILE (KIND[, FORMAT]) -->``; the local maps are
also joined. The expected values come from the page's own statements (the frames, which
variance wins, information = inverse covariance, the g2o id offset) and from the geometry the
examples were made from, not from the readers: the two-map example was made from features at
(1, 1), (2, -1), (3, 1.5), (4.5, 0.5) and poses (2, 0, 0.1), (4, 0.3, 0.15), rounded to 3 digits.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from cli_runner import run
from mapjoin import io as mapio
from mapjoin.joining import join

SPEC = Path(__file__).resolve().parent.parent / "docs" / "formats.md"
_EXAMPLE = re.compile(r"<!-- example: (\S+) \(([^)]*)\) -->\n```(\w+)\n(.*?)```\n", re.DOTALL)
_FENCE = re.compile(r"^```(yaml|csv|text)$", re.MULTILINE)


def _examples() -> dict[str, tuple[str, str]]:
    """File name -> (kind, text) of every marked example on the page."""
    found = {name: (kind, text) for name, kind, _language, text in _EXAMPLE.findall(SPEC.read_text())}
    assert found, "no examples found in docs/formats.md"
    return found


EXAMPLES = _examples()


def _write(tmp_path: Path, name: str) -> Path:
    path = tmp_path / name
    path.write_text(EXAMPLES[name][1])
    return path


def test_every_yaml_csv_and_text_block_of_the_spec_is_a_checked_example():
    blocks = len(_FENCE.findall(SPEC.read_text()))
    assert blocks == len(EXAMPLES) == len(_EXAMPLE.findall(SPEC.read_text()))


def test_the_kinds_named_are_ones_this_test_checks():
    known = {"local maps", "local maps, linearslam", "global map", "ground truth", "minima table", "g2o of global.csv"}
    assert {kind for kind, _ in EXAMPLES.values()} <= known


@pytest.mark.parametrize("name", sorted(EXAMPLES))
def test_each_example_is_read(tmp_path, name):
    kind, _ = EXAMPLES[name]
    path = _write(tmp_path, name)
    if kind.startswith("local maps"):
        maps = mapio.read_maps([str(path)], format="linearslam" if "linearslam" in kind else None)
        assert maps
        result = join(maps)
        assert len(result.global_map.pose_ids) == len(maps)
    elif kind == "global map":
        assert len(mapio.read_global_map(str(path)).pose_ids) >= 1
    elif kind == "ground truth":
        assert len(mapio.read_truth(str(path)).pose_ids) == 1
    elif kind == "minima table":
        table = mapio.read_minima_table(str(path))
        assert table.a.tolist() == [203570.0, 5.0] and table.c_phi.tolist() == [-0.0028, 2.9]


def test_the_yaml_and_csv_examples_hold_the_same_maps(tmp_path):
    from_yaml = mapio.read_maps([str(_write(tmp_path, "two-maps.yaml"))])
    from_csv = mapio.read_maps([str(_write(tmp_path, "two-maps.csv"))])
    assert [(m.start_id, m.end_id) for m in from_yaml] == [(m.start_id, m.end_id) for m in from_csv] == [(0, 1), (1, 2)]
    for a, b in zip(from_yaml, from_csv):
        assert a.feature_ids.tolist() == b.feature_ids.tolist()
        np.testing.assert_array_equal(a.features, b.features)
        np.testing.assert_array_equal(a.end_pose, b.end_pose)
        np.testing.assert_array_equal(a.feature_variances, b.feature_variances)
        np.testing.assert_array_equal(a.pose_variances, b.pose_variances)


@pytest.mark.parametrize("name", ["two-maps.yaml", "two-maps.csv"])
def test_joining_the_example_recovers_the_geometry_it_was_made_from(tmp_path, name):
    """The frames as the page states them: each map in its start pose's frame, the global map in the first's."""
    result = mapio.read_maps([str(_write(tmp_path, name))])
    global_map = join(result).global_map
    truth = {1: (1.0, 1.0), 2: (2.0, -1.0), 3: (3.0, 1.5), 4: (4.5, 0.5)}
    assert global_map.feature_ids.tolist() == [1, 2, 3, 4]
    np.testing.assert_allclose(global_map.features, [truth[i] for i in global_map.feature_ids.tolist()], atol=0.01)
    np.testing.assert_allclose(global_map.poses, [[2.0, 0.0, 0.1], [4.0, 0.3, 0.15]], atol=0.01)


def test_the_example_joins_through_the_command_line(tmp_path):
    result = run("-q", "join", str(_write(tmp_path, "two-maps.yaml")))
    assert result.exit_code == 0 and result.output.startswith("kind,id,x,y,phi,weight_xy,weight_phi\n")


def test_the_covariance_wins_over_the_stored_variances(tmp_path):
    """As the page says: with a covariance, marginal = mean of each block's diagonal, information = 2 / trace of
    the block of the inverse; the example's var fields (0.02, 0.01) are not used."""
    [local_map] = mapio.read_maps([str(_write(tmp_path, "with-covariance.yaml"))])
    covariance = np.array([[0.010, 0.001, 0.0002, 0.002, 0.000], [0.001, 0.012, 0.0003, 0.000, 0.002],
                           [0.0002, 0.0003, 0.001, 0.0001, 0.0002], [0.002, 0.000, 0.0001, 0.020, 0.001],
                           [0.000, 0.002, 0.0002, 0.001, 0.024]])
    marginal = join([local_map], covariance="marginal").global_map
    assert marginal.feature_variances.tolist() == pytest.approx([0.022])
    np.testing.assert_allclose(marginal.pose_variances, [[0.011, 0.001]], rtol=1e-12)
    information = np.linalg.inv(covariance)
    joined = join([local_map], covariance="information").global_map
    assert joined.feature_variances.tolist() == pytest.approx([2 / (information[3, 3] + information[4, 4])])
    np.testing.assert_allclose(joined.pose_variances,
                               [[2 / (information[0, 0] + information[1, 1]), 1 / information[2, 2]]], rtol=1e-12)


def test_the_linear_slam_example_holds_the_inverse_of_its_information_matrix(tmp_path):
    [local_map] = mapio.read_maps([str(_write(tmp_path, "localmap_3.txt"))], format="linearslam")
    assert (local_map.start_id, local_map.end_id) == (2, 3)
    assert local_map.feature_ids.tolist() == [5, 6]
    np.testing.assert_array_equal(local_map.end_pose, [1.5, 0.2, 0.05])
    np.testing.assert_array_equal(local_map.features, [[2.0, 1.0], [3.0, -0.5]])
    np.testing.assert_allclose(local_map.covariance, np.diag(1 / np.array([100, 100, 1000, 50, 50, 40, 40.0])),
                               rtol=1e-15)


def test_the_g2o_example_is_what_the_global_map_example_is_written_as(tmp_path):
    global_map = mapio.read_global_map(str(_write(tmp_path, "global.csv")))
    target = tmp_path / "out.g2o"
    mapio.write_global_map(global_map, str(target))
    assert target.read_text() == EXAMPLES["global.g2o"][1]


def test_the_global_map_examples_carry_what_the_page_says(tmp_path):
    with_cov = mapio.read_global_map(str(_write(tmp_path, "global-cov.csv")))
    np.testing.assert_array_equal(with_cov.feature_covariances, [[[0.021, 0.001], [0.001, 0.019]]])
    np.testing.assert_array_equal(with_cov.pose_covariances,
                                  [[[0.011, 0.0005, 0.0001], [0.0005, 0.009, 0.0002], [0.0001, 0.0002, 0.001]]])
    from_yaml = mapio.read_global_map(str(_write(tmp_path, "global.yaml")))
    np.testing.assert_array_equal(from_yaml.feature_covariances, with_cov.feature_covariances)
    np.testing.assert_array_equal(from_yaml.pose_covariances, with_cov.pose_covariances)
    assert from_yaml.provenance.maps == ("first", "second") and from_yaml.provenance.strategy == "sequential"


def test_the_readme_local_map_example_is_read_and_joined(tmp_path):
    blocks = re.findall(r"```yaml\n(.*?)```\n", (SPEC.parent.parent / "README.md").read_text(), re.DOTALL)
    assert blocks
    for number, text in enumerate(blocks):
        path = tmp_path / f"readme-{number}.yaml"
        path.write_text(text)
        [local_map] = mapio.read_maps([str(path)])
        assert join([local_map]).global_map.feature_ids.tolist() == local_map.feature_ids.tolist()
