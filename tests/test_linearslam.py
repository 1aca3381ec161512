"""Linear SLAM text local maps, I-SLSJF .mat writing, g2o export, and convert between every pair of formats."""

from __future__ import annotations

import io
import itertools
import logging
import re
import tempfile
from pathlib import Path

import numpy as np
import pytest
import scipy.io
from cli_runner import run
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp
from test_formats import assert_same

from mapjoin import io as mapio
from mapjoin.errors import InputError
from mapjoin.io import linearslam
from mapjoin.maps import GlobalMap, LocalMap

EPS = np.finfo(float).eps
TXT_8240 = "linearslam_txt/8240_data_50_local_maps"
MAT_8240 = "8240_data_50_local_maps"


def parse_linearslam(path: Path) -> tuple[int, np.ndarray, np.ndarray, np.ndarray]:
    """A Linear SLAM file read independently of mapjoin (numpy's loadtxt): reference id, ids, values, information."""
    lines = path.read_text().splitlines()
    size = int(lines[1])
    state = np.loadtxt(lines[2:2 + size], ndmin=2)
    return int(lines[0]), state[:, 0].astype(np.int64), state[:, 1], np.loadtxt(lines[2 + size:2 + 2 * size], ndmin=2)


def full_covariance(local_map: LocalMap) -> np.ndarray:
    """The covariance a map stands for: its full one, else the diagonal of its spherical variances."""
    if local_map.covariance is not None:
        return local_map.covariance
    return np.diag(np.concatenate([local_map.pose_variances[[0, 0, 1]], np.repeat(local_map.feature_variances, 2)]))


def relative_error(actual: np.ndarray, expected: np.ndarray) -> float:
    return float(np.linalg.norm(actual - expected) / np.linalg.norm(expected))


# ---------------------------------------------------------------------------------------
# The distributed Linear SLAM files against the I-SLSJF ones


def test_linearslam_folder_reads_to_the_mat_folder_up_to_the_inversion(data_dir):
    txt = mapio.read_maps([str(data_dir / TXT_8240)])
    mat = mapio.read_maps([str(data_dir / MAT_8240)])
    assert [m.end_id for m in txt] == [m.end_id for m in mat] == list(range(1, 51))
    for a, b in zip(txt, mat):
        assert (a.start_id, a.end_id) == (b.start_id, b.end_id)
        assert np.array_equal(a.feature_ids, b.feature_ids)
        assert np.array_equal(a.end_pose, b.end_pose) and np.array_equal(a.features, b.features)
        _, ids, values, information = parse_linearslam(data_dir / TXT_8240 / f"localmap_{b.end_id}.txt")
        assert np.array_equal(ids[:3], [-b.end_id] * 3) and np.array_equal(ids[3:], np.repeat(b.feature_ids, 2))
        assert np.array_equal(values, np.concatenate([b.end_pose, b.features.ravel()]))
        condition = np.linalg.cond(b.covariance)
        # the stored matrix is the inverse of I-SLSJF's covariance (checked without mapjoin's inversion) ...
        residual = information @ b.covariance - np.eye(len(ids))
        assert np.linalg.norm(residual) <= 1e-9 * condition
        # ... and mapjoin's covariance from it is I-SLSJF's to rounding, amplified by the conditioning
        assert relative_error(a.covariance, b.covariance) <= 10 * condition * EPS


def test_joining_the_linearslam_folder_equals_joining_the_mat_folder(data_dir, tmp_path):
    for name, folder in (("txt", TXT_8240), ("mat", MAT_8240)):
        result = run("join", str(data_dir / folder), "-o", str(tmp_path / f"{name}.csv"))
        assert result.exit_code == 0, result.output
        assert "joined 50 maps: 612 features, 50 poses" in result.stderr
    a, b = (mapio.read_global_map(tmp_path / f"{name}.csv") for name in ("txt", "mat"))
    assert np.array_equal(a.feature_ids, b.feature_ids) and np.array_equal(a.pose_ids, b.pose_ids)
    assert np.abs(a.features - b.features).max() < 1e-9 and np.abs(a.poses - b.poses).max() < 1e-9


def test_written_information_matches_the_distributed_files(data_dir, tmp_path):
    result = run("convert", str(data_dir / MAT_8240), "-o", f"{tmp_path}/txt/", "--to", "linearslam")
    assert result.exit_code == 0, result.output
    for k in range(1, 51):
        ours = parse_linearslam(tmp_path / "txt" / f"localmap_{k}.txt")
        theirs = parse_linearslam(data_dir / TXT_8240 / f"localmap_{k}.txt")
        assert ours[0] == theirs[0] == k - 1
        assert np.array_equal(ours[1], theirs[1]) and np.array_equal(ours[2], theirs[2])
        # theirs inverts I-SLSJF's covariance as stored, asymmetric by rounding (up to 2.4e-9 relative);
        # mapjoin inverts its symmetric part, so the two agree on the symmetric part of theirs
        assert np.array_equal(ours[3], ours[3].T)
        condition = np.linalg.cond(ours[3])
        assert relative_error(ours[3], (theirs[3] + theirs[3].T) / 2) <= 10 * condition * EPS


def test_linearslam_to_mat_gives_the_i_slsjf_files(data_dir, tmp_path):
    result = run("convert", str(data_dir / TXT_8240), "-o", f"{tmp_path}/mat/", "--to", "mat")
    assert result.exit_code == 0, result.output
    for k in (1, 17, 50):
        ours = scipy.io.loadmat(tmp_path / "mat" / f"localmap_{k}.mat")
        theirs = scipy.io.loadmat(data_dir / MAT_8240 / f"localmap_{k}.mat")
        assert np.array_equal(ours["localmap_st"], theirs["localmap_st"])
        symmetric = (theirs["localmap_P"] + theirs["localmap_P"].T) / 2  # as stored: asymmetric by rounding
        assert np.array_equal(ours["localmap_P"], ours["localmap_P"].T)
        assert relative_error(ours["localmap_P"], symmetric) <= 10 * np.linalg.cond(symmetric) * EPS


# ---------------------------------------------------------------------------------------
# Round trips between every pair of local-map formats

FINITE = st.floats(-1e6, 1e6, allow_nan=False)  # coordinates and angles within every accepted range
VARIANCES = st.floats(1e-8, 1e8)
POSE_VARIANCES = st.floats(mapio.STAB_NOISE, 1e8)  # below, reading a .mat adds STAB_NOISE (I-SLSJF's rule)


@st.composite
def chain_maps(draw) -> LocalMap:
    """A map every format holds exactly: from pose k-1 to k and feature ids 1..2^53 (.mat, Linear SLAM), end-pose
    variances of at least STAB_NOISE (.mat)."""
    m = draw(st.integers(0, 4))
    end = draw(st.integers(1, 10**9))
    ids = np.array(draw(st.lists(st.integers(1, 2**53 - 1), min_size=m, max_size=m, unique=True)), dtype=np.int64)
    pose = draw(hnp.arrays(np.float64, (3,), elements=FINITE))
    features = draw(hnp.arrays(np.float64, (m, 2), elements=FINITE))
    if draw(st.booleans()):
        size = 3 + 2 * m
        rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
        root = rng.normal(size=(size, size)) * draw(st.sampled_from([1e-2, 1.0, 1e3]))
        covariance = root @ root.T + np.diag(rng.uniform(1e-4, 1.0, size)) * np.trace(root @ root.T) / size
        covariance[:3, :3] += np.eye(3) * mapio.STAB_NOISE
        return LocalMap.from_covariance("m", end - 1, end, pose, ids, features, (covariance + covariance.T) / 2)
    return LocalMap("m", end - 1, end, pose, ids, features, draw(hnp.arrays(np.float64, (m,), elements=VARIANCES)),
                    draw(hnp.arrays(np.float64, (2,), elements=POSE_VARIANCES)))


def through(local_map: LocalMap, fmt: str, folder: Path) -> LocalMap:
    """``local_map`` written as ``fmt`` into ``folder`` and read back."""
    [path] = mapio.write_maps([local_map], f"{folder}/{fmt}/", fmt)
    [back] = mapio.read_maps([path])
    return back


@settings(max_examples=40, deadline=None)
@given(chain_maps())
def test_every_pair_of_formats_round_trips(local_map):
    """Every format keeps a map's estimate exactly and the covariance it stands for (CSV: its spherical
    summary); only Linear SLAM text, which stores the inverse, rounds, within the conditioning."""
    expected = full_covariance(local_map)
    tolerance = 50 * np.linalg.cond(expected) * EPS
    with tempfile.TemporaryDirectory() as scratch:
        for first, second in itertools.product(mapio.MAP_FORMATS, repeat=2):
            pair = Path(scratch) / f"{first}-{second}"
            back = through(through(local_map, first, pair), second, pair)
            assert (back.start_id, back.end_id) == (local_map.start_id, local_map.end_id), (first, second)
            assert np.array_equal(back.feature_ids, local_map.feature_ids), (first, second)
            assert np.array_equal(back.end_pose, local_map.end_pose), (first, second)
            assert np.array_equal(back.features, local_map.features), (first, second)
            if "csv" in (first, second) and local_map.covariance is not None:
                actual, wanted = ((m.feature_variances, m.pose_variances) for m in (back, local_map))
                assert all(np.allclose(a, w, rtol=tolerance, atol=0) for a, w in zip(actual, wanted)), (first, second)
            elif "linearslam" in (first, second):
                assert relative_error(full_covariance(back), expected) <= tolerance, (first, second)
            else:
                assert np.array_equal(full_covariance(back), expected), (first, second)


@settings(max_examples=40, deadline=None)
@given(chain_maps())
def test_mat_files_written_are_what_scipy_reads(local_map):
    with tempfile.TemporaryDirectory() as scratch:
        [path] = mapio.write_maps([local_map], f"{scratch}/", "mat")
        assert Path(path).name == f"localmap_{local_map.end_id}.mat"
        variables = scipy.io.loadmat(path)
    expected_state = np.column_stack([np.concatenate([[0, 0, 0], np.repeat(local_map.feature_ids, 2)]),
                                      np.concatenate([local_map.end_pose, local_map.features.ravel()])])
    assert np.array_equal(variables["localmap_st"], expected_state)
    assert np.array_equal(variables["localmap_P"], full_covariance(local_map))


@settings(max_examples=40, deadline=None)
@given(chain_maps())
def test_linearslam_text_written_is_what_an_independent_reader_sees(local_map):
    stream = io.StringIO()
    mapio.write_maps([local_map], stream, "linearslam")
    with tempfile.TemporaryDirectory() as scratch:
        path = Path(scratch) / "localmap_1.txt"
        path.write_text(stream.getvalue())
        reference, ids, values, information = parse_linearslam(path)
    assert reference == local_map.start_id
    assert np.array_equal(ids, np.concatenate([[-local_map.end_id] * 3, np.repeat(local_map.feature_ids, 2)]))
    assert np.array_equal(values, np.concatenate([local_map.end_pose, local_map.features.ravel()]))
    covariance = full_covariance(local_map)
    assert np.array_equal(information, information.T)
    assert np.linalg.norm(information @ covariance - np.eye(len(ids))) <= 50 * np.linalg.cond(covariance) * EPS


def test_rows_in_another_order_read_to_the_same_map():
    ordered = "2\n5\n-3 1.0\n-3 2.0\n-3 0.5\n7 4.0\n7 5.0\n" + matrix_text(EXAMPLE_INFORMATION)
    order = [3, 4, 0, 1, 2]  # the feature first, then the pose
    lines = ordered.splitlines()
    shuffled = "\n".join(lines[:2] + [lines[2 + i] for i in order]
                         + [matrix_text(EXAMPLE_INFORMATION[np.ix_(order, order)]).rstrip("\n")]) + "\n"
    [a] = mapio.read_map_file(io.StringIO(ordered), "linearslam")
    [b] = mapio.read_map_file(io.StringIO(shuffled), "linearslam")
    assert np.array_equal(a.end_pose, b.end_pose) and np.array_equal(a.features, b.features)
    assert np.allclose(a.covariance, b.covariance, rtol=1e-14, atol=0)
    assert np.allclose(a.covariance @ EXAMPLE_INFORMATION, np.eye(5), atol=1e-14)


@pytest.mark.parametrize("upper", ["0.1", "0.10000000000000002", "1e-1", ".1"])
def test_the_matrix_is_read_whole_whether_or_not_its_text_is_symmetric(upper):
    """The reader parses only the lower triangle when the text mirrors itself; an upper triangle
    written differently (another digit within the symmetry tolerance, another spelling) is parsed
    too, and the map is the inverse of the symmetrised matrix (numpy's inverse, not mapjoin's)."""
    rows = [[repr(value) for value in row] for row in EXAMPLE_INFORMATION.tolist()]
    rows[1][2] = upper  # entry (2, 3); (3, 2) stays 0.1
    text = "2\n5\n-3 1.0\n-3 2.0\n-3 0.5\n7 4.0\n7 5.0\n" + "".join(" ".join(row) + "\n" for row in rows)
    [local_map] = mapio.read_map_file(io.StringIO(text), "linearslam")
    information = np.array([[float(value) for value in row] for row in rows])
    expected = np.linalg.inv((information + information.T) / 2)
    assert np.allclose(local_map.covariance, expected, rtol=1e-14, atol=1e-15)
    assert np.array_equal(local_map.covariance, local_map.covariance.T)


def test_a_map_without_features_reads():
    text = "0\n3\n-1 0.00088\n-1 -0.15647\n-1 0.01153\n" + matrix_text(EXAMPLE_INFORMATION[:3, :3])
    [local_map] = mapio.read_map_file(io.StringIO(text), "linearslam")
    assert local_map.size == 0 and local_map.end_id == 1
    assert np.allclose(local_map.covariance, np.linalg.inv(EXAMPLE_INFORMATION[:3, :3]), rtol=1e-14)


# ---------------------------------------------------------------------------------------
# Detection, folders, stdin


def test_localmap_txt_files_are_linearslam_and_other_txt_files_are_not():
    assert mapio.detect_format("maps/localmap_12.txt") == "linearslam"
    assert mapio.detect_format("global.g2o") == "g2o"
    with pytest.raises(InputError, match=re.escape("notes.txt: cannot tell the format from the extension '.txt'")):
        mapio.detect_format("notes.txt")


def test_folders_of_linearslam_files_are_read_in_map_order(tmp_path):
    for k in (10, 2, 1):
        (tmp_path / f"localmap_{k}.txt").write_text(example_text(start=k - 1, end=k))
    (tmp_path / "notes.txt").write_text("not a map")
    assert [m.end_id for m in mapio.read_maps([str(tmp_path)])] == [1, 2, 10]


def test_linearslam_text_on_stdin_is_recognised():
    result = run("convert", "-", "-o", "-", "--to", "csv", input=example_text())
    assert result.exit_code == 0, result.output
    assert result.stdout.splitlines()[1].startswith("<stdin>,2,3,pose,3,1.0,2.0,0.5,")


# ---------------------------------------------------------------------------------------
# Bad input

EXAMPLE_INFORMATION = np.diag([1.0, 2.0, 3.0, 4.0, 5.0]) + 0.1 * (np.eye(5, k=1) + np.eye(5, k=-1))


def matrix_text(matrix: np.ndarray) -> str:
    return "".join(" ".join(repr(value) for value in row) + "\n" for row in matrix.tolist())


def example_text(start: int = 2, end: int = 3, information: np.ndarray = EXAMPLE_INFORMATION) -> str:
    """A valid map from pose ``start`` to ``end`` with feature 7 (lines 6 and 7); the matrix is lines 8-12."""
    return f"{start}\n5\n-{end} 1.0\n-{end} 2.0\n-{end} 0.5\n7 4.0\n7 5.0\n" + matrix_text(information)


def replace_line(text: str, number: int, line: str) -> str:
    lines = text.splitlines()
    lines[number - 1] = line
    return "\n".join(lines) + "\n"


ASYMMETRIC = EXAMPLE_INFORMATION.copy()
ASYMMETRIC[0, 1] = 0.2
NOT_POSITIVE = EXAMPLE_INFORMATION.copy()
NOT_POSITIVE[3, 3] = -4.0
TWO_FEATURES = np.diag([1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0])

# (line, what it is replaced by, the message after "<file>, "); the example's lines 6-7 are feature 7
BAD_LINES = [
    (1, "x", "line 1: expected the reference pose index"),
    (2, "4", "line 2: expected the state dimension d = 3 + 2m (m features), got 4"),
    (2, "7", "line 8: expected `id value`, one of d = 7 state rows (2 fields), got 5 fields: '1.0 0.1 0.0 0.0 0.0'"),
    (2, "3", "line 6: expected a row of the 3x3 information matrix (3 fields), got 2 fields"),
    (5, "-3", "line 5: expected `id value`, one of d = 5 state rows (2 fields), got 1 fields: '-3'"),
    (6, "7 abc", "line 6: expected a finite number in field 2, got 'abc'"),
    (6, "7 nan", "line 6: expected a finite number in field 2, got 'nan'"),
    (7, "7.5 5.0", "line 7: expected an integer id in field 1, got '7.5'"),
    (10, "0.0 0.0 nan 3.0 0.1", "line 10: expected a finite number in field 3, got 'nan'"),
    (9, "0 1 2 3", "line 9: expected a row of the 5x5 information matrix (5 fields), got 4 fields"),
    (7, "8 5.0", "line 7: expected the y row of feature 7 (x on line 6), got id 8"),
    (5, "-4 0.5", ("line 3: expected one end pose: three consecutive rows with the same negative id -k; got negative "
                   "ids -3 on line 3, -3 on line 4, -4 on line 5")),
]
BAD_FILES = [
    ("\n".join(example_text().splitlines()[:10]),
     "line 11: expected a row of the 5x5 information matrix (5 fields), got the end of the file"),
    (example_text() + "1 2 3\n", "line 13: expected nothing after the 5 rows"),
    (example_text(information=ASYMMETRIC),
     "line 8: expected a symmetric information matrix, but entries (1, 2) and (2, 1) differ: 0.2 vs 0.1"),
    (example_text(information=NOT_POSITIVE),
     "line 11: expected a positive definite information matrix; its leading 4x4 block is not"),
    ("2\n7\n-3 1\n-3 2\n-3 0.5\n7 4\n7 5\n7 6\n7 7\n" + matrix_text(TWO_FEATURES),
     "line 8: duplicate feature id 7 (also on line 6)"),
    (example_text().replace("-3 ", "3 "),
     "line 3: expected one end pose: three consecutive rows with the same negative id -k; got negative ids none"),
    (example_text(start=3), "line 3: the end pose id 3 (rows with id -3) equals the reference pose index"),
]
BAD_LINEARSLAM = [(replace_line(example_text(), number, line), message) for number, line, message in BAD_LINES]
BAD_LINEARSLAM += BAD_FILES


@pytest.mark.parametrize("text, message", BAD_LINEARSLAM)
def test_bad_linearslam_input_names_the_file_and_line(tmp_path, text, message):
    path = tmp_path / "localmap_3.txt"
    path.write_text(text)
    with pytest.raises(InputError) as raised:
        mapio.read_maps([str(path)])
    assert str(raised.value).startswith(f"{path}, {message}")


def test_bad_linearslam_input_is_one_line_from_the_cli(tmp_path):
    (tmp_path / "localmap_1.txt").write_text(example_text(start=0, end=1))
    (tmp_path / "localmap_2.txt").write_text(replace_line(example_text(start=1, end=2), 6, "7 nan"))
    result = run("join", str(tmp_path))
    assert result.exit_code == 1
    assert result.stderr == (f"Error: {tmp_path / 'localmap_2.txt'}, line 6: expected a finite number in field 2, "
                             "got 'nan'\n")


# ---------------------------------------------------------------------------------------
# Writing: what each format cannot hold

MAP = LocalMap("m", 4, 5, [1.0, 2.0, 0.1], [3], [[4.0, 5.0]], [0.2], [0.1, 0.01])


@pytest.mark.parametrize("maps, target, fmt, message", [
    ([MAP], "localmap_7.mat", "mat", ("localmap_7.mat: an I-SLSJF .mat local map takes its number k (its end pose) "
                                      "from the file name; name this one localmap_5.mat")),
    ([MAP, MAP], "maps.mat", "mat", "maps.mat: a mat file holds one local map, got 2; write them to a folder"),
    ([MAP, MAP], "maps.txt", "linearslam", "maps.txt: a linearslam file holds one local map, got 2"),
    ([LocalMap("m", 2, 5, [0.0] * 3, [], np.zeros((0, 2)), [], [1.0, 1.0])], "dir/", "mat",
     ("m: cannot be written as an I-SLSJF .mat file, which holds map k from pose k-1 to pose k; this map runs from "
      "pose 2 to 5")),
    ([LocalMap("m", 1, 0, [0.0] * 3, [], np.zeros((0, 2)), [], [1.0, 1.0])], "dir/", "linearslam",
     "m: cannot be written as Linear SLAM text: its end pose id 0"),
    ([LocalMap("m", 4, 5, [0.0] * 3, [2**53], [[0.0, 0.0]], [1.0], [1.0, 1.0])], "dir/", "mat",
     "m: feature id 9007199254740992 is not exact as a double"),
    ([MAP], "-", "mat", "<stdout>: a .mat file cannot be written to stdout or a text stream"),
], ids=["mat-name", "mat-two-maps", "txt-two-maps", "mat-not-k-1-to-k", "txt-end-id-0", "mat-id-2^53", "mat-stdout"])
def test_maps_a_format_cannot_hold_are_refused(tmp_path, monkeypatch, maps, target, fmt, message):
    monkeypatch.chdir(tmp_path)
    with pytest.raises(InputError) as raised:
        mapio.write_maps(maps, target, fmt)
    assert str(raised.value).startswith(message)
    assert list(tmp_path.iterdir()) == []


def test_writing_feature_id_0_as_linearslam_warns(caplog):
    local_map = LocalMap("m", 0, 1, [0.0] * 3, [0], [[1.0, 2.0]], [1.0], [1.0, 1.0])
    with caplog.at_level(logging.WARNING, logger="mapjoin"):
        [back] = mapio.read_map_file(io.StringIO(formats_text(local_map)), "linearslam")
    assert "feature id 0 written as Linear SLAM text" in caplog.text
    assert back.feature_ids.tolist() == [0]


def test_writing_a_mat_file_a_reader_will_stabilise_warns(tmp_path, caplog):
    still = LocalMap("m", 0, 1, [0.0] * 3, [], np.zeros((0, 2)), [], [1e-8, 1e-8])
    with caplog.at_level(logging.WARNING, logger="mapjoin"):
        [path] = mapio.write_maps([still], f"{tmp_path}/", "mat")
        [back] = mapio.read_maps([path])
    assert "reading the .mat file back adds 1e-06 to the pose diagonal" in caplog.text
    assert np.array_equal(np.diagonal(back.covariance), [1e-8 + 1e-6] * 2 + [1e-8 + 1e-6])


def formats_text(local_map: LocalMap) -> str:
    stream = io.StringIO()
    mapio.write_maps([local_map], stream, "linearslam")
    return stream.getvalue()


def test_convert_writes_a_single_map_file_named_for_mat(tmp_path):
    (tmp_path / "localmap_3.txt").write_text(example_text())
    result = run("convert", str(tmp_path / "localmap_3.txt"), "-o", str(tmp_path / "localmap_3.mat"))
    assert result.exit_code == 0, result.output
    [back] = mapio.read_maps([str(tmp_path / "localmap_3.mat")])
    assert (back.start_id, back.end_id) == (2, 3)
    result = run("convert", str(tmp_path / "localmap_3.txt"), "-o", str(tmp_path / "map.mat"))
    assert result.exit_code == 1 and "name this one localmap_3.mat" in result.stderr


# ---------------------------------------------------------------------------------------
# g2o export of a global map

G2O_FIELDS = {"VERTEX_SE2": 5, "VERTEX_XY": 4}


def parse_g2o(text: str) -> tuple[dict[int, list[float]], dict[int, list[float]], list[str]]:
    """A strict reading of a g2o vertex file: every line a comment or a vertex with an unused 32-bit id."""
    poses, points, comments, seen = {}, {}, [], set()
    for line in text.splitlines():
        fields = line.split()
        if not fields or fields[0].startswith("#"):
            comments.append(line)
            continue
        assert G2O_FIELDS.get(fields[0]) == len(fields), line
        vertex = int(fields[1])
        assert 0 <= vertex < 2**31 and vertex not in seen, line
        seen.add(vertex)
        values = [float(value) for value in fields[2:]]
        assert all(np.isfinite(values)), line
        (poses if fields[0] == "VERTEX_SE2" else points)[vertex] = values
    return poses, points, comments


@st.composite
def global_maps(draw) -> GlobalMap:
    n, p = draw(st.integers(0, 5)), draw(st.integers(0, 5))
    def ids(size: int, top: int) -> np.ndarray:
        return np.array(draw(st.lists(st.integers(0, top), min_size=size, max_size=size, unique=True)), dtype=np.int64)

    return GlobalMap(ids(n, 10**6), draw(hnp.arrays(np.float64, (n, 2), elements=FINITE)), np.ones(n),
                     ids(p, 10**5), draw(hnp.arrays(np.float64, (p, 3), elements=FINITE)), np.ones((p, 2)))


@settings(max_examples=60, deadline=None)
@given(global_maps())
def test_g2o_export_is_a_valid_vertex_file_with_the_stated_ids(global_map):
    stream = io.StringIO()
    mapio.write_global_map(global_map, stream, "g2o")
    poses, points, comments = parse_g2o(stream.getvalue())
    offset = int(re.search(r"VERTEX_XY <feature id \+ ([0-9]+)>", comments[0])[1])
    assert offset > max(global_map.pose_ids.tolist(), default=0) and str(offset).strip("0") == "1"
    assert poses == {i: pose for i, pose in zip(global_map.pose_ids.tolist(), global_map.poses.tolist())}
    assert points == {i + offset: xy for i, xy in zip(global_map.feature_ids.tolist(), global_map.features.tolist())}


def test_join_writes_g2o(data_dir, tmp_path):
    result = run("join", str(data_dir / "VicPark_200_local_maps"), "-o", str(tmp_path / "vicpark.g2o"))
    assert result.exit_code == 0, result.output
    poses, points, comments = parse_g2o((tmp_path / "vicpark.g2o").read_text())
    assert sorted(poses) == list(range(1, 201)) and len(points) == 299 and min(points) > 1000
    assert "VERTEX_XY <feature id + 1000>" in comments[0]


def test_g2o_ids_beyond_32_bits_are_refused():
    global_map = GlobalMap(np.array([2**31]), np.zeros((1, 2)), np.ones(1), np.array([1]), np.zeros((1, 3)),
                           np.ones((1, 2)))
    with pytest.raises(InputError, match="vertex id 2147483658 does not fit g2o's 32-bit ids"):
        mapio.write_global_map(global_map, io.StringIO(), "g2o")


def test_g2o_is_write_only():
    with pytest.raises(InputError, match="cannot read a global map as g2o; expected one of csv, yaml"):
        mapio.read_global_map(io.StringIO("VERTEX_SE2 1 0 0 0\n"), "g2o")


# ---------------------------------------------------------------------------------------
# A folder read at once (inverted and checked a stack per size) against its files read one by one

FAR_POSE = example_text().replace("-3 1.0\n", "-3 1e10\n")  # parses; the map's check refuses x = 1e10 m
FOLDER_FILES = [example_text(), "2\n7\n-3 1\n-3 2\n-3 0.5\n7 4\n7 5\n8 6\n8 7\n" + matrix_text(TWO_FEATURES),
                example_text(information=EXAMPLE_INFORMATION * 3.5), FAR_POSE,
                example_text(information=NOT_POSITIVE), FAR_POSE.replace(matrix_text(EXAMPLE_INFORMATION),
                                                                         matrix_text(NOT_POSITIVE)),
                *(text for text, _ in BAD_LINEARSLAM[::3])]


def test_a_map_failing_inversion_and_its_checks_reports_the_inversion(tmp_path):
    """In a file's order: its information is inverted, then the map checked (a far pose)."""
    path = tmp_path / "localmap_3.txt"
    path.write_text(FOLDER_FILES[5])
    with pytest.raises(InputError, match="line 11: expected a positive definite information matrix"):
        mapio.read_maps([str(tmp_path)])
    path.write_text(FAR_POSE)
    with pytest.raises(InputError, match="end_pose: expected finite coordinates"):
        mapio.read_maps([str(tmp_path)])


def one_by_one(paths: list[Path]) -> list[LocalMap] | str:
    """The files read in turn with ``linearslam.read``: their maps, or the first error's message."""
    maps = []
    try:
        for path in paths:
            maps += linearslam.read(path.read_text(), str(path))
    except InputError as error:
        return str(error)
    return maps


@settings(deadline=None, max_examples=60)
@given(st.lists(st.integers(0, len(FOLDER_FILES) - 1), min_size=1, max_size=7))
def test_a_folder_read_at_once_is_its_files_read_one_by_one(choices):
    with tempfile.TemporaryDirectory() as folder:
        paths = []
        for k, choice in enumerate(choices, 1):
            text = FOLDER_FILES[choice].replace("2\n", f"{2 * k}\n", 1).replace("-3 ", f"-{2 * k + 1} ")
            paths.append(Path(folder) / f"localmap_{k}.txt")
            paths[-1].write_text(text)
        expected = one_by_one(paths)
        try:
            maps = mapio.read_maps([folder])
        except InputError as error:
            assert str(error) == expected
            return
        assert not isinstance(expected, str), expected
        assert len(maps) == len(expected)
        for a, b in zip(maps, expected):
            assert_same(a, b)
