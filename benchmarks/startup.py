"""Start-up: whole commands on the issue's datasets, before and after, beside Linear SLAM's times (issue 17, item 6).

    python benchmarks/startup.py [--rounds N] [--before SRC] [--data DIR]
    python benchmarks/startup.py --crossover [--rounds N]

Whole commands as typed (``python -m mapjoin join|refine DATASET -o out.csv``), each in a
fresh interpreter, from the ``src`` folders given (``--before``: e.g. a checkout of an
earlier commit, ``git archive COMMIT src | tar -x -C DIR``; ``--after``: by default this tree), both
compiled to bytecode beforehand. The rounds interleave every command and tree, so that the
load of the shared machine falls on all alike; medians of the rounds (wall time, and CPU
time of the process, which that load moves less). In the same rounds the reference
commands: ``python -c pass``, ``import numpy``, ``import numpy, scipy.sparse.linalg`` and
``mapjoin --help`` (before), the machine measures the issue's figures were taken with:
Linear SLAM's times are shown as measured there and scaled by this machine's speed
relative to that one (here / there, for the scipy import and for ``--help``).

``--crossover``: where the dense backend of the exact solve (refine/dense.py) stops paying
for itself: the first K maps of VicPark 200 and of DLR 200 (and 8240's 50) refined in a fresh
interpreter (reading, fast join, solve, marginal covariances) with each backend forced, OpenBLAS's
threads as the command sets them (``mapjoin.__main__.one_blas_thread``); median wall times by the
dense work of one factorisation in the problem's partition (``refine.dense.Partition.work``, what
``DENSE_WORK`` bounds).
"""

from __future__ import annotations

import argparse
import compileall
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from common import DATA, ROOT, write_section

from mapjoin.__main__ import BLAS_THREAD_VARIABLES

DATASETS = ("VicPark_200_local_maps", "DLR_200_local_maps", "8240_data_50_local_maps", "VicPark_6898_local_maps")
#: the issue's refine target, also run quiet (``-q``: no chi^2 warning, whose bounds import scipy.special)
QUIET = "VicPark_200_local_maps"
TINY = "535_data_5_local_maps"  # not in the issue's table: a refine small enough for the dense backend
#: the issue's table (same run there): Linear SLAM C++, mapjoin join, mapjoin refine; whole commands, seconds
ISSUE = {"VicPark_200_local_maps": (0.50, 0.40, 1.03), "DLR_200_local_maps": (0.27, 0.50, 1.17),
         "8240_data_50_local_maps": (0.13, 0.40, 1.05), "VicPark_6898_local_maps": (5.36, 1.76, 4.05)}
#: the issue's machine: a fresh interpreter importing numpy and scipy.sparse.linalg (0.63-0.77 s: the middle),
#: and `mapjoin --help`
ISSUE_SCIPY, ISSUE_HELP = 0.70, 0.33

_CROSSOVER_CHILD = """
import sys
from mapjoin.__main__ import one_blas_thread
one_blas_thread()   # as the command: OpenBLAS on one thread unless the environment says otherwise
from mapjoin import io
from mapjoin.joining import join
from mapjoin.refine.problem import ExactProblem
from mapjoin.refine.solver import minimise
folder, count, backend = sys.argv[1], int(sys.argv[2]), sys.argv[3]
maps = io.read_maps([folder])[:count]
problem = ExactProblem(maps, backend=backend)
found = minimise(problem, problem.pack(join(maps, strategy="tree").global_map))
problem.marginals(found.final_factor(problem))
print(problem.n_unknowns, problem._partition.work if backend == "dense" else 0)
"""


def timed(command: list[str], src: Path | None, cwd: str) -> tuple[float, float, str]:
    """Wall and CPU seconds of one run of ``command`` with ``src`` first on the path; its stdout."""
    env = dict(os.environ)
    # OpenBLAS's threads: its own default (before) or what the command sets (after), not this shell's
    for name in ("PYTHONDONTWRITEBYTECODE", *BLAS_THREAD_VARIABLES):
        env.pop(name, None)
    if src is not None:
        env["PYTHONPATH"] = str(src)
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    start = time.perf_counter()
    process = subprocess.run(command, env=env, cwd=cwd, capture_output=True, text=True, check=False)
    wall = time.perf_counter() - start
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if process.returncode:
        raise SystemExit(f"{' '.join(command)} exited with {process.returncode}: {process.stderr}")
    return wall, after.ru_utime + after.ru_stime - before.ru_utime - before.ru_stime, process.stdout


def run_rounds(cases: dict[str, tuple[list[str], Path | None]], rounds: int, cwd: str) -> dict[str, tuple]:
    """Median wall and CPU seconds of every case, the cases interleaved round by round (order reversed
    every other round)."""
    walls: dict[str, list[float]] = {name: [] for name in cases}
    cpus: dict[str, list[float]] = {name: [] for name in cases}
    names = list(cases)
    for r in range(rounds):
        for name in names if r % 2 == 0 else names[::-1]:
            wall, cpu, _ = timed(*cases[name], cwd)
            walls[name].append(wall)
            cpus[name].append(cpu)
        print(f"round {r + 1}/{rounds}", file=sys.stderr)
    return {name: (statistics.median(walls[name]), statistics.median(cpus[name])) for name in cases}


def compile_tree(src: Path) -> None:
    """Bytecode for ``src``, as an installed package has (this shell may set PYTHONDONTWRITEBYTECODE)."""
    compileall.compile_dir(src, quiet=1)


def commands(args: argparse.Namespace) -> str:
    """The whole-command table, before and after, with the references and the issue's figures scaled."""
    trees = {"after": args.after.resolve()} | ({"before": args.before.resolve()} if args.before else {})
    for src in trees.values():
        compile_tree(src)
    python = sys.executable
    scratch = tempfile.mkdtemp(prefix="mapjoin-startup-")
    cases: dict[str, tuple[list[str], Path | None]] = {
        "python -c pass": ([python, "-c", "pass"], None),
        "import numpy": ([python, "-c", "import numpy"], None),
        "import numpy, scipy.sparse.linalg": ([python, "-c", "import numpy, scipy.sparse.linalg"], None),
        "import numpy, scipy.sparse.linalg, scipy.special": (
            [python, "-c", "import numpy, scipy.sparse.linalg, scipy.special"], None),
        "import numpy (one BLAS thread)": (
            [python, "-c", "import os; os.environ['OPENBLAS_NUM_THREADS'] = '1'; import numpy"], None)}
    for tree, src in trees.items():
        cases[f"--help ({tree})"] = ([python, "-m", "mapjoin", "--help"], src)
        runs = ([(name, command) for name in DATASETS for command in ("join", "refine")]
                + [(QUIET, "-q refine"), (TINY, "refine")])
        for name, command in runs:
            cases[f"{command} {name} ({tree})"] = ([python, "-m", "mapjoin", *command.split(), str(args.data / name),
                                                    "-o", os.path.join(scratch, f"{tree}.csv")], src)
    load = os.getloadavg()
    medians = run_rounds(cases, args.rounds, scratch)
    load_end = os.getloadavg()
    scipy_ratio = medians["import numpy, scipy.sparse.linalg"][0] / ISSUE_SCIPY
    help_tree = "before" if "before" in trees else "after"
    help_ratio = medians[f"--help ({help_tree})"][0] / ISSUE_HELP

    def cell(key: str) -> str:
        wall, cpu = medians[key]
        return f"{wall:.3f} ({cpu:.3f})"

    lines = [(f"Medians of {args.rounds} interleaved rounds, wall seconds (CPU seconds of the process in brackets), "
              f"a fresh `{Path(python).name}` per run, bytecode compiled, 2-core shared machine, load average "
              f"{load[0]:.2f} at the start and {load_end[0]:.2f} at the end."), "",
             "| reference | here | issue's machine | here / there |", "|---|---:|---:|---:|",
             f"| `python -c pass` | {cell('python -c pass')} | | |",
             f"| `python -c \"import numpy\"` | {cell('import numpy')} | | |",
             f"| the same, `OPENBLAS_NUM_THREADS=1` (as `mapjoin` sets it) | {cell('import numpy (one BLAS thread)')} "
             "| | |",
             (f"| `python -c \"import numpy, scipy.sparse.linalg\"` | {cell('import numpy, scipy.sparse.linalg')} | "
              f"0.63-0.77 | {scipy_ratio:.2f} |"),
             ("| `python -c \"import numpy, scipy.sparse.linalg, scipy.special\"` (the chi^2 warning's quantiles) | "
              f"{cell('import numpy, scipy.sparse.linalg, scipy.special')} | | |")]
    lines += [f"| `mapjoin --help` ({tree}) | {cell(f'--help ({tree})')} | 0.33 | "
              f"{medians[f'--help ({tree})'][0] / ISSUE_HELP:.2f} |" for tree in trees]
    columns = [tree for tree in ("before", "after") if tree in trees]
    lines += ["", "| command | " + " | ".join(columns) + " | Linear SLAM there | scaled by the scipy import | "
              "scaled by `--help` | issue's mapjoin there |", "|---|" + "---:|" * (len(columns) + 4)]
    for name in DATASETS:
        linear, join_there, refine_there = ISSUE[name]
        for command, there in (("join", join_there), ("refine", refine_there)):
            key = f"{command} {name}"
            lines.append(f"| `{command} {name}` | " + " | ".join(cell(f"{key} ({tree})") for tree in columns)
                         + f" | {linear:.2f} | {linear * scipy_ratio:.2f} | {linear * help_ratio:.2f} | "
                           f"{there:.2f} |")
    key = f"-q refine {QUIET}"
    linear, _, refine_there = ISSUE[QUIET]
    lines.append(f"| `{key}` | " + " | ".join(cell(f"{key} ({tree})") for tree in columns)
                 + f" | {linear:.2f} | {linear * scipy_ratio:.2f} | {linear * help_ratio:.2f} | {refine_there:.2f} |")
    lines.append(f"| `refine {TINY}` | " + " | ".join(cell(f"refine {TINY} ({tree})") for tree in columns)
                 + " | | | | |")
    return "\n".join(lines)


def crossover(args: argparse.Namespace) -> str:
    """Whole-process times of refining the first K maps with each backend forced."""
    compile_tree(ROOT / "src")
    scratch = tempfile.mkdtemp(prefix="mapjoin-crossover-")
    cases, unknowns = {}, {}
    for name, counts in (("535_data_5_local_maps", (5,)),
                         ("VicPark_200_local_maps", (2, 4, 8, 16, 25, 40, 80, 100, 120, 150, 200)),
                         ("DLR_200_local_maps", (5, 10, 20, 30, 60, 80, 100, 120, 140, 160, 180, 200)),
                         ("8240_data_50_local_maps", (50,))):
        for count in counts:
            for backend in ("dense", "sparse"):
                cases[f"{name} {count} {backend}"] = ([sys.executable, "-c", _CROSSOVER_CHILD, str(args.data / name),
                                                       str(count), backend], ROOT / "src")
            n, work = timed(*cases[f"{name} {count} dense"], scratch)[2].split()
            unknowns[(name, count)] = int(n), float(work)
    load = os.getloadavg()
    medians = run_rounds(cases, args.rounds, scratch)
    load_end = os.getloadavg()
    lines = [(f"Medians of {args.rounds} interleaved rounds (load average {load[0]:.2f} at the start, "
              f"{load_end[0]:.2f} at the end), wall seconds "
              "(CPU seconds in brackets) of a fresh interpreter reading the maps, joining them (tree), solving and "
              "computing the marginal covariances with the backend forced, OpenBLAS on one thread as in the "
              "command:"), "",
             "| maps | unknowns | dense work (MFlop) | dense | sparse | dense / sparse (wall) |",
             "|---|---:|---:|---:|---:|---:|"]
    for (name, count), (n, work) in sorted(unknowns.items(), key=lambda item: item[1][1]):
        dense, sparse = medians[f"{name} {count} dense"], medians[f"{name} {count} sparse"]
        lines.append(f"| first {count} of {name} | {n} | {work / 1e6:.0f} | {dense[0]:.3f} ({dense[1]:.3f}) | "
                     f"{sparse[0]:.3f} ({sparse[1]:.3f}) | {dense[0] / sparse[0]:.2f} |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=7, help="interleaved runs of every command (medians)")
    parser.add_argument("--before", type=Path, help="the src folder of the tree to compare with")
    parser.add_argument("--after", type=Path, default=ROOT / "src", help="the src folder measured (default: this one)")
    parser.add_argument("--data", type=Path, default=DATA, help="folder of the datasets (default: %(default)s)")
    parser.add_argument("--crossover", action="store_true", help="measure the dense backend's crossover instead")
    args = parser.parse_args()
    if args.crossover:
        text = crossover(args)
        write_section("startup-crossover", text)
    else:
        text = commands(args)
        write_section("startup", text)
    print(text)


if __name__ == "__main__":
    main()
