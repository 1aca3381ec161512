"""Outputs (mapjoin.io.outputs): refused before any input is read, never an input or each other, all or nothing.

The acceptance runs are in test_boundary_fuzz.py and test_boundary_process.py; these are the
causes they do not reach, one test each.
"""

from __future__ import annotations

import io
import os
import threading
from pathlib import Path

import pytest
from click.testing import CliRunner

from mapjoin import io as mapio
from mapjoin.cli import main
from mapjoin.errors import InputError
from mapjoin.io import outputs as outputs_module


def run(folder: Path, *args: str) -> tuple[int, str]:
    """``mapjoin -q ARGS`` in ``folder``; (exit code, stderr)."""
    code, _, stderr = run_with_stdout(folder, *args)
    return code, stderr


def run_with_stdout(folder: Path, *args: str) -> tuple[int, str, str]:
    """``mapjoin -q ARGS`` in ``folder``; (exit code, stdout, stderr), never a Python exception."""
    cwd = os.getcwd()
    os.chdir(folder)
    try:
        result = CliRunner().invoke(main, ["-q", *args])
    finally:
        os.chdir(cwd)
    assert result.exception is None or isinstance(result.exception, SystemExit), repr(result.exception)
    return result.exit_code, result.stdout, result.stderr


def listing(folder: Path) -> list[str]:
    return sorted(path.relative_to(folder).as_posix() for path in folder.rglob("*"))


@pytest.fixture
def maps(tmp_path) -> Path:
    """A folder ``maps/`` of three YAML local maps in ``tmp_path``."""
    code, stderr = run(tmp_path, "simulate", "-o", "maps/", "--maps", "3", "--seed", "2")
    assert code == 0, stderr
    os.remove(tmp_path / "maps" / "truth.yaml")
    return tmp_path / "maps"


def test_converting_a_folder_into_itself_is_refused(maps, tmp_path):
    before = listing(tmp_path)
    code, stderr = run(tmp_path, "convert", "maps/", "-o", "maps/", "--to", "csv")
    assert code == 1 and "holds the input file" in stderr and "maps" in stderr, stderr
    assert listing(tmp_path) == before


def test_an_output_folder_holding_an_input_is_refused(maps, tmp_path):
    (tmp_path / "alias").symlink_to("maps")
    code, stderr = run(tmp_path, "convert", "maps/localmap_1.yaml", "-o", "alias/", "--to", "csv")
    assert code == 1 and "holds the input file maps/localmap_1.yaml" in stderr, stderr
    assert not (tmp_path / "maps" / "localmap_1.csv").exists()


def test_a_file_in_an_output_folder_that_is_a_hard_link_to_an_input_is_refused(maps, tmp_path):
    (tmp_path / "out").mkdir()
    os.link(maps / "localmap_2.yaml", tmp_path / "out" / "localmap_2.yaml")
    before = (maps / "localmap_2.yaml").read_bytes()
    code, stderr = run(tmp_path, "convert", "maps/localmap_2.yaml", "-o", "out/")
    assert code == 1 and "out/localmap_2.yaml: is the input file maps/localmap_2.yaml" in stderr, stderr
    assert (maps / "localmap_2.yaml").read_bytes() == before and listing(tmp_path / "out") == ["localmap_2.yaml"]


def test_names_differing_only_in_case_are_refused_and_the_error_says_why(maps, tmp_path):
    code, stderr = run(tmp_path, "join", "maps/", "-o", "out.csv", "--report", "OUT.csv")
    assert code == 1 and "differs only in letter case from the -o output out.csv" in stderr, stderr
    assert "case-insensitive" in stderr and len(stderr.strip().splitlines()) == 1


def test_two_outputs_on_stdout_are_refused(maps, tmp_path):
    code, stderr = run(tmp_path, "join", "maps/", "-o", "-", "--report", "-")
    assert code == 1 and "-o and --report both write to stdout" in stderr, stderr


@pytest.mark.parametrize("args,message", [
    (["join", "maps/", "-o", "maps"], "maps: is a folder; expected a file"),
    (["convert", "maps/", "-o", "file.csv/"], "file.csv/: is a file; expected a folder"),
    (["build", "raw.isam", "-o", "file.csv/sub/"], "is not a folder"),
    (["simulate", "-o", "sim/", "--truth", "nowhere/truth.yaml"], "the folder nowhere does not exist"),
])
def test_unusable_output_paths_are_refused_first(maps, tmp_path, args, message):
    (tmp_path / "file.csv").write_text("keep\n")
    (tmp_path / "raw.isam").write_text("not read\n")
    before = listing(tmp_path)
    code, stderr = run(tmp_path, *args)
    assert code == 1 and message in stderr, stderr
    assert listing(tmp_path) == before and (tmp_path / "file.csv").read_text() == "keep\n"


def test_outputs_are_refused_before_a_slow_input_is_read(tmp_path):
    """An input that would block forever (a FIFO nobody writes) is never opened when an output is bad."""
    os.mkfifo(tmp_path / "maps.yaml")
    result: list[tuple[int, str]] = []
    worker = threading.Thread(target=lambda: result.append(run(tmp_path, "join", "maps.yaml", "-o", "no/out.csv")),
                              daemon=True)
    worker.start()
    worker.join(60)
    if worker.is_alive():  # unblock the reader so the thread can end
        os.close(os.open(tmp_path / "maps.yaml", os.O_WRONLY | os.O_NONBLOCK))
        pytest.fail("the input was opened before the output was checked")
    code, stderr = result[0]
    assert code == 1 and "no/out.csv" in stderr, stderr


def test_ctrl_c_while_writing_a_folder_leaves_nothing(maps, tmp_path, monkeypatch):
    written = []
    write_file = outputs_module._write_file

    def interrupted(path, content, name):
        if written:
            raise KeyboardInterrupt
        written.append(name)
        write_file(path, content, name)

    monkeypatch.setattr(outputs_module, "_write_file", interrupted)
    local_maps = mapio.read_maps([str(maps)])
    (tmp_path / "existing").mkdir()
    before = listing(tmp_path)
    for target in (tmp_path / "new" / "deeper", tmp_path / "existing"):
        written.clear()
        with pytest.raises(KeyboardInterrupt):
            mapio.write_maps(local_maps, f"{target}/", "csv")
        assert written
    assert listing(tmp_path) == before


def test_ctrl_c_while_the_outputs_are_renamed_into_place_waits_for_the_last_one(tmp_path, monkeypatch):
    """A commit of several files is all or nothing against Ctrl-C too: a SIGINT arriving during the renames is
    delivered after the last one (pytest runs tests in the main thread, where Python receives signals)."""
    import signal

    replace = os.replace
    renamed = []

    def interrupted(source, target):
        if not renamed:
            os.kill(os.getpid(), signal.SIGINT)  # a real Ctrl-C to this process, between the two renames
        replace(source, target)
        renamed.append(os.path.basename(target))

    monkeypatch.setattr(outputs_module.os, "replace", interrupted)
    (tmp_path / "a.csv").write_text("old a\n")
    with pytest.raises(KeyboardInterrupt):
        with mapio.Outputs(files={"-o": str(tmp_path / "a.csv"), "--report": str(tmp_path / "b.csv")}):
            mapio.write_output("new a\n", tmp_path / "a.csv")
            mapio.write_output("new b\n", tmp_path / "b.csv")
    assert sorted(renamed) == ["a.csv", "b.csv"]
    assert listing(tmp_path) == ["a.csv", "b.csv"]
    assert (tmp_path / "a.csv").read_text() == "new a\n" and (tmp_path / "b.csv").read_text() == "new b\n"


def test_a_folder_is_made_with_its_parents_only_when_committed(maps, tmp_path):
    local_maps = mapio.read_maps([str(maps)])
    target = tmp_path / "a" / "b"
    with mapio.Outputs(folders={"-o": str(target)}):
        mapio.write_maps(local_maps, f"{target}/", "yaml")
        assert not (tmp_path / "a").exists()
    assert listing(tmp_path / "a") == ["b", "b/localmap_1.yaml", "b/localmap_2.yaml", "b/localmap_3.yaml"]
    assert [p for p in os.listdir(tmp_path) if p.startswith(".")] == []


def test_a_symbolic_link_is_written_through_and_a_stream_written_at_commit(tmp_path):
    (tmp_path / "real.csv").write_text("old\n")
    (tmp_path / "link.csv").symlink_to("real.csv")
    stream = io.StringIO()
    with mapio.Outputs(files={"-o": str(tmp_path / "link.csv")}):
        mapio.write_output("new\n", tmp_path / "link.csv")
        mapio.write_output("text\n", stream)
        assert stream.getvalue() == "" and (tmp_path / "real.csv").read_text() == "old\n"
    assert (tmp_path / "link.csv").is_symlink() and (tmp_path / "real.csv").read_text() == "new\n"
    assert stream.getvalue() == "text\n"


def test_a_failure_after_staging_discards_every_staged_file(tmp_path):
    (tmp_path / "a.csv").write_text("old a\n")
    with pytest.raises(InputError, match="boom"):
        with mapio.Outputs(files={"-o": str(tmp_path / "a.csv"), "--report": str(tmp_path / "b.csv")}):
            mapio.write_output("new a\n", tmp_path / "a.csv")
            raise InputError("boom")
    assert listing(tmp_path) == ["a.csv"] and (tmp_path / "a.csv").read_text() == "old a\n"


def test_the_same_file_staged_twice_is_refused(tmp_path):
    with pytest.raises(InputError, match="written twice"):
        with mapio.Outputs():
            mapio.write_output("1\n", tmp_path / "x.csv")
            mapio.write_output("2\n", tmp_path / "./x.csv")
    assert listing(tmp_path) == []


def test_check_minima_keeps_its_batch_input(tmp_path):
    (tmp_path / "t.csv").write_text("a,c_phi\n5,2.5\n")
    (tmp_path / "T.link").symlink_to("t.csv")
    for output in ("t.csv", "./t.csv", "T.CSV", "T.link"):
        code, stderr = run(tmp_path, "check-minima", "--batch", "t.csv", "-o", output)
        assert code == 1 and "input" in stderr, (output, stderr)
    assert (tmp_path / "t.csv").read_text() == "a,c_phi\n5,2.5\n"
