"""Streaming joins: a stream of maps joined as it is read equals the join of the same maps in memory, bit for bit;
its memory does not grow with the stream; an error anywhere in the stream writes nothing; the simulator and the
CSV reader stream with the same output as at once."""

from __future__ import annotations

import dataclasses
import io
import logging
import tracemalloc
from itertools import chain

import numpy as np
import pytest
from cli_runner import run
from hypothesis import given, settings
from hypothesis import strategies as st

from mapjoin import InputError, JoinError
from mapjoin import io as mapio
from mapjoin.faults import corrupted
from mapjoin.io import csv_blocks, csv_maps
from mapjoin.io.outputs import Outputs, Parts
from mapjoin.joining import join, join_sequential
from mapjoin.simulation import simulate, simulate_stream
from mapjoin.streaming import join_stream

_GLOBAL_FIELDS = ("feature_ids", "features", "feature_variances", "pose_ids", "poses", "pose_variances")


def _assert_same_join(streamed, in_memory) -> None:
    """Every array of the global map equal (not close), the provenance and every report record equal."""
    for name in _GLOBAL_FIELDS:
        a, b = getattr(streamed.global_map, name), getattr(in_memory.global_map, name)
        assert a.shape == b.shape and np.array_equal(a, b), name
    assert streamed.global_map.provenance == in_memory.global_map.provenance
    assert len(streamed.report) == len(in_memory.report)
    assert list(streamed.report) == list(in_memory.report)


def _text(maps, fmt: str) -> str:
    stream = io.StringIO()
    mapio.write_maps(maps, stream, fmt)
    return stream.getvalue()


@settings(max_examples=25, deadline=None)
@given(count=st.integers(1, 40), seed=st.integers(0, 2**16), chunk=st.integers(1, 9),
       fmt=st.sampled_from(["yaml", "csv"]), block=st.integers(2, 200),
       covariance=st.sampled_from(["information", "marginal", "identity"]))
def test_a_streamed_join_equals_the_join_in_memory(count, seed, chunk, fmt, block, covariance):
    """A simulated stream in both formats, read map by map (CSV in blocks of ``block`` lines) and joined ``chunk``
    maps at a time, gives the very numbers of reading the whole text and joining the list."""
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(csv_blocks, "BLOCK_LINES", block)
        patch.setattr(logging.getLogger("mapjoin"), "disabled", True)  # the simulated runs' inconsistent joins
        text = _text(simulate(count, seed=seed, steps_per_map=3, full_covariance=fmt == "yaml").maps, fmt)
        in_memory = join(mapio.registry.by_name[fmt].local_maps.read(text, "<stdin>"), covariance)
        streamed = join_stream(mapio.iter_maps("-", stdin=io.StringIO(text), format=fmt), covariance, chunk=chunk)
    _assert_same_join(streamed.result, in_memory)
    assert streamed.origin_id == 0


def test_a_stream_of_real_maps_equals_the_join_in_memory(data_dir):
    maps = mapio.read_maps(str(data_dir / "VicPark_200_local_maps"))
    _assert_same_join(join_stream(iter(maps), chunk=17).result, join_sequential(maps))


def test_the_report_reads_as_a_sequence_of_records(data_dir):
    maps = mapio.read_maps(str(data_dir / "DLR_200_local_maps"))
    streamed, in_memory = join_stream(maps, chunk=50).result.report, join_sequential(maps).report
    assert streamed[0] == in_memory[0] and streamed[-1] == in_memory[-1]
    assert streamed[3:40:7] == list(in_memory[3:40:7])
    assert any(r.minima == 2 for r in in_memory) == any(r.minima == 2 for r in streamed)
    with pytest.raises(IndexError):
        streamed[len(in_memory)]
    with pytest.raises(IndexError):
        streamed[-len(in_memory) - 1]


def _peak_bytes(maps: int, streamed: bool) -> int:
    """tracemalloc's peak while joining a simulated run of ``maps`` maps over a world of a fixed size (``laps``
    grows with the run), so that the global map stops growing; the maps are made as they are taken, 16 at a
    time. Not streamed: the peak of making the list of maps (what joining them in memory starts from)."""
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr("mapjoin.simulation._CHUNK", 16)
        patch.setattr(logging.getLogger("mapjoin"), "disabled", True)
        run_ = simulate_stream(maps, seed=1, laps=maps / 20, full_covariance=False)
        local_maps = chain.from_iterable(run_.chunks)
        tracemalloc.start()
        try:
            if streamed:
                join_stream(local_maps, chunk=64)
            else:
                list(local_maps)
            return tracemalloc.get_traced_memory()[1]
        finally:
            tracemalloc.stop()


def test_memory_does_not_grow_with_the_stream():
    """Ten times the maps over the same world: the streamed join's peak grows by what it keeps per map (an end
    pose, a report row, a name: a few hundred bytes), far less than the maps it reads take (measured beside it,
    so that the bound is one the in-memory join, which holds them all, would exceed)."""
    small, large = _peak_bytes(80, True), _peak_bytes(800, True)
    per_map = (large - small) / 720
    per_input = _peak_bytes(800, False) / 800
    assert per_map < 1000 and per_map < per_input / 4, (per_map, per_input)


def _late_error_stream(tmp_path, fmt: str, error: str):
    """A stream of 60 maps whose map 50 has a bad feature value (``error="value"``), or whose last map ends at an
    earlier map's pose (``error="chain"``); its path and the line of the bad value."""
    maps = list(simulate(60, seed=5, steps_per_map=2, full_covariance=False).maps)
    text = _text(maps, fmt)
    needle = repr(float(maps[49].features[0, 0]))
    line = next(number for number, row in enumerate(text.splitlines(), 1) if needle in row)
    if error == "value":
        text = text.replace(needle, "nan-ish", 1)
    else:
        moved = mapio.registry.by_name[fmt].local_maps.read(text, "x")
        last = moved[59]
        moved[59] = type(last)("again", 59, 3, last.end_pose, last.feature_ids, last.features,
                               last.feature_variances, last.pose_variances)
        text = _text(moved, fmt)
    path = tmp_path / f"stream.{fmt}"
    path.write_text(text)
    return path, line


@pytest.mark.parametrize("fmt", ["yaml", "csv"])
@pytest.mark.parametrize("error", ["value", "chain"])
def test_an_error_late_in_the_stream_writes_nothing(tmp_path, monkeypatch, fmt, error):
    """The maps before the error are joined (chunks of 8, blocks of 40 lines) before it is read: still one line
    naming the file and the line (or the map), exit 1, and no output of any kind."""
    monkeypatch.setattr("mapjoin.streaming.CHUNK", 8)
    monkeypatch.setattr(csv_blocks, "BLOCK_LINES", 40)
    path, line = _late_error_stream(tmp_path, fmt, error)
    outputs = [tmp_path / "g.csv", tmp_path / "r.csv", tmp_path / "t.tum"]
    result = run("join", "-", "-o", str(outputs[0]), "--report", str(outputs[1]), "--trajectory",
                 str(outputs[2]), "--input-format", fmt, input=path.read_text())
    assert result.exit_code == 1, result.output
    message = result.stderr.strip()
    assert "\n" not in message and "Traceback" not in message
    if error == "value":
        assert message.startswith(f"Error: <stdin>, line {line}, "), message
    else:
        assert "pose 3 appears twice in the chain" in message and "again" in message, message
    assert not any(p.exists() for p in outputs) and sorted(tmp_path.iterdir()) == [path]


def test_join_stops_on_an_inconsistent_join_as_in_memory(data_dir):
    maps = mapio.read_maps(str(data_dir / "VicPark_200_local_maps"))
    with pytest.raises(JoinError) as in_memory:
        join(maps, gate=0.5, on_inconsistent="stop")
    with pytest.raises(JoinError) as streamed:
        join_stream(iter(maps), gate=0.5, on_inconsistent="stop", chunk=10)
    assert str(streamed.value) == str(in_memory.value)
    with pytest.raises(ValueError, match="in memory"):
        join_stream(iter(maps), on_inconsistent="skip")


def test_the_command_joins_a_stream_as_it_joined_the_list(data_dir, tmp_path):
    """The command's outputs from a stream on stdin are those of the in-memory join (the tree strategy still
    reads every map first; both strategies' outputs are checked against the library's in-memory join)."""
    folder = data_dir / "DLR_200_local_maps"
    maps = mapio.read_maps(str(folder))
    text = _text(maps, "csv")
    for strategy in ("sequential", "tree"):
        out = tmp_path / f"{strategy}.csv"
        result = run("join", "-", "-o", str(out), "--strategy", strategy, input=text)
        assert result.exit_code == 0, result.output
        expected = join(csv_maps.read(text, "<stdin>"), strategy=strategy).global_map
        got = mapio.read_global_map(str(out))
        assert np.array_equal(got.features, expected.features) and np.array_equal(got.poses, expected.poses)


@settings(max_examples=20, deadline=None)
@given(count=st.integers(1, 60), block=st.integers(2, 120), named=st.booleans())
def test_csv_blocks_read_as_the_whole_text(count, block, named):
    """Maps read a block of lines at a time are those of the whole text: names (numbered or not), values, and the
    line an error names."""
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(csv_blocks, "BLOCK_LINES", block)
        _check_blocks(count, named)


def _check_blocks(count: int, named: bool) -> None:
    text = _text(simulate(count, seed=count, steps_per_map=2, full_covariance=False).maps, "csv")
    if not named:
        text = "".join(line.split(",", 1)[1] for line in text.splitlines(keepends=True))
    whole = csv_maps.read(text, "s.csv")
    blocks = list(csv_blocks.read_lines(io.StringIO(text, newline=""), "s.csv"))
    assert [m.name for m in blocks] == [m.name for m in whole]
    for a, b in zip(blocks, whole):
        for name in ("feature_ids", "features", "feature_variances", "end_pose", "pose_variances"):
            assert np.array_equal(getattr(a, name), getattr(b, name))
    lines = text.splitlines(keepends=True)
    bad = len(lines) - 1
    lines[bad] = lines[bad].replace("feature", "featur").replace("pose", "pos")
    with pytest.raises(InputError) as expected:
        csv_maps.read("".join(lines), "s.csv")
    with pytest.raises(type(expected.value)) as got:
        list(csv_blocks.read_lines(iter(lines), "s.csv"))
    assert str(got.value) == str(expected.value)


def test_a_csv_map_whose_rows_come_back_in_a_later_block_is_refused(monkeypatch):
    monkeypatch.setattr(csv_blocks, "BLOCK_LINES", 30)
    lines = _text(simulate(12, seed=2, steps_per_map=2, full_covariance=False).maps, "csv").splitlines(keepends=True)
    third = [line for line in lines if line.startswith("sim-3,")]
    others = [line for line in lines if not line.startswith("sim-3,")]
    text = "".join(others[:12] + third[:2] + others[12:] + third[2:])
    with pytest.raises(InputError) as error:
        list(csv_blocks.read_lines(io.StringIO(text, newline=""), "s.csv"))
    assert str(error.value) == (f"s.csv, line {len(others) + 3}: the rows of the map 'sim-3' continue here after "
                                "other maps' rows; a CSV stream is read a block of lines at a time, so each map's "
                                "rows must be consecutive")
    assert len(csv_maps.read(text, "s.csv")) == 12  # a file read at once allows it


@pytest.mark.parametrize("fmt", ["yaml", "csv"])
@pytest.mark.parametrize("covariances", [True, False])
def test_the_simulator_streams_the_maps_it_makes_at_once(monkeypatch, fmt, covariances):
    """Maps made 7 at a time (the noise drawn chunk by chunk) and written as they are made: the text of making
    them all at once (512 at a time) and writing them together."""
    count = 40 if covariances else 600
    at_once = io.StringIO()
    mapio.write_maps(simulate(count, seed=9, steps_per_map=2).maps, at_once, fmt, covariances=covariances)
    monkeypatch.setattr("mapjoin.simulation._CHUNK", 7)
    streamed = io.StringIO()
    mapio.write_map_stream(simulate_stream(count, seed=9, steps_per_map=2).chunks, streamed, fmt,
                           covariances=covariances)
    assert streamed.getvalue() == at_once.getvalue()


def test_parts_are_written_all_or_nothing(tmp_path):
    """A file written from parts exists only once every part is written; an error while they are made leaves
    nothing."""
    target = tmp_path / "out.txt"

    def parts(fail: bool):
        yield "a\n"
        if fail:
            raise ValueError("stop")
        yield "b\n"

    with pytest.raises(ValueError), Outputs(files={"-o": str(target)}) as outputs:
        outputs.write(Parts(parts(True)), str(target))
    assert list(tmp_path.iterdir()) == []
    with Outputs(files={"-o": str(target)}) as outputs:
        outputs.write(Parts(parts(False)), str(target))
    assert target.read_text() == "a\nb\n"


@pytest.mark.parametrize("writer", ["global map", "report"])
def test_long_outputs_written_in_blocks_are_the_text_written_at_once(data_dir, monkeypatch, writer):
    """The global map (with and without covariances) and the report are written a block of rows at a time, so
    that 10⁶ maps' outputs are never held as text: blocks of 5 rows give the text of one block of them all."""
    maps = mapio.read_maps(str(data_dir / "DLR_200_local_maps"))
    fast = join(maps)
    if writer == "global map":
        from mapjoin.refine import refine

        module, outputs = "mapjoin.io.global_maps", [(fast.global_map, mapio.write_global_map),
                                                       (refine(maps).global_map, mapio.write_global_map)]
    else:
        module, outputs = "mapjoin.io.tables", [(fast.report, mapio.write_table),
                                                (join_stream(maps).result.report, mapio.write_table)]
    texts = []
    for rows in (1 << 30, 5):
        monkeypatch.setattr(f"{module}._ROWS_PER_PART", rows)
        written = []
        for data, write in outputs:
            stream = io.StringIO()
            write(data, stream, "csv")
            written.append(stream.getvalue())
        texts.append(written)
    assert texts[0] == texts[1] and all(text.count("\n") > 150 for text in texts[0])


@pytest.mark.parametrize("chunk", [1, 7, 64])
def test_a_streamed_join_tests_its_joins_as_the_join_in_memory(chunk):
    """The consistency check of a streamed run with loop closures (three laps of 300 maps) equals the in-memory
    join's: chi2, features_cost, variance_factor, p and flag of every join. The maps' variances are a quarter of
    the simulator's, so the variance factor grows above 1 and varies, and joins whose own cost fails are retested
    with the chain's drift (chi2 below cost): both paths are taken, across chunks of every size. Two feature ids
    of map 150 are swapped, so that a join is flagged (the clean run flags none since the fused estimates' bias,
    docs/method.md#drift)."""
    maps = [dataclasses.replace(m, feature_variances=m.feature_variances / 4, pose_variances=m.pose_variances / 4)
            for m in simulate(300, seed=3, steps_per_map=4, laps=3.0, full_covariance=False).maps]
    maps = corrupted(maps, 150, "swap")[0]
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(logging.getLogger("mapjoin"), "disabled", True)  # the loop closures' warnings
        in_memory = join_sequential(maps)
        streamed = join_stream(iter(maps), chunk=chunk)
    records = list(in_memory.report)
    assert sum(r.chi2 < r.cost for r in records) >= 10  # retested with the drift
    assert len({r.variance_factor for r in records}) > 10 and max(r.variance_factor for r in records) > 1.5
    assert sum(r.flag for r in records) > 0
    for column in ("chi2", "features_cost", "variance_factor", "p", "flag"):
        assert [getattr(r, column) for r in streamed.result.report] == [getattr(r, column) for r in records], column
    _assert_same_join(streamed.result, in_memory)
