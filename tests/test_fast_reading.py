"""The fast readers (YAML as mapjoin writes it, Linear SLAM rows of plain decimals) give, bit for bit, the maps
and the errors of the line-tracking readers; YAML streams are read document by document."""

from __future__ import annotations

import contextlib
import dataclasses
import io
from collections.abc import Iterator
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from test_formats import assert_same, local_maps

from mapjoin import io as mapio
from mapjoin.errors import InputError
from mapjoin.io import linearslam, yaml_maps, yamldoc

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
