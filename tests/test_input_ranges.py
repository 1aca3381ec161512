"""Regression tests of the input boundary: numbers, sizes and parsers (the issue "Nothing breaks at the boundary").

Each case is one cause the hostile user's fuzz found; each ran into a traceback, a numpy
warning, a wrong answer, an unbounded allocation or a silently accepted input before. Every
run goes through the command line, in-process, and must end in a one-line error naming the
input (exit 1) or the option (exit 2), with no Python warning.
"""

from __future__ import annotations

import os
import re
import struct
import subprocess
import sys
import warnings
import zlib
from pathlib import Path

import pytest
from click.testing import CliRunner

from mapjoin.cli import main

ISAM = ("ODOMETRY 0 1 1.0 0.0 0.1 10 0 0 10 0 100\nLANDMARK 0 10 2.0 1.0 25 0 25\nLANDMARK 1 10 1.0 1.0 25 0 25\n"
        "ODOMETRY 1 2 1.0 0.0 0.1 10 0 0 10 0 100\nLANDMARK 2 10 0.2 1.2 25 0 25\nLANDMARK 2 11 1.0 -1.0 25 0 25\n"
        "LANDMARK 1 11 2.0 -1.0 25 0 25\n")
G2O = ("VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1 0 0\nVERTEX_SE2 2 2 0 0\nVERTEX_XY 10 2 1\nFIX 0\n"
       "EDGE_SE2 0 1 1 0 0.1 10 0 0 10 0 100\nEDGE_SE2 1 2 1 0 0.1 10 0 0 10 0 100\n"
       "EDGE_SE2_XY 0 10 2 1 25 0 25\nEDGE_SE2_XY 1 10 1 1 25 0 25\nEDGE_SE2_XY 2 10 0 1 25 0 25\n")


def mapjoin(folder: Path, *args: str, stdin: str | None = None) -> tuple[int, str]:
    """``mapjoin -q ARGS`` run in ``folder``: (exit code, stderr); no traceback and no Python warning."""
    cwd = os.getcwd()
    os.chdir(folder)
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            result = CliRunner().invoke(main, ["-q", *args], input=stdin)
    finally:
        os.chdir(cwd)
    assert result.exception is None or isinstance(result.exception, SystemExit), repr(result.exception)
    assert not [str(w.message) for w in caught]
    return result.exit_code, result.stderr


def refused(folder: Path, *args: str, naming: str, stdin: str | None = None) -> str:
    """The one-line error of a run that must fail on bad input, which names ``naming``."""
    code, stderr = mapjoin(folder, *args, stdin=stdin)
    lines = stderr.strip().splitlines()
    assert code == 1 and len(lines) == 1 and naming in lines[0], (code, stderr)
    assert len(lines[0]) < 300, lines[0]
    return lines[0]


def usage_error(folder: Path, *args: str, option: str) -> str:
    code, stderr = mapjoin(folder, *args)
    assert code == 2 and option in stderr.strip().splitlines()[-1], (code, stderr)
    return stderr


@pytest.fixture(scope="module")
def maps(tmp_path_factory) -> Path:
    """A folder with three simulated maps as YAML and CSV."""
    folder = tmp_path_factory.mktemp("maps")
    assert mapjoin(folder, "simulate", "--maps", "3", "--seed", "2", "-o", "maps.yaml")[0] == 0
    assert mapjoin(folder, "convert", "maps.yaml", "-o", "maps.csv")[0] == 0
    assert mapjoin(folder, "join", "maps.yaml", "-o", "global.csv")[0] == 0
    return folder


def _replace_first_number(text: str, after: str, value: str) -> str:
    """``text`` with the first number after the first ``after`` replaced by ``value``."""
    start = text.index(after) + len(after)
    match = re.compile(r"-?[0-9][0-9.e+-]*").search(text, start)
    return text[:match.start()] + value + text[match.end():]


# ---------------------------------------------------------------------------------------
# Extreme numbers


@pytest.mark.parametrize("value", ["1e200", "-1e308", "1e10"])
@pytest.mark.parametrize("name", ["maps.yaml", "maps.csv"])
def test_extreme_coordinates_are_refused_naming_the_file(maps, tmp_path, name, value):
    text = (maps / name).read_text()
    (tmp_path / name).write_text(_replace_first_number(text, "x: ", value) if name.endswith("yaml")
                                 else _set_cell(text, "feature", "x", value))
    line = refused(tmp_path, "join", name, "-o", "out.csv", naming=name)
    assert "coordinates" in line and "1e+09" in line


def test_extreme_coordinates_in_a_mat_file_are_refused(maps, tmp_path):
    from mapjoin.io import matfile

    assert mapjoin(tmp_path, "convert", str(maps / "maps.yaml"), "-o", "mats/", "--to", "mat")[0] == 0
    path = tmp_path / "mats" / "localmap_1.mat"
    variables = matfile.variables(path.read_bytes(), str(path))
    variables["localmap_st"][4, 1] = 1e200
    path.write_bytes(matfile.dump(variables))
    refused(tmp_path, "join", "mats/localmap_1.mat", "-o", "out.csv", naming="localmap_1.mat")


def _set_cell(text: str, kind: str, column: str, value: str) -> str:
    """CSV ``text`` with ``column`` of its first ``kind`` row set to ``value``."""
    lines = text.splitlines()
    header = lines[0].split(",")
    row = next(i for i, line in enumerate(lines) if line.split(",")[header.index("kind")] == kind)
    cells = lines[row].split(",")
    cells[header.index(column)] = value
    lines[row] = ",".join(cells)
    return "\n".join(lines) + "\n"


@pytest.mark.parametrize("value", ["1e-320", "1e-31", "1e31"])
def test_variances_out_of_range_are_refused_naming_the_file(maps, tmp_path, value):
    (tmp_path / "maps.csv").write_text(_set_cell((maps / "maps.csv").read_text(), "feature", "var_xy", value))
    line = refused(tmp_path, "join", "maps.csv", "-o", "out.csv", naming="maps.csv")
    assert "variances in [1e-30, 1e+30]" in line


def test_angles_beyond_a_million_radians_are_refused(maps, tmp_path):
    (tmp_path / "maps.csv").write_text(_set_cell((maps / "maps.csv").read_text(), "pose", "phi", "1e14"))
    assert "angles (rad)" in refused(tmp_path, "join", "maps.csv", "-o", "out.csv", naming="maps.csv")


def test_raw_data_out_of_range_is_refused_naming_the_line(tmp_path):
    (tmp_path / "big.isam").write_text(ISAM.replace("LANDMARK 0 10 2.0", "LANDMARK 0 10 1e200"))
    assert "line 2" in refused(tmp_path, "build", "big.isam", "--maps", "2", "-o", "maps/", naming="big.isam")
    (tmp_path / "tiny.isam").write_text(ISAM.replace("2.0 1.0 25 0 25", "2.0 1.0 1e-320 0 1e-320"))
    assert "line 2" in refused(tmp_path, "build", "tiny.isam", "--maps", "2", "-o", "maps/", naming="tiny.isam")


def test_too_many_maps_for_the_raw_data_names_the_file(tmp_path):
    (tmp_path / "raw.isam").write_text(ISAM)
    refused(tmp_path, "build", "raw.isam", "--maps", "3", "-o", "maps/", naming="raw.isam")


@pytest.mark.parametrize("args", [["--a", "2", "--c-phi", "1e308"], ["--a", "2", "--c-phi", "-1e308"],
                                  ["--a", "2", "--c-phi", "1e14"], ["--a", "1e308", "--c-phi", "0.5"]])
def test_check_minima_refuses_extreme_options(tmp_path, args):
    usage_error(tmp_path, "check-minima", *args, option="--")


@pytest.mark.parametrize("row", ["2,1e308", "2,-1e308", "2,1e14", "1e308,0.5", "nan,1"])
@pytest.mark.parametrize("command", [["check-minima", "--batch", "t.csv"], ["plot-minima", "t.csv", "-o", "f.png"]])
def test_minima_tables_out_of_range_are_refused(tmp_path, row, command):
    (tmp_path / "t.csv").write_text(f"a,c_phi\n1,0.5\n{row}\n")
    assert refused(tmp_path, *command, naming="t.csv")


def test_compare_refuses_global_maps_whose_sums_would_overflow(maps, tmp_path):
    text = (maps / "global.csv").read_text()
    (tmp_path / "a.csv").write_text(text)
    (tmp_path / "b.csv").write_text(_set_cell(text, "feature", "x", "1e300"))
    refused(tmp_path, "compare", "a.csv", "b.csv", naming="b.csv")


# ---------------------------------------------------------------------------------------
# Option values


@pytest.mark.parametrize("value", ["nan", "inf", "-inf", "-1", "１"])
def test_refine_tolerance_must_be_a_finite_number(maps, value):
    usage_error(maps, "refine", "maps.yaml", "-o", "out.csv", "--tolerance", value, option="--tolerance")


@pytest.mark.parametrize("value", ["nan", "inf", "-inf"])
def test_check_minima_options_refuse_nan_and_inf(tmp_path, value):
    usage_error(tmp_path, "check-minima", "--a", value, "--c-phi", "0.5", option="--a")
    usage_error(tmp_path, "check-minima", "--a", "2", "--c-phi", value, option="--c-phi")


# ---------------------------------------------------------------------------------------
# Memory bombs


def _limited_run(folder: Path, *args: str) -> subprocess.CompletedProcess:
    """``python -m mapjoin -q ARGS`` with at most 1.5 GB of address space: an unbounded allocation fails."""
    import resource

    def limit() -> None:
        resource.setrlimit(resource.RLIMIT_AS, (1_500_000_000, 1_500_000_000))

    environment = {**os.environ, "PYTHONPATH": str(Path(__file__).parents[1] / "src")}
    return subprocess.run([sys.executable, "-m", "mapjoin", "-q", *args], cwd=folder, capture_output=True,
                          text=True, preexec_fn=limit, env=environment, timeout=120)


@pytest.mark.skipif(sys.platform != "linux", reason="address-space limits as on Linux")
def test_a_mat_file_claiming_2_31_rows_is_refused_without_allocating(maps, tmp_path):
    assert mapjoin(tmp_path, "convert", str(maps / "maps.yaml"), "-o", "mats/", "--to", "mat")[0] == 0
    data = bytearray((tmp_path / "mats" / "localmap_1.mat").read_bytes())
    dimensions = data.index(struct.pack("<II", 5, 8))  # the first dimensions subelement: localmap_st's
    struct.pack_into("<ii", data, dimensions + 8, 2**31 - 1, 2)
    (tmp_path / "localmap_1.mat").write_bytes(bytes(data))
    result = _limited_run(tmp_path, "join", "localmap_1.mat", "-o", "out.csv")
    assert result.returncode == 1 and result.stderr.count("\n") == 1, result.stderr
    assert "localmap_1.mat" in result.stderr and "2147483647" in result.stderr


def test_a_compressed_variable_inflating_beyond_the_bound_is_refused(maps, tmp_path, monkeypatch):
    from mapjoin.io import matfile

    monkeypatch.setattr(matfile, "MAX_DECOMPRESSED", 1000)
    assert mapjoin(tmp_path, "convert", str(maps / "maps.yaml"), "-o", "mats/", "--to", "mat")[0] == 0
    data = (tmp_path / "mats" / "localmap_1.mat").read_bytes()
    packed = zlib.compress(data[128:] + bytes(2000))
    (tmp_path / "localmap_1.mat").write_bytes(data[:128] + struct.pack("<II", 15, len(packed)) + packed)
    assert "compressed" in refused(tmp_path, "join", "localmap_1.mat", "-o", "out.csv", naming="localmap_1.mat")


def test_an_endless_special_file_is_read_up_to_the_bound(tmp_path, monkeypatch):
    from mapjoin.io import paths

    monkeypatch.setattr(paths, "MAX_STREAM_BYTES", 1 << 20)
    line = refused(tmp_path, "join", "/dev/zero", "--input-format", "csv", "-o", "out.csv", naming="/dev/zero")
    assert "a line of more than 1048576 characters" in line  # read line by line: no newline in sight


def test_stdin_is_read_up_to_the_bound(tmp_path, monkeypatch):
    from mapjoin.io import paths

    monkeypatch.setattr(paths, "MAX_STREAM_BYTES", 1 << 20)
    refused(tmp_path, "join", "-", "--input-format", "csv", "-o", "out.csv", naming="<stdin>",
            stdin="kind\n" * (1 << 19))


# ---------------------------------------------------------------------------------------
# Parsers that accepted what they should refuse


def test_a_table_with_two_a_columns_is_refused(tmp_path):
    (tmp_path / "t.csv").write_text("a,c_phi,a\n1,0.5,2\n")
    assert "twice" in refused(tmp_path, "check-minima", "--batch", "t.csv", naming="t.csv")


def test_a_local_map_table_with_a_repeated_column_is_refused(maps, tmp_path):
    lines = (maps / "maps.csv").read_text().splitlines()
    (tmp_path / "maps.csv").write_text("\n".join(line + "," + line.split(",")[5] for line in lines) + "\n")
    refused(tmp_path, "join", "maps.csv", "-o", "out.csv", naming="maps.csv")


@pytest.mark.parametrize("number", ["２.0", "2_0.0", "٢.0"])
def test_raw_numbers_must_use_ascii_digits(tmp_path, number):
    (tmp_path / "raw.isam").write_text(ISAM.replace("LANDMARK 0 10 2.0", f"LANDMARK 0 10 {number}"))
    assert "line 2" in refused(tmp_path, "build", "raw.isam", "--maps", "2", "-o", "maps/", naming="raw.isam")


@pytest.mark.parametrize("number", ["２", "1_0"])
def test_csv_numbers_must_use_ascii_digits(maps, tmp_path, number):
    text = (maps / "maps.csv").read_text()
    (tmp_path / "maps.csv").write_text(_set_cell(text, "feature", "x", number))
    refused(tmp_path, "join", "maps.csv", "-o", "out.csv", naming="maps.csv")


@pytest.mark.parametrize("line", ["FIX", "FIX 0 1", "FIX x"])
def test_a_malformed_fix_line_is_refused(tmp_path, line):
    (tmp_path / "raw.g2o").write_text(G2O.replace("FIX 0", line))
    assert "line 5" in refused(tmp_path, "build", "raw.g2o", "--maps", "2", "-o", "maps/", naming="raw.g2o")


def test_a_well_formed_fix_line_is_accepted(tmp_path):
    (tmp_path / "raw.g2o").write_text(G2O)
    assert mapjoin(tmp_path, "build", "raw.g2o", "--maps", "2", "-o", "maps/")[0] == 0


def test_an_unknown_token_is_echoed_cut(tmp_path):
    (tmp_path / "raw.isam").write_text("X" * 3_000_000 + " 1 2\n" + ISAM)
    line = refused(tmp_path, "build", "raw.isam", "--raw-format", "isam", "--maps", "2", "-o", "maps/",
                   naming="raw.isam")
    assert "XXX..." in line


def test_a_long_bad_csv_header_is_echoed_cut(maps, tmp_path):
    (tmp_path / "maps.csv").write_text((maps / "maps.csv").read_text().replace("kind", "x" * 5000 + "kind", 1))
    assert "..." in refused(tmp_path, "join", "maps.csv", "-o", "out.csv", naming="maps.csv")


# ---------------------------------------------------------------------------------------
# YAML and Linear SLAM text


@pytest.mark.parametrize("name", ["maps.yaml", "minima.yaml"])
def test_a_yaml_key_given_twice_is_refused(maps, tmp_path, name):
    if name == "maps.yaml":
        text = (maps / "maps.yaml").read_text().replace("start_id: 0\n", "start_id: 0\nstart_id: 7\n", 1)
        args = ["join", name, "-o", "out.csv"]
    else:
        text = "- {a: 1, c_phi: 0.5, a: 2}\n"
        args = ["check-minima", "--batch", name]
    (tmp_path / name).write_text(text)
    assert "appears twice" in refused(tmp_path, *args, naming=name)


@pytest.mark.parametrize("character", ["\x00", "\x1b", "\x07"])
def test_a_yaml_control_character_gives_one_line_naming_its_line(maps, tmp_path, character):
    lines = (maps / "maps.yaml").read_text().splitlines(keepends=True)
    lines[2] = character + lines[2]
    (tmp_path / "maps.yaml").write_text("".join(lines))
    assert "line 3" in refused(tmp_path, "join", "maps.yaml", "-o", "out.csv", naming="maps.yaml")


@pytest.mark.parametrize("field", [0, 1])
def test_linearslam_numbers_must_use_ascii_digits(maps, tmp_path, field):
    assert mapjoin(tmp_path, "convert", str(maps / "maps.yaml"), "-o", "txt/", "--to", "linearslam")[0] == 0
    path = tmp_path / "txt" / "localmap_1.txt"
    lines = path.read_text().splitlines()
    cells = lines[3].split()
    cells[field] = cells[field].replace("1", "１").replace("2", "２").replace("4", "４")
    lines[3] = " ".join(cells)
    path.write_text("\n".join(lines) + "\n")
    assert "line 4" in refused(tmp_path, "join", "txt/localmap_1.txt", "-o", "out.csv", naming="localmap_1.txt")


def test_a_long_bad_minima_header_is_echoed_cut(tmp_path):
    (tmp_path / "t.csv").write_text("x" * 5000 + "a,c_phi\n1,0.5\n")
    assert "..." in refused(tmp_path, "check-minima", "--batch", "t.csv", naming="t.csv")


def test_linearslam_information_entries_out_of_range_are_refused(maps, tmp_path):
    assert mapjoin(tmp_path, "convert", str(maps / "maps.yaml"), "-o", "txt/", "--to", "linearslam")[0] == 0
    path = tmp_path / "txt" / "localmap_1.txt"
    lines = path.read_text().splitlines()
    first = 2 + int(lines[1])  # the information matrix's first row
    cells = lines[first].split()
    cells[0] = "1e308"
    lines[first] = " ".join(cells)
    path.write_text("\n".join(lines) + "\n")
    line = refused(tmp_path, "join", "txt/localmap_1.txt", "-o", "out.csv", naming="localmap_1.txt")
    assert f"line {first + 1}" in line and "information" in line
