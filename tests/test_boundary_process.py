"""The boundary of a real process: Ctrl-C, closed or full stdout, pipes closed early, special files.

These need a process of their own (what happens at interpreter exit, signals, file
descriptors), so they run ``python -m mapjoin`` as a user would.
"""

from __future__ import annotations

import os
import signal
import stat
import subprocess
import sys
import time
from pathlib import Path

import pytest

MAPJOIN = [sys.executable, "-m", "mapjoin"]


# the sequential join of a long simulated run drifts and fails the consistency check at its loop
# closures (docs/method.md#chi-square-check); gate 0 keeps those warnings out of the one-line checks
QUIET_CHECK = ("--gate", "0")


def mapjoin(*args: str, cwd: Path, **kwargs) -> subprocess.CompletedProcess:
    return subprocess.run([*MAPJOIN, *args], cwd=cwd, capture_output=True, text=True, timeout=120, **kwargs)


def assert_one_line_error(stderr: str) -> None:
    assert "Traceback" not in stderr and "Exception ignored" not in stderr, stderr
    assert len(stderr.strip().splitlines()) == 1, stderr


@pytest.fixture(scope="module")
def maps(tmp_path_factory) -> Path:
    """A YAML stream of 400 simulated local maps (enough work to interrupt, and output to overflow a pipe)."""
    folder = tmp_path_factory.mktemp("process")
    result = mapjoin("simulate", "-o", "maps.yaml", "--maps", "400", "--seed", "1", cwd=folder)
    assert result.returncode == 0, result.stderr
    return folder / "maps.yaml"


@pytest.fixture(scope="module")
def joined(maps, tmp_path_factory) -> bytes:
    """The output of the uninterrupted command the Ctrl-C test interrupts."""
    folder = tmp_path_factory.mktemp("uninterrupted")
    result = mapjoin("join", str(maps), "--refine", "-o", "out.csv", *QUIET_CHECK, cwd=folder)
    assert result.returncode == 0, result.stderr
    return (folder / "out.csv").read_bytes()


@pytest.mark.parametrize("delay", [0.25, 0.4, 0.6, 0.9, 1.3, 2.0])
def test_ctrl_c_at_any_moment_is_one_line_and_exit_130(maps, joined, tmp_path, delay):
    process = subprocess.Popen([*MAPJOIN, "join", str(maps), "--refine", "-o", "out.csv", *QUIET_CHECK], cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    time.sleep(delay)
    process.send_signal(signal.SIGINT)
    stdout, stderr = process.communicate(timeout=120)
    assert "Traceback" not in stderr and "Exception ignored" not in stderr, stderr
    # all or nothing, whenever the signal came: the whole output, or no file at all (no temporary left either)
    written = sorted(p.name for p in tmp_path.iterdir())
    assert written in ([], ["out.csv"]), written
    if written:
        assert (tmp_path / "out.csv").read_bytes() == joined
    if process.returncode == 0:  # finished before the signal arrived, or the signal came after it had finished
        assert written == ["out.csv"]
        assert "interrupted" not in stderr, stderr
    else:
        # 130 from mapjoin's guard; -SIGINT when the signal came while the interpreter itself was still
        # starting, before any of mapjoin's code ran (Python then ends by the signal, silently), or, under
        # `python -m` only, while a class was being made from a string (a dataclass's __init__): CPython then
        # ends by the signal after mapjoin's one line, whatever exit code mapjoin gave
        assert process.returncode in (130, -signal.SIGINT), (process.returncode, stderr)
        # one line for the interruption; before it only what the command said before the signal (a join's
        # progress, "refined to the exact join ..."), never a second error. A signal between the commit of
        # the output and the command's end still says so (the output is then whole, as checked above)
        lines = stderr.strip().splitlines()
        assert not lines or lines[-1] == "mapjoin: interrupted", stderr
        assert not [line for line in lines[:-1] if "error" in line.lower() or "interrupted" in line], stderr


def test_closed_stdout_is_one_line_and_nonzero(maps, tmp_path):
    result = subprocess.run([*MAPJOIN, "join", str(maps), *QUIET_CHECK], cwd=tmp_path, stdin=subprocess.DEVNULL,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, timeout=120,
                            preexec_fn=lambda: os.close(1))
    assert result.returncode != 0
    assert_one_line_error(result.stderr)


def test_full_stdout_is_one_line_and_nonzero(maps, tmp_path):
    with open("/dev/full", "w") as full:
        result = subprocess.run([*MAPJOIN, "join", str(maps), *QUIET_CHECK], cwd=tmp_path, stdout=full, stderr=subprocess.PIPE,
                                text=True, timeout=120)
    assert result.returncode == 1
    assert_one_line_error(result.stderr)


def test_a_pipe_closed_early_ends_quietly(maps, tmp_path):
    """``mapjoin join ... | head -c 100``: no message, as other Unix tools end."""
    process = subprocess.Popen([*MAPJOIN, "join", str(maps), *QUIET_CHECK], cwd=tmp_path, stdout=subprocess.PIPE,
                               stderr=subprocess.PIPE)
    assert len(process.stdout.read(100)) == 100
    process.stdout.close()
    stderr = process.stderr.read().decode()
    process.wait(timeout=120)
    assert stderr == "", stderr
    assert process.returncode in (0, 141, -signal.SIGPIPE)


def _device(path: Path, minor: int) -> bool:
    """A character device like /dev/null (minor 3) or /dev/full (minor 7) at ``path``; False without the right."""
    try:
        os.mknod(path, stat.S_IFCHR | 0o666, os.makedev(1, minor))
    except (PermissionError, OSError):
        return False
    return True


@pytest.mark.parametrize("command", [["join", "{maps}", "-o", "{target}"],
                                     ["join", "{maps}", "-o", "out.csv", "--report", "{target}"],
                                     ["simulate", "--maps", "2", "-o", "{target}", "--format", "csv"]])
def test_a_device_output_is_written_through_not_replaced(maps, tmp_path, command):
    null = tmp_path / "null"
    if not _device(null, 3):
        pytest.skip("creating a device node needs root (CI runs as root)")
    result = mapjoin(*[part.format(maps=maps, target=null) for part in command], cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    assert stat.S_ISCHR(os.lstat(null).st_mode), "the device node was replaced by a regular file"


def test_a_full_device_output_fails_in_one_line(maps, tmp_path):
    full = tmp_path / "full"
    if not _device(full, 7):
        pytest.skip("creating a device node needs root (CI runs as root)")
    result = mapjoin("join", str(maps), "-o", str(full), *QUIET_CHECK, cwd=tmp_path)
    assert result.returncode == 1
    assert_one_line_error(result.stderr)
    assert stat.S_ISCHR(os.lstat(full).st_mode)


def test_a_fifo_output_is_written_through(maps, tmp_path):
    fifo = tmp_path / "pipe"
    os.mkfifo(fifo)
    reader = os.open(fifo, os.O_RDONLY | os.O_NONBLOCK)  # a reader waiting before the writer starts
    chunks = []
    try:
        process = subprocess.Popen([*MAPJOIN, "join", str(maps), "-o", str(fifo)], cwd=tmp_path,
                                   stderr=subprocess.PIPE, text=True)
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline:
            try:
                chunk = os.read(reader, 1 << 16)
            except BlockingIOError:
                chunk = None
            if chunk:
                chunks.append(chunk)
            elif process.poll() is not None:
                break
            else:
                time.sleep(0.01)
        process.wait(timeout=10)
    finally:
        os.close(reader)
    assert process.returncode == 0, process.stderr.read()
    assert b"".join(chunks).startswith(b"kind,id,x,y,phi")
    assert stat.S_ISFIFO(os.lstat(fifo).st_mode)


def test_an_output_through_a_symlink_replaces_the_file_it_points_to(maps, tmp_path):
    """Documented choice: a symbolic link is written through (the link stays, its target gets the output)."""
    (tmp_path / "real.csv").write_text("old\n")
    os.symlink("real.csv", tmp_path / "link.csv")
    result = mapjoin("join", str(maps), "-o", "link.csv", cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    assert os.path.islink(tmp_path / "link.csv")
    assert (tmp_path / "real.csv").read_text().startswith("kind,id,x,y,phi")


@pytest.mark.parametrize("args", [["check-minima", "--a", "2", "--c-phi", "nan"], ["join", "--bogus"], ["nosuch"],
                                  ["refine", "x.yaml", "--tolerance", "inf"]])
def test_a_usage_error_is_one_line_and_exit_2(tmp_path, args):
    result = mapjoin(*args, cwd=tmp_path)
    assert result.returncode == 2
    assert_one_line_error(result.stderr)
    assert result.stderr.startswith("Error: ") and "--help" in result.stderr


@pytest.mark.parametrize("input_format", ["yaml", "csv", "linearslam"])
def test_an_endless_input_stops_at_the_bound_in_one_line(tmp_path, input_format):
    """/dev/zero (no line end, no end): an error naming it, not unbounded memory or time."""
    result = mapjoin("join", "/dev/zero", "--input-format", input_format, "-o", "out.csv", cwd=tmp_path)
    assert result.returncode == 1
    assert_one_line_error(result.stderr)
    assert "/dev/zero" in result.stderr and not (tmp_path / "out.csv").exists()
