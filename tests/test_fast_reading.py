"""The fast readers (YAML as mapjoin writes it, Linear SLAM rows of plain decimals) give, bit for bit, the maps
and the errors of the line-tracking readers; YAML streams are read document by document."""

from __future__ import annotations

import contextlib
import dataclasses
import io
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from test_formats import assert_same, local_maps, same_array

from mapjoin import io as mapio
from mapjoin.errors import InputError
from mapjoin.io import linearslam, numbers, yaml_maps, yamldoc
from mapjoin.maps import LocalMap

DATASETS = ("VicPark_200_local_maps", "DLR_200_local_maps", "8240_data_50_local_maps", "535_data_5_local_maps")


@contextlib.contextmanager
def line_tracking() -> Iterator[None]:
    """Readers with their fast paths off: every document and file is read by the line-tracking path."""
    fast_yaml, fast_rows = yaml_maps._fast_document, linearslam._plain_rows
    yaml_maps._fast_document, linearslam._plain_rows = (lambda text: None), (lambda lines, size: None)
    try:
        yield
    finally:
        yaml_maps._fast_document, linearslam._plain_rows = fast_yaml, fast_rows


def both_ways(read, *args):
    """``read(*args)`` with the fast paths and with line tracking only."""
    fast = read(*args)
    with line_tracking():
        return fast, read(*args)


def outcome(read, *args):
    """``read(*args)``, or the message of the error it raises."""
    try:
        return read(*args)
    except InputError as error:
        return str(error)


def assert_same_maps(actual, expected) -> None:
    assert len(actual) == len(expected)
    for a, b in zip(actual, expected):
        assert_same(a, b)


def fast_documents(text: str) -> int:
    """How many documents of a YAML stream the fast path parses."""
    return sum(yaml_maps._fast_document(chunk) is not None
               for _, chunk in yamldoc.split_documents(io.StringIO(text, newline="")))


@pytest.mark.parametrize("dataset", DATASETS)
def test_fast_and_line_tracking_readers_agree_on_the_real_datasets(data_dir, tmp_path, dataset):
    maps = mapio.read_maps([str(data_dir / dataset)])
    stream = tmp_path / "maps.yaml"
    mapio.write_maps(maps, stream, "yaml")
    assert fast_documents(stream.read_text()) == len(maps)
    mapio.write_maps(maps, f"{tmp_path}/yaml/", "yaml")
    mapio.write_maps(maps[:20], f"{tmp_path}/txt/", "linearslam")  # (inverting covariances takes a while)
    mapio.write_maps(maps, tmp_path / "maps.csv", "csv")
    for source in (stream, tmp_path / "yaml", tmp_path / "txt", tmp_path / "maps.csv"):
        fast, tracked = both_ways(mapio.read_maps, [str(source)])
        assert_same_maps(fast, tracked)
    with stream.open() as file:  # a stream, read as stdin is
        fast = mapio.read_map_file(file, "yaml", name="<stdin>")
    assert_same_maps(fast, mapio.read_map_file(io.StringIO(stream.read_text()), "yaml", name="<stdin>"))
    for path in (tmp_path / "txt").iterdir():
        text = path.read_text()
        lines = text.splitlines()
        assert linearslam._plain_rows(lines, int(lines[1])) is not None


@settings(deadline=None, max_examples=50)
@given(st.lists(local_maps(), min_size=1, max_size=4))
def test_fast_and_line_tracking_readers_agree_on_written_maps(maps):
    text = io.StringIO()
    mapio.write_maps(maps, text, "yaml")
    fast, tracked = both_ways(yaml_maps.read, text.getvalue(), "s.yaml")
    assert_same_maps(fast, tracked)
    for local_map in maps:
        with contextlib.suppress(InputError):  # a map Linear SLAM text cannot hold (end id 0, singular)
            text = linearslam.dump([local_map])
            fast, tracked = both_ways(outcome, linearslam.read, text, "m.txt")
            if isinstance(fast, str):  # both refuse it alike (e.g. huge variances, whose inverse rounds to 0)
                assert fast == tracked
            else:
                assert_same_maps(fast, tracked)


def written_stream(count: int = 3) -> str:
    maps = mapio.read_maps(["-"], stdin=io.StringIO(_SIMULATED), format="yaml")[:count]
    text = io.StringIO()
    mapio.write_maps(maps, text, "yaml")
    return text.getvalue()


_SIMULATED = ""


@pytest.fixture(scope="module", autouse=True)
def simulated_stream(simulated_folder):
    """Three of the simulated maps, as one YAML stream (:func:`written_stream`)."""
    global _SIMULATED
    _SIMULATED = "".join(path.read_text() for path in sorted(Path(simulated_folder).glob("localmap_*.yaml"))[:3])


@pytest.mark.parametrize(("old", "new"), [
    ("var: ", "var: -"),                         # a variance <= 0
    ("- {id: ", "- {id: 7, x: 0.0, y: 0.0, var: 1.0}\n- {id: 7, x: 0.0, y: 0.0, var: 1.0}\n- {id: "),  # duplicate
    ("x: ", "x: 1.0e999"),                       # not finite (inf)
    ("end_id: ", "end_id: 99999999999999999999"),  # an id beyond 64 bits
    ("version: 1", "version: 2"),
    ("format: mapjoin/local-map", "format: other"),
    ("- [", "- [1.0, "),                          # a covariance row too long
    ("covariance:\n", "covariance:\n- [1.0]\n"),  # a row too many
    ("phi: ", "phi: 1e-3, var_pih: "),            # an unknown field close to a known one (a typo)
])
def test_errors_of_fast_documents_name_the_line_as_before(old, new):
    text = written_stream()
    last = text.rindex("\n---\n") + 1
    broken = text[:last] + text[last:].replace(old, new, 1)
    errors = []
    for read in (lambda: yaml_maps.read(broken, "s.yaml"), lambda: list(yaml_maps.read_lines(
            io.StringIO(broken, newline=""), "s.yaml"))):
        for tracking in (False, True):
            with line_tracking() if tracking else contextlib.nullcontext(), pytest.raises(InputError) as error:
                read()
            errors.append(str(error.value))
    assert len(set(errors)) == 1, errors
    assert "line " in errors[0]


def test_a_stream_is_read_document_by_document():
    text = written_stream()
    documents = [chunk for _, chunk in yamldoc.split_documents(io.StringIO(text, newline=""))] * 3

    class Documents(io.TextIOBase):
        """A stream handing out one document per read, counting the reads."""

        reads = 0

        def read(self, size: int = -1) -> str:
            self.reads += 1
            return documents[self.reads - 1] if self.reads <= len(documents) else ""

    stream = Documents()
    maps = mapio.iter_map_file(stream, "yaml", name="<stdin>")
    first = next(maps)
    assert stream.reads == 3  # the first document, the second to know the first is numbered, the third's start
    assert first.name.startswith("<stdin>#")  # named as one of several
    assert len([first, *maps]) == len(documents)


def test_directives_comments_and_document_ends_stay_with_their_document():
    text = "# head\n%YAML 1.1\n---\na: 1\n...\n# between\n%YAML 1.1\n--- \nb: 2\n---\r\nc: 3\n"
    chunks = list(yamldoc.split_documents(io.StringIO(text, newline="")))
    assert [line for line, _ in chunks] == [0, 6, 9]
    assert "".join(chunk for _, chunk in chunks) == text
    assert [len(yamldoc.documents(chunk, "s")) for _, chunk in chunks] == [1, 1, 1]



NAMES = ["../shared/data/localmap_1.mat", "./maps/m.yaml", "map 1", "0001", "1e5", "yes", "null", "-", "<stdin>#3",
         "a: b", "#x", "'quoted'", "tab\there", "ü/ß.mat", " padded", "x # not a comment", "[1, 2]", ".5", "~", ""]


@pytest.mark.parametrize("name", NAMES)
def test_any_written_name_is_read_fast_and_as_the_line_tracking_reader_reads_it(name):
    """The name line (a path, often relative) does not send a document to the slow path (``../`` did)."""
    first = mapio.read_maps(["-"], stdin=io.StringIO(_SIMULATED), format="yaml")[0]
    text = io.StringIO()
    mapio.write_maps([dataclasses.replace(first, name=name)], text, "yaml")
    assert fast_documents(text.getvalue()) == 1
    fast, tracked = both_ways(yaml_maps.read, text.getvalue(), "s.yaml")
    assert_same_maps(fast, tracked)
    assert yaml_maps._fast_document(text.getvalue())["name"] == name


# ---------------------------------------------------------------------------------------
# Matrices read by their lower triangle, and number spellings the fast paths may or may not take

#: spellings of a number x, each a function of x (None: not for this x), and fixed texts, plain or not
SPELLINGS = [
    repr,
    lambda x: f"{x:.17e}",                                      # 1.23e+00: an exponent with its sign
    lambda x: f"{x:.17E}".replace("E+", "E"),                   # 1.23E00: without (YAML 1.1 wants one)
    lambda x: f"+{x!r}" if x >= 0 else None,
    lambda x: repr(x).replace("0.", ".", 1) if repr(x).lstrip("-").startswith("0.") else None,  # .5, -.5
    lambda x: repr(x).replace(".", "", 1) if repr(x).endswith(".0") else None,  # 10 from 1.0 (an int to YAML)
    lambda x: ("-0" if x < 0 else "0") + repr(abs(x)),          # leading zero: 01.5
    lambda x: repr(x).replace("0", "_0", 1) if "0" in repr(x)[1:] else None,
    *(lambda x, text=text: text for text in (
        "1", "-0", "0", "08", "-.5", ".5", "5.", "1e5", "1.e5", ".5e-3", "-.5e3", "+.5", "1.5e+3", "1.0e999",
        ".inf", "-.inf", ".nan", "inf", "nan", "1_0.0", "0x10", "\uff11.0", "1.5.5", "1e", ".", "-", "e5")),
]


_OF_VALUE = 8  # the first spellings depend on the value; the rest are fixed texts


def spelled(x: float, spelling) -> str:
    """x in ``spelling`` (one of :data:`SPELLINGS`), or as repr writes it when that one is not for x."""
    text = spelling(x)
    return repr(x) if text is None else text


@st.composite
def spelled_matrices(draw, values: np.ndarray) -> list[list[str]]:
    """The symmetric matrix ``values`` as rows of number texts: as repr writes them, some otherwise spelled
    (in some examples only by spellings of their own value); the text mirrors itself unless one entry is
    spelled anew (often as the same number)."""
    size = len(values)
    spellings = st.sampled_from(SPELLINGS[:_OF_VALUE] if draw(st.booleans()) else SPELLINGS)
    rows = [[""] * size for _ in range(size)]
    for i in range(size):
        for j in range(i + 1):
            rows[i][j] = rows[j][i] = spelled(float(values[i, j]), draw(spellings) if draw(st.booleans()) else repr)
    if draw(st.booleans()):
        i, j = draw(st.integers(0, size - 1)), draw(st.integers(0, size - 1))
        rows[i][j] = spelled(float(values[i, j]), draw(st.sampled_from(SPELLINGS)))
    return rows


def float_or_none(text: str) -> float | None:
    try:
        return float(text)
    except ValueError:
        return None


@settings(deadline=None, max_examples=200)
@given(st.data(), st.integers(2, 6))
def test_a_matrix_is_read_as_every_token_read_by_float(data, size):
    """:func:`numbers.symmetric_matrix` against reading each token with float (brute force); it checks and
    reads the lower triangle alone exactly when the text mirrors itself."""
    values = np.arange(size * size, dtype=float).reshape(size, size) / 7
    rows = data.draw(spelled_matrices(values + values.T))
    tokens = [token for row in rows for token in row]
    checked = []
    matrix = numbers.symmetric_matrix(tokens, size, lambda read: checked.append(list(read)) or True)
    mirrored = all(rows[i][j] == rows[j][i] for i in range(size) for j in range(size))
    [read] = checked
    assert len(read) == (size * (size + 1) // 2 if mirrored else size * size)
    expected = [float_or_none(token) for token in tokens]
    if None in expected:
        assert matrix is None
    else:
        assert np.array_equal(matrix, np.array(expected).reshape(size, size), equal_nan=True)
        assert np.array_equal(np.signbit(matrix), np.signbit(np.array(expected).reshape(size, size)))
    assert numbers.symmetric_matrix(tokens, size, lambda read: False) is None
    assert numbers.symmetric_matrix(tokens[:-1], size, lambda read: True) is None


@settings(deadline=None, max_examples=200)
@given(st.data(), st.integers(2, 6), st.sampled_from([", ", " "]))
def test_the_lower_triangle_of_mirrored_rows_is_found_as_splitting_every_row_finds_it(data, size, separator):
    """:func:`numbers.mirrored_lower` against splitting each row whole and comparing the tokens (brute force),
    on rows that mirror themselves or not, with a token too many or too few, or another separator."""
    values = np.arange(size * size, dtype=float).reshape(size, size) / 7
    matrix = data.draw(spelled_matrices(values + values.T))
    rows = [separator.join(row) for row in matrix]
    change = data.draw(st.sampled_from(["none", "none", "extra", "missing", "separator", "swap"]))
    i = data.draw(st.integers(0, size - 1))
    if change == "extra":
        rows[i] += separator + "1.0"
    elif change == "missing":
        rows[i] = rows[i].rpartition(separator)[0]
    elif change == "separator":
        rows[i] = rows[i].replace(separator, separator + " ", 1)
    elif change == "swap" and i < size - 1:
        rows[i], rows[i + 1] = rows[i + 1], rows[i]
    cells = [row.split(separator) for row in rows]
    mirrored = (all(len(row) == size for row in cells)
                and all(cells[i][j] == cells[j][i] for i in range(size) for j in range(size)))
    expected = [cells[i][j] for i in range(size) for j in range(i + 1)] if mirrored else None
    assert numbers.mirrored_lower(rows, separator, size) == expected
    if mirrored and None not in map(float_or_none, expected):
        assert same_array(numbers.lower_matrix(expected, size),
                          np.array([[float(token) for token in row] for row in cells]))


def yaml_covariance(rows: list[list[str]], layout: str) -> str:
    """Covariance rows as YAML: as mapjoin writes them, or with one change of ``layout``."""
    separators = [", "] * len(rows)
    if layout in ("comma", "spaces"):
        separators[-1] = {"comma": ",", "spaces": ",  "}[layout]
    lines = [f"- [{separator.join(row)}]\n" for separator, row in zip(separators, rows)]
    if layout == "comment":
        lines.insert(1, "# a comment\n")
    elif layout == "trailing":
        lines.append("# the end\n")
    elif layout == "block":
        lines[-1] = "- " + "  ".join(f"- {token}\n" for token in rows[-1])
    elif layout == "crlf":
        lines[0] = lines[0].replace("\n", "\r\n")
    return "covariance:\n" + "".join(lines)


def pyyaml_matrix(text: str) -> np.ndarray | None:
    """The covariance PyYAML (mapjoin's loader) reads from a document, if all its entries are finite numbers."""
    try:
        [document] = yamldoc.documents(text, "s.yaml")
    except InputError:
        return None
    rows = document.data["covariance"]
    entries = [value for row in rows for value in row]
    if any(type(value) not in (int, float) for value in entries) or not np.isfinite(entries).all():
        return None
    return np.array(rows, dtype=float)


@settings(deadline=None, max_examples=150)
@given(local_maps(covariance=st.just(True)), st.data(),
       st.sampled_from(["flow"] * 4 + ["comma", "spaces", "comment", "trailing", "block", "crlf"]))
def test_the_fast_yaml_covariance_is_what_pyyaml_reads(local_map, data, layout):
    """Whatever the fast path reads is PyYAML's reading, bit for bit; whatever it leaves, the line-tracking
    path reads: the same maps, or the same error, either way."""
    head = yaml_maps.dump([local_map]).split("covariance:\n")[0]
    text = head + yaml_covariance(data.draw(spelled_matrices(local_map.covariance)), layout)
    fast = yaml_maps._fast_document(text)
    expected = pyyaml_matrix(text)
    if fast is not None and np.isfinite(fast["covariance"]).all():  # (not finite: the checks send it on)
        assert expected is not None
        assert same_array(fast["covariance"], expected)
    fast_maps, tracked = both_ways(outcome, yaml_maps.read, text, "s.yaml")
    if isinstance(fast_maps, str):
        assert fast_maps == tracked
    else:
        assert_same_maps(fast_maps, tracked)


@pytest.mark.parametrize(("spelling", "fast"), [
    ("1.5", True), ("-1.5e-03", True), (".5", True), ("1.5e3", True), ("1.5E+3", True), ("+1.5", True),
    ("01.5", True), ("5.", True), (".5e-3", True),
    ("-.5", False), ("+.5", False), ("-.5e3", False), ("1", False), ("-0", False), ("08", False), ("1e5", False),
    ("1_0.0", False), (".inf", False), ("inf", False), ("nan", False), ("\uff11.0", False), ("1.5.5", False)])
def test_which_spellings_the_fast_yaml_path_reads(spelling, fast):
    """Floats with a point go fast (when the text mirrors itself, through the lower triangle); integers,
    ``-.5`` (text to YAML 1.1) and anything not a decimal go to PyYAML."""
    local_map = LocalMap.from_covariance("m", 0, 1, [0.0, 0.0, 0.0], [], np.empty((0, 2)), np.eye(3))
    head = yaml_maps.dump([local_map]).split("covariance:\n")[0]
    rows = [[spelling if i == j == 0 else repr(float(i == j)) for j in range(3)] for i in range(3)]
    parsed = yaml_maps._fast_document(head + yaml_covariance(rows, "flow"))
    assert (parsed is not None) == fast
    if fast:
        assert parsed["covariance"][0, 0] == float(spelling)


def linearslam_text(local_map: LocalMap, rows: list[list[str]], separator: str) -> str:
    """A map as Linear SLAM text with the information matrix ``rows`` (texts) joined by ``separator``."""
    lines = linearslam.dump([local_map]).splitlines()
    size = int(lines[1])
    return "\n".join([*lines[:2 + size], *(separator.join(row) for row in rows)]) + "\n"


@settings(deadline=None, max_examples=100)
@given(local_maps(covariance=st.just(True)), st.data(), st.sampled_from([" ", " ", "\t", "  ", " \u3000"]))
def test_the_fast_linearslam_rows_are_what_line_tracking_reads(local_map, data, separator):
    """Linear SLAM text spelled otherwise: the fast path's maps or errors are the line-tracking path's."""
    with contextlib.suppress(InputError):  # a map Linear SLAM text cannot hold (end id 0, singular)
        lines = linearslam.dump([local_map]).splitlines()
        size = int(lines[1])
        information = np.array([[float(token) for token in line.split()] for line in lines[2 + size:]])
        text = linearslam_text(local_map, data.draw(spelled_matrices(information)), separator)
        fast, tracked = both_ways(outcome, linearslam.read, text, "m.txt")
        if isinstance(fast, str):
            assert fast == tracked
        else:
            assert_same_maps(fast, tracked)
