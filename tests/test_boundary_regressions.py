"""Regression tests of the causes a wider hostile fuzz found after the first boundary work (issue 16).

Each test is one cause; each ran into a traceback, a message on two lines or naming nothing, an
unbounded allocation, or a number read as something other than what it says. Runs go through
the command line (in-process unless the cause needs a real process) and must end in one line
naming the input or option, exit 1.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
import tracemalloc
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from hypothesis import given, settings
from hypothesis import strategies as st
from test_outputs import run as run_in

from mapjoin.cli import main
from mapjoin.errors import InputError

SRC = Path(__file__).resolve().parents[1] / "src"


def run(folder: Path, *args: str) -> tuple[int, list[str]]:
    """``mapjoin -q ARGS`` in ``folder``: the exit code and the lines on stderr (never a Python exception)."""
    code, stderr = run_in(folder, *args)
    return code, stderr.strip().splitlines()


def refused(folder: Path, *args: str, naming: str) -> str:
    """The one line of a run that fails (exit 1) naming ``naming``."""
    code, lines = run(folder, *args)
    assert code == 1 and len(lines) == 1 and naming in lines[0], (code, lines)
    return lines[0]


@pytest.fixture(scope="module")
def maps(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("maps")
    assert run(folder, "simulate", "--maps", "3", "--seed", "2", "-o", "maps.yaml")[0] == 0
    assert run(folder, "convert", "maps.yaml", "-o", "ls/", "--to", "linearslam")[0] == 0
    return folder


# ---------------------------------------------------------------------------------------
# stdin that is not UTF-8, under a locale whose stdin lets bad bytes through as surrogates


def test_stdin_not_utf8_is_one_line_in_a_real_process(maps):
    """Python's stdin decodes with errors="surrogateescape" under C.UTF-8 and POSIX locales: the YAML parser
    then raised UnicodeEncodeError (a traceback). The bytes are now decoded, strictly, by mapjoin."""
    data = (maps / "maps.yaml").read_bytes()
    middle = data.index(b"\n", len(data) // 2)
    env = dict(os.environ, PYTHONPATH=str(SRC), LC_ALL="C.UTF-8")
    result = subprocess.run([sys.executable, "-m", "mapjoin", "join", "-", "-o", "out.csv"], cwd=maps, env=env,
                            input=data[:middle] + b"\xe9\xff" + data[middle:], capture_output=True, timeout=120)
    stderr = result.stderr.decode()
    assert result.returncode == 1 and "Traceback" not in stderr, stderr
    assert len(stderr.strip().splitlines()) == 1 and "<stdin>" in stderr and "UTF-8" in stderr, stderr
    assert not (maps / "out.csv").exists()


# ---------------------------------------------------------------------------------------
# Output names


@pytest.mark.parametrize("option", ["-o", "--report", "--trajectory"])
def test_an_empty_output_name_is_refused_naming_the_option(maps, option):
    """"" was taken for the current folder: "is a folder; expected a file", naming nothing."""
    args = {"-o": ["-o", ""], "--report": ["-o", "g.csv", "--report", ""], "--trajectory": ["--trajectory", ""]}
    line = refused(maps, "join", "maps.yaml", *args[option], naming=option)
    assert "empty" in line and not (maps / "g.csv").exists()


def test_a_file_name_with_a_line_end_is_named_on_one_line(maps):
    line = refused(maps, "join", "no\nsuch.yaml", naming="no\\nsuch.yaml")
    assert "no such file" in line
    line = refused(maps, "join", "maps.yaml", "-o", "a\nb.csv", "--report", "a\nb.csv", naming="a\\nb.csv")
    assert not list(maps.glob("a*"))


def test_a_very_long_file_name_is_cut_in_the_middle(maps):
    name = "d/" * 3000 + "x.csv"
    line = refused(maps, "join", "maps.yaml", "-o", name, naming="x.csv")
    assert len(line) < 300 and line.startswith("Error: d/d/") and "..." in line


# ---------------------------------------------------------------------------------------
# YAML numbers: decimal only


@pytest.mark.parametrize("value", ["0x10", "0b101", "1_000", "1:30", "1_0.5", "0o17", "1:30.5"])
@pytest.mark.parametrize("field", ["x", "id"])
def test_yaml_numbers_in_other_bases_or_with_underscores_are_refused(maps, value, field):
    """YAML 1.1 reads 0x10 as 16, 1_000 as 1000 and 1:30 as 90 (base 60): silently accepted before."""
    text = (maps / "maps.yaml").read_text()
    match = list(re.finditer(rf"\b{field}: (-?[0-9.e-]+)", text))[2]
    (maps / "bad.yaml").write_text(text[:match.start(1)] + value + text[match.end(1):])
    line = refused(maps, "join", "bad.yaml", naming="bad.yaml")
    assert repr(value) in line and f".{field}" in line


def test_a_yaml_integer_with_a_leading_zero_is_decimal(maps):
    """0777 was YAML 1.1's octal 511: a feature id other than the one written. It is 777, as written."""
    text = (maps / "maps.yaml").read_text()
    match = list(re.finditer(r"\bid: ([0-9]+)", text))[0]
    (maps / "zero.yaml").write_text(text[:match.start(1)] + "0777" + text[match.end(1):])
    (maps / "ten.yaml").write_text(text[:match.start(1)] + "777" + text[match.end(1):])
    from mapjoin.io import read_maps

    [zero, *_], [ten, *_] = read_maps(maps / "zero.yaml"), read_maps(maps / "ten.yaml")
    assert 777 in ten.feature_ids.tolist()
    np.testing.assert_array_equal(zero.feature_ids, ten.feature_ids)


# ---------------------------------------------------------------------------------------
# Linear SLAM: a long token costs memory in proportion to its own length


def test_a_long_linearslam_token_does_not_widen_every_cell(maps):
    """The fields went into a fixed-width string array, every cell as wide as the longest: one 3 MB token in a
    map of d = 20 asked for 4.8 GB (53 s). The memory is now about the file's."""
    from mapjoin.io import linearslam

    text = (maps / "ls" / "localmap_2.txt").read_text()
    lines = text.splitlines()
    lines[-1] = "7" * 500_000 + "x " + lines[-1].split(" ", 1)[1]  # the first entry of the last row
    tracemalloc.start()
    try:
        with pytest.raises(InputError, match=r"line \d+: expected a finite number"):
            linearslam.read("\n".join(lines) + "\n", "localmap_2.txt")
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak < 40e6, f"peak {peak / 1e6:.0f} MB for a 0.5 MB token"


# ---------------------------------------------------------------------------------------
# g2o vertices


@pytest.mark.parametrize("line,naming", [("VERTEX_SE2 1 inf 0 0", "line 2"), ("VERTEX_SE2 1 1 0 nan", "line 2"),
                                         ("VERTEX_XY 10 2 1e308", "line 4")])
def test_g2o_vertex_estimates_must_be_finite_and_in_range(tmp_path, line, naming):
    """The estimates of VERTEX lines are not used by build, but inf or 1e308 there was accepted without a word."""
    text = ("VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1 0 0\nVERTEX_SE2 2 2 0 0\nVERTEX_XY 10 2 1\nFIX 0\n"
            "EDGE_SE2 0 1 1 0 0.1 10 0 0 10 0 100\nEDGE_SE2 1 2 1 0 0.1 10 0 0 10 0 100\n"
            "EDGE_SE2_XY 0 10 2 1 25 0 25\nEDGE_SE2_XY 1 10 1 1 25 0 25\nEDGE_SE2_XY 2 10 0 1 25 0 25\n").splitlines()
    number = int(naming.split()[1]) - 1
    text[number] = line
    (tmp_path / "raw.g2o").write_text("\n".join(text) + "\n")
    refused(tmp_path, "build", "raw.g2o", "-o", "maps/", "--maps", "2", naming=f"raw.g2o, {naming}")
    assert not (tmp_path / "maps").exists()


# ---------------------------------------------------------------------------------------
# simulate's sizes and seed


@pytest.mark.parametrize("args", [["--maps", "99999999999999999999"], ["--steps-per-map", "1000000000", "--maps", "2"],
                                  ["--robots", "100000000", "--maps", "1000"], ["--seed", "-1"]])
def test_simulate_refuses_a_size_or_seed_it_cannot_take_at_once(tmp_path, args):
    """A huge --maps raised numpy's "Maximum allowed size exceeded" (a traceback), 10^8 maps ran out of memory,
    and a negative --seed reached the library's ValueError (a traceback)."""
    code, lines = run(tmp_path, "simulate", *args, "-o", "sim/")
    assert code == 2 and args[0] in lines[-1], (code, lines)  # in-process, click adds its usage lines above
    assert not list(tmp_path.iterdir())


def test_the_simulation_bound_is_the_product_of_maps_and_steps():
    from mapjoin.simulation import MAX_STEPS, simulate

    with pytest.raises(ValueError, match="at most"):
        simulate(MAX_STEPS // 10 + 1, steps_per_map=10)


# ---------------------------------------------------------------------------------------
# An output's format is checked with the output, before any input is read


@pytest.mark.parametrize("args,naming", [
    (["join", "missing.yaml", "--report", "r.g2o"], "r.g2o"),
    (["join", "missing.yaml", "-o", "g.mat"], "g.mat"),
    (["join", "missing.yaml", "--trajectory", "t.yaml"], "t.yaml"),
    (["join", "missing.yaml", "--associate", "--associations", "a.xyz"], "a.xyz"),
    (["refine", "missing.yaml", "--report", "r.tum"], "r.tum"),
    (["merge", "missing.csv", "other.csv", "--report", "m.mat"], "m.mat"),
    (["build", "missing.isam", "-o", "maps/", "--global-map", "g.xyz"], "g.xyz"),
    (["check-minima", "--batch", "missing.csv", "-o", "x.g2o"], "x.g2o"),
    (["convert", "missing.yaml", "-o", "c.json"], "c.json"),
    (["convert", "missing.yaml", "-o", "-", "--to", "mat"], "<stdout>"),
    (["simulate", "--maps", "2", "-o", "s.csv", "--truth", "t.g2o"], "t.g2o"),
])
def test_an_output_format_that_cannot_hold_its_data_is_refused_before_reading(tmp_path, args, naming):
    """The writers found these only after the work: below the work's warnings (two lines and more), and after
    reading every input (here missing, so an error about the input came first)."""
    refused(tmp_path, *args, naming=naming)
    assert not list(tmp_path.iterdir())


def test_build_with_a_bad_global_map_name_is_one_line_even_with_warnings(tmp_path):
    (tmp_path / "raw.isam").write_text(
        "ODOMETRY 0 1 1.0 0.0 0.1 10 0 0 10 0 100\nLANDMARK 0 10 2.0 1.0 25 0 25\nLANDMARK 1 10 1.0 1.0 25 0 25\n"
        "ODOMETRY 1 2 1.0 0.0 0.1 10 0 0 10 0 100\nLANDMARK 2 10 0.2 1.2 25 0 25\nLANDMARK 2 11 1.0 -1.0 25 0 25\n"
        "LANDMARK 1 11 2.0 -1.0 25 0 25\n")  # its chi^2 is far from its dof: build warns
    result = CliRunner().invoke(main, ["build", str(tmp_path / "raw.isam"), "-o", str(tmp_path / "maps/"),
                                       "--maps", "2", "--global-map", str(tmp_path / "g.mat")])
    lines = result.stderr.strip().splitlines()
    assert result.exit_code == 1 and len(lines) == 1 and "g.mat" in lines[0], lines


def test_a_failed_fetch_leaves_no_cache_folder_behind(tmp_path):
    """The cache folder (--into and its parents) was made before the download, and left when it failed."""
    code, lines = run(tmp_path, "datasets", "fetch", "sim-535", "--source", str(tmp_path / "nowhere"),
                      "--into", str(tmp_path / "a" / "b" / "cache"))
    assert code == 1 and len(lines) == 1 and "nowhere" in lines[0], lines
    assert not list(tmp_path.iterdir())


@pytest.mark.parametrize("args", [["compare", "", "g.csv"], ["check-minima", "--batch", ""],
                                  ["plot", "g.csv", "-o", ""], ["build", "", "-o", "-"]])
def test_an_empty_input_name_is_shown_as_such(tmp_path, args):
    """An error about "" began with ': ' and named nothing."""
    (tmp_path / "g.csv").write_text("")
    assert refused(tmp_path, *args, naming="''").startswith("Error: '': ")


@pytest.mark.parametrize("args", [["join", "maps.yaml", "-o", "a\0b.csv"], ["check-minima", "--batch", "t\0.csv"],
                                  ["datasets", "list", "--into", "c\0"], ["join", "m\0.yaml"]])
def test_a_nul_character_in_an_argument_is_a_usage_error(maps, args):
    """os raises ValueError ("embedded null byte") on such a name: a traceback from -o, --batch, --into, ..."""
    code, lines = run(maps, *args)
    assert code == 2 and "NUL" in lines[-1], (code, lines)


def test_a_file_is_flushed_before_its_rename_and_the_folder_after(tmp_path, monkeypatch):
    """The issue's "fsynced before the rename, and the folder after it", checked by the order of the calls."""
    from mapjoin.io import Outputs, write_output

    calls: list[tuple[str, str]] = []
    real_fsync, real_replace = os.fsync, os.replace

    def fsync(descriptor: int) -> None:
        calls.append(("fsync", os.readlink(f"/proc/self/fd/{descriptor}")))
        real_fsync(descriptor)

    def replace(source, target) -> None:
        calls.append(("replace", os.fspath(target)))
        real_replace(source, target)

    monkeypatch.setattr(os, "fsync", fsync)
    monkeypatch.setattr(os, "replace", replace)
    target = tmp_path / "out.csv"
    with Outputs(files={"-o": str(target)}):
        write_output("a,b\n", str(target))
    kinds = [kind for kind, _ in calls]
    assert kinds == ["fsync", "replace", "fsync"], calls
    assert calls[0][1].startswith(str(tmp_path / ".out.csv.")) and calls[1][1] == str(target)
    assert calls[2][1] == str(tmp_path) and target.read_text() == "a,b\n"


# ---------------------------------------------------------------------------------------
# Closed standard streams, in a real process


def _process(args: list[str], cwd: Path, shell_redirect: str) -> subprocess.CompletedProcess:
    line = " ".join([sys.executable, "-m", "mapjoin", *args]) + " " + shell_redirect
    return subprocess.run(["bash", "-c", line], cwd=cwd, env=dict(os.environ, PYTHONPATH=str(SRC)),
                          capture_output=True, text=True, timeout=120)


@pytest.mark.parametrize("args", [["--help"], ["--version"]])
@pytest.mark.parametrize("redirect", [">&-", "> /dev/full"])
def test_help_and_version_on_a_closed_or_full_stdout_are_one_line(tmp_path, args, redirect):
    """click writes these while parsing, outside the commands' guard: an OSError traceback."""
    result = _process(args, tmp_path, redirect)
    assert result.returncode == 1 and "Traceback" not in result.stderr, result.stderr
    assert result.stderr.strip().splitlines() == [result.stderr.strip()] and "stdout" in result.stderr


@pytest.mark.parametrize("args", [["join", "-"], ["check-minima", "--batch", "-"], ["convert", "-", "--input-format",
                                                                                   "csv", "-o", "-"]])
def test_a_closed_stdin_is_one_line(tmp_path, args):
    """sys.stdin is None when the process starts with descriptor 0 closed: an AttributeError traceback."""
    result = _process(args, tmp_path, "<&-")
    assert result.returncode == 1 and result.stderr.strip() == "Error: <stdin>: cannot read: stdin is closed", \
        result.stderr


def test_a_file_larger_than_one_read_is_read_whole(maps, monkeypatch):
    """One os.read gives at most 2 GiB on Linux: a larger file was read cut, silently. Here reads give 1000 bytes."""
    from mapjoin.io import paths, read_maps

    real_read = os.read
    monkeypatch.setattr(paths.os, "read", lambda descriptor, size: real_read(descriptor, min(size, 1000)))
    whole = (maps / "maps.yaml").read_bytes()
    assert len(whole) > 3000
    assert paths.read_file(str(maps / "maps.yaml"), "maps.yaml", True) == whole
    monkeypatch.undo()
    assert len(read_maps(maps / "maps.yaml")) == 3


def test_a_long_source_in_a_fetch_error_is_cut(tmp_path):
    """datasets' errors echoed the URL and the system's reason whole: 6 kB on one line for a 3 kB --source."""
    code, lines = run(tmp_path, "datasets", "fetch", "sim-535", "--source", "x" * 3000, "--into", "cache")
    assert code == 1 and len(lines) == 1 and len(lines[0]) < 800, (code, len(lines[0]))
    assert not list(tmp_path.iterdir())


# ---------------------------------------------------------------------------------------
# Found by the property fuzz after the merges of 2026-11-26


def test_an_end_pose_variance_written_as_a_huge_integer_is_read_as_a_number(tmp_path):
    """`var_xy: 99999999999999999999999` (an int beyond int64, below the float range) made an object array
    and a TypeError in the missing-variance check, when a map gives variances and no covariance."""
    text = ("format: mapjoin/local-map\nversion: 1\nname: example\nstart_id: 0\nend_id: 1\n"
            "end_pose: {x: 1.0, y: 2.0, phi: 0.1, var_xy: 99999999999999999999999, var_phi: 0.001}\n"
            "features:\n- {id: 12, x: 3.0, y: 4.0, var: 0.02}\n- {id: 14, x: 5.0, y: 6.0, var: 0.02}\n")
    (tmp_path / "huge.yaml").write_text(text)
    from mapjoin.io import read_maps

    [local_map] = read_maps(tmp_path / "huge.yaml")
    assert local_map.pose_variances[0] == 1e23


def test_a_label_the_font_cannot_draw_is_one_warning_line_not_python_warnings(tmp_path):
    """`plot --label $'\\a'`: matplotlib warned "Glyph 7 (\\x07) missing from font(s)" through Python's
    warnings, once per character; now one line of mapjoin's naming the code points, and the figure written."""
    pytest.importorskip("matplotlib")
    import warnings

    assert run(tmp_path, "simulate", "--maps", "3", "--seed", "2", "-o", "maps.yaml")[0] == 0
    assert run(tmp_path, "join", "maps.yaml", "-o", "global.csv")[0] == 0
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        result = CliRunner().invoke(main, ["plot", str(tmp_path / "global.csv"), "-o", str(tmp_path / "p.png"),
                                           "--label", "a\x07b\u4e00\x07"])
    assert result.exit_code == 0 and not caught, (result.stderr, [str(w.message) for w in caught])
    lines = [line for line in result.stderr.splitlines() if "glyph" in line]
    assert lines == ["warning: the font has no glyph for U+0007, U+4E00 (drawn as a box)"]
    assert (tmp_path / "p.png").stat().st_size > 0


# ---------------------------------------------------------------------------------------
# Found by the re-check of the boundary after the features since issue 16 (harness in the report)


def _flagged_maps(folder: Path) -> bytes:
    """A valid stream of 4 maps whose third map has two features moved 3 m: its join is flagged inconsistent."""
    import yaml

    assert run(folder, "simulate", "--maps", "4", "--steps-per-map", "4", "--seed", "4", "-o", "maps.yaml")[0] == 0
    documents = list(yaml.safe_load_all((folder / "maps.yaml").read_text()))
    documents[2]["features"][0]["x"] += 3.0
    documents[2]["features"][1]["y"] -= 3.0
    return yaml.safe_dump_all(documents, explicit_start=True, sort_keys=False).encode()


@pytest.mark.parametrize("source", ["fifo", "process substitution"])
def test_a_flagged_streamed_join_does_not_read_a_fifo_or_pipe_again(tmp_path, source):
    """The streamed join confirms its flags by reading its files again; only `-` was exempt. A FIFO read again
    blocked for ever (no writer left); a process substitution's /dev/fd/N, read again empty, refused a valid
    input ("expected at least one local map, found none"). Both join now, the flags left to the fast test."""
    data = _flagged_maps(tmp_path)
    (tmp_path / "bad.yaml").write_bytes(data)
    env = dict(os.environ, PYTHONPATH=str(SRC))
    command = [sys.executable, "-m", "mapjoin", "join", "--input-format", "yaml", "-o", "out.csv"]
    if source == "fifo":
        os.mkfifo(tmp_path / "maps.fifo")
        writer = subprocess.Popen(["bash", "-c", "cat bad.yaml > maps.fifo"], cwd=tmp_path)
        try:
            result = subprocess.run(command + ["maps.fifo"], cwd=tmp_path, env=env, capture_output=True, text=True,
                                    timeout=60)
        finally:
            writer.kill()
            writer.wait()
    else:
        line = " ".join(command) + " <(cat bad.yaml)"
        result = subprocess.run(["bash", "-c", line], cwd=tmp_path, env=env, capture_output=True, text=True,
                                timeout=60)
    assert result.returncode == 0 and "Traceback" not in result.stderr, result.stderr
    assert "read once" in result.stderr and "inconsistent" in result.stderr, result.stderr
    assert (tmp_path / "out.csv").stat().st_size > 0


def test_read_once_tells_regular_files_from_streams(tmp_path):
    from mapjoin.io import read_once

    (tmp_path / "a.yaml").write_text("x")
    os.mkfifo(tmp_path / "f")
    os.symlink("a.yaml", tmp_path / "link.yaml")
    assert [read_once(p) for p in (str(tmp_path / "a.yaml"), tmp_path / "link.yaml", str(tmp_path / "f"), "-",
                                   "/dev/zero", str(tmp_path / "missing"))] == [False, False, True, True, True, True]


@pytest.mark.parametrize("how", ["file", "stdin"])
@pytest.mark.parametrize("cut_character", [False, True])
def test_bytes_that_are_not_utf8_past_the_first_block_are_named_by_their_line_and_byte(maps, how, cut_character):
    """A stream is decoded a block (64 K characters) at a time; the error gave the offset in its block ("at
    byte 61184" for a byte at 519936) and no line. Now the line, the bytes and their offset in the source, counted
    here from the bytes themselves; ``cut_character``: a valid 2-byte character straddles the block boundary."""
    from mapjoin.io import lines

    data = (maps / "maps.yaml").read_bytes()
    while len(data) < 3 * lines._BLOCK:
        data += data[data.index(b"---", 3):]
    if cut_character:  # a comment line whose "é" has its 2 bytes either side of the first block's end
        before = data.rindex(b"\n", 0, lines._BLOCK - 10) + 1
        comment = b"#" + b"x" * (lines._BLOCK - 2 - before) + "é".encode() + b"\n"
        data = data[:before] + comment + data[before:]
        assert data[lines._BLOCK - 1:lines._BLOCK + 1] == "é".encode()
    start = data.index(b"\n", 2 * lines._BLOCK) + 1
    data = data[:start] + b"\xe9\xff" + data[start:]
    line_number = data[:start].count(b"\n") + 1
    expected = f"line {line_number}: expected UTF-8 text, got b'\\xe9' at byte {start} "
    (maps / "big.yaml").write_bytes(data)
    if how == "file":
        line = refused(maps, "join", "big.yaml", "-o", "big.csv", naming="big.yaml")
    else:
        result = CliRunner().invoke(main, ["-q", "join", "-", "--input-format", "yaml", "-o", str(maps / "big.csv")],
                                    input=data)
        assert result.exit_code == 1 and len(result.stderr.strip().splitlines()) == 1, result.stderr
        line = result.stderr.strip()
    assert expected in line, (expected, line)
    assert not (maps / "big.csv").exists()


def test_bytes_that_are_not_utf8_in_a_file_read_whole_are_named_by_their_line(maps):
    """The readers of whole files (a global map's JSON) gave the byte and no line."""
    assert run(maps, "join", "maps.yaml", "-o", "g.json")[0] == 0
    data = (maps / "g.json").read_bytes()
    start = data.index(b"\n", len(data) // 2) + 1
    (maps / "g.json").write_bytes(data[:start] + b"\xff" + data[start:])
    line = refused(maps, "compare", "g.json", "g.json", naming="g.json")
    line_number = data[:start].count(b"\n") + 1
    assert f"g.json, line {line_number}: expected UTF-8 text, got b'\\xff' at byte {start} " in line, line


@pytest.mark.parametrize("args", [
    ["plot", "global.csv", "--label", "$\\frac{$", "-o", "p.png"],  # mathtext that does not parse
    ["plot", "global.csv", "--label", "$\\nosuchcommand$", "-o", "p.svg"],
    ["plot", "global.csv", "--label", "\udcff", "-o", "p.pdf"],  # an argument byte that is not UTF-8
    ["plot", "g\udcff.csv", "-o", "p.png"],  # ... in a file name, the default label
    ["plot", "$\\frac{$.csv", "--truth", "$\\foo$.yaml", "-o", "p.png"],
    ["plot-join", "$\\frac{$.yaml", "--join", "1", "-o", "p.png"],  # the title names the maps
    ["plot-minima", "$\\frac{$ report.csv", "-o", "p.png"]])  # the title names the table
def test_labels_and_file_names_are_drawn_as_they_are(tmp_path, args):
    """A label or file name with $...$ was parsed as mathtext (ParseSyntaxException, a traceback) and one with a
    lone surrogate (Python's stand-in for a byte that is not UTF-8) made the font engine raise a TypeError.
    Both are drawn literally now (the surrogate as U+FFFD)."""
    pytest.importorskip("matplotlib")
    assert run(tmp_path, "simulate", "--maps", "3", "--seed", "2", "-o", ".", "--format", "yaml")[0] == 0
    assert run(tmp_path, "join", ".", "-o", "global.csv", "--report", "$\\frac{$ report.csv")[0] == 0
    for name in ("g\udcff.csv", "$\\frac{$.csv"):
        (tmp_path / name).write_bytes((tmp_path / "global.csv").read_bytes())
    (tmp_path / "$\\frac{$.yaml").write_bytes((tmp_path / "localmap_1.yaml").read_bytes()
                                              + (tmp_path / "localmap_2.yaml").read_bytes())
    (tmp_path / "$\\foo$.yaml").write_bytes((tmp_path / "truth.yaml").read_bytes())
    code, lines = run(tmp_path, *args)
    assert code == 0 and (tmp_path / args[-1]).stat().st_size > 0, lines


@pytest.mark.parametrize("args", [[], ["--associate"], ["--refine"]])
def test_a_covariance_with_variances_below_the_range_is_refused_naming_the_file(maps, args):
    """A covariance scaled by 1e-300 passed (entries within +-1e30, positive definite): the join's weights
    overflowed and the error named the "global map" (no file, no field), or numpy warned (divide by zero) on
    the way with --associate. Its diagonal holds variances: now checked against the variances' range."""
    import yaml

    documents = list(yaml.safe_load_all((maps / "maps.yaml").read_text()))
    documents[1]["covariance"] = [[value * 1e-300 for value in row] for row in documents[1]["covariance"]]
    (maps / "tiny.yaml").write_text(yaml.safe_dump_all(documents, explicit_start=True, sort_keys=False))
    line = refused(maps, "join", "tiny.yaml", *args, "-o", "tiny.csv", naming="tiny.yaml")
    assert "field covariance: expected finite variances in [1e-30, 1e+30] on the diagonal" in line, line
    assert not (maps / "tiny.csv").exists()


@pytest.mark.parametrize("variance,expected", [
    (1e-31, "expected finite variances in [1e-30, 1e+30] on the diagonal, got 1e-31 at index (3, 3)"),
    (1e-300, "on the diagonal, got 1e-300 at index (3, 3)"),
    (0.0, "expected a positive definite matrix"),  # as before: not positive definite comes first
    (1e31, "expected finite covariance entries in [-1e+30, 1e+30]"), (float("nan"), "expected finite numbers")])
def test_local_map_covariance_diagonal_range(variance, expected):
    from mapjoin.maps import LocalMap

    covariance = np.diag([0.01, 0.01, 0.001, 0.02, 0.02])
    LocalMap("ok", 0, 1, [1.0, 0.0, 0.1], [7], [[2.0, 1.0]], [0.02], [0.01, 0.001], covariance)
    covariance[3, 3] = variance
    with pytest.raises(InputError) as error:
        LocalMap("m", 0, 1, [1.0, 0.0, 0.1], [7], [[2.0, 1.0]], [0.02], [0.01, 0.001], covariance)
    assert str(error.value).startswith("m, covariance: ") and expected in str(error.value), str(error.value)


@pytest.mark.parametrize("value", ["１", "1_0", "٣"])
@pytest.mark.parametrize("args,option", [
    (["simulate", "-o", "s.yaml", "--maps"], "--maps"), (["simulate", "-o", "s.yaml", "--seed"], "--seed"),
    (["simulate", "-o", "s.yaml", "--steps-per-map"], "--steps-per-map"),
    (["simulate", "-o", "w/", "--robots"], "--robots"),
    (["join", "maps.yaml", "--strategy", "tree", "-o", "j.csv", "--jobs"], "--jobs"),
    (["refine", "maps.yaml", "-o", "j.csv", "--max-iterations"], "--max-iterations"),
    (["plot-join", "maps.yaml", "-o", "p.png", "--join"], "--join"),
    (["merge", "maps.yaml", "maps.yaml", "--associate", "--min-common"], "--min-common"),
    (["build", "raw.isam", "-o", "b/", "--maps"], "--maps"), (["build", "raw.isam", "-o", "b/", "--poses-per-map"],
                                                               "--poses-per-map"),
    (["build", "raw.isam", "-o", "b/", "--jobs"], "--jobs")])
def test_integer_options_take_ascii_digits_only(maps, args, option, value):
    """click's int took fullwidth and other Unicode digits and underscores (`--maps １` was 1, `--seed 1_0` 10),
    which the float options (FiniteFloat) and every text format refuse."""
    code, lines = run(maps, *args, value)  # in-process: click's usage lines before it (`python -m mapjoin`: one line)
    assert code == 2 and option in lines[-1] and f"ASCII digits, got '{value}'" in lines[-1], lines
    assert not any((maps / name).exists() for name in ("s.yaml", "w", "j.csv", "p.png", "b"))


# ---------------------------------------------------------------------------------------
# An outside fuzz of valid-looking maps at the edges of the accepted values (issue fuzzwide)

#: a 3x3 covariance of rank one to rounding (eigenvalues 1e29, then +-1e12 of rounding noise), from the fuzz:
#: numpy's Cholesky factorises it, its inverse does not exist (LinAlgError: Singular matrix)
ROUNDED_RANK_ONE = [[7.757644815196646e+27, -1.4865856513241328e+28, -2.2239373610078087e+28],
                    [-1.4865856513241328e+28, 2.848721424308696e+28, 4.2616972664712814e+28],
                    [-2.2239373610078087e+28, 4.2616972664712814e+28, 6.3755140941716395e+28]]


def _one_map(covariance: list[list[float]] | None, *, name: str = "m", start: int = 0) -> str:
    lines = ["---", "format: mapjoin/local-map", "version: 1", f"name: {name}", f"start_id: {start}",
             f"end_id: {start + 1}", "end_pose: {x: 1.0, y: 0.5, phi: 0.2, var_xy: 0.01, var_phi: 0.001}",
             "features: []"]
    if covariance is not None:
        lines += ["covariance:"] + [f"- [{', '.join(map(repr, row))}]" for row in covariance]
    return "\n".join(lines) + "\n"


def test_the_rounded_rank_one_covariance_has_a_cholesky_factor_but_no_inverse():
    """What made the traceback: an independent look at the matrix the next test gives the command line."""
    matrix = np.array(ROUNDED_RANK_ONE)
    np.linalg.cholesky(matrix)
    eigenvalues = np.linalg.eigvalsh(matrix)
    assert eigenvalues[0] / eigenvalues[-1] < 1e-15
    with pytest.raises(np.linalg.LinAlgError):
        np.linalg.inv(matrix)


@pytest.mark.parametrize("args", [["join", "m.yaml", "-o", "j.csv"], ["join", "m.yaml", "--strategy", "tree",
                                                                      "-o", "j.csv"],
                                  ["refine", "m.yaml", "-o", "j.csv"], ["convert", "m.yaml", "-o", "c.csv"]])
def test_a_covariance_singular_to_rounding_is_refused_naming_the_file_line_and_share(tmp_path, args):
    """It passed the positive-definiteness check (numpy's Cholesky factorised it), then the information mode's
    inverse raised LinAlgError: a traceback. It is now refused where it is read, naming the entry that the
    entries before it determine and its share of its variance."""
    (tmp_path / "m.yaml").write_text(_one_map([[0.01, 0, 0], [0, 0.01, 0], [0, 0, 0.001]], name="a")
                                     + _one_map(ROUNDED_RANK_ONE, name="b", start=1))
    line = refused(tmp_path, *args, naming="m.yaml")
    assert re.search(r"m\.yaml, line 2[12], field covariance: expected a positive definite matrix, but it is singular "
                     r"to rounding: entry [12]'s variance given the entries before it is [0-9.e+-]+ of its own "
                     r"\(at least 1e-12\)", line), line
    assert not {"j.csv", "c.csv"} & {p.name for p in tmp_path.iterdir()}


@settings(max_examples=60, deadline=None, derandomize=os.environ.get("CI") == "true", database=None)
@given(size=st.sampled_from([3, 5, 7]), seed=st.integers(0, 2**32 - 1), spread=st.floats(0, 14),
       dependent=st.booleans())
def test_covariances_are_refused_iff_an_entry_is_a_combination_of_others_whatever_their_units(size, seed, spread,
                                                                                               dependent):
    """Scale-free: a well-conditioned correlation matrix under standard deviations 10^-spread .. 10^spread
    (variances over nearly the whole accepted range) is accepted; one whose last entry is a combination of the
    others (to rounding) is refused, as eigenvalues of its correlation matrix show (an independent witness)."""
    from mapjoin.maps import CONDITIONAL_SHARE, LocalMap

    rng = np.random.default_rng(seed)
    factor = rng.normal(size=(size, size)) + 3 * np.eye(size)
    if dependent:
        factor[-1] = rng.normal(size=size - 1) @ factor[:-1]
    correlation = factor @ factor.T
    deviations = 10.0 ** rng.uniform(-spread, spread, size)
    covariance = correlation * deviations[:, None] * deviations[None, :]
    covariance = (covariance + covariance.T) / 2
    normalised = covariance / np.sqrt(np.outer(np.diag(covariance), np.diag(covariance)))
    eigenvalues = np.linalg.eigvalsh(normalised)
    m = (size - 3) // 2
    arguments = ("m", 0, 1, [1.0, 0.0, 0.1], list(range(m)), np.tile([2.0, 1.0], (m, 1)), [0.02] * m, [0.01, 0.001])
    if eigenvalues[0] > 1e-9 * eigenvalues[-1]:
        LocalMap(*arguments, covariance)
    elif eigenvalues[0] < CONDITIONAL_SHARE * 1e-2 * eigenvalues[-1]:
        with pytest.raises(InputError, match="m, covariance: expected a positive definite matrix"):
            LocalMap(*arguments, covariance)


def test_the_real_covariances_are_far_from_singular_to_rounding(data_dir):
    """The datasets' least share (1.6e-4, the 8240 simulation) is eight orders above the bound."""
    from mapjoin.maps import CONDITIONAL_SHARE

    for name in ("535_data_5_local_maps", "8240_data_50_local_maps", "DLR_200_local_maps", "VicPark_200_local_maps"):
        from mapjoin import io as mapio

        for local_map in mapio.read_maps(str(data_dir / name)):
            covariance = local_map.covariance
            shares = np.diag(np.linalg.cholesky(covariance)) ** 2 / np.diag(covariance)
            assert shares.min() > 1e6 * CONDITIONAL_SHARE, (name, local_map.name, shares.min())


@pytest.mark.parametrize("args", [["join"], ["join", "--strategy", "tree"], ["join", "--refine"],
                                  ["refine", "--start", "sequential"]])
def test_a_join_beyond_the_global_ranges_names_the_maps_joined(tmp_path, args):
    """A heading variance of 1e30 rad^2 (in range) carried to a feature 1e9 m away (in range) gives a variance near
    1e48 m^2, beyond the global maps' 1e40: the error named "global map" and an index, no file. Now it names
    the maps joined, the field and the value."""
    (tmp_path / "big.yaml").write_text(
        "format: mapjoin/local-map\nversion: 1\nstart_id: 0\nend_id: 1\n"
        "end_pose: {x: 1.0, y: 0.0, phi: 0.0, var_xy: 0.01, var_phi: 1.0e+30}\nfeatures:\n"
        "- {id: 1, x: 1.0, y: 1.0, var: 0.01}\n---\nformat: mapjoin/local-map\nversion: 1\nstart_id: 1\nend_id: 2\n"
        "end_pose: {x: 1.0, y: 0.0, phi: 0.0, var_xy: 0.01, var_phi: 0.001}\nfeatures:\n"
        "- {id: 2, x: 1.0e+9, y: 0.0, var: 0.01}\n")
    line = refused(tmp_path, args[0], "big.yaml", *args[1:], "-o", "j.csv", naming="big.yaml#1 ... big.yaml#2")
    found = re.search(r"their join gives (\w+) outside the accepted values: expected finite variances in "
                      r"\[1e-40, 1e\+40\], got ([0-9.e+]+)", line)
    assert found and found.group(1) in ("feature_variances", "pose_variances"), line
    assert 1e40 < float(found.group(2)) <= 1e30 * (1e9 + 2) ** 2, line  # at most var_phi * distance^2
    assert not (tmp_path / "j.csv").exists()


SINGULAR = "the normal equations of the exact join are singular"


@pytest.mark.parametrize("args,naming,reasons", [
    (["refine", "s.csv", "-o", "j.csv"], "s.csv#m1 ... s.csv#m2 (2 maps): ",
     ("their join gives feature_variances outside", SINGULAR)),
    (["join", "w.csv", "--on-inconsistent", "skip", "-o", "j.csv"], "w.csv#m1 ... w.csv#m2 (2 maps): ", (SINGULAR,))])
def test_an_exact_solve_lost_to_rounding_names_the_maps(tmp_path, args, naming, reasons):
    """Variances 1e-30 and 1e30 on one feature (each in range) leave the exact solve to rounding: a negative
    marginal variance (named "global map", no file) or singular normal equations in a flagged join's
    confirmation (named nothing at all). Both now name the maps. Which of the two the refine meets is rounding's
    choice (numpy 2.4.6 finds the equations singular first): either is one line naming the maps."""
    header = "map,start_id,end_id,kind,id,x,y,phi,var_xy,var_phi\n"
    (tmp_path / "s.csv").write_text(
        header + "m1,0,1,pose,1,1.0,0.0,0.0,0.01,0.001\nm1,0,1,feature,1,1.0,1.0,,0.01,\nm1,0,1,feature,2,2.0,1.0,,1e+30,\n"
        "m2,1,2,pose,2,1.0,0.0,0.0,0.01,0.001\nm2,1,2,feature,1,0.0,1.0,,0.01,\nm2,1,2,feature,2,1.0,1e9,,1e-30,\n")
    (tmp_path / "w.csv").write_text(
        header + "m1,0,1,pose,1,1.0,59966908.75412725,-1.0705663794155362,0.006932947168914299,1e-30\n"
        "m1,0,1,feature,0,1e-09,-1000000000.0,,0.002708842663638487,\n"
        "m2,1,2,pose,2,163442613.23725843,1e-30,1000000.0,0.0023973698652508322,0.0007356256382746153\n"
        "m2,1,2,feature,0,-323118458.365921,-465932701.00110793,,1e-29,\n"
        "m3,2,3,pose,3,3.0,-68908355.04375333,1.1906040069804078,0.0064991824375832,0.0004964035472255722\n"
        "m3,2,3,feature,0,-281115920.0308918,58397061.87318683,,1e+29,\n")
    line = refused(tmp_path, *args, naming=naming)
    assert any(line.startswith(f"Error: {naming}{reason}") for reason in reasons), line
    assert not (tmp_path / "j.csv").exists()


def test_an_association_gate_singular_to_rounding_leaves_the_features_new(tmp_path):
    """A heading variance of 1e12 rad^2 carried 1e9 m makes each gate's 2 x 2 covariance u var_phi u^T (1e30 m^2,
    rank one) to rounding: its determinant came out 0 or negative, numpy warned (divide by zero, invalid value)
    and the distances were inf or NaN. Such a gate now takes no candidate: the second map's features stay new
    (13 global ids for 5 + 8 features), and numpy says nothing."""
    import warnings

    (tmp_path / "far.csv").write_text("\n".join([
        "map,start_id,end_id,kind,id,x,y,phi,var_xy,var_phi,i,j,cov",
        "m1,0,1,pose,1,-1000000000.0,-0.6520394668202627,-2.737741716774767,1e-06,1000000000000.0,,,",
        "m1,0,1,feature,1000,-0.5320856831477929,-1.744981474024664,,1.0,,,,",
        "m1,0,1,feature,1001,-3.0623729576797434,-2.852686775909452,,0.00949162257699445,,,,",
        "m1,0,1,feature,1002,3.1889374134422965,0.1474066747959366,,0.0096016742814155,,,,",
        "m1,0,1,feature,1003,-3.25705423049768,1e-300,,0.004676911621654133,,,,",
        "m1,0,1,feature,1004,-1.1248329323261252,-1000000000.0,,0.009460694942786844,,,,",
        "m2,1,2,pose,2,2.5465191595604875,0.00635192498676318,-1.7175794628116634,0.00662721325684245,1e-30,,,",
        "m2,1,2,feature,2000,1.1095502826655732,1000000.0,,1e-30,,,,",
        "m2,1,2,feature,2001,-3.775395813289647,999999999.9,,0.005372774091011107,,,,",
        "m2,1,2,feature,2002,4.849153615380315,3.38739401312972,,1e-12,,,,",
        "m2,1,2,feature,2003,-2.928689501920787,3.019141557291144,,1e-06,,,,",
        "m2,1,2,feature,2004,1000000.0,999999999.9,,0.006066263372810623,,,,",
        "m2,1,2,feature,2005,0.4315005075429399,0.0,,0.004576798127665752,,,,",
        "m2,1,2,feature,2006,-0.30181517929345425,-1000000000.0,,0.005647609064848839,,,,",
        "m2,1,2,feature,2007,1000000.0,-1.0,,0.005507566420921683,,,,",
    ]) + "\n")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        code, lines = run(tmp_path, "join", "far.csv", "--associate", "-o", "j.csv", "--associations", "ids.csv")
    assert code == 0, lines
    ids = (tmp_path / "ids.csv").read_text().splitlines()[1:]
    assert sorted(int(row.split(",")[2]) for row in ids) == list(range(13)), ids


EDGE_CHAIN = """\
---
format: mapjoin/local-map
version: 1
start_id: 0
end_id: 1
end_pose: {x: -1000000000.0, y: 1.0, phi: 1000000.0, var_xy: 1e-12, var_phi: 1e+30}
features:
- {id: 4, x: 1.0, y: -3.0, var: 1e+30}
---
format: mapjoin/local-map
version: 1
start_id: 1
end_id: 2
end_pose: {x: -1000000000.0, y: 1000000.0, phi: 3.141592653589793, var_xy: 1e-12, var_phi: 1000000.0}
features:
- {id: 0, x: 1000000.0, y: 0.0, var: 1000000000000.0}
---
format: mapjoin/local-map
version: 1
start_id: 2
end_id: 3
end_pose: {x: 1.0, y: -1000000000.0, phi: 0.0, var_xy: 1000000000000.0, var_phi: 1e+30}
features:
- {id: 3, x: 1.0, y: 1000000000.0, var: 1000000000000.0}
"""


@pytest.mark.parametrize("strategy", ["sequential", "tree"])
def test_a_joint_test_singular_to_rounding_leaves_the_features_new(tmp_path, strategy):
    """What the outside-style fuzz found (hypothesis, ``edge_maps``): the third map's one candidate pair is in its
    gate, but the joint test's 3 x 3 ``P_link^-1 + H^T W H`` (a heading variance of 1e30 and a lever of 1e9 m
    against variances of 1e-12) is singular to rounding, and numpy's LinAlgError escaped as a traceback. Such a
    pair cannot be tested: the join rejects it (the report's ``rejected``), its feature stays new, numpy says
    nothing. The first two maps' features (one of variance 1e30, compatible with anything) are one feature."""
    import warnings

    (tmp_path / "edge.yaml").write_text(EDGE_CHAIN)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        code, lines = run(tmp_path, "join", "edge.yaml", "--associate", "--strategy", strategy, "-o", "j.csv",
                          "--associations", "ids.csv", "--report", "report.csv")
    assert code == 0, lines
    ids = [row.split(",") for row in (tmp_path / "ids.csv").read_text().splitlines()[1:]]
    assert [(m, g) for m, _, g in ids] == [("1", "0"), ("2", "0"), ("3", "1")], ids
    report = (tmp_path / "report.csv").read_text().splitlines()
    header = report[0].split(",")
    last = dict(zip(header, report[-1].split(",")))
    assert (last["common"], last["new"], last["rejected"]) == ("0", "1", "1"), last


def test_a_yaml_value_nested_deeper_than_repr_goes_is_named_in_one_line(tmp_path):
    """`features: [[[[...]]]]` 1000 deep parsed (PyYAML) and then its error message's repr of the value raised
    RecursionError: a traceback. The value is now described instead."""
    (tmp_path / "deep.yaml").write_text(
        "format: mapjoin/local-map\nversion: 1\nstart_id: 0\nend_id: 1\n"
        "end_pose: {x: 1.0, y: 0.0, phi: 0.0, var_xy: 0.01, var_phi: 0.001}\n"
        f"features: {'[' * 1000}{']' * 1000}\n")
    line = refused(tmp_path, "join", "deep.yaml", "-o", "j.csv", naming="deep.yaml, line 6, field features[0]")
    assert "nested too deep to show" in line and len(line) < 200, line


@pytest.mark.parametrize("entry", [(0, 0), (2, 4), (4, 2)])
def test_a_mat_covariance_holding_inf_is_refused_without_numpy_warnings(tmp_path, entry):
    """The Cholesky check of a stack of covariances, one holding inf, divided inf by inf (numpy's RuntimeWarning
    on stderr beside the one-line error). The finite check names it; numpy says nothing."""
    import warnings

    from mapjoin.io import matfile

    state = np.array([[0, 1.0], [0, 0.5], [0, 0.1], [7, 2.0], [7, 1.0]])
    covariance = np.diag([0.01, 0.01, 0.001, 0.02, 0.02])
    folder = tmp_path / "m"
    folder.mkdir()
    (folder / "localmap_1.mat").write_bytes(matfile.dump({"localmap_st": state, "localmap_P": covariance}))
    covariance[entry] = np.inf
    (folder / "localmap_2.mat").write_bytes(matfile.dump({"localmap_st": state, "localmap_P": covariance}))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        line = refused(tmp_path, "join", "m", "--strategy", "tree", "--covariance", "marginal", "-o", "j.csv",
                       naming="m/localmap_2.mat")
    assert "inf" in line, line
