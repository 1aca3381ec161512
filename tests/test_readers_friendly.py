"""Readers a person can write for: CSV by header name with the full covariance, YAML variances optional beside a
covariance, unknown fields ignored with one warning (near misses refused), missing fields saying what to write;
conversions that drop information say so once."""

from __future__ import annotations

import csv
import io
import json
import random

import numpy as np
import pytest
from cli_runner import run
from hypothesis import given, settings
from hypothesis import strategies as st

import mapjoin
from mapjoin.io import csv_maps, yaml_maps

PLAIN_CSV = """\
map,start_id,end_id,kind,id,x,y,phi,var_xy,var_phi
a,0,1,pose,1,1.0,2.0,0.1,0.01,0.001
a,0,1,feature,12,3.0,4.0,,0.02,
a,0,1,feature,14,5.0,6.0,,0.03,
b,1,2,pose,2,1.0,2.0,0.1,0.01,0.001
b,1,2,feature,12,3.0,4.0,,0.02,
"""

# one map, one feature: its 5x5 covariance (x y phi f12x f12y), positive definite, correlated
COVARIANCE = np.array([[0.04, 0.01, 0.002, 0.01, 0.0],
                       [0.01, 0.05, 0.001, 0.0, 0.01],
                       [0.002, 0.001, 0.003, 0.001, 0.002],
                       [0.01, 0.0, 0.001, 0.06, 0.02],
                       [0.0, 0.01, 0.002, 0.02, 0.08]])


def covariance_rows(matrix: np.ndarray, prefix: str = "m,0,1,cov,,,,,,,") -> str:
    i, j = np.triu_indices(len(matrix))
    return "".join(f"{prefix}{a},{b},{float(matrix[a, b])!r}\n" for a, b in zip(i.tolist(), j.tolist()))


def with_covariance(var_xy: str = "0.01", var_phi: str = "0.001", feature_var: str = "0.02") -> str:
    return ("map,start_id,end_id,kind,id,x,y,phi,var_xy,var_phi,i,j,cov\n"
            f"m,0,1,pose,1,1.0,2.0,0.1,{var_xy},{var_phi},,,\n"
            f"m,0,1,feature,12,3.0,4.0,,{feature_var},,,,\n" + covariance_rows(COVARIANCE))


def read_csv(text: str) -> list[mapjoin.LocalMap]:
    return csv_maps.read(text, "maps.csv")


def assert_same_maps(actual, expected) -> None:
    assert len(actual) == len(expected)
    for a, b in zip(actual, expected):
        assert (a.start_id, a.end_id) == (b.start_id, b.end_id)
        for key in ("end_pose", "feature_ids", "features", "feature_variances", "pose_variances"):
            assert np.array_equal(getattr(a, key), getattr(b, key)), key
        assert (a.covariance is None) == (b.covariance is None)
        if a.covariance is not None:
            assert np.array_equal(a.covariance, b.covariance)


# ---------------------------------------------------------------------------------------------- CSV


def test_refine_of_the_csv_copy_solves_the_same_problem_as_the_mat_maps(tmp_path, data_dir):
    """The 535 simulation converted to CSV refines to the same chi^2 (7.83) as its .mat maps: the covariance
    travelled (with spherical variances only it ended at 0.15, a different problem)."""
    maps = str(data_dir / "535_data_5_local_maps")
    result = run("convert", maps, "-o", str(tmp_path / "maps.csv"))
    assert result.exit_code == 0 and "warning" not in result.stderr
    summaries = []
    for source in (maps, str(tmp_path / "maps.csv")):
        result = run("refine", source, "-o", str(tmp_path / "exact.csv"), "--json")
        assert result.exit_code == 0, result.output
        summaries.append(json.loads(result.stdout))
    assert summaries[1]["chi2"] == pytest.approx(summaries[0]["chi2"], rel=1e-9)
    assert summaries[0]["chi2"] == pytest.approx(7.83, abs=0.01)


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 2**32 - 1), st.booleans())
def test_csv_columns_in_any_order_with_spaces_read_the_same(seed, covariances):
    """A file mapjoin wrote, its columns shuffled and its cells padded with spaces (by the csv module, not
    mapjoin), reads as the same maps."""
    maps = mapjoin.simulate(3, seed=seed % 1000).maps
    if not covariances:
        maps = [mapjoin.LocalMap(m.name, m.start_id, m.end_id, m.end_pose, m.feature_ids, m.features,
                                 m.feature_variances, m.pose_variances) for m in maps]
    rows = list(csv.reader(io.StringIO(csv_maps.dump(maps))))
    shuffle = random.Random(seed)
    order = list(range(len(rows[0])))
    shuffle.shuffle(order)
    buffer = io.StringIO()
    writer = csv.writer(buffer)
    for row in rows:
        writer.writerow([" " * shuffle.randrange(3) + row[k] + " " * shuffle.randrange(3) for k in order])
    assert_same_maps(read_csv(buffer.getvalue()), read_csv(csv_maps.dump(maps)))


def test_csv_without_a_map_column_groups_rows_by_end_id():
    text = "\n".join(",".join(cell for k, cell in enumerate(line.split(",")) if k) for line in
                     PLAIN_CSV.splitlines()) + "\n"
    assert text.startswith("start_id,end_id,kind")
    assert_same_maps(read_csv(text), read_csv(PLAIN_CSV))
    assert [m.name for m in read_csv(text)] == ["maps.csv#1", "maps.csv#2"]


def test_csv_feature_variance_may_be_named_var_as_in_yaml():
    assert_same_maps(read_csv(PLAIN_CSV.replace("var_xy", "var")), read_csv(PLAIN_CSV))
    with pytest.raises(mapjoin.InputError, match="the columns var and var_xy are the same variance"):
        read_csv(PLAIN_CSV.replace("var_phi\n", "var\n", 1))


def test_csv_covariance_rows_give_the_full_matrix():
    [local_map] = read_csv(with_covariance())
    assert np.array_equal(local_map.covariance, COVARIANCE)
    assert local_map.feature_variances.tolist() == [0.02] and local_map.pose_variances.tolist() == [0.01, 0.001]


def test_csv_variances_left_out_beside_a_covariance_are_its_marginal_ones():
    expected_pose = [(COVARIANCE[0, 0] + COVARIANCE[1, 1]) / 2, COVARIANCE[2, 2]]
    expected_feature = [(COVARIANCE[3, 3] + COVARIANCE[4, 4]) / 2]
    for text in (with_covariance("", "", ""),
                 "\n".join(",".join(c for k, c in enumerate(line.split(",")) if k not in (8, 9))
                           for line in with_covariance().splitlines()) + "\n"):   # the columns left out
        [local_map] = read_csv(text)
        assert np.allclose(local_map.pose_variances, expected_pose, rtol=1e-15)
        assert np.allclose(local_map.feature_variances, expected_feature, rtol=1e-15)


@pytest.mark.parametrize(("text", "message"), [
    (with_covariance().replace("m,0,1,cov,,,,,,,3,4,", "m,0,1,cov,,,,,,,4,3,"),
     "line 17, column i: expected i <= j"),
    (with_covariance().replace("m,0,1,cov,,,,,,,3,4,", "m,0,1,cov,,,,,,,3,5,"),
     "line 17, column j: expected i, j below 5 (the map's covariance is 5x5: 3 + 2 x 1 features), got j=5"),
    (with_covariance().replace("m,0,1,cov,,,,,,,3,4,", "m,0,1,cov,,,,,,,3,3,"),
     "line 17, column i: entry (3, 3) given twice for map 'm'"),
    (with_covariance().replace("m,0,1,cov,,,,,,,3,4,0.02\n", ""),
     "line 2, column kind: map 'm' has 14 cov rows; expected 15 (every entry i <= j of its 5x5 covariance), "
     "missing (3, 4)"),
    (with_covariance().replace("m,0,1,cov,,,,,,,3,4,0.02", "m,0,1,cov,,,,,,,3,4,nan"),
     "line 17, column cov: expected a finite number, got 'nan'"),
    (with_covariance().replace("m,0,1,cov,,,,,,,3,4,", "m,0,1,cov,12,,,,,,3,4,"),
     "line 17, column id: expected an empty cell (a cov row holds one covariance entry"),
    (with_covariance("", "0.001").replace(",,,,,,,", ",,,,,,,", 1), None),   # a variance left out: fine
    (PLAIN_CSV.replace("a,0,1,feature,14,5.0,6.0,,0.03,", "a,0,1,feature,14,5.0,6.0,,,"),
     "line 4, column var_xy: expected a positive finite number, got ''"),
    (PLAIN_CSV.replace(",var_phi", ",var_pih"),
     "line 1: unknown column 'var_pih' (did you mean 'var_phi'?)"),
    (PLAIN_CSV.replace("map,start_id,end_id,kind", "map,start_id,end,kind"),
     "line 1: expected the header to name the columns start_id, end_id, kind, id, x, y, phi (any order; "
     "optional: map, var_xy, var_phi, i, j, cov), missing end_id"),
    (with_covariance().replace(",i,j,cov", ",i,k,cov"),
     "line 4, column kind: a cov row needs the columns i, j and cov; the header has no j"),
])
def test_csv_errors_name_the_line_the_column_and_the_value(text, message):
    if message is None:
        assert read_csv(text)
        return
    with pytest.raises(mapjoin.InputError) as error:
        read_csv(text)
    assert str(error.value).startswith("maps.csv, " + message), str(error.value)


def test_csv_unknown_columns_are_ignored_with_one_warning(tmp_path):
    lines = PLAIN_CSV.splitlines()
    text = "\n".join([lines[0] + ",stamp,sensor", *(line + f",{k}.5,lidar" for k, line in enumerate(lines[1:]))]) + "\n"
    (tmp_path / "maps.csv").write_text(text)
    (tmp_path / "plain.csv").write_text(PLAIN_CSV)
    assert_same_maps(mapjoin.read_maps(str(tmp_path / "maps.csv")), read_csv(PLAIN_CSV))
    result = run("join", str(tmp_path / "maps.csv"), "-o", str(tmp_path / "g.csv"), "--gate", "0")
    assert result.exit_code == 0
    warnings = [line for line in result.stderr.splitlines() if "warning" in line]  # the toy maps' joins pass no check
    assert warnings == [f"mapjoin: warning: {tmp_path / 'maps.csv'}: ignored the columns 'stamp', 'sensor' "
                        "(not read by mapjoin)"]


def test_csv_round_trips_covariances_exactly(tmp_path, data_dir):
    maps = mapjoin.read_maps(str(data_dir / "DLR_200_local_maps"))[:20]
    assert_same_maps(read_csv(csv_maps.dump(maps)), maps)


# ---------------------------------------------------------------------------------------------- YAML

YAML_MAP = """\
format: mapjoin/local-map
version: 1
start_id: 0
end_id: 1
end_pose: {x: 1.0, y: 2.0, phi: 0.1}
features:
- {id: 12, x: 3.0, y: 4.0}
covariance:
""" + "".join(f"- {row}\n" for row in COVARIANCE.tolist())


def test_yaml_variances_left_out_beside_a_covariance_are_its_marginal_ones():
    [local_map] = yaml_maps.read(YAML_MAP, "m.yaml")
    assert np.allclose(local_map.pose_variances, [(0.04 + 0.05) / 2, 0.003], rtol=1e-15)
    assert np.allclose(local_map.feature_variances, [(0.06 + 0.08) / 2], rtol=1e-15)
    assert np.array_equal(local_map.covariance, COVARIANCE)


@pytest.mark.parametrize("mode", ["marginal", "information"])
def test_yaml_covariance_wins_over_variances_given_beside_it(tmp_path, mode):
    """Variances far from the covariance's change nothing: the join (and refine) use the covariance."""
    second = YAML_MAP.replace("start_id: 0\nend_id: 1", "start_id: 1\nend_id: 2")
    (tmp_path / "left_out.yaml").write_text(YAML_MAP + "---\n" + second)
    bogus = (YAML_MAP.replace("phi: 0.1}", "phi: 0.1, var_xy: 9.0, var_phi: 0.5}").replace("y: 4.0}", "y: 4.0, var: 7.0}"))
    (tmp_path / "given.yaml").write_text(bogus + "---\n" + second)
    outputs = []
    for name in ("left_out", "given"):
        result = run("join", str(tmp_path / f"{name}.yaml"), "--covariance", mode, "-o", "-")
        assert result.exit_code == 0, result.output
        outputs.append(result.stdout)
    assert outputs[0] == outputs[1]


def test_yaml_variance_missing_without_a_covariance_names_the_field():
    text = YAML_MAP.split("covariance:")[0].replace("phi: 0.1}", "phi: 0.1, var_xy: 0.1, var_phi: 0.01}")
    with pytest.raises(mapjoin.InputError, match=r"^m\.yaml, line 7, field features\[0\]\.var: missing; expected a "
                                                 r"positive finite number \(it may be left out only when"):
        yaml_maps.read(text, "m.yaml")


@pytest.mark.parametrize(("drop", "message"), [
    ("format: mapjoin/local-map\n", "m.yaml, line 1: missing field 'format' (expected 'mapjoin/local-map')"),
    ("version: 1\n", "m.yaml, line 1: missing field 'version' (expected 1)"),
])
def test_yaml_missing_header_field_says_what_to_write(drop, message):
    with pytest.raises(mapjoin.InputError) as error:
        yaml_maps.read(YAML_MAP.replace(drop, ""), "m.yaml")
    assert str(error.value) == message


def test_yaml_unknown_fields_warn_once_per_stream_and_near_misses_are_refused(tmp_path):
    stamped = YAML_MAP.replace("end_id: 1\n", "end_id: 1\nstamp: 12.5\n").replace("y: 4.0}", "y: 4.0, label: tree}")
    second = stamped.replace("start_id: 0\nend_id: 1", "start_id: 1\nend_id: 2")
    (tmp_path / "maps.yaml").write_text(stamped + "---\n" + second)
    result = run("join", str(tmp_path / "maps.yaml"), "-o", str(tmp_path / "g.csv"))
    assert result.exit_code == 0, result.output
    warnings = [line for line in result.stderr.splitlines() if "warning" in line]
    assert warnings == [f"mapjoin: warning: {tmp_path / 'maps.yaml'}: ignored the fields 'stamp', 'features[].label' "
                        "(not read by mapjoin)"]
    (tmp_path / "typo.yaml").write_text(YAML_MAP.replace("covariance:", "covarience:"))
    result = run("join", str(tmp_path / "typo.yaml"), "-o", str(tmp_path / "h.csv"))
    assert result.exit_code == 1 and not (tmp_path / "h.csv").exists()
    assert result.stderr.startswith(f"Error: {tmp_path / 'typo.yaml'}, line 1: unknown field 'covarience' (did you "
                                    "mean 'covariance'?)")


# ---------------------------------------------------------------------------------------------- conversions


def test_a_conversion_that_drops_variances_says_so_once(tmp_path):
    """Maps whose variances are not their covariance's marginal ones, written as Linear SLAM text (which stores
    the information matrix alone): one warning for all files; read back, the variances are the marginal ones."""
    maps = [mapjoin.LocalMap(f"m{k}", k, k + 1, [1.0, 0.0, 0.1], [12], [[3.0, 4.0]], [0.5], [0.2, 0.02], COVARIANCE)
            for k in range(3)]
    (tmp_path / "maps.yaml").write_text(yaml_maps.dump(maps))
    result = run("convert", str(tmp_path / "maps.yaml"), "-o", str(tmp_path / "txt") + "/", "--to", "linearslam")
    assert result.exit_code == 0, result.output
    warnings = [line for line in result.stderr.splitlines() if "warning" in line]
    assert len(warnings) == 1 and "the variances of 3 maps differ from their covariance's marginal" in warnings[0]
    back = mapjoin.read_maps(str(tmp_path / "txt"))
    assert np.allclose(back[0].feature_variances, [(0.06 + 0.08) / 2], rtol=1e-9)
    result = run("convert", str(tmp_path / "txt"), "-o", str(tmp_path / "again") + "/", "--to", "mat")
    assert result.exit_code == 0 and "warning" not in result.stderr  # nothing more to drop


@pytest.mark.parametrize("command", [["simulate", "-o", "{tmp}/out.csv", "--maps", "3"],
                                     ["convert", "{tmp}/maps.yaml", "-o", "{tmp}/out.csv"]])
def test_no_covariances_writes_spherical_variances_only_and_says_so(tmp_path, command):
    simulation = mapjoin.simulate(3, seed=0)
    mapjoin.write_maps(simulation.maps, str(tmp_path / "maps.yaml"), "yaml")
    result = run(*[part.format(tmp=tmp_path) for part in command], "--no-covariances")
    assert result.exit_code == 0, result.output
    assert [line for line in result.stderr.splitlines() if "warning" in line] == [
        "mapjoin: warning: dropped the full covariances of 3 maps as asked: only their spherical variances are written"]
    back = mapjoin.read_maps(str(tmp_path / "out.csv"))
    assert all(m.covariance is None for m in back)
    for written, original in zip(back, simulation.maps):
        assert np.array_equal(written.feature_variances, original.feature_variances)
        assert np.array_equal(written.features, original.features)
    assert "cov" not in (tmp_path / "out.csv").read_text().splitlines()[0]
