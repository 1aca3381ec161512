"""Readers and writers: exact round trips, the real I-SLSJF data, bad input, garbage."""

from __future__ import annotations

import csv
import dataclasses
import io
import json
import logging
import os
import re
import struct
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import scipy.io
import yaml
from hypothesis import assume, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from mapjoin import io as mapio
from mapjoin.errors import InputError
from mapjoin.maps import GlobalMap, GroundTruth, LocalMap, Provenance

# ---------------------------------------------------------------------------------------
# Strategies and helpers

FLOATS = st.floats(allow_nan=False, allow_infinity=False)
VALUES = st.floats(-1e6, 1e6)  # coordinates and angles within every accepted range (README, "Accepted values")
VARIANCES = st.floats(1e-30, 1e30)
IDS = st.integers(0, 2**63 - 1)
NAMES = st.text(st.characters(blacklist_categories=("Cs",)), max_size=8)


def floats(shape: tuple[int, ...], elements=VALUES):
    return hnp.arrays(np.float64, shape, elements=elements)


def unique_ids(size: int):
    return st.lists(IDS, min_size=size, max_size=size, unique=True).map(lambda ids: np.array(ids, dtype=np.int64))


@st.composite
def local_maps(draw, covariance=st.booleans()) -> LocalMap:
    m = draw(st.integers(0, 4))
    start = draw(st.integers(0, 10**12))
    end = draw(st.integers(0, 10**12).filter(lambda end: end != start))
    full = None
    if draw(covariance):
        rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
        scale = draw(st.sampled_from([1e-5, 1.0, 1e4]))
        root = rng.normal(size=(3 + 2 * m, 3 + 2 * m)) * scale
        full = root @ root.T + np.eye(3 + 2 * m) * scale**2
        full = (full + full.T) / 2
    return LocalMap(draw(NAMES), start, end, draw(floats((3,))), draw(unique_ids(m)), draw(floats((m, 2))),
                    draw(floats((m,), VARIANCES)), draw(floats((2,), VARIANCES)), full)


@st.composite
def symmetric_blocks(draw, count: int, size: int) -> np.ndarray:
    upper = np.triu(draw(floats((count, size, size))))
    return upper + np.triu(upper, 1).transpose(0, 2, 1)


@st.composite
def global_maps(draw, covariances=st.booleans()) -> GlobalMap:
    n, p = draw(st.integers(0, 4)), draw(st.integers(0, 4))
    with_covariances = draw(covariances)
    provenance = Provenance(tuple(draw(st.lists(NAMES, max_size=3))), draw(NAMES), draw(NAMES), draw(NAMES))
    return GlobalMap(draw(unique_ids(n)), draw(floats((n, 2))), draw(floats((n,), VARIANCES)),
                     draw(unique_ids(p)), draw(floats((p, 3))), draw(floats((p, 2), VARIANCES)), provenance,
                     draw(symmetric_blocks(n, 2)) if with_covariances else None,
                     draw(symmetric_blocks(p, 3)) if with_covariances else None)


@st.composite
def truths(draw) -> GroundTruth:
    n, p = draw(st.integers(0, 4)), draw(st.integers(0, 4))
    return GroundTruth(draw(unique_ids(n)), draw(floats((n, 2))), draw(unique_ids(p)), draw(floats((p, 3))))


def same_array(a: np.ndarray | None, b: np.ndarray | None) -> bool:
    """Bit-for-bit equality (so -0.0 != 0.0); None only equals None."""
    if a is None or b is None:
        return a is None and b is None
    return a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()


def assert_same(actual: Any, expected: Any, *, skip: tuple[str, ...] = ()) -> None:
    """Equal dataclasses, arrays compared bit for bit; empty covariance stacks count as None."""
    for field in dataclasses.fields(expected):
        if field.name in skip:
            continue
        a, b = getattr(actual, field.name), getattr(expected, field.name)
        if field.name.endswith("covariances"):
            a, b = (None if value is None or not len(value) else value for value in (a, b))
        if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
            assert same_array(a, b), (field.name, a, b)
        else:
            assert a == b, field.name


def read_names(source: str, maps: list[LocalMap]) -> list[str]:
    """The names maps written to ``source`` read back with (see formats' "Map names")."""
    if len(maps) == 1:
        return [source]
    return [f"{source}#{local_map.name or number}" for number, local_map in enumerate(maps, 1)]


def written(write, value, fmt: str) -> str:
    buffer = io.StringIO()
    write(value, buffer, fmt)
    return buffer.getvalue()


@pytest.fixture(scope="session")
def scratch(tmp_path_factory) -> Path:
    """A folder hypothesis tests may reuse (function-scoped tmp_path cannot be used with @given)."""
    return tmp_path_factory.mktemp("scratch")


@pytest.fixture
def mapjoin_log(caplog):
    """caplog wired to the "mapjoin" logger directly (the CLI stops it from propagating)."""
    logger = logging.getLogger("mapjoin")
    propagate, level = logger.propagate, logger.level
    logger.addHandler(caplog.handler)
    logger.propagate = False
    logger.setLevel(logging.DEBUG)
    caplog.handler.setLevel(logging.DEBUG)
    try:
        yield caplog
    finally:
        logger.removeHandler(caplog.handler)
        logger.propagate, logger.level = propagate, level


def warnings_of(caplog) -> list[str]:
    return [record.getMessage() for record in caplog.records if record.levelno == logging.WARNING]


VALID_YAML = """\
format: mapjoin/local-map
version: 1
name: example
start_id: 0
end_id: 1
end_pose: {x: 1.0, y: 2.0, phi: 0.1, var_xy: 0.01, var_phi: 0.001}
features:
- {id: 12, x: 3.0, y: 4.0, var: 0.02}
- {id: 14, x: 5.0, y: 6.0, var: 0.02}
- {id: 15, x: 7.0, y: 8.0, var: 1e-2}
"""

VALID_CSV = """\
map,start_id,end_id,kind,id,x,y,phi,var_xy,var_phi
a,0,1,pose,1,1.0,2.0,0.1,0.01,0.001
a,0,1,feature,12,3.0,4.0,,0.02,
a,0,1,feature,14,5.0,6.0,,0.02,
b,1,2,pose,2,1.0,2.0,0.1,0.01,0.001
b,1,2,feature,12,3.0,4.0,,0.02,
"""

EXAMPLE_GLOBAL = GlobalMap(np.array([12, 14]), np.array([[3.0, 4.0], [5.0, 6.0]]), np.array([0.02, 0.03]),
                           np.array([1, 2]), np.array([[1.0, 2.0, 0.1], [2.0, 3.0, 0.2]]),
                           np.array([[0.01, 0.001], [0.02, 0.002]]),
                           Provenance(("a.mat", "b.mat"), "marginal", "bisection", "sequential"),
                           np.array([np.eye(2), 2 * np.eye(2)]), np.array([np.eye(3), 3 * np.eye(3)]))
EXAMPLE_TRUTH = GroundTruth(np.array([12]), np.array([[3.0, 4.0]]), np.array([0, 1]),
                            np.array([[0.0, 0.0, 0.0], [1.0, 2.0, 0.1]]))


def handmade_mat(endian: str, **arrays: Any) -> bytes:
    """A minimal uncompressed MAT v5 file of double matrices, written by hand in either byte order."""
    def element(kind: int, payload: bytes) -> bytes:
        return struct.pack(endian + "II", kind, len(payload)) + payload + bytes(-len(payload) % 8)

    header = (b"MATLAB 5.0 MAT-file, handmade".ljust(116) + bytes(8) + struct.pack(endian + "H", 0x0100)
              + (b"IM" if endian == "<" else b"MI"))
    body = b""
    for name, value in arrays.items():
        value = np.asarray(value, dtype=float)
        body += element(14, element(6, struct.pack(endian + "II", 6, 0))
                        + element(5, np.array(value.shape, endian + "i4").tobytes())
                        + element(1, name.encode()) + element(9, value.astype(endian + "f8").tobytes(order="F")))
    return header + body


def mat_bytes(compress: bool = True, **variables: Any) -> bytes:
    buffer = io.BytesIO()
    scipy.io.savemat(buffer, variables, do_compression=compress)
    return buffer.getvalue()


EXAMPLE_STATE = np.array([[0, 1.0], [0, 2.0], [0, 0.1], [12, 3.0], [12, 4.0], [14, 5.0], [14, 6.0]])
EXAMPLE_P = np.diag(np.arange(1.0, 8.0)) * 1e-3


def example_mat(compress: bool = True, **changes: Any) -> bytes:
    """A two-feature I-SLSJF local map, with some variables replaced (None: left out)."""
    variables = {"localmap_st": EXAMPLE_STATE, "localmap_P": EXAMPLE_P, **changes}
    return mat_bytes(compress, **{key: value for key, value in variables.items() if value is not None})


def flipped(data: bytes, offset: int, value: int) -> bytes:
    return data[:offset] + bytes([value]) + data[offset + 1:]



# ---------------------------------------------------------------------------------------
# Exact round trips


@settings(deadline=None)
@given(local_maps(), st.sampled_from(["yaml", "csv"]))
def test_single_local_map_round_trips_through_a_stream(local_map, fmt):
    assume(fmt != "csv" or local_map.name == local_map.name.strip(" \t"))  # refused: see below
    [back] = mapio.read_map_file(io.StringIO(written(mapio.write_maps, [local_map], fmt)), fmt)
    assert back.name == "<stream>"
    assert_same(back, local_map, skip=("name",))


@settings(deadline=None)
@given(st.lists(local_maps(), min_size=1, max_size=4, unique_by=lambda local_map: local_map.name),
       st.sampled_from(["yaml", "csv"]), st.booleans())
def test_local_map_streams_round_trip(maps, fmt, sniff):
    assume(fmt != "csv" or all(m.name == m.name.strip(" \t") for m in maps))  # refused: see below
    back = mapio.read_map_file(io.StringIO(written(mapio.write_maps, maps, fmt)), None if sniff else fmt)
    assert [m.name for m in back] == read_names("<stream>", maps)
    for actual, expected in zip(back, maps, strict=True):
        assert_same(actual, expected, skip=("name",))


def test_a_map_name_with_blanks_around_it_is_refused_by_the_csv_writer():
    """CSV reading ignores blanks around a cell, so such a name would not come back (two maps
    named '' and '\\t' would even become one): refused, naming the map."""
    local_map = LocalMap(name="\tfirst", start_id=0, end_id=1, end_pose=np.zeros(3), feature_ids=np.array([1]),
                         features=np.ones((1, 2)), pose_variances=np.ones(2), feature_variances=np.ones(1))
    with pytest.raises(InputError, match="has blanks around it"):
        written(mapio.write_maps, [local_map], "csv")


@settings(max_examples=25, deadline=None)
@given(st.lists(local_maps(), min_size=1, max_size=3, unique_by=lambda local_map: local_map.name),
       st.sampled_from(["yaml", "csv"]))
def test_local_maps_round_trip_through_files(scratch, maps, fmt):
    assume(fmt != "csv" or all(m.name == m.name.strip(" \t") for m in maps))  # refused: see below
    path = scratch / f"maps.{fmt}"
    assert mapio.write_maps(maps, path, fmt) == [str(path)]
    back = mapio.read_maps([str(path)])
    assert [m.name for m in back] == read_names(str(path), maps)
    for actual, expected in zip(back, maps, strict=True):
        assert_same(actual, expected, skip=("name",))


@settings(max_examples=10, deadline=None)
@given(st.lists(local_maps(), min_size=1, max_size=4, unique_by=lambda local_map: local_map.end_id))
def test_local_maps_round_trip_through_a_folder(scratch, maps):
    folder = scratch / f"folder{len(list(scratch.iterdir()))}"
    paths = mapio.write_maps(maps, f"{folder}/", "yaml")
    assert paths == [str(folder / f"localmap_{local_map.end_id}.yaml") for local_map in maps]
    back = mapio.read_maps([str(folder)])
    assert [m.name for m in back] == sorted(paths, key=lambda path: int(re.findall(r"[0-9]+", path)[-1]))
    for actual, expected in zip(back, sorted(maps, key=lambda local_map: local_map.end_id), strict=True):
        assert_same(actual, expected, skip=("name",))


@settings(deadline=None)
@given(global_maps(), st.sampled_from(["yaml", "csv"]))
def test_global_maps_round_trip(global_map, fmt):
    back = mapio.read_global_map(io.StringIO(written(mapio.write_global_map, global_map, fmt)), fmt)
    assert_same(back, global_map, skip=("name",) if fmt == "yaml" else ("name", "provenance"))
    if fmt == "csv":
        assert back.provenance == Provenance()


@settings(max_examples=25, deadline=None)
@given(global_maps(), st.sampled_from(["yaml", "csv"]))
def test_global_maps_round_trip_through_files(scratch, global_map, fmt):
    path = scratch / f"global.{fmt}"
    mapio.write_global_map(global_map, path)
    back = mapio.read_global_map(path)
    assert back.name == str(path)
    assert_same(back, global_map, skip=("name",) if fmt == "yaml" else ("name", "provenance"))


@pytest.mark.parametrize("fmt", ["yaml", "csv"])
@pytest.mark.parametrize("with_covariances", [True, False], ids=["covariances", "no-covariances"])
def test_global_map_columns(fmt, with_covariances):
    global_map = EXAMPLE_GLOBAL if with_covariances else dataclasses.replace(
        EXAMPLE_GLOBAL, feature_covariances=None, pose_covariances=None)
    text = written(mapio.write_global_map, global_map, fmt)
    if fmt == "csv":
        header = text.splitlines()[0].split(",")
        spherical = ["var_xy", "var_phi"] if with_covariances else ["weight_xy", "weight_phi"]
        assert header[:7] == ["kind", "id", "x", "y", "phi", *spherical]
        assert len(header) == (13 if with_covariances else 7)
        assert text.splitlines()[1].startswith("feature,12,3.0,4.0,,0.02,")
    else:
        document = yaml.safe_load(text)
        assert document["format"] == "mapjoin/global-map" and document["version"] == 1
        assert document["provenance"]["maps"] == ["a.mat", "b.mat"]
        assert ("cov" in document["poses"][1]) == with_covariances
        assert set(document["poses"][1]) >= ({"var_xy", "var_phi"} if with_covariances else {"weight_xy", "weight_phi"})
        assert ("var" if with_covariances else "weight") in document["features"][0]
    assert_same(mapio.read_global_map(io.StringIO(text)), global_map, skip=("name", "provenance"))


@settings(deadline=None)
@given(truths(), st.sampled_from(["yaml", "csv"]))
def test_ground_truth_round_trips(truth, fmt):
    back = mapio.read_truth(io.StringIO(written(mapio.write_truth, truth, fmt)), fmt)
    assert_same(back, truth, skip=("name",))


def test_ground_truth_files(tmp_path):
    for fmt in ("csv", "yaml"):
        mapio.write_truth(EXAMPLE_TRUTH, tmp_path / f"truth.{fmt}")
        assert_same(mapio.read_truth(tmp_path / f"truth.{fmt}"), EXAMPLE_TRUTH, skip=("name",))
    assert (tmp_path / "truth.csv").read_text().splitlines()[:2] == ["kind,id,x,y,phi", "feature,12,3.0,4.0,"]
    assert yaml.safe_load((tmp_path / "truth.yaml").read_text())["format"] == "mapjoin/ground-truth"


@dataclasses.dataclass
class Row:
    name: str
    joins: int
    cost: float
    gap: float | None
    residual: Any  # a numpy scalar
    certified: bool


ROWS = st.builds(Row, NAMES, st.integers(-10**6, 10**6), FLOATS, st.none() | FLOATS,
                 FLOATS.map(np.float64), st.booleans())


def plain(row: Row) -> dict[str, Any]:
    return {**dataclasses.asdict(row), "residual": float(row.residual)}


@settings(deadline=None)
@given(st.lists(ROWS, max_size=4), st.sampled_from(["csv", "yaml", "json"]))
def test_tables_round_trip(rows, fmt):
    text = written(mapio.write_table, rows, fmt)
    if fmt == "json":
        assert json.loads(text) == [plain(row) for row in rows]
    elif fmt == "yaml":
        assert yaml.safe_load(text) == [plain(row) for row in rows]
    elif rows:
        back = list(csv.DictReader(io.StringIO(text, newline="")))
        assert list(back[0]) == [field.name for field in dataclasses.fields(Row)]
        for line, row in zip(back, rows, strict=True):
            assert line["name"] == row.name and int(line["joins"]) == row.joins
            assert float(line["cost"]) == row.cost and line["cost"] == repr(row.cost)
            assert line["gap"] == ("" if row.gap is None else repr(row.gap))
            assert line["residual"] == repr(float(row.residual))
    else:
        assert text == ""


def test_table_files_and_numpy_values(tmp_path):
    rows = [Row("a", 1, 0.5, None, np.float64(2.5), True), Row("b", 2, 1e-7, 3.0, np.int64(4), False)]
    for fmt in mapio.TABLE_FORMATS:
        mapio.write_table(rows, tmp_path / f"report.{fmt}")
    assert (tmp_path / "report.csv").read_text() == (
        "name,joins,cost,gap,residual,certified\na,1,0.5,,2.5,True\nb,2,1e-07,3.0,4,False\n")
    assert json.loads((tmp_path / "report.json").read_text())[0]["gap"] is None
    assert yaml.safe_load((tmp_path / "report.yaml").read_text())[1]["residual"] == 4
    with pytest.raises(TypeError):
        mapio.write_table([rows[0], EXAMPLE_TRUTH], io.StringIO(), "csv")


# ---------------------------------------------------------------------------------------
# The YAML and CSV local-map formats in detail


def test_valid_examples_read():
    [example] = mapio.read_map_file(io.StringIO(VALID_YAML))
    assert example.name == "<stream>" and example.feature_ids.tolist() == [12, 14, 15]
    assert example.feature_variances[2] == 0.01  # 1e-2, without a dot, is a number
    assert example.covariance is None
    first, second = mapio.read_map_file(io.StringIO(VALID_CSV))
    assert (first.name, first.start_id, first.end_id, first.size) == ("<stream>#a", 0, 1, 2)
    assert (second.name, second.start_id, second.end_id, second.size) == ("<stream>#b", 1, 2, 1)
    assert second.end_pose.tolist() == [1.0, 2.0, 0.1] and second.pose_variances.tolist() == [0.01, 0.001]


def test_maps_are_named_after_their_file(tmp_path):
    unnamed = VALID_YAML.replace("name: example\n", "")
    (tmp_path / "one.yaml").write_text(VALID_YAML)
    (tmp_path / "two.yaml").write_text(f"---\n{VALID_YAML}---\n{unnamed.replace('end_id: 1', 'end_id: 2')}")
    (tmp_path / "maps.csv").write_text(VALID_CSV)
    names = [m.name for m in mapio.read_maps([str(tmp_path / name) for name in ("one.yaml", "two.yaml",
                                                                                  "maps.csv")])]
    assert names == [str(tmp_path / "one.yaml"), f"{tmp_path / 'two.yaml'}#example", f"{tmp_path / 'two.yaml'}#2",
                     f"{tmp_path / 'maps.csv'}#a", f"{tmp_path / 'maps.csv'}#b"]


def test_yaml_writes_floats_exactly_and_quotes_number_like_names():
    local_map = LocalMap("1e-6", 0, 1, [1e-6, 1e9, -0.0], [7], [[5e-324, 0.1 + 0.2]], [1e-30], [1e-6, 3.0])
    text = written(mapio.write_maps, [local_map], "yaml")
    assert "'1e-6'" in text and "0.30000000000000004" in text
    [back] = mapio.read_map_file(io.StringIO(text), "yaml")
    assert_same(back, local_map, skip=("name",))


def test_csv_accepts_crlf_a_bom_and_interleaved_maps(tmp_path):
    lines = VALID_CSV.splitlines()
    shuffled = [lines[0], lines[1], lines[4], lines[2], lines[5], lines[3]]
    path = tmp_path / "maps.csv"
    path.write_bytes(("\ufeff" + "\r\n".join(shuffled) + "\r\n").encode())
    first, second = mapio.read_maps([str(path)])
    assert first.feature_ids.tolist() == [12, 14] and second.feature_ids.tolist() == [12]


def test_csv_keeps_full_covariances_without_a_warning(mapjoin_log):
    maps = [LocalMap.from_covariance(name, 0, 1, [0, 0, 0], [3], [[1, 2]], np.eye(5) + 0.1) for name in "ab"]
    text = written(mapio.write_maps, maps, "csv")
    assert warnings_of(mapjoin_log) == []
    assert all(np.array_equal(m.covariance, np.eye(5) + 0.1) for m in mapio.read_map_file(io.StringIO(text), "csv"))


def test_write_maps_targets(tmp_path, monkeypatch):
    maps = mapio.read_map_file(io.StringIO(VALID_CSV))
    assert mapio.write_maps(maps, io.StringIO(), "yaml") == []
    stdout = io.StringIO()
    monkeypatch.setattr("sys.stdout", stdout)
    assert mapio.write_maps(maps, "-", "csv") == []
    assert stdout.getvalue().startswith("map,start_id")
    (tmp_path / "existing").mkdir()
    assert mapio.write_maps(maps, tmp_path / "existing", "csv") == [
        str(tmp_path / "existing" / "localmap_1.csv"), str(tmp_path / "existing" / "localmap_2.csv")]
    with pytest.raises(InputError, match="a mat file holds one local map, got 2"):
        mapio.write_maps(maps, tmp_path / "maps.mat", "mat")
    with pytest.raises(InputError, match="both would be localmap_1.yaml"):
        mapio.write_maps([maps[0], maps[0]], f"{tmp_path}/clash/", "yaml")
    assert not (tmp_path / "clash").exists()


def test_global_yaml_provenance_is_optional():
    text = ("format: mapjoin/global-map\nversion: 1\nfeatures: []\n"
            "poses:\n- {id: 1, x: 1, y: 2, phi: 0, var_xy: 1, var_phi: 1}\n")
    global_map = mapio.read_global_map(io.StringIO(text))
    assert global_map.provenance == Provenance() and global_map.poses.tolist() == [[1.0, 2.0, 0.0]]
    assert global_map.feature_covariances is None and global_map.features.shape == (0, 2)


def minima_columns(table: mapio.MinimaTable) -> tuple[list, list, list | None]:
    return table.a.tolist(), table.c_phi.tolist(), None if table.join is None else table.join.tolist()


@pytest.mark.parametrize("name, text", [
    ("t.csv", "minima,c_phi,map,a\n1,2.5,\"x, y\",5\n2,1,z,0.5\n"),       # any column order, more columns
    ("t.txt", "a,c_phi\n5,2.5\n\n0.5,1\n"),                                # other extension: CSV by content
    ("t.yaml", "# a batch\n- {a: 5, c_phi: 2.5, minima: 2}\n- {c_phi: 1, a: 0.5}\n"),
    ("t.json", '[{"a": 5, "c_phi": 2.5}, {"a": 0.5, "c_phi": 1.0}]'),
    ("t.txt", '[{"a": 5, "c_phi": 2.5}, {"a": 0.5, "c_phi": 1.0}]'),         # JSON by content
])
def test_minima_table_without_a_join_column(tmp_path, name, text):
    path = tmp_path / name
    path.write_text(text)
    for source in (path, io.StringIO(text)):
        assert minima_columns(mapio.read_minima_table(source)) == ([5.0, 0.5], [2.5, 1.0], None)


@pytest.mark.parametrize("text", ["c_phi,join,a\n2.5,7,5\n1,9,0.5\n",
                                  "- {join: 7, a: 5, c_phi: 2.5}\n- {join: 9, a: 0.5, c_phi: 1}\n"])
def test_minima_table_with_a_join_column_from_stdin(text, monkeypatch):
    monkeypatch.setattr("sys.stdin", io.StringIO(text))
    table = mapio.read_minima_table("-")
    assert table.source == "<stdin>" and minima_columns(table) == ([5.0, 0.5], [2.5, 1.0], [7, 9])


@pytest.mark.parametrize("name, text, message", [
    ("q.txt", "a,c_phi\n-1,2\n", "q.txt, line 2, column a: expected a non-negative finite number, got '-1'"),
    ("q.csv", "\na,phi\n1,2\n", "q.csv, line 2: expected a header with the columns a and c_phi"),
    ("q.csv", "a,c_phi,join\n1,2,x\n", "q.csv, line 2, column join: expected a non-negative integer"),
    ("q.csv", "a,c_phi\n1,2\n3\n", "q.csv, line 3: expected 2 fields, got 1"),
    ("q.csv", "a,c_phi\n", "q.csv: expected at least one row with a and c_phi, found none"),
    ("q.yaml", "- {join: 1, a: 1, c_phi: 0}\n- {a: 2, c_phi: 0}\n", "q.yaml, line 2, field [1].join: missing"),
    ("q.yaml", "- {a: 1, c_phi: .nan}\n", "q.yaml, line 1, field [0].c_phi: expected a finite number"),
    ("q.json", '{"a": 1, "c_phi": 0}', "q.json, line 1: expected a list"),
    ("q.json", '[[1, 0]]', "q.json, line 1, field [0]: expected a mapping"),
    ("q.mat", "a,c_phi\n1,2\n", "q.mat: expected a table with the columns a and c_phi (.csv, .yaml or .json)"),
])
def test_minima_table_errors_name_the_file_line_and_column(tmp_path, name, text, message):
    path = tmp_path / name
    path.write_text(text)
    with pytest.raises(InputError, match=re.escape(os.path.join(tmp_path, message))):
        mapio.read_minima_table(path)


def test_truth_of_a_simulate_folder_and_of_a_folder_without_truth(tmp_path, monkeypatch):
    for name, fmt in (("truth.yml", "yaml"), ("truth.csv", "csv")):
        folder = tmp_path / name.replace(".", "_")
        folder.mkdir()
        mapio.write_truth(EXAMPLE_TRUTH, folder / name, fmt)
        assert_same(mapio.read_truth(folder), EXAMPLE_TRUTH, skip=("name",))
        assert mapio.read_truth(str(folder)).name == str(folder / name)
    monkeypatch.setattr("sys.stdin", io.StringIO(written(mapio.write_truth, EXAMPLE_TRUTH, "yaml")))
    assert_same(mapio.read_truth("-"), EXAMPLE_TRUTH, skip=("name",))
    with pytest.raises(InputError, match=re.escape(f"{tmp_path}: holds no ground truth; expected truth.yaml")):
        mapio.read_truth(tmp_path)


# ---------------------------------------------------------------------------------------
# Input resolution, format detection, stdin


@pytest.mark.parametrize("name, expected", [
    ("maps/a.yaml", "yaml"), ("A.YML", "yaml"), ("x.csv", "csv"), ("localmap_3.mat", "mat"), ("r.json", "json")])
def test_detect_format(name, expected):
    assert mapio.detect_format(name) == expected
    assert mapio.detect_format(name, "csv") == "csv"


@pytest.mark.parametrize("name, explicit, message", [
    ("maps.txt", None, "maps.txt: cannot tell the format from the extension '.txt'"),
    ("maps", None, "maps: cannot tell the format from no extension"),
    ("-", None, "<stdin>: cannot tell the format"),
    ("a.csv", "xml", "unknown format 'xml'"),
], ids=["unknown-extension", "no-extension", "stdin", "unknown-explicit"])
def test_detect_format_errors(name, explicit, message):
    with pytest.raises(InputError, match=re.escape(message)):
        mapio.detect_format(name, explicit)


def test_folders_order_maps_by_number_and_ignore_other_files(tmp_path):
    for k in (1, 2, 9, 10, 11):
        (tmp_path / f"localmap_{k}.yaml").write_text(VALID_YAML.replace("end_id: 1", f"end_id: {k}"))
    for other in ("notes.txt", "localmap_x.yaml", "VicPark_clean_data.mat"):
        (tmp_path / other).write_text("ignored")
    (tmp_path / "localmap_5.yaml").mkdir()
    paths = mapio.resolve_inputs([str(tmp_path)])
    assert [Path(path).name for path in paths] == [f"localmap_{k}.yaml" for k in (1, 2, 9, 10, 11)]
    assert [m.end_id for m in mapio.read_maps([str(tmp_path)])] == [1, 2, 9, 10, 11]


def test_globs_sort_naturally_and_stdin_is_kept(tmp_path):
    for name in ("m10.csv", "m9.csv", "m1.csv", "other.yaml"):
        (tmp_path / name).write_text(VALID_CSV)
    paths = mapio.resolve_inputs([str(tmp_path / "m*.csv"), "-"])
    assert [Path(path).name for path in paths[:-1]] == ["m1.csv", "m9.csv", "m10.csv"] and paths[-1] == "-"


def test_a_folder_with_two_files_for_one_map_is_refused(tmp_path):
    (tmp_path / "localmap_1.yaml").write_text(VALID_YAML)
    (tmp_path / "localmap_01.csv").write_text(VALID_CSV)
    with pytest.raises(InputError, match="for map 1; keep one"):
        mapio.resolve_inputs([str(tmp_path)])


@pytest.mark.parametrize("text", [VALID_YAML, "# comment\n" + VALID_YAML, "---\n" + VALID_YAML,
                                  "%YAML 1.1\n---\n" + VALID_YAML, VALID_CSV],
                         ids=["format", "comment", "document-start", "directive", "csv"])
def test_stdin_formats_are_sniffed(text):
    maps = mapio.read_maps(["-"], stdin=io.StringIO(text))
    assert maps[0].end_id == 1


def test_stdin_with_mixed_inputs_and_a_format_for_what_names_do_not_tell(tmp_path):
    (tmp_path / "first.yaml").write_text(VALID_YAML)
    (tmp_path / "second.txt").write_text(VALID_CSV)
    maps = mapio.read_maps([str(tmp_path / "first.yaml"), "-", str(tmp_path / "second.txt")],
                             stdin=io.StringIO(VALID_CSV), format="csv")
    second = tmp_path / "second.txt"
    assert [m.name for m in maps] == [str(tmp_path / "first.yaml"), "<stdin>#a", "<stdin>#b", f"{second}#a",
                                      f"{second}#b"]


def test_stdin_is_read_once():
    with pytest.raises(InputError, match="more than once"):
        mapio.read_maps(["-", "-"], stdin=io.StringIO(VALID_CSV))


# ---------------------------------------------------------------------------------------
# The real I-SLSJF data


def test_vicpark_200_matches_the_mat_files(data_dir):
    folder = data_dir / "VicPark_200_local_maps"
    maps = mapio.read_maps([str(folder)])
    assert len(maps) == 200
    assert [(m.start_id, m.end_id) for m in maps] == [(k - 1, k) for k in range(1, 201)]
    assert Path(maps[9].name).name == "localmap_10.mat"  # by number, not by name
    assert maps[0].size == 22
    assert len(np.unique(np.concatenate([m.feature_ids for m in maps]))) == 299
    for local_map in maps:
        raw = scipy.io.loadmat(local_map.name)
        state, covariance = raw["localmap_st"], raw["localmap_P"]
        assert local_map.size == (len(state) - 3) // 2
        assert local_map.feature_ids.tolist() == state[3::2, 0].astype(int).tolist()
        assert same_array(local_map.end_pose, state[:3, 1].copy())
        assert same_array(local_map.features, state[3:, 1].reshape(-1, 2))
        np.testing.assert_allclose(local_map.covariance, covariance, rtol=0, atol=1e-12)
        np.testing.assert_array_equal(local_map.covariance, local_map.covariance.T)


@pytest.mark.parametrize("k", [3718, 6779])
def test_maps_where_the_robot_did_not_move_get_i_slsjf_stabilisation(data_dir, mapjoin_log, k):
    path = data_dir / "VicPark_6898_local_maps" / f"localmap_{k}.mat"
    raw = scipy.io.loadmat(path)["localmap_P"].diagonal()
    assert (raw[:3] < 1e-6).any()
    [local_map] = mapio.read_map_file(path)
    np.testing.assert_array_equal(local_map.covariance.diagonal(), np.r_[raw[:3] + 1e-6, raw[3:]])
    [warning] = warnings_of(mapjoin_log)
    assert str(path) in warning and "did not move" in warning and "1e-06" in warning


def test_maps_where_the_robot_moved_are_read_as_they_are(data_dir, mapjoin_log):
    path = data_dir / "VicPark_6898_local_maps" / "localmap_3717.mat"
    [local_map] = mapio.read_map_file(path)
    np.testing.assert_array_equal(local_map.covariance.diagonal(),
                                  scipy.io.loadmat(path)["localmap_P"].diagonal())
    assert warnings_of(mapjoin_log) == []


def test_the_whole_vicpark_6898_folder_reads(data_dir, mapjoin_log):
    maps = mapio.read_maps([str(data_dir / "VicPark_6898_local_maps")])
    assert [m.end_id for m in maps] == list(range(1, 6899))
    warnings = warnings_of(mapjoin_log)
    assert len(warnings) == 2 and "localmap_3718.mat" in warnings[0] and "localmap_6779.mat" in warnings[1]


def test_covariances_symmetric_up_to_rounding_are_symmetrised(data_dir):
    maps = mapio.read_maps([str(data_dir / "8240_data_50_local_maps")])
    assert len(maps) == 50
    raw = scipy.io.loadmat(maps[0].name)["localmap_P"]
    assert not np.array_equal(raw, raw.T)
    np.testing.assert_array_equal(maps[0].covariance, maps[0].covariance.T)
    np.testing.assert_allclose(maps[0].covariance, raw, rtol=0, atol=1e-10)


@pytest.mark.parametrize("endian", ["<", ">"], ids=["little-endian", "big-endian"])
def test_mat_files_in_either_byte_order(tmp_path, endian):
    path = tmp_path / "localmap_2.mat"
    path.write_bytes(handmade_mat(endian, localmap_st=EXAMPLE_STATE, localmap_P=EXAMPLE_P))
    [local_map] = mapio.read_map_file(path)
    assert (local_map.start_id, local_map.end_id) == (1, 2)
    assert same_array(local_map.features, EXAMPLE_STATE[3:, 1].reshape(-1, 2))
    assert same_array(local_map.covariance, EXAMPLE_P)


def test_mat_corruption_that_crashed_scipy_hits_a_type_code():
    """In example_mat(False) byte 192 is the type code (9, miDOUBLE) of localmap_st's data;
    changing it made scipy.io.loadmat crash the interpreter (see BAD_INPUTS)."""
    assert example_mat(False)[192] == 9


@pytest.mark.parametrize("folder, step", [("VicPark_200_local_maps", 1), ("VicPark_6898_local_maps", 97),
                                          ("DLR_200_local_maps", 1), ("8240_data_50_local_maps", 1),
                                          ("535_data_5_local_maps", 1)])
def test_real_mat_files_read_as_scipy_reads_them(data_dir, folder, step):
    for path in mapio.resolve_inputs([str(data_dir / folder)])[::step]:
        [local_map] = mapio.read_map_file(path)
        raw = scipy.io.loadmat(path)
        state, covariance = raw["localmap_st"], raw["localmap_P"]
        assert local_map.feature_ids.tolist() == state[3::2, 0].astype(int).tolist()
        assert same_array(local_map.end_pose, state[:3, 1].copy())
        assert same_array(local_map.features, state[3:, 1].reshape(-1, 2))
        scale = np.sqrt(np.outer(covariance.diagonal(), covariance.diagonal()))
        assert (np.abs(local_map.covariance - covariance) <= 1e-6 * scale + 1.1e-6 * np.eye(len(state))).all()


def test_mat_files_saved_by_scipy(tmp_path):
    for compress in (True, False):
        path = tmp_path / f"localmap_{4 + compress}.mat"
        path.write_bytes(example_mat(compress))
        [local_map] = mapio.read_map_file(path)
        assert (local_map.start_id, local_map.end_id) == (3 + compress, 4 + compress)
        assert local_map.feature_ids.tolist() == [12, 14] and local_map.features.tolist() == [[3, 4], [5, 6]]
        np.testing.assert_allclose(local_map.feature_variances, [0.0045, 0.0065], rtol=1e-15)


# ---------------------------------------------------------------------------------------
# Bad input: one clear InputError each, naming the file and the line or field

FOLDER = object()  # content marker: make an (empty) folder


def read_one(path: str) -> Any:
    return mapio.read_map_file(path)


def read_all(path: str) -> Any:
    return mapio.read_maps([path])


def writes_over_input(path: str) -> None:
    mapio.check_not_overwriting([path], [os.path.join(os.path.dirname(path), ".", os.path.basename(path))])


def covariance_yaml(matrix: str) -> str:
    return VALID_YAML.replace("features:\n", "features: []\ncovariance: " + matrix + "\n").split("- {id")[0]


BAD_INPUTS = [
    pytest.param("localmap_1.yaml", VALID_YAML.replace("var: 0.02}\n- {id: 14", "var: 0.02\n- {id: 14"), read_one,
                 ["malformed YAML", "line 9"], id="malformed-yaml"),
    pytest.param("localmap_1.yaml", VALID_YAML.replace("end_pose: {x: 1.0, y: 2.0, phi: 0.1, var_xy: 0.01, "
                                                       "var_phi: 0.001}\n", ""),
                 read_one, ["line 1, field end_pose: missing; expected a mapping"], id="yaml-missing-end-pose"),
    pytest.param("localmap_1.yaml", VALID_YAML.replace("version: 1", "version: 2"), read_one,
                 ["line 2, field version: unsupported version 2"], id="yaml-wrong-version"),
    pytest.param("localmap_1.yaml", VALID_YAML.replace("var: 1e-2", "var: -1"), read_one,
                 ["line 10, field features[2].var: expected a positive finite number, got -1"],
                 id="yaml-negative-variance"),
    pytest.param("localmap_1.yaml", VALID_YAML.replace("id: 15", "id: 14"), read_one,
                 ["line 10, field features[2].id: duplicate id 14"], id="yaml-duplicate-feature-id"),
    pytest.param("localmap_1.yaml", VALID_YAML.replace("x: 5.0", "x: .nan"), read_one,
                 ["line 9, field features[1].x: expected a finite number, got nan"], id="yaml-nan"),
    pytest.param("localmap_1.yaml", VALID_YAML.replace("features:", "featurs:"), read_one,
                 ["line 1: unknown field 'featurs'"], id="yaml-unknown-field"),
    pytest.param("localmap_1.yaml", VALID_YAML.replace("end_id: 1", "end_id: one"), read_one,
                 ["line 5, field end_id: expected a non-negative integer, got 'one'"], id="yaml-mistyped-id"),
    pytest.param("localmap_1.yaml", VALID_YAML.replace("mapjoin/local-map", "mapjoin/global-map"), read_one,
                 ["line 1, field format: expected mapjoin/local-map, got 'mapjoin/global-map'"],
                 id="yaml-wrong-kind"),
    pytest.param("localmap_1.yaml", covariance_yaml("[[1, 0, 0], [0, 1, 0], [0, 0, -1]]"), read_one,
                 ["line 8, field covariance: expected a positive definite matrix"], id="yaml-covariance-not-pd"),
    pytest.param("localmap_1.yaml", covariance_yaml("[[1, 0, 0], [0, 1, 0], [0, 0, true]]"), read_one,
                 ["line 8, field covariance[2][2]: expected a finite number, got True"],
                 id="yaml-covariance-bool"),
    pytest.param("localmap_1.yaml", covariance_yaml("[[1, 0], [0, 1]]"), read_one,
                 ["field covariance: expected 3 rows of 3 numbers, got 2 rows"], id="yaml-covariance-shape"),
    pytest.param("maps.csv", VALID_CSV.replace("3.0,4.0,,0.02", "nan,4.0,,0.02", 1), read_one,
                 ["line 3, column x: expected a finite number, got 'nan'"], id="csv-nan"),
    pytest.param("maps.csv", VALID_CSV.replace("a,0,1,feature,14,5.0,6.0,,0.02,", "a,0,1,feature,14,5.0,6.0"),
                 read_one, ["line 4: expected 10 fields, got 7"], id="csv-short-row"),
    pytest.param("maps.csv", VALID_CSV.replace("6.0,,0.02,", "6.0,,-0.02,"), read_one,
                 ["line 4, column var_xy: expected a positive finite number, got '-0.02'"],
                 id="csv-negative-variance"),
    pytest.param("maps.csv", VALID_CSV.replace("feature,14", "feature,12"), read_one,
                 ["line 4, column id: duplicate id 12 in this map"], id="csv-duplicate-feature-id"),
    pytest.param("maps.csv", VALID_CSV.replace("a,0,1,feature,14,5.0,6.0,,0.02,", "a,0,1,pose,1,1,2,3,4,5"),
                 read_one, ["line 4, column kind: map 'a' has a second pose row"], id="csv-two-pose-rows"),
    pytest.param("maps.csv", VALID_CSV.replace("b,1,2,pose,2,1.0,2.0,0.1,0.01,0.001\n", ""), read_one,
                 ["line 5, column kind: map 'b' has no pose row"], id="csv-no-pose-row"),
    pytest.param("maps.csv", VALID_CSV.replace("a,0,1,feature,14", "a,0,2,feature,14"), read_one,
                 ["line 4, column start_id: map 'a' has start_id,end_id [0, 1] on line 2"],
                 id="csv-inconsistent-ids"),
    pytest.param("maps.csv", VALID_CSV.replace("feature,14,5.0,6.0,,", "feature,14,5.0,6.0,0.5,"), read_one,
                 ["line 4, column phi: expected an empty cell"], id="csv-feature-with-phi"),
    pytest.param("maps.csv", VALID_CSV.replace("a,0,1,pose,1,", "a,0,1,pose,7,"), read_one,
                 ["line 2, column id: expected the end_id 1 on the pose row, got 7"], id="csv-pose-id"),
    pytest.param("maps.csv", VALID_CSV.replace("b,1,2", "b,2,2"), read_one,
                 ["line 5, map 'b', field end_id: end pose id equals start pose id (2)"], id="csv-start-is-end"),
    pytest.param("localmap_1.yaml", VALID_YAML.replace("start_id: 0", "start_id: 1"), read_one,
                 ["line 5, field end_id: end pose id equals start pose id (1)"], id="yaml-start-is-end"),
    pytest.param("maps.csv", VALID_CSV.replace("feature,14", "landmark,14"), read_one,
                 ["line 4, column kind: expected feature, pose or cov, got 'landmark'"], id="csv-bad-kind"),
    pytest.param("maps.csv", VALID_CSV.replace("var_phi", "var_theta"), read_one,
                 ["line 2, column var_phi: missing; expected a positive finite number"], id="csv-bad-header"),
    pytest.param("maps.csv", "", read_one, ["line 1: expected the header"], id="csv-empty"),
    pytest.param("maps.csv", VALID_CSV.splitlines()[0] + "\n", read_one,
                 ["expected at least one local map"], id="csv-no-maps"),
    pytest.param("maps.csv", b"map,kind\n\xff\xfe\n", read_one, ["expected UTF-8 text"], id="not-utf8"),
    pytest.param("localmap_1.mat", "this is not a mat file, just text", read_one,
                 ["expected a MATLAB v5 .mat file"], id="mat-not-a-mat-file"),
    pytest.param("localmap_1.mat", flipped(example_mat(False), 192, 88), read_one,
                 ["corrupt .mat file: numeric array 'localmap_st' is malformed"], id="mat-corrupt-type-code"),
    pytest.param("localmap_1.mat", example_mat(True)[:-10], read_one,
                 ["truncated .mat file"], id="mat-truncated"),
    pytest.param("localmap_1.mat", flipped(example_mat(True), 200, 0), read_one,
                 ["corrupt compressed data"], id="mat-corrupt-compressed"),
    pytest.param("localmap_1.mat", flipped(example_mat(True), 125, 2), read_one,
                 ["got version 0x0200 (save with -v7 or -v6)"], id="mat-v73"),
    pytest.param("localmap_1.mat", example_mat(localmap_P=None), read_one,
                 ["localmap_P: missing; expected the I-SLSJF variables localmap_st and localmap_P"],
                 id="mat-missing-P"),
    pytest.param("localmap_1.mat", example_mat(localmap_P=np.eye(5)), read_one,
                 ["localmap_P: expected 7x7 (the size of localmap_st), got (5, 5)"], id="mat-P-wrong-size"),
    pytest.param("localmap_1.mat", example_mat(localmap_st=np.array([[0, 1.0], [0, 2.0], [0, 0.1], [12, 3.0],
                                                                     [13, 4.0], [14, 5.0], [14, 6.0]])),
                 read_one, ["localmap_st row 4: feature id 12 on the x row but 13 on the y row (row 5)"],
                 id="mat-id-mismatch"),
    pytest.param("localmap_1.mat", example_mat(localmap_st=np.ones((6, 2))), read_one,
                 ["localmap_st: expected (3+2m)x2 [id, value] rows, got shape (6, 2)"], id="mat-state-shape"),
    pytest.param("localmap_1.mat", example_mat(localmap_st=np.array([[0, 1.0], [0, 2.0], [0, 0.1], [1.5, 3.0],
                                                                     [1.5, 4.0], [14, 5.0], [14, 6.0]])),
                 read_one, ["localmap_st row 4: expected a non-negative integer feature id, got 1.5"],
                 id="mat-fractional-id"),
    pytest.param("localmap_1.mat", example_mat(localmap_P=np.diag(np.arange(1.0, 8.0)) + np.eye(7, k=1)), read_one,
                 ["covariance: expected a symmetric matrix"], id="mat-asymmetric"),
    pytest.param("localmap_1.mat", example_mat(localmap_st="text"), read_one,
                 ["localmap_st: expected a real numeric matrix, got a char array"], id="mat-text-variable"),
    pytest.param("localmap_1.mat", example_mat(localmap_P=EXAMPLE_P * 1j), read_one,
                 ["localmap_P: expected a real numeric matrix, got a complex array"], id="mat-complex"),
    pytest.param("map.mat", example_mat(), read_one, ["name it localmap_<k>.mat"], id="mat-no-number"),
    pytest.param("empty", FOLDER, read_all, ["expected local-map files named localmap_<k>"], id="empty-folder"),
    pytest.param("missing.yaml", None, read_all, ["no such file or folder"], id="nonexistent-path"),
    pytest.param("missing*.yaml", None, read_all, ["no file matches"], id="glob-without-matches"),
    pytest.param("maps.txt", VALID_CSV, read_one, ["cannot tell the format from the extension '.txt'"],
                 id="unknown-extension"),
    pytest.param("maps.yaml", VALID_YAML, lambda path: mapio.read_global_map(path),
                 ["line 1, field format: expected mapjoin/global-map"], id="local-map-as-global-map"),
    pytest.param("localmap_1.yaml", VALID_YAML, writes_over_input, ["is the input file", "choose another output"],
                 id="output-is-input"),
]


@pytest.mark.parametrize("name, content, action, fragments", BAD_INPUTS)
def test_bad_input_raises_a_clear_input_error(tmp_path, name, content, action, fragments):
    path = tmp_path / name
    if content is FOLDER:
        path.mkdir()
    elif isinstance(content, bytes):
        path.write_bytes(content)
    elif isinstance(content, str):
        path.write_text(content)
    with pytest.raises(InputError) as raised:
        action(str(path))
    message = str(raised.value)
    assert message.startswith(str(path)) or str(path) in message
    for fragment in fragments:
        assert fragment in message


def test_unknown_stdin_format_asks_for_format():
    with pytest.raises(InputError, match=re.escape("<stdin>: cannot tell the format")) as raised:
        mapio.read_maps(["-"], stdin=io.StringIO("hello\n"))
    assert "give its format" in str(raised.value)


@pytest.mark.parametrize("text", ["", "\n", "  \n\t\n"])
def test_an_empty_stream_is_said_to_be_empty_not_of_unknown_format(text):
    with pytest.raises(InputError) as raised:
        mapio.read_maps(["-"], stdin=io.StringIO(text))
    assert str(raised.value) == "<stdin>: is empty"


def test_mat_cannot_come_from_a_text_stream():
    with pytest.raises(InputError, match="cannot be read from a text stream"):
        mapio.read_map_file(io.StringIO("x"), "mat")


def test_outputs_that_are_links_to_inputs_are_refused(tmp_path):
    source = tmp_path / "localmap_1.yaml"
    source.write_text(VALID_YAML)
    (tmp_path / "soft.yaml").symlink_to(source)
    os.link(source, tmp_path / "hard.yaml")
    for output in ("soft.yaml", "hard.yaml"):
        with pytest.raises(InputError, match="is the input file"):
            mapio.check_not_overwriting([str(source)], [str(tmp_path / output)])
    mapio.check_not_overwriting([str(source), "-"], [str(tmp_path / "new.csv"), "-"])


def test_outputs_reached_through_a_linked_folder_are_refused_whether_or_not_they_exist(tmp_path):
    folder = tmp_path / "maps"
    folder.mkdir()
    (folder / "localmap_1.yaml").write_text(VALID_YAML)
    (tmp_path / "alias").symlink_to(folder)
    for name in ("localmap_1.yaml", "not_yet.csv"):  # the same file, or the same path once links are resolved
        with pytest.raises(InputError, match=f"alias/{name}: is the input file .*maps/{name}"):
            mapio.check_not_overwriting([str(folder / "missing.yaml"), str(folder / name)],
                                          [str(tmp_path / "alias" / name)])
    mapio.check_not_overwriting([str(folder / "localmap_1.yaml")], [str(tmp_path / "alias" / "not_yet.csv")])


# ---------------------------------------------------------------------------------------
# Garbage: reading raises InputError or succeeds, never anything else

TEXT_READERS = [
    *(lambda text, fmt=fmt: mapio.read_map_file(io.StringIO(text), fmt) for fmt in ("yaml", "csv", None)),
    *(lambda text, fmt=fmt: mapio.read_global_map(io.StringIO(text), fmt) for fmt in ("yaml", "csv")),
    *(lambda text, fmt=fmt: mapio.read_truth(io.StringIO(text), fmt) for fmt in ("yaml", "csv")),
    lambda text: mapio.read_minima_table(io.StringIO(text)),
]
VALID_TEXTS = [
    VALID_YAML, VALID_CSV, covariance_yaml("[[1, 0, 0], [0, 1, 0], [0, 0, 1]]"),
    written(mapio.write_global_map, EXAMPLE_GLOBAL, "yaml"),
    written(mapio.write_global_map, EXAMPLE_GLOBAL, "csv"),
    written(mapio.write_truth, EXAMPLE_TRUTH, "yaml"), written(mapio.write_truth, EXAMPLE_TRUTH, "csv"),
    "a,c_phi\n5,2.5\n",
]
NASTY_TOKENS = ["", "nan", ".inf", "-1", "0", "1e999", "99999999999999999999999", "true", "null", "~", "[", "]",
                "{", "}", ",", ":", "'", '"', "---", "...", "&a", "*a", "!!python/object:os.system", "!!float x",
                "2001-13-45", "1.5", "pose", "feature", "\x00", "\t", "<<: *a", "? [1]", "é"]


def reads_or_refuses(text: str) -> None:
    for read in TEXT_READERS:
        try:
            read(text)
        except InputError:
            pass


@settings(deadline=None)
@given(st.text(max_size=300))
def test_random_text_only_raises_input_error(text):
    reads_or_refuses(text)


@settings(deadline=None)
@given(st.binary(max_size=300))
def test_random_bytes_only_raise_input_error(data):
    reads_or_refuses(data.decode("utf-8", errors="replace"))


@st.composite
def mutated_texts(draw) -> str:
    text = draw(st.sampled_from(VALID_TEXTS))
    how = draw(st.sampled_from(["truncate", "delete-line", "replace-token", "insert"]))
    if how == "truncate":
        return text[:draw(st.integers(0, len(text)))]
    if how == "delete-line":
        lines = text.splitlines(keepends=True)
        del lines[draw(st.integers(0, len(lines) - 1))]
        return "".join(lines)
    replacement = draw(st.sampled_from(NASTY_TOKENS) | st.text(max_size=4))
    if how == "insert":
        at = draw(st.integers(0, len(text)))
        return text[:at] + replacement + text[at:]
    token = draw(st.sampled_from(list(re.finditer(r"[^\s,:{}\[\]]+", text))))
    return text[:token.start()] + replacement + text[token.end():]


@settings(max_examples=400, deadline=None)
@given(mutated_texts())
def test_mutated_files_only_raise_input_error(text):
    reads_or_refuses(text)


@settings(deadline=None)
@given(st.binary(max_size=400) | st.sampled_from([example_mat(True), example_mat(False)]).flatmap(
    lambda data: st.tuples(st.integers(0, len(data)), st.integers(0, len(data) - 1), st.integers(0, 255),
                           st.booleans()).map(
        lambda cut: data[:cut[0]] if cut[3] else data[:cut[1]] + bytes([cut[2]]) + data[cut[1] + 1:])))
def test_garbage_mat_files_only_raise_input_error(scratch, data):
    path = scratch / "localmap_1.mat"
    path.write_bytes(data)
    try:
        mapio.read_map_file(path)
    except InputError as error:
        assert str(path) in str(error)


# ---------------------------------------------------------------------------------------
# Atomic writes


def test_atomic_write_writes_exactly_and_leaves_no_temporary_file(tmp_path):
    mapio.write_output("a,b\r\n1,2\n", tmp_path / "out.csv")
    assert (tmp_path / "out.csv").read_bytes() == b"a,b\r\n1,2\n"
    assert os.listdir(tmp_path) == ["out.csv"]


def test_a_failed_atomic_write_keeps_the_old_file(tmp_path, monkeypatch):
    path = tmp_path / "out.yaml"
    path.write_text("old")
    with pytest.raises(UnicodeEncodeError):
        mapio.write_output("new \ud800", path)
    def refuse(*args):
        raise PermissionError(13, "Permission denied")

    monkeypatch.setattr(os, "replace", refuse)
    with pytest.raises(InputError, match=re.escape(f"{path}: cannot write (Permission denied)")):
        mapio.write_output("new", path)
    assert path.read_text() == "old"
    assert os.listdir(tmp_path) == ["out.yaml"]


def test_atomic_write_into_a_missing_folder_names_the_file(tmp_path):
    with pytest.raises(InputError, match=re.escape(str(tmp_path / "no" / "out.csv"))):
        mapio.write_global_map(EXAMPLE_GLOBAL, tmp_path / "no" / "out.csv")
