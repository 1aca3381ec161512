"""In-process join times of two source trees of mapjoin, side by side in one run.

    python benchmarks/compare_trees.py BEFORE_SRC AFTER_SRC [--rounds N] [DATASET ...]

For a change that must not slow the joins down (a refactoring, say): ``BEFORE_SRC`` and
``AFTER_SRC`` are the ``src`` folders of two checkouts (``git archive COMMIT | tar -x -C DIR``).
Each round starts, for each tree in turn (the order alternating between rounds), a fresh
interpreter with that tree first on its path, which reads the maps once and times each join
five times, keeping the best. Times are the process's CPU time, which the other load of a shared
machine moves less than wall time; the tree join with two jobs is timed on the wall clock (its
work is done in other processes). Printed per dataset and join: the median over the rounds of
each tree and their ratio, and the ratio of the best rounds.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
from pathlib import Path

from common import DATA

DATASETS = ("VicPark_200_local_maps", "DLR_200_local_maps", "8240_data_50_local_maps", "VicPark_6898_local_maps")
JOINS = (("sequential", "bisection", 1), ("tree", "bisection", 1), ("tree", "bisection", 2),
         ("sequential", "golden", 1))

# run in the child: the maps read once, each join timed five times (the best kept)
_CHILD = """
import json, logging, sys, time
from mapjoin import io
from mapjoin.joining import join
logging.disable(logging.WARNING)
maps = io.read_maps([sys.argv[1]])
times = []
for strategy, solver, jobs in json.loads(sys.argv[2]):
    clock = time.perf_counter if jobs > 1 else time.process_time
    best = float("inf")
    for _ in range(5):
        start = clock()
        join(maps, strategy=strategy, solver=solver, jobs=jobs)
        best = min(best, clock() - start)
    times.append(best)
print(json.dumps(times))
"""


def child_times(source: str, folder: str) -> list[float]:
    """The best of five times of each of JOINS, in a fresh interpreter importing mapjoin from ``source``."""
    environment = {**os.environ, "PYTHONPATH": source}
    output = subprocess.run([sys.executable, "-c", _CHILD, folder, json.dumps(JOINS)], env=environment,
                            check=True, capture_output=True, text=True).stdout
    return json.loads(output)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("before")
    parser.add_argument("after")
    parser.add_argument("datasets", nargs="*", default=DATASETS)
    parser.add_argument("--rounds", type=int, default=7)
    parser.add_argument("--data", type=Path, default=DATA, help="folder of the datasets (default: %(default)s)")
    args = parser.parse_args()
    print(f"load average {os.getloadavg()[0]:.2f} at the start")
    for name in args.datasets:
        folder = str(args.data / name)
        rounds: dict[str, list[list[float]]] = {"before": [], "after": []}
        for number in range(args.rounds):
            trees = [("before", args.before), ("after", args.after)]
            for label, source in trees if number % 2 == 0 else trees[::-1]:
                rounds[label].append(child_times(source, folder))
        for index, (strategy, solver, jobs) in enumerate(JOINS):
            before = [times[index] for times in rounds["before"]]
            after = [times[index] for times in rounds["after"]]
            median_before, median_after = statistics.median(before), statistics.median(after)
            print(f"{name} {strategy} ({solver}, {jobs} job{'s' if jobs > 1 else ''}): "
                  f"{1e3 * median_before:.1f} ms -> {1e3 * median_after:.1f} ms, after/before "
                  f"{median_after / median_before:.3f} (best rounds {min(after) / min(before):.3f})")
    print(f"load average {os.getloadavg()[0]:.2f} at the end")


if __name__ == "__main__":
    main()
