"""What the benchmark scripts share: where the data is, median timing, and writing their README section."""

from __future__ import annotations

import argparse
import compileall
import logging
import os
import statistics
import time
from collections.abc import Callable
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DATA = Path(os.environ.get("MAPJOIN_DATA", ROOT.parent / "shared" / "data"))
README = ROOT / "benchmarks" / "README.md"


def dataset_arguments(doc: str, datasets: tuple[str, ...]) -> argparse.Namespace:
    """Command-line arguments of the scripts that run over real datasets: names, --repeat, --data."""
    parser = argparse.ArgumentParser(description=doc.splitlines()[0])
    parser.add_argument("datasets", nargs="*", default=datasets)
    parser.add_argument("--repeat", type=int, default=5, help="runs per measurement (medians)")
    parser.add_argument("--data", type=Path, default=DATA, help="folder of the datasets (default: %(default)s)")
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


def write_section(name: str, text: str) -> None:
    """Replace the text between ``<!-- name:begin -->`` and ``<!-- name:end -->`` in benchmarks/README.md
    (the markers are appended at the end when missing)."""
    begin, end = f"<!-- {name}:begin -->", f"<!-- {name}:end -->"
    content = README.read_text()
    if begin not in content or end not in content:
        content = f"{content.rstrip()}\n\n{begin}\n{end}\n"
    head, rest = content.split(begin, 1)
    README.write_text(f"{head}{begin}\n{text}\n{end}{rest.split(end, 1)[1]}")
