"""Which start leads refine to the optimum: the sequential join, the tree join (refine's default) and,
on simulated runs, the ground truth (its chi^2 is the reference).

    python benchmarks/refine_starts.py [--maps N ...] [--seeds S ...] [--spherical] [DATASET ...]

For each real dataset and each simulated run (``simulate(N, seed=S)``, full covariances as ``mapjoin
simulate`` writes them; ``--spherical``: their spherical variances only), in-process, without the
marginal covariances: ``refine`` from each start, its iterations, final chi^2, whether it converged
(and why it stopped), the relative gradient at the end (max |J^T r| over the largest column norm of J
times |r|: ~1e-16 at a stationary point) and the solve's time. Written between the ``starts`` markers
of benchmarks/README.md (with ``--spherical`` between ``starts-spherical``).
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # before numpy: one BLAS thread

import argparse
import logging
import sys
import time

import numpy as np
from common import DATA, write_section

from mapjoin.io import read_maps
from mapjoin.joining import join
from mapjoin.maps import GlobalMap
from mapjoin.refine import DEFAULT_START, refine
from mapjoin.refine.problem import ExactProblem
from mapjoin.simulation import simulate

DATASETS = ("535_data_5_local_maps", "8240_data_50_local_maps", "DLR_200_local_maps", "VicPark_200_local_maps",
            "VicPark_6898_local_maps")


def relative_gradient(problem: ExactProblem, x: np.ndarray) -> float:
    """max |J^T r| / (largest column norm of J * |r|), as tests/test_refine.py measures it."""
    J, r = problem.jacobian(x), problem.residual(x)
    column_norms = np.sqrt(np.asarray(J.multiply(J).sum(axis=0))).ravel()
    return float(np.max(np.abs(J.T @ r)) / (column_norms.max() * np.linalg.norm(r)))


def truth_start(problem: ExactProblem, truth) -> GlobalMap:
    """The ground truth as a global map of ``problem``'s poses and features (unit variances: unused)."""
    where = np.searchsorted(truth.feature_ids, problem.feature_ids)
    return GlobalMap(feature_ids=problem.feature_ids, features=truth.features[where],
                     feature_variances=np.ones(problem.n_features), pose_ids=problem.pose_ids,
                     poses=truth.poses[problem.pose_ids], pose_variances=np.ones((problem.n_maps, 2)))


def rows(label: str, maps, truth=None) -> list[str]:
    """One table row per start of ``maps``."""
    problem = ExactProblem(maps)
    starts = {"sequential": None, "tree": None, **({"truth": truth_start(problem, truth)} if truth else {})}
    lines = []
    for start, initial in starts.items():
        initial = initial or join(maps, strategy=start).global_map
        began = time.perf_counter()
        result = refine(maps, initial, covariances=False)
        seconds = time.perf_counter() - began
        name = f"{start} (default)" if start == DEFAULT_START else start
        state = "yes" if result.converged else f"**no**: {result.reason}"
        lines.append(f"| {label} | {name} | {result.iterations} | {result.cost:.6f} | {state} | "
                     f"{relative_gradient(problem, problem.pack(result.global_map)):.1e} | {seconds:.1f} |")
        print(lines[-1], flush=True)
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("datasets", nargs="*", default=DATASETS)
    parser.add_argument("--maps", type=int, nargs="*", default=[1000], help="simulated runs' map counts")
    parser.add_argument("--seeds", type=int, nargs="*", default=[0, 1, 2, 3], help="their seeds")
    parser.add_argument("--spherical", action="store_true", help="simulated maps with spherical variances only")
    parser.add_argument("--data", default=DATA, help="folder of the datasets (default: %(default)s)")
    args = parser.parse_args()
    logging.getLogger("mapjoin").setLevel(logging.ERROR)  # the fast joins' consistency warnings: thousands
    load = os.getloadavg()[0]
    lines = ["| data | start | iterations | chi^2 | converged | relative gradient | solve (s) |",
             "|---|---|---:|---:|---|---:|---:|"]
    for name in args.datasets:
        lines += rows(name, read_maps([os.path.join(args.data, name)]))
    for count in args.maps:
        for seed in args.seeds:
            run = simulate(count, seed=seed, full_covariance=not args.spherical)
            lines += rows(f"simulate {count}, seed {seed}", run.maps, run.truth)
    kind = "spherical variances only" if args.spherical else "full covariances"
    command = " ".join(["python benchmarks/refine_starts.py", *sys.argv[1:]])
    header = (f"`{command}` (in-process, simulated maps with {kind}; load average {load:.1f} at the start, "
              f"{os.getloadavg()[0]:.1f} at the end, 2 cores shared: times are indicative):")
    write_section("starts-spherical" if args.spherical else "starts", "\n".join([header, "", *lines]))


if __name__ == "__main__":
    main()
