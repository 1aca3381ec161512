"""What the benchmark scripts share: where the data is, median timing, and writing their README section."""

from __future__ import annotations

import argparse
import compileall
import logging
import os
import statistics
import subprocess
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DATA = Path(os.environ.get("MAPJOIN_DATA", ROOT.parent / "shared" / "data"))
README = ROOT / "benchmarks" / "README.md"


def dataset_arguments(doc: str, datasets: tuple[str, ...],
                      options: Callable[[argparse.ArgumentParser], object] | None = None) -> argparse.Namespace:
    """Command-line arguments of the scripts that run over real datasets: names, --repeat, --data (and the
    script's own ``options``, added to the parser)."""
    parser = argparse.ArgumentParser(description=doc.splitlines()[0])
    parser.add_argument("datasets", nargs="*", default=datasets)
    parser.add_argument("--repeat", type=int, default=5, help="runs per measurement (medians)")
    parser.add_argument("--data", type=Path, default=DATA, help="folder of the datasets (default: %(default)s)")
    if options is not None:
        options(parser)
    args = parser.parse_args()
    logging.getLogger("mapjoin").setLevel(logging.ERROR)
    return args


def compile_mapjoin() -> str:
    """Compile the imported mapjoin package to bytecode, as an installed package is, so that
    timings of fresh interpreters leave out compiling it (which PYTHONDONTWRITEBYTECODE or a
    read-only editable checkout would otherwise repeat in every run); returns a note saying so."""
    import mapjoin

    package = Path(mapjoin.__file__).parent
    compileall.compile_dir(package, quiet=1)
    return f"bytecode of {package} compiled beforehand"


def median_seconds(run: Callable[[], object], repeats: int) -> tuple[float, object]:
    """Median wall time of ``run`` over ``repeats`` calls, and the last result."""
    times, result = [], None
    for _ in range(repeats):
        start = time.perf_counter()
        result = run()
        times.append(time.perf_counter() - start)
    return statistics.median(times), result


# the command in a fresh interpreter that reports its own peak resident set on exit: VmHWM
# belongs to the process's new address space, while rusage's maxrss would carry over the
# high-water mark of this (large) benchmark process through fork and exec (Linux only)
_RUN_AND_REPORT_PEAK = """
import runpy, sys
sys.argv = ["mapjoin", *sys.argv[1:]]
try:
    runpy.run_module("mapjoin", run_name="__main__", alter_sys=True)
finally:
    status = open("/proc/self/status").read()
    print("VmHWM", status.split("VmHWM:")[1].split()[0], file=sys.stderr)
"""


def whole_command(arguments: list[str], repeat: int, stdin: Path | Sequence[str] | None = None
                  ) -> tuple[float, float]:
    """Median wall time (s) and largest peak RSS (MB) of ``mapjoin ARGUMENTS`` in a fresh interpreter.

    ``stdin``: a file to read standard input from, or a command whose output is piped into it
    (started with it and timed with it, as a shell pipe is).
    """
    times, peaks = [], []
    command = [sys.executable, "-c", _RUN_AND_REPORT_PEAK, *arguments]
    for _ in range(repeat):
        start = time.perf_counter()
        if stdin is None or isinstance(stdin, Path):
            with open(stdin or os.devnull, "rb") as file:
                process = subprocess.run(command, stdin=file, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                                         text=True)
        else:
            with subprocess.Popen(stdin, stdout=subprocess.PIPE) as producer:
                process = subprocess.run(command, stdin=producer.stdout, stdout=subprocess.DEVNULL,
                                         stderr=subprocess.PIPE, text=True)
                producer.stdout.close()
        times.append(time.perf_counter() - start)
        if process.returncode:
            raise SystemExit(f"mapjoin {' '.join(arguments)} exited with {process.returncode}: {process.stderr}")
        peaks.append(int(process.stderr.split("VmHWM")[-1].split()[0]) / 1024)
    return statistics.median(times), max(peaks)


def write_section(name: str, text: str) -> None:
    """Replace the text between ``<!-- name:begin -->`` and ``<!-- name:end -->`` in benchmarks/README.md
    (the markers are appended at the end when missing)."""
    begin, end = f"<!-- {name}:begin -->", f"<!-- {name}:end -->"
    content = README.read_text()
    if begin not in content or end not in content:
        content = f"{content.rstrip()}\n\n{begin}\n{end}\n"
    head, rest = content.split(begin, 1)
    README.write_text(f"{head}{begin}\n{text}\n{end}{rest.split(end, 1)[1]}")
