"""What the fast join's uncertainty columns mean, and what real covariances cost (issue 14, part 3).

    python benchmarks/uncertainty.py [--repeat N]

NEES table: on the simulations with ground truth (535 and 8240 steps, and a 1,000-map
``mapjoin simulate --seed 0`` run), the average feature / pose NEES that ``evaluate``
computes (:func:`mapjoin.evaluation.evaluate`) for four estimate-and-uncertainty pairs:

* ``fast, weights``: the fast sequential join with its spherical weights (what it writes);
* ``fast, linearised``: the fast estimate with the marginals of the exact problem
  linearised at it (one factorisation and the selected inversion of mapjoin.refine);
* ``1 Gauss-Newton step``: ``refine(..., max_iterations=1)`` from the fast join, its marginals;
* ``exact``: the exact join from that fast join (``join --refine --strategy S``) and its marginals,
  with its chi^2.

The 1,000-map run is joined by both strategies: from the sequential join, which drifts
far on it, the exact solver ends in another local minimum (its chi^2 says so); from the tree
join, the default start of ``--refine``, it reaches the optimum.

Cost table: on VicPark 6898 and 8240, the fast join and, relative to it, the linearised
marginals (problem set-up, J^T J, factorisation, selected inversion) and the whole
``--refine`` (solve and marginals); medians of ``--repeat`` runs. Written between the
``uncertainty`` markers of benchmarks/README.md.
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # before numpy: one BLAS thread

import dataclasses
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
from common import dataset_arguments, median_seconds, write_section

from mapjoin import io as mapio
from mapjoin.evaluation import evaluate
from mapjoin.joining import STRATEGIES, join, join_sequential
from mapjoin.maps import GlobalMap
from mapjoin.refine import refine
from mapjoin.refine.problem import ExactProblem

SIMULATIONS = ("535_data_5_local_maps", "8240_data_50_local_maps")
TIMED = ("VicPark_6898_local_maps", "8240_data_50_local_maps")


def linearised(maps, fast: GlobalMap) -> GlobalMap:
    """``fast`` with the marginals of the exact problem linearised at it (no step taken)."""
    problem = ExactProblem(maps)
    data, _, _ = problem.linearise(problem.pack(fast))
    poses, features = problem.marginals(problem.factorise(data))
    return dataclasses.replace(fast, feature_covariances=features[np.searchsorted(problem.feature_ids, fast.feature_ids)],
                               pose_covariances=poses[np.searchsorted(problem.pose_ids, fast.pose_ids)])


def nees_row(label: str, maps, truth, strategy: str = "sequential") -> str:
    """The table's row for ``maps``: NEES of the four pairs, the fast join by ``strategy``, and the
    exact join's chi^2 / degrees of freedom (iterations up to 1000: a local minimum shows as chi^2)."""
    fast = join(maps, strategy=strategy).global_map
    exact = refine(maps, fast, max_iterations=1000)
    estimates = {"fast, weights": fast, "fast, linearised": linearised(maps, fast),
                 "1 Gauss-Newton step": refine(maps, fast, max_iterations=1).global_map,
                 "exact": exact.global_map}
    cells = []
    for estimate in estimates.values():
        result = evaluate(estimate, truth)
        cells.append(f"{result.nees_features:.4g} / {result.nees_poses:.4g}")
    return (f"| {label} | {strategy} | " + " | ".join(cells)
            + f" | {exact.cost:.0f} / {exact.degrees_of_freedom} ({exact.iterations} it) |")


def main() -> None:
    args = dataset_arguments(__doc__, TIMED)
    rows = []
    for name in SIMULATIONS:
        maps = mapio.read_maps(args.data / name)
        rows.append(nees_row(name, maps, mapio.read_truth_folder(args.data / name, maps=len(maps))))
    with tempfile.TemporaryDirectory() as folder:
        subprocess.run([sys.executable, "-m", "mapjoin", "simulate", "-o", folder, "--maps", "1000", "--seed", "0"],
                       check=True)
        maps = mapio.read_maps(folder + "/localmap_*.yaml")
        truth = mapio.read_truth(Path(folder) / "truth.yaml")
        rows += [nees_row("simulate --maps 1000 --seed 0", maps, truth, strategy) for strategy in STRATEGIES]
    costs = []
    for name in args.datasets:
        maps = mapio.read_maps(args.data / name)
        join_time, fast = median_seconds(lambda: join_sequential(maps, warn=False), args.repeat)
        lin_time, _ = median_seconds(lambda: linearised(maps, fast.global_map), args.repeat)
        exact_time, _ = median_seconds(lambda: refine(maps, fast.global_map), args.repeat)
        costs.append(f"| {name} | {join_time:.3f} | {lin_time:.3f} ({lin_time / join_time:.2f}x) | "
                     f"{exact_time:.3f} ({exact_time / join_time:.2f}x) |")
    load = os.getloadavg()[0]
    write_section("uncertainty", "\n".join([
        "Average NEES, features / poses (expected 2 / 3), against ground truth:", "",
        "| data | fast join | fast, weights | fast, linearised | 1 Gauss-Newton step | exact (`--refine`) "
        "| exact chi^2 / dof |",
        "|---|---|---|---|---|---|---|", *rows, "",
        f"Cost, seconds (median of {args.repeat}; load average {load:.1f} on 2 cores; compare ratios):", "",
        "| data | fast join | linearised marginals | `--refine` (solve + marginals) |",
        "|---|---|---|---|", *costs]))


if __name__ == "__main__":
    main()
