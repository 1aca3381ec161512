"""The boundary holds, whatever the input: a fuzz over every command and input format.

Valid inputs of every format are mutated (one field at a time, extreme floats, broken
structure, bytes flipped) and given to every command that reads them; outputs are aimed
at every input and every other output (directly, through ``./``, a symbolic link, a hard
link, another case). Each run must keep the boundary's contract:

- the exit code is one of 0, 1, 2, 3 (no crash);
- nothing on stderr reads "Traceback" or "Exception ignored", and no Python warning
  (e.g. numpy's RuntimeWarning) is raised;
- an error (exit 1) is exactly one line and names the file (or option) at fault;
- on an error (exit 1, 2, 130) no file is created, changed or left behind;
- the inputs' bytes never change.

The runs are in-process (click's runner) to stay fast; what needs a real process
(Ctrl-C, a closed stdout, special files) is in ``test_boundary_process.py``. Under CI the
examples are derandomised so that a run is reproducible.
"""

from __future__ import annotations

import hashlib
import os
import re
import shutil
import warnings
from collections.abc import Callable
from pathlib import Path

import pytest
from click.testing import CliRunner
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from mapjoin.cli import main

CI = os.environ.get("CI") == "true"
FUZZ = settings(max_examples=40, deadline=None, derandomize=CI, database=None,
                suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])

HOSTILE_NUMBERS = ("nan", "NaN", "inf", "-inf", "1e308", "-1e308", "1e200", "-1e200", "1e-320", "-1e-320",
                   "0", "-0", "0.0", "-1", "1e400", "99999999999999999999999", "-99999999999999999999999",
                   "１２", "0x10", "1_000", "", " ", "abc", "1e", "--1", "3.4.5", "\x00", "\x07", "1e15", "-1e15")


def snapshot(folder: Path) -> dict[str, tuple[str, str]]:
    """Every entry below ``folder``: relative path -> (kind, SHA-256 of its bytes or its link target)."""
    entries = {}
    for path in sorted(folder.rglob("*")):
        name = path.relative_to(folder).as_posix()
        if path.is_symlink():
            entries[name] = ("link", os.readlink(path))
        elif path.is_file():
            entries[name] = ("file", hashlib.sha256(path.read_bytes()).hexdigest())
        elif path.is_dir():
            entries[name] = ("dir", "")
        else:
            entries[name] = ("special", "")
    return entries


def invoke(folder: Path, args: list[str], *, stdin: str | bytes | None = None, inputs: tuple[str, ...] = (),
           names: tuple[str, ...] = ()) -> tuple[int, str]:
    """Run ``mapjoin -q ARGS`` in ``folder`` and check the boundary contract; (exit code, stderr).

    ``inputs``: files (relative to folder) whose bytes must not change; ``names``: strings of which
    at least one must appear in a one-line error."""
    before = snapshot(folder)
    cwd = os.getcwd()
    os.chdir(folder)
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            result = CliRunner().invoke(main, ["-q", *args], input=stdin, catch_exceptions=True)
    finally:
        os.chdir(cwd)
    after = snapshot(folder)
    where = f"mapjoin -q {' '.join(map(repr, args))}"
    stderr = result.stderr
    if result.exception is not None and not isinstance(result.exception, SystemExit):
        import traceback

        trace = "".join(traceback.format_exception(result.exception))
        pytest.fail(f"{where}: raised\n{trace}")
    assert result.exit_code in {0, 1, 2, 3}, (where, result.exit_code, stderr)
    assert "Traceback" not in stderr and "Exception ignored" not in stderr, (where, stderr)
    assert not [str(w.message) for w in caught], (where, [str(w.message) for w in caught])
    for name in inputs:
        assert after.get(name) == before.get(name), f"{where}: input {name} changed"
    if result.exit_code not in (0, 3):  # 3: written, but to look at (two minima, refine not converged)
        assert after == before, f"{where}: exit {result.exit_code} but files changed: " \
                                f"{sorted(set(after.items()) ^ set(before.items()))}"
    if result.exit_code == 1:
        lines = stderr.strip().splitlines()
        assert len(lines) == 1, (where, stderr)
        assert len(lines[0]) <= 600, (where, f"error of {len(lines[0])} characters")
        if names:
            assert any(name in lines[0] for name in names), (where, stderr)
    if result.exit_code == 2:
        assert stderr.strip().splitlines()[-1].startswith("Error:"), (where, stderr)
    return result.exit_code, stderr


# ---------------------------------------------------------------------------------------
# Valid inputs of every format, made once by the command line itself


@pytest.fixture(scope="module")
def valid(tmp_path_factory) -> Path:
    """A folder of small valid inputs: local maps as YAML/CSV streams, .mat and Linear SLAM files, a global
    map (CSV, YAML, JSON), truth files (YAML, CSV), minima tables (CSV, YAML, JSON) and iSAM/g2o raw data."""
    folder = tmp_path_factory.mktemp("valid")
    runner = CliRunner()

    def run(*args: str) -> None:
        result = runner.invoke(main, ["-q", *args], catch_exceptions=False)
        assert result.exit_code == 0, (args, result.output)

    os.chdir(folder)
    try:
        run("simulate", "-o", "maps.yaml", "--maps", "3", "--steps-per-map", "3", "--seed", "4", "--truth", "truth.yaml")
        run("convert", "maps.yaml", "-o", "maps.csv")
        run("convert", "maps.yaml", "-o", "mats/", "--to", "mat")
        run("convert", "maps.yaml", "-o", "txt/", "--to", "linearslam")
        run("join", "maps.yaml", "-o", "global.csv", "--report", "report.csv")
        run("join", "maps.yaml", "-o", "global.yaml")
        run("join", "maps.yaml", "-o", "global.json", "--report", "report.json")
        run("simulate", "-o", "sim.csv", "--maps", "3", "--steps-per-map", "3", "--seed", "4", "--truth", "truth.csv")
        run("simulate", "-o", "own", "--maps", "3", "--steps-per-map", "3", "--seed", "4", "--local-ids")
        run("join", "own", "--associate", "--associations", "ids.csv", "-o", "associated.csv")
    finally:
        os.chdir(Path(__file__).parent)
    shutil.copy(folder / "mats" / "localmap_1.mat", folder / "map1.mat")
    shutil.copy(folder / "mats" / "localmap_2.mat", folder / "map2.mat")
    shutil.copy(folder / "txt" / "localmap_1.txt", folder / "localmap_1.txt")
    (folder / "minima.csv").write_text("join,a,c_phi\n1,2.5,1.0\n2,0.5,-3.0\n")
    (folder / "raw.isam").write_text(
        "ODOMETRY 0 1 1.0 0.0 0.1 10 0 0 10 0 100\nLANDMARK 0 10 2.0 1.0 25 0 25\nLANDMARK 1 10 1.0 1.0 25 0 25\n"
        "ODOMETRY 1 2 1.0 0.0 0.1 10 0 0 10 0 100\nLANDMARK 2 10 0.2 1.2 25 0 25\nLANDMARK 2 11 1.0 -1.0 25 0 25\n"
        "LANDMARK 1 11 2.0 -1.0 25 0 25\n")
    (folder / "raw.g2o").write_text(
        "VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1 0 0.1\nVERTEX_SE2 2 2 0 0.2\nVERTEX_XY 10 2 1\nVERTEX_XY 11 1 -1\nFIX 0\n"
        "EDGE_SE2 0 1 1.0 0.0 0.1 100 0 0 100 0 1000\nEDGE_SE2 1 2 1.0 0.0 0.1 100 0 0 100 0 1000\n"
        "EDGE_SE2_XY 0 10 2.0 1.0 50 0 50\nEDGE_SE2_XY 1 10 1.0 1.0 50 0 50\nEDGE_SE2_XY 2 10 0.2 1.2 50 0 50\n"
        "EDGE_SE2_XY 2 11 1.0 -1.0 50 0 50\nEDGE_SE2_XY 1 11 2.0 -1.0 50 0 50\n")
    (folder / "minima.yaml").write_text("- {join: 1, a: 2.5, c_phi: 1.0}\n- {join: 2, a: 0.5, c_phi: -3.0}\n")
    rows = [line.split(",") for line in (folder / "ids.csv").read_text().splitlines()[1:]]
    (folder / "ids.yaml").write_text("".join(f"- {{map: {m}, local_id: {l}, global_id: {g}}}\n" for m, l, g in rows))
    (folder / "ids.json").write_text("[" + ", ".join(f'{{"map": {m}, "local_id": {l}, "global_id": {g}}}'
                                                     for m, l, g in rows) + "]\n")
    return folder


def _fresh(valid: Path, tmp_path: Path, name: str) -> Path:
    """A new working folder holding a copy of the valid input ``name``."""
    work = tmp_path / f"w{len(list(tmp_path.iterdir()))}"
    work.mkdir()
    source = valid / name
    if source.is_dir():
        shutil.copytree(source, work / name)
    else:
        shutil.copy(source, work / name)
    return work


NUMBER = re.compile(rb"-?[0-9]+(?:\.[0-9]*)?(?:[eE][-+]?[0-9]+)?")


@st.composite
def text_mutation(draw, content: bytes) -> bytes:
    """``content`` with one hostile change: a number replaced, a line dropped/doubled/cut, bytes inserted."""
    kind = draw(st.sampled_from(["number", "number", "number", "line", "truncate", "insert"]))
    if kind == "number":
        spans = [m.span() for m in NUMBER.finditer(content)]
        start, end = draw(st.sampled_from(spans))
        value = draw(st.sampled_from(HOSTILE_NUMBERS)).encode()
        return content[:start] + value + content[end:]
    lines = content.split(b"\n")
    if kind == "line":
        i = draw(st.integers(0, len(lines) - 1))
        how = draw(st.sampled_from(["drop", "double", "swap"]))
        if how == "drop":
            del lines[i]
        elif how == "double":
            lines.insert(i, lines[i])
        else:
            j = draw(st.integers(0, len(lines) - 1))
            lines[i], lines[j] = lines[j], lines[i]
        return b"\n".join(lines)
    position = draw(st.integers(0, len(content)))
    if kind == "truncate":
        return content[:position]
    junk = draw(st.sampled_from([b"\x00", b"\xff\xfe", b"\x1b[2J", b"\t", b": :", b"{", b"- [", b",,,", b"\r",
                                 "é".encode(), b"x" * 5000]))
    return content[:position] + junk + content[position:]


@st.composite
def binary_mutation(draw, content: bytes) -> bytes:
    """``content`` (a .mat file) with bytes overwritten (huge sizes too), cut or inserted."""
    kind = draw(st.sampled_from(["overwrite", "huge", "truncate", "insert"]))
    position = draw(st.integers(0, len(content) - 1))
    if kind == "overwrite":
        value = draw(st.binary(min_size=1, max_size=8))
        return content[:position] + value + content[position + len(value):]
    if kind == "huge":
        position -= position % 4
        value = draw(st.sampled_from([b"\xff\xff\xff\x7f", b"\x00\x00\x00\x80", b"\xff\xff\xff\xff", b"\x00\x00\x10\x00"]))
        return content[:position] + value + content[position + 4:]
    if kind == "truncate":
        return content[:position]
    return content[:position] + draw(st.binary(min_size=1, max_size=16)) + content[position:]


# The commands that read each kind of input, with where they write (relative to the work folder).
LOCAL_MAP_COMMANDS: list[Callable[[str], list[str]]] = [
    lambda f: ["join", f, "-o", "out.csv", "--report", "report.csv"],
    lambda f: ["join", f, "--associate", "--associations", "ids.csv", "-o", "out.csv"],
    lambda f: ["join", f, "--associate", "--strategy", "tree", "--report", "report.yaml", "-o", "out.yaml"],
    lambda f: ["join", f, "--strategy", "tree", "--covariance", "marginal", "-o", "out.yaml"],
    lambda f: ["join", f, "--covariance", "identity", "--solver", "golden", "-o", "out.g2o"],
    lambda f: ["refine", f, "-o", "out.csv", "--max-iterations", "5"],
    lambda f: ["convert", f, "-o", "converted/", "--to", "yaml"],
    lambda f: ["convert", f, "-o", "converted.csv"],
]


def _local_map_case(valid: Path, tmp_path: Path, name: str, mutate, data, command: int) -> None:
    work = _fresh(valid, tmp_path, name)
    original = (valid / name).read_bytes()
    (work / name).write_bytes(data.draw(mutate(original)))
    invoke(work, LOCAL_MAP_COMMANDS[command](name), inputs=(name,), names=(name,))


@pytest.mark.parametrize("name", ["maps.yaml", "maps.csv", "localmap_1.txt"])
@FUZZ
@given(data=st.data(), command=st.integers(0, len(LOCAL_MAP_COMMANDS) - 1))
def test_mutated_text_local_maps_keep_the_boundary(valid, tmp_path, name, data, command):
    _local_map_case(valid, tmp_path, name, text_mutation, data, command)


@FUZZ
@given(data=st.data(), command=st.integers(0, len(LOCAL_MAP_COMMANDS) - 1))
def test_mutated_mat_files_keep_the_boundary(valid, tmp_path, data, command):
    _local_map_case(valid, tmp_path, "map1.mat", binary_mutation, data, command)


@FUZZ
@given(data=st.data(), which=st.sampled_from(["map1.mat", "map2.mat"]))
def test_mutated_pair_for_check_minima_keeps_the_boundary(valid, tmp_path, data, which):
    work = _fresh(valid, tmp_path, "map1.mat")
    shutil.copy(valid / "map2.mat", work / "map2.mat")
    (work / which).write_bytes(data.draw(binary_mutation((valid / which).read_bytes())))
    invoke(work, ["check-minima", "map1.mat", "map2.mat", "--json"], inputs=("map1.mat", "map2.mat"),
           names=(which,))


GLOBAL_MAP_COMMANDS: list[Callable[[str], list[str]]] = [
    lambda f: ["compare", f, "ref.csv", "--json"],
    lambda f: ["evaluate", f, "--truth", "truth.yaml", "--json"],
    lambda f: ["evaluate", f, "--truth", "truth.yaml", "--align", "rigid"],
    lambda f: ["merge", "ref.csv", f, "-o", "out.csv", "--report", "report.csv"],
    lambda f: ["merge", "ref.csv", f, "--associate", "-o", "out.yaml"],
]


@pytest.mark.parametrize("name", ["global.csv", "global.yaml", "global.json"])
@FUZZ
@given(data=st.data(), command=st.integers(0, len(GLOBAL_MAP_COMMANDS) - 1))
def test_mutated_global_maps_keep_the_boundary(valid, tmp_path, name, data, command):
    work = _fresh(valid, tmp_path, name)
    shutil.copy(valid / "global.csv", work / "ref.csv")
    shutil.copy(valid / "truth.yaml", work / "truth.yaml")
    (work / name).write_bytes(data.draw(text_mutation((valid / name).read_bytes())))
    invoke(work, GLOBAL_MAP_COMMANDS[command](name), inputs=(name, "ref.csv", "truth.yaml"), names=(name,))


@pytest.mark.parametrize("name", ["truth.yaml", "truth.csv"])
@FUZZ
@given(data=st.data())
def test_mutated_truth_keeps_the_boundary(valid, tmp_path, name, data):
    work = _fresh(valid, tmp_path, name)
    shutil.copy(valid / "global.csv", work / "global.csv")
    (work / name).write_bytes(data.draw(text_mutation((valid / name).read_bytes())))
    invoke(work, ["evaluate", "global.csv", "--truth", name], inputs=(name, "global.csv"), names=(name,))


@pytest.mark.parametrize("name", ["ids.csv", "ids.yaml", "ids.json"])
@FUZZ
@given(data=st.data(), which=st.sampled_from(["found", "true"]))
def test_mutated_correspondence_tables_keep_the_boundary(valid, tmp_path, name, data, which):
    """``evaluate --associations``: either table (the join's or the true one) mutated."""
    work = _fresh(valid, tmp_path, "own")
    shutil.copy(valid / "associated.csv", work / "associated.csv")
    shutil.copy(valid / name, work / name)
    table = name if which == "found" else "own/associations.csv"
    (work / table).write_bytes(data.draw(text_mutation((work / table).read_bytes())))
    invoke(work, ["evaluate", "associated.csv", "--truth", "own/truth.yaml", "--associations", name, "--json"],
           inputs=(name, "own/associations.csv", "associated.csv"), names=(table,))


@pytest.mark.parametrize("name", ["minima.csv", "report.csv", "minima.yaml", "report.json"])
@FUZZ
@given(data=st.data())
def test_mutated_minima_tables_keep_the_boundary(valid, tmp_path, name, data):
    work = _fresh(valid, tmp_path, name)
    (work / name).write_bytes(data.draw(text_mutation((valid / name).read_bytes())))
    invoke(work, ["check-minima", "--batch", name, "-o", "minima.json"], inputs=(name,), names=(name,))


@pytest.mark.parametrize("name", ["raw.isam", "raw.g2o"])
@FUZZ
@given(data=st.data())
def test_mutated_raw_data_keeps_the_boundary(valid, tmp_path, name, data):
    work = _fresh(valid, tmp_path, name)
    (work / name).write_bytes(data.draw(text_mutation((valid / name).read_bytes())))
    invoke(work, ["build", name, "-o", "maps/", "--maps", "2", "--global-map", "batch.csv"], inputs=(name,),
           names=(name,))


FLOAT_OPTIONS = [
    lambda v: ["check-minima", "--a", v, "--c-phi", "0.5"],
    lambda v: ["check-minima", "--a", "2", "--c-phi", v],
    lambda v: ["check-minima", "--a", v, "--c-phi", v, "--json"],
    lambda v: ["refine", "maps.yaml", "-o", "out.csv", "--tolerance", v],
    lambda v: ["plot-minima", "--a", v, "--c-phi", "0.1", "-o", "fig.png"],
]


@FUZZ
@given(value=st.one_of(st.sampled_from(HOSTILE_NUMBERS), st.floats().map(repr)),
       command=st.integers(0, len(FLOAT_OPTIONS) - 1))
def test_float_options_keep_the_boundary(valid, tmp_path, value, command):
    work = _fresh(valid, tmp_path, "maps.yaml")
    args = FLOAT_OPTIONS[command](value)
    if args[0] == "plot-minima" and "plot-minima" not in main.commands:
        return
    invoke(work, args, inputs=("maps.yaml",))


# ---------------------------------------------------------------------------------------
# Outputs that are inputs or each other, under every alias


def _alias(work: Path, target: str, how: str) -> str:
    """Another name for ``target`` (which may not exist yet) in ``work``."""
    if how == "same":
        return target
    if how == "dot":
        return f"./{target}"
    if how == "case":
        return target.upper()
    if how == "symlink":
        os.symlink(target, work / f"link-{target}")
        return f"link-{target}"
    if how == "hardlink":
        os.link(work / target, work / f"hard-{target}")
        return f"hard-{target}"
    raise AssertionError(how)


ALIASES = ("same", "dot", "case", "symlink", "hardlink")

# command line with {i} = an input name and {a}/{b} = two outputs
OUTPUT_CASES = {
    "join": (["join", "maps.yaml", "-o", "{a}", "--report", "{b}"], "maps.yaml", "out.csv", "rep.csv"),
    "join-refine": (["join", "maps.yaml", "--refine", "-o", "{a}", "--report", "{b}"], "maps.yaml", "out.csv", "rep.csv"),
    "refine": (["refine", "maps.yaml", "-o", "{a}"], "maps.yaml", "out.csv", None),
    "convert": (["convert", "maps.yaml", "-o", "{a}"], "maps.yaml", "conv.csv", None),
    "simulate": (["simulate", "--maps", "3", "-o", "{a}", "--truth", "{b}"], None, "sim.csv", "truth.csv"),
    "build": (["build", "raw.isam", "--raw-format", "isam", "--maps", "2", "-o", "{a}", "--global-map", "{b}"],
              "raw.isam", "maps.csv", "batch.csv"),
    "check-minima": (["check-minima", "--batch", "minima.csv", "-o", "{a}"], "minima.csv", "res.csv", None),
}


def _output_collision_cases():
    for command, (_, given_input, first, second) in OUTPUT_CASES.items():
        for how in ALIASES:
            if given_input:
                yield pytest.param(command, "input", how, id=f"{command}-output-is-input-{how}")
            if second and how != "hardlink":
                yield pytest.param(command, "outputs", how, id=f"{command}-two-outputs-{how}")


@pytest.mark.parametrize("command,clash,how", list(_output_collision_cases()))
def test_no_output_is_an_input_or_another_output(valid, tmp_path, command, clash, how):
    args, given_input, first, second = OUTPUT_CASES[command]
    work = tmp_path / "w"
    work.mkdir()
    for name in ("maps.yaml", "raw.isam", "minima.csv"):
        shutil.copy(valid / name, work / name)
    if clash == "input":
        a, b = _alias(work, given_input, how), second
    else:
        if how == "symlink":  # a dangling link to where the first output will be written
            a, b = first, _alias(work, first, how)
        else:
            a, b = first, _alias(work, first, how)
    line = [part.format(a=a, b=b) for part in args]
    code, stderr = invoke(work, line, inputs=tuple(n for n in ("maps.yaml", "raw.isam", "minima.csv")))
    assert code == 1, (line, stderr)


# ---------------------------------------------------------------------------------------
# All or nothing


PARTIAL_CASES = [
    ["join", "maps.yaml", "-o", "out.csv", "--report", "missing/dir/rep.csv"],
    ["join", "maps.yaml", "-o", "missing/out.csv", "--report", "rep.csv"],
    ["build", "raw.isam", "--raw-format", "isam", "--maps", "2", "-o", "maps/", "--global-map", "missing/b.csv"],
    ["simulate", "--maps", "3", "-o", "sim/", "--truth", "missing/t.yaml"],
    ["convert", "maps.yaml", "-o", "blocked/", "--to", "yaml"],
]


@pytest.mark.parametrize("line", PARTIAL_CASES, ids=lambda line: "-".join(line[:1] + line[-2:]))
def test_a_failing_output_leaves_no_other_output(valid, tmp_path, line):
    work = tmp_path / "w"
    work.mkdir()
    for name in ("maps.yaml", "raw.isam"):
        shutil.copy(valid / name, work / name)
    (work / "blocked").mkdir()
    (work / "blocked" / "localmap_2.yaml").mkdir()  # a folder where convert wants to write a file
    code, stderr = invoke(work, line, inputs=("maps.yaml", "raw.isam"))
    assert code == 1, stderr


def test_outputs_are_checked_before_any_input_is_read(valid, tmp_path):
    """A bad output path is refused before the (here unreadable) inputs are touched."""
    work = tmp_path / "w"
    work.mkdir()
    code, stderr = invoke(work, ["join", "does-not-exist.yaml", "-o", "missing/out.csv"])
    assert code == 1 and "missing" in stderr, stderr


# ---------------------------------------------------------------------------------------
# Every option of every command, and stdin


#: a runnable command line of each command, whose options the next test sets one at a time
BASE_LINES = {
    "join": ["join", "maps.yaml", "-o", "o.csv"],
    "refine": ["refine", "maps.yaml", "-o", "o.csv", "--max-iterations", "3"],
    "convert": ["convert", "maps.yaml", "-o", "c.yaml"],
    "simulate": ["simulate", "--maps", "2", "--steps-per-map", "3", "-o", "s.yaml"],
    "build": ["build", "raw.isam", "--maps", "2", "-o", "b.yaml"],
    "check-minima": ["check-minima", "--a", "2", "--c-phi", "0.5"],
    "evaluate": ["evaluate", "global.csv", "--truth", "truth.yaml"],
    "compare": ["compare", "global.csv", "global.yaml"],
    "merge": ["merge", "global.csv", "global.yaml", "-o", "m.csv"],
    "plot": ["plot", "global.csv", "-o", "p.png"],
    "plot-join": ["plot-join", "maps.yaml", "-o", "pj.png"],
    "plot-minima": ["plot-minima", "report.csv", "-o", "pm.png"],
    "datasets list": ["datasets", "list", "--into", "cache"],
    "datasets fetch": ["datasets", "fetch", "sim-535", "--source", "nowhere", "--into", "cache"],
}

HOSTILE_VALUES = (*HOSTILE_NUMBERS, "-", "/", ".", "missing/dir/x", "/dev/zero", "maps.yaml", "a\nb", "x" * 3000,
                  "é", "2", "99999999999999999999999999999")


def _options() -> list[tuple[str, tuple[str, ...]]]:
    """(command, the option's names) for every option of every command that takes a value."""
    import click

    found = []
    for command in BASE_LINES:
        group, *sub = command.split()
        cli_command = main.commands.get(group)
        if cli_command is None:  # plot commands without matplotlib
            continue
        for name in sub:
            cli_command = cli_command.commands[name]
        for parameter in cli_command.params:
            if isinstance(parameter, click.Option) and not parameter.is_flag and not parameter.count:
                found.append((command, tuple(parameter.opts)))
    return found


OPTIONS = _options()


def test_the_option_table_covers_every_command():
    # compare has no option with a value (its runs are in the global-map fuzz above)
    assert {command for command, _ in OPTIONS} >= set(BASE_LINES) - {"compare", "plot", "plot-join", "plot-minima"}
    assert len(OPTIONS) > 50


@settings(FUZZ, max_examples=80)
@given(option=st.sampled_from(OPTIONS), value=st.sampled_from(HOSTILE_VALUES))
def test_every_option_of_every_command_keeps_the_boundary(valid, tmp_path, option, value):
    from mapjoin.errors import one_line

    command, names = option
    work = _fresh(valid, tmp_path, "maps.yaml")
    for other in ("global.csv", "global.yaml", "truth.yaml", "raw.isam", "report.csv"):
        shutil.copy(valid / other, work / other)
    args = list(BASE_LINES[command])
    given_as = next((name for name in names if name in args), None)
    if given_as:
        args[args.index(given_as) + 1] = value
    else:
        args += [names[-1], value]
    inputs = [name for name in BASE_LINES[command] if (work / name).is_file() and name in args]  # still read
    invoke(work, args, inputs=tuple(inputs),
           names=(*names, one_line(value)[:20] or "''", "<stdout>", *BASE_LINES[command][1:],
                  *(("<stdin>",) if value == "-" else ())))  # an input given as '-' is named <stdin>


@settings(FUZZ, max_examples=30)
@given(data=st.data(), name=st.sampled_from(["maps.yaml", "maps.csv"]))
def test_mutated_stdin_keeps_the_boundary(valid, tmp_path, data, name):
    work = tmp_path / f"w{len(list(tmp_path.iterdir()))}"
    work.mkdir()
    stdin = data.draw(text_mutation((valid / name).read_bytes()))
    invoke(work, ["join", "-", "--input-format", name.split(".")[1], "-o", "out.csv"], stdin=stdin,
           names=("<stdin>",))


# ---------------------------------------------------------------------------------------
# Valid maps whose values are extreme together (each in range): what an outside fuzz found (issue fuzzwide)

EDGE_COORDINATES = (0.0, 1.0, -3.0, 1e-300, 1e6, 1e9, -1e9)
EDGE_VARIANCES = (1e-30, 1e-12, 0.01, 1e6, 1e12, 1e30)
EDGE_ANGLES = (0.0, 3.141592653589793, -1e6, 1e6)

EDGE_COMMANDS: list[list[str]] = [
    ["join", "edge.yaml", "-o", "out.csv", "--report", "report.csv"],
    ["join", "edge.yaml", "--strategy", "tree", "-o", "out.csv"],
    ["join", "edge.yaml", "--associate", "-o", "out.csv"],
    ["join", "edge.yaml", "--on-inconsistent", "skip", "-o", "out.csv"],
    ["refine", "edge.yaml", "--max-iterations", "5", "-o", "out.csv"],
]


@st.composite
def edge_maps(draw) -> str:
    """A YAML chain of 2-3 maps, features shared by id, every number drawn from the edges of its accepted range;
    some maps with a full covariance: a diagonal one, or a rank-one one to rounding (which must be refused)."""
    documents = []
    for k in range(draw(st.integers(2, 3))):
        number = st.sampled_from(EDGE_COORDINATES)
        variance = st.sampled_from(EDGE_VARIANCES)
        ids = draw(st.lists(st.integers(0, 4), min_size=1, max_size=3, unique=True))
        pose = (draw(number), draw(number), draw(st.sampled_from(EDGE_ANGLES)), draw(variance), draw(variance))
        features = [(i, draw(number), draw(number), draw(variance)) for i in ids]
        lines = ["---", "format: mapjoin/local-map", "version: 1", f"start_id: {k}", f"end_id: {k + 1}",
                 "end_pose: {x: %r, y: %r, phi: %r, var_xy: %r, var_phi: %r}" % pose, "features:",
                 *("- {id: %d, x: %r, y: %r, var: %r}" % feature for feature in features)]
        covariance = draw(st.sampled_from([None, None, "diagonal", "rank one"]))
        if covariance:
            d = 3 + 2 * len(features)
            diagonal = [pose[3], pose[3], pose[4], *(v for *_, v in features for _ in range(2))]
            rows = ([[diagonal[i] if i == j else 0.0 for j in range(d)] for i in range(d)] if covariance == "diagonal"
                    else [[0.01 * (1 + i) * (1 + j) for j in range(d)] for i in range(d)])
            lines += ["covariance:", *(f"- [{', '.join(map(repr, row))}]" for row in rows)]
        documents.append("\n".join(lines))
    return "\n".join(documents) + "\n"


@FUZZ
@given(text=edge_maps(), command=st.integers(0, len(EDGE_COMMANDS) - 1))
def test_valid_maps_with_extreme_values_together_keep_the_boundary(tmp_path, text, command):
    """Each value is accepted; together (a heading variance of 1e30 carried 1e9 m, variances 60 orders apart, a
    covariance singular to rounding) they made tracebacks (numpy's LinAlgError), numpy warnings and errors that
    named no file. A failure must now be one line naming the file or its maps (``edge.yaml#...``)."""
    work = tmp_path / f"w{len(list(tmp_path.iterdir()))}"
    work.mkdir()
    (work / "edge.yaml").write_text(text)
    invoke(work, EDGE_COMMANDS[command], inputs=("edge.yaml",), names=("edge.yaml",))
