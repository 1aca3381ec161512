"""Timing and memory of the exact join (mapjoin.refine) on the real datasets.

    python benchmarks/refine_scale.py [--repeat N] [DATASET ...]   (default: all four)

For each dataset: refine's default start (the fast tree join, mapjoin.refine.DEFAULT_START), then refine from
it: solve time (set-up + iterations), covariance time (selected inversion), their total
and its ratio to the fast join's time (machines are noisy: compare ratios), iterations,
final chi^2, and the peak memory the refine allocated (tracemalloc; numpy arrays
included, SuperLU's own memory not), medians of ``--repeat`` runs for the times. Written
between the ``refine`` markers of benchmarks/README.md.
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # before numpy: one BLAS thread

import resource
import statistics
import time
import tracemalloc

from common import dataset_arguments, write_section

from mapjoin.io import read_maps
from mapjoin.joining import join
from mapjoin.refine import DEFAULT_START, refine

DATASETS = ("VicPark_200_local_maps", "DLR_200_local_maps", "8240_data_50_local_maps", "VicPark_6898_local_maps")


def main() -> None:
    args = dataset_arguments(__doc__, DATASETS)
    lines = ["| dataset | maps | unknowns | fast join (s) | solve (s) | cov (s) | refine total (s) | refine / join "
             "| iterations | chi^2 | peak (MB) |", "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for name in args.datasets:
        maps = read_maps([str(args.data / name)])
        joins, solves, covs, totals = [], [], [], []
        for _ in range(args.repeat):
            start = time.perf_counter()
            initial = join(maps, strategy=DEFAULT_START).global_map
            joins.append(time.perf_counter() - start)
            start = time.perf_counter()
            result = refine(maps, initial)
            totals.append(time.perf_counter() - start)
            solves.append(result.seconds)
            covs.append(result.covariance_seconds)
        tracemalloc.start()
        refine(maps, initial)
        peak = tracemalloc.get_traced_memory()[1] / 2**20
        tracemalloc.stop()
        joined, solve, cov, total = (statistics.median(v) for v in (joins, solves, covs, totals))
        lines.append(f"| {name} | {len(maps)} | {result.unknowns} | {joined:.3f} | {solve:.3f} | {cov:.3f} | "
                     f"{total:.3f} | {total / joined:.2f} | {result.iterations} | {result.cost:.6f} | {peak:.1f} |")
        print(lines[-1])
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    write_section("refine", "\n".join([
        f"Refine started from its default start, the fast {DEFAULT_START} join (in-process, maps loaded, "
        f"`OPENBLAS_NUM_THREADS=1`, "
        f"medians of {args.repeat}; load average {os.getloadavg()[0]:.1f} at the end): solve = set-up and "
        "iterations, cov = the marginal covariances by selected inversion, peak = memory refine allocated "
        "(tracemalloc; SuperLU's own not included).", "", *lines, "", f"Max RSS of the whole run: {rss:.0f} MB."]))


if __name__ == "__main__":
    main()
