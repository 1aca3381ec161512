"""Speed of mapjoin on the real datasets: reading, each join strategy, refine, and whole commands.

    python benchmarks/speed.py [--repeat N] [DATASET ...]     (default: the four below)

In-process (maps loaded once; medians of ``--repeat`` runs): reading the folder, the
sequential join, the tree join with 1 and 2 processes, the exact refinement (solve and
marginal covariances), and each fast join's distance from the exact one (the paper's
metric: mean absolute x, y, phi). Whole commands (a fresh interpreter per run, as a
user types them; medians of ``--repeat``): ``mapjoin join`` with each strategy and
``mapjoin refine``, with the peak resident memory of the process (its VmHWM, Linux), beside
the time a fresh interpreter takes only to import numpy, and numpy with scipy.sparse.linalg.
Results are printed and written between the ``speed`` markers of benchmarks/README.md.
"""

from __future__ import annotations

import os
import statistics
import subprocess
import sys
import tempfile
import time

from common import compile_mapjoin, dataset_arguments, median_seconds, whole_command, write_section

from mapjoin import io as mapio
from mapjoin.evaluation import compare
from mapjoin.joining import join
from mapjoin.refine import refine

DATASETS = ("VicPark_200_local_maps", "DLR_200_local_maps", "8240_data_50_local_maps", "VicPark_6898_local_maps")
COMMANDS = {
    "join (sequential)": ["join"],
    "join --strategy tree": ["join", "--strategy", "tree"],
    "join --strategy tree --jobs 2": ["join", "--strategy", "tree", "--jobs", "2"],
    "refine": ["refine"],
}


def import_floor(repeat: int) -> tuple[float, float]:
    """Median wall time (s) of a fresh interpreter importing numpy, and numpy with scipy.sparse.linalg
    (what refine needs): the part of every whole command that mapjoin does not control."""
    floors = []
    for modules in ("numpy", "numpy, scipy.sparse.linalg"):
        times = []
        for _ in range(repeat):
            start = time.perf_counter()
            subprocess.run([sys.executable, "-c", f"import {modules}"], check=True)
            times.append(time.perf_counter() - start)
        floors.append(statistics.median(times))
    return floors[0], floors[1]


def main() -> None:
    args = dataset_arguments(__doc__, DATASETS)
    inprocess = ["| dataset | maps | read (s) | sequential join (ms) | tree join (ms) | tree, 2 jobs (ms) | "
                 "refine (s) | sequential vs exact: x, y (m), phi (rad) | tree vs exact |",
                 "|---|---:|---:|---:|---:|---:|---:|---|---|"]
    commands = ["| dataset | " + " | ".join(COMMANDS) + " |", "|---|" + "---:|" * len(COMMANDS)]
    compiled = compile_mapjoin()
    for name in args.datasets:
        folder = str(args.data / name)
        read, maps = median_seconds(lambda: mapio.read_maps([folder]), args.repeat)  # noqa: B023
        times, distances = {}, {}
        for label, strategy, jobs in (("sequential", "sequential", 1), ("tree", "tree", 1), ("tree2", "tree", 2)):
            times[label], result = median_seconds(lambda: join(maps, strategy=strategy, jobs=jobs),  # noqa: B023
                                                  args.repeat)
            distances[label] = result.global_map
        refine_time, exact = median_seconds(lambda: refine(maps), args.repeat)  # noqa: B023
        metric = {}
        for label in ("sequential", "tree"):
            d = compare(distances[label], exact.global_map)
            metric[label] = f"{d.mean_abs_x:.3f}, {d.mean_abs_y:.3f}, {d.mean_abs_phi:.4f}"
        inprocess.append(f"| {name} | {len(maps)} | {read:.3f} | {1e3 * times['sequential']:.1f} | "
                         f"{1e3 * times['tree']:.1f} | {1e3 * times['tree2']:.1f} | {refine_time:.3f} "
                         f"({exact.iterations} it., chi^2 {exact.cost:.3f}) | {metric['sequential']} | "
                         f"{metric['tree']} |")
        cells = []
        with tempfile.TemporaryDirectory() as scratch:
            for arguments in COMMANDS.values():
                seconds, peak = whole_command([*arguments, folder, "-o", os.path.join(scratch, "out.csv")],
                                              args.repeat)
                cells.append(f"{seconds:.2f} s, {peak:.0f} MB")
        commands.append(f"| {name} | " + " | ".join(cells) + " |")
        print(inprocess[-1], commands[-1], sep="\n", file=sys.stderr)
    numpy_floor, scipy_floor = import_floor(args.repeat)
    text = "\n".join([f"In-process, maps loaded, medians of {args.repeat} (2-core shared machine, "
                      f"{os.cpu_count()} CPUs visible):", "", *inprocess, "",
                      f"Whole commands as typed (`python -m mapjoin ... DATASET -o out.csv`: summary, warnings "
                      f"and refine's chi^2 check included), a fresh `{sys.executable}` per run, {compiled}, "
                      f"reading included; median wall time of {args.repeat} and peak RSS. In the same run, a "
                      f"fresh interpreter that only imports numpy takes {numpy_floor:.2f} s, and numpy with "
                      f"scipy.sparse.linalg (refine's imports) {scipy_floor:.2f} s:", "", *commands])
    print(text)
    write_section("speed", text)


if __name__ == "__main__":
    main()
