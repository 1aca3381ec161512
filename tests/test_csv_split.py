"""The CSV layer's fast split (``str.split`` on commas and line ends) against Python's csv module.

A CSV of local maps with full covariances has a row per covariance entry (10^7 rows for 10^4 maps), so
``csvtable.Table`` splits a plain text (no quotes, carriage returns, NULs or blank lines, every row as wide as
the header) with ``str.split``; every other text goes through :mod:`csv`. Both must give the same table.
"""

from __future__ import annotations

import io
import string

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mapjoin.errors import InputError
from mapjoin.io import csv_blocks, csv_maps, csvtable
from mapjoin.simulation import simulate

_CELL = st.text(alphabet=string.ascii_letters + string.digits + " \t.-+e_", max_size=6)


def _by_csv(text: str, offset: int = 0):
    """The header, cells and line numbers :mod:`csv` gives (the reference)."""
    header, body, lines = csvtable._split_csv(text, "t.csv", offset)
    return header, body, list(lines)


@settings(max_examples=300, deadline=None)
@given(width=st.integers(1, 5), data=st.data(), trailing=st.booleans(), offset=st.integers(0, 100))
def test_the_fast_split_is_csv_on_plain_text(width, data, trailing, offset):
    rows = data.draw(st.lists(st.lists(_CELL, min_size=width, max_size=width), min_size=1, max_size=8))
    text = "\n".join(",".join(row) for row in rows) + ("\n" if trailing else "")
    simple = csvtable._split_simple(text, offset)
    header, body, lines = _by_csv(text, offset)
    if text and "\n\n" not in text and not text.startswith("\n"):
        assert simple is not None   # no blank line: the fast split takes it
    if simple is not None:          # (a blank line it leaves to csv, which skips it)
        assert simple[0] == header
        assert simple[1].shape == (len(body), width)
        assert simple[1].tolist() == body
        assert list(simple[2]) == lines


@pytest.mark.parametrize("text", ['a,b\n"1",2\n', "a,b\r\n1,2\r\n", "a,b\n\n1,2\n", "a,b\n1,2\n3\n", "a,b\n1,2\n\n",
                                  "\na,b\n1,2\n", "", "a,b\n1,2,3\n"])
def test_the_fast_split_declines_what_csv_must_read(text):
    assert csvtable._split_simple(text, 0) is None


@pytest.mark.parametrize("text, where", [("a,b\n1,2\n3\n", "line 3"), ("a,b\n1,2\n3,4,5\n", "line 3")])
def test_a_row_of_another_width_is_still_named_by_its_line(text, where):
    with pytest.raises(InputError, match=where):
        csvtable.Table(text, "t.csv", None)


def test_a_table_is_the_same_either_way(monkeypatch):
    text = csv_maps.dump(simulate(6, seed=3, steps_per_map=2).maps)
    fast = csvtable.Table(text, "s.csv", None)
    monkeypatch.setattr(csvtable, "_split_simple", lambda text, offset: None)
    slow = csvtable.Table(text, "s.csv", None)
    assert fast.header == slow.header and fast.header_line == slow.header_line
    assert np.array_equal(fast.lines, slow.lines)
    assert fast.cells.dtype == slow.cells.dtype == object and fast.cells.tolist() == slow.cells.tolist()


@pytest.mark.parametrize("block", [7, 50, 1 << 16])
def test_maps_with_covariances_read_in_blocks_equal_the_whole_text(block, monkeypatch):
    """Blocks taken a batch of lines at a time, then line by line to a map's end: the maps of the whole text,
    covariances included, and a quoted name (the csv module's split) too."""
    maps = simulate(9, seed=4, steps_per_map=2).maps
    text = csv_maps.dump(maps)
    quoted = text.replace("sim-5,", '"sim,5",')
    monkeypatch.setattr(csv_blocks, "BLOCK_LINES", block)
    for source in (text, quoted):
        whole = csv_maps.read(source, "s.csv")
        blocks = list(csv_blocks.read_lines(io.StringIO(source, newline=""), "s.csv"))
        assert [m.name for m in blocks] == [m.name for m in whole]
        for a, b in zip(blocks, whole):
            assert np.array_equal(a.covariance, b.covariance) and np.array_equal(a.features, b.features)
    assert [m.name for m in whole][4].endswith("sim,5")
