"""The CSV layer's fast split and block reading on what they must still get right: a row of another width
named by its line, and maps with covariances read a batch of lines at a time (tests/test_csv_fast_paths.py
checks the split itself against Python's csv module).
"""

from __future__ import annotations

import io

import numpy as np
import pytest

from mapjoin.errors import InputError
from mapjoin.io import csv_blocks, csv_maps, csvtable
from mapjoin.simulation import simulate

@pytest.mark.parametrize("text, where", [("a,b\n1,2\n3\n", "line 3"), ("a,b\n1,2\n3,4,5\n", "line 3")])
def test_a_row_of_another_width_is_still_named_by_its_line(text, where):
    with pytest.raises(InputError, match=where):
        csvtable.Table(text, "t.csv", None)


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
