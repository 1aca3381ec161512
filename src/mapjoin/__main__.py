"""The ``mapjoin`` command and ``python -m mapjoin``: the command line inside the process's outermost guard.

Everything a user can do to a running process ends in one line on stderr and a
documented exit code, never a traceback or an "Exception ignored" at exit:

- Ctrl-C at any moment, start-up included: ``mapjoin: interrupted``, exit 130 (the
  writers clean up their temporary files on the way out), unless the command had finished: a
  Ctrl-C after its outputs are committed is ignored, and its own exit code stands;
- stdout closed, full or failing when the data is flushed: one line, exit 1;
- a reader that stops early (``mapjoin join ... | head``): quiet, exit 0;
- a usage error (an unknown option, a value out of range): one line, exit 2.

This module imports only the standard library and :mod:`mapjoin.errors` (which imports nothing) before
the guard is in place.
"""

from __future__ import annotations

import errno
import os
import signal
import sys
from typing import NoReturn

from .errors import EXIT_INTERRUPTED


class _ClosedStdout:
    """Stands in for ``sys.stdout`` when the process was started with file descriptor 1 closed."""

    def write(self, _text: str) -> int:
        raise OSError(errno.EBADF, "stdout is closed", "<stdout>")

    def flush(self) -> None:
        pass


def _silence_stdout() -> None:
    """Point file descriptor 1 at /dev/null so that the interpreter's last flush cannot fail again."""
    try:
        null = os.open(os.devnull, os.O_WRONLY)
        os.dup2(null, 1)
        os.close(null)
    except OSError:
        pass


def _flush_stdout(code: int) -> int:
    """Flush the data written to stdout now, while an error can still be reported; the exit code."""
    try:
        sys.stdout.flush()
    except BrokenPipeError:  # the reader has gone: as other Unix tools, end quietly
        _silence_stdout()
    except OSError as error:
        _silence_stdout()
        if code == 0:  # a command that failed has said why in its one line
            print(f"mapjoin: error: cannot write to stdout ({error.strerror or error})", file=sys.stderr)
        return code or 1
    return code


#: the variables OpenBLAS takes its thread count from (the first set one), when it is loaded with numpy
BLAS_THREAD_VARIABLES = ("OPENBLAS_NUM_THREADS", "GOTO_NUM_THREADS", "OMP_NUM_THREADS")


def one_blas_thread() -> None:
    """Let numpy's and scipy's OpenBLAS run on one thread in this process (and those it starts), unless the
    environment chose a count or numpy is loaded already (a program calling :func:`run`: its BLAS is its own).

    Measured on whole commands (benchmarks/README.md, "Start-up"): this project's BLAS calls are small (a
    map's blocks, SuperLU's supernodes, the selected inversion's), and on the shared 2-core machine OpenBLAS's
    default second thread made ``refine`` of VicPark 200 take 1.08 s instead of 0.73 s (load 3) and larger
    refines no faster (3000 simulated maps). OpenBLAS reads the variable when it is loaded: this runs first."""
    if "numpy" not in sys.modules and not any(name in os.environ for name in BLAS_THREAD_VARIABLES):
        os.environ["OPENBLAS_NUM_THREADS"] = "1"


def run(argv: list[str] | None = None) -> NoReturn:
    """Run the command line with ``argv`` (default: the process's arguments) and exit."""
    one_blas_thread()
    if sys.stdout is None:
        sys.stdout = _ClosedStdout()  # type: ignore[assignment]
    try:
        from .cli import main

        code = main.main(args=argv, prog_name="mapjoin", standalone_mode=False)
        # the command is done, its outputs committed and its summary said: a Ctrl-C from now on changes
        # nothing, so it must not turn a finished command's exit code into 130 (or kill the interpreter's exit)
        signal.signal(signal.SIGINT, signal.SIG_IGN)
    except KeyboardInterrupt:
        code = _interrupted()
    except BaseException as error:  # click's own exits and errors in non-standalone mode
        code = _exit_code(error)
    sys.exit(_flush_stdout(code if isinstance(code, int) else 0))


def _interrupted() -> int:
    _silence_stdout()
    print("mapjoin: interrupted", file=sys.stderr)
    return EXIT_INTERRUPTED


def _exit_code(error: BaseException) -> int:
    """Show a click error or abort as click's standalone mode would; the exit code."""
    import click

    if isinstance(error, click.exceptions.Abort):
        return _interrupted() if isinstance(error.__cause__, KeyboardInterrupt) else 1
    if isinstance(error, click.UsageError) and not isinstance(error, click.exceptions.NoArgsIsHelpError):
        # one line, as every other error: no usage block
        command = error.ctx.command_path if error.ctx else "mapjoin"
        print(f"Error: {' '.join(error.format_message().split())} (see '{command} --help')", file=sys.stderr)
        return error.exit_code
    if isinstance(error, click.ClickException):
        error.show()
        return error.exit_code
    if isinstance(error, click.exceptions.Exit):
        return error.exit_code
    if isinstance(error, SystemExit):
        return error.code if isinstance(error.code, int) else 1
    if isinstance(error, OSError) and error.filename in (None, "<stdout>"):
        # click's own writes outside the commands (whose OSErrors cli.MapjoinGroup turns into one line): --help and
        # --version on a closed or full stdout
        _silence_stdout()
        if isinstance(error, BrokenPipeError):
            return 0
        print(f"mapjoin: error: cannot write to stdout ({error.strerror or error})", file=sys.stderr)
        return 1
    raise error


if __name__ == "__main__":
    run()
