"""The CSV layer's fast paths (``mapjoin.io.csvtable``) give exactly what the csv module gives.

Reading text without quotes, CR or NUL splits lines at commas instead of running ``csv.reader`` (all
cells at once when every line has as many);
writing rows of which none needs quoting replaces the CRLF record ends at once instead of record by
record. Both are compared here with the csv module used directly, on text and rows drawn to hit the
awkward cases (blank lines, blanks, quotes, line ends inside cells, a missing last line end).
"""

from __future__ import annotations

import csv
import io

from hypothesis import given, settings
from hypothesis import strategies as st

import numpy as np

from mapjoin.io.csvtable import Table, _rows, numeric_kind_text, to_text

pieces = st.sampled_from(["a", "1.5", "-2e-3", ",", "\n", "\n\n", " ", "\t", "x,y", "é", '"', '""', "\r\n", "\r",
                          "map", "kind"])
texts = st.lists(pieces, max_size=40).map("".join)


def reference_rows(text: str, offset: int) -> tuple[list[list[str]], list[int]]:
    """``csv.reader``'s rows with a cell and their lines (a malformed text: None)."""
    reader = csv.reader(io.StringIO(text, newline=""))
    rows, lines = [], []
    for row in reader:
        if row:
            rows.append(row)
            lines.append(reader.line_num + offset)
    return rows, lines


@settings(max_examples=400, deadline=None)
@given(texts, st.integers(0, 5))
def test_rows_are_the_csv_readers(text, offset):
    try:
        expected = reference_rows(text, offset)
    except csv.Error:
        return  # malformed (the csv module's own path handles it, and it has quotes)
    rows, lines = _rows(text, "s", offset)
    assert ([list(row) for row in rows], lines) == expected


def test_a_plain_table_reads_as_through_the_csv_module():
    text = "map,kind,x\n\nm1, pose ,1.5\nm2,feature,2\n"
    table = Table(text, "s", None)
    quoted = Table(text.replace("m1", '"m1"'), "s", None)   # the csv module's path
    assert table.cells.tolist() == quoted.cells.tolist() == [["m1", "pose", "1.5"], ["m2", "feature", "2"]]
    assert table.lines.tolist() == quoted.lines.tolist() == [3, 4]


cells = st.one_of(st.none(), st.integers(-10**6, 10**6), st.floats(allow_nan=False),
                  st.text(st.sampled_from(["a", ",", " ", '"', "\n", "\r", "é", "1"]), max_size=5))


@settings(max_examples=300, deadline=None)
@given(st.lists(st.lists(cells, min_size=1, max_size=5), max_size=8))
def test_written_text_is_the_csv_writers_with_lf_record_ends(rows):
    expected = []
    for row in rows:  # one record at a time, its CRLF end made LF (a CR or LF inside a cell is quoted)
        buffer = io.StringIO()
        csv.writer(buffer, lineterminator="\r\n").writerow(row)
        expected.append(buffer.getvalue()[:-2] + "\n")
    assert to_text(rows) == "".join(expected)


numeric_columns = st.integers(0, 6).flatmap(lambda count: st.lists(st.one_of(
    st.none(),
    st.lists(st.floats(width=64), min_size=count, max_size=count).map(lambda v: np.array(v, dtype=float)),
    st.lists(st.integers(-2**63, 2**63 - 1), min_size=count, max_size=count).map(lambda v: np.array(v, dtype=np.int64)),
), min_size=1, max_size=8).map(lambda columns: (count, columns)))


@settings(max_examples=300, deadline=None)
@given(numeric_columns, st.sampled_from(["feature", "pose"]))
def test_numeric_rows_are_written_as_the_csv_module_writes_them(counted, kind):
    """Integer and float columns (nan, infinities, -0.0, subnormals, the int64 extremes; None: empty cells) as
    ``csv.writer`` writes the rows ``[kind, *values]`` of their Python numbers, with LF line ends."""
    count, columns = counted
    buffer = io.StringIO()
    rows = [[kind, *(None if column is None else column[i].item() for column in columns)] for i in range(count)]
    csv.writer(buffer, lineterminator="\n").writerows(rows)
    assert numeric_kind_text(kind, count, columns) == buffer.getvalue()
