"""Stage 2 of the consistency test: the joins the fast statistic flags, confirmed on the exact problem.

    python benchmarks/confirmation.py [DATASET ...]     (default: the five local-map folders)

For each dataset and strategy (default covariance mode, default gate), the joins the fast (stage-1)
statistic flags, and how many of them the exact statistic (docs/method.md#confirmation: the increase
of the exact least-squares optimum when the join's right piece is added) still flags, with three
variance factors: none, the fast statistic's running factor, and the pieces' own exact chi2/dof (the
one used). Then the times: the join, the confirmations, and the maps the exact solves held. The same
on ``mapjoin simulate`` runs (consistent by construction; 200 maps, seeds 0-4, two laps and half a
lap, both covariance modes). Then each dataset with one map corrupted (end heading + 0.6 rad; a
common feature moved 5 m; two feature ids swapped), the sequential join holding the corrupted value:
its exact statistic, whether it stays flagged and what its confirmation cost; and the first flagged (confirmed)
tree join whose pieces hold the corrupted map. Written between the
``confirmation`` markers of benchmarks/README.md.
"""

from __future__ import annotations

import os
import time

import numpy as np
from common import dataset_arguments, write_section

from mapjoin import io as mapio
from mapjoin.confirmation import Pieces, confirm, increment, piece_bounds, variance_factor
from mapjoin.consistency import DEFAULT_GATE, p_values
from mapjoin.faults import corrupted
from mapjoin.joining import join
from mapjoin.simulation import simulate

DATASETS = ("535_data_5_local_maps", "8240_data_50_local_maps", "DLR_200_local_maps", "VicPark_200_local_maps",
            "VicPark_6898_local_maps")
SEEDS = range(5)


def timed(run):
    began = time.perf_counter()
    value = run()
    return value, time.perf_counter() - began


def variants(maps, result, strategy) -> np.ndarray:
    """Of the joins stage 1 flags (one minimum, linked): how many the exact statistic still flags with no
    variance factor, with the fast statistic's, with the pieces' own (the one used)."""
    pieces = Pieces(maps, result.global_map)
    counts = np.zeros(3, dtype=int)
    for r in result.report:
        if not (r.flag and r.minima == 1 and r.action == "joined"):
            continue
        exact = increment(pieces, *piece_bounds(maps, r, strategy))
        factors = [1.0, r.variance_factor, variance_factor(exact, r.variance_factor)]
        p = p_values(np.array([exact.chi2 / s for s in factors]), np.full(3, exact.dof))
        counts += p < DEFAULT_GATE
    return counts


def measure(maps, covariance, strategy):
    """Stage-1 flags, the variants' counts, flags after confirmation, join and confirmation seconds, maps solved."""
    result, join_seconds = timed(lambda: join(maps, covariance, strategy=strategy))
    confirmed, confirm_seconds = timed(lambda: confirm(maps, result, strategy, DEFAULT_GATE))
    assert sum(r.flag for r in confirmed.report) == variants(maps, result, strategy)[2] + sum(
        r.flag and r.minima == 2 for r in result.report)
    solved = sum(piece_bounds(maps, r, strategy)[2] for r in confirmed.report if r.exact_p is not None)
    return (sum(r.flag for r in result.report), variants(maps, result, strategy),
            sum(r.flag for r in confirmed.report), join_seconds, confirm_seconds, solved)


def tree_flag(chain, k: int) -> str:
    """The first flagged tree join (confirmed) whose pieces hold map k: its number and exact p (or two minima)."""
    report = join(chain, strategy="tree", confirm=confirm).report
    for r in report:
        first, _, stop = piece_bounds(chain, r, "tree")
        if r.flag and first <= k < stop:
            return f"join {r.join}, " + ("two minima" if r.exact_p is None else f"exact p = {r.exact_p:.2g}")
    return "none"


def main() -> None:
    args = dataset_arguments(__doc__, DATASETS)
    load = os.getloadavg()[0]
    clean = ["| dataset | strategy | stage 1 flags | exact: nominal / fast factor / pieces' factor | flagged after | "
             "join s | confirmations s |", "|---|---|---|---|---|---|---|"]
    bad = ["| dataset | corrupted | join | stage 1 p | exact chi2 / dof | exact p | flagged | join s | "
           "confirmation s | tree: flagged join holding it |", "|---|---|---|---|---|---|---|---|---|---|"]
    totals = np.zeros(2, dtype=int)
    for name in args.datasets:
        maps = mapio.read_maps(str(args.data / name))
        for strategy in ("sequential", "tree"):
            before, counts, after, tj, tc, _ = measure(maps, "information", strategy)
            totals += [before, after]
            clean.append(f"| {name} | {strategy} | {before} | {' / '.join(map(str, counts.tolist()))} | {after} | "
                         f"{tj:.3f} | {tc:.3f} |")
        k = len(maps) // 2
        for how in ("heading", "feature", "swap"):
            chain, number = corrupted(maps, k, how)
            result, tj = timed(lambda: join(chain))
            confirmed, tc = timed(lambda: confirm(chain, result, "sequential", DEFAULT_GATE))
            r = confirmed.report[number - 1]
            bad.append(f"| {name} | {how} | {number} | {result.report[number - 1].p:.2g} | "
                       f"{r.exact_chi2 / r.dof:.3g} | {r.exact_p:.2g} | {r.flag} | {tj:.3f} | {tc:.3f} | "
                       f"{tree_flag(chain, k)} |")
    clean.append(f"| all five | both | {totals[0]} | | {totals[1]} | | |")
    simulated = ["| run | mode | strategy | stage 1 flags | exact: nominal / fast factor / pieces' factor | "
                 "flagged after | join s | confirmations s |", "|---|---|---|---|---|---|---|---|"]
    for laps in (2.0, 0.5):
        runs = [list(simulate(200, seed=seed, laps=laps).maps) for seed in SEEDS]
        for mode in ("information", "marginal"):
            for strategy in ("sequential", "tree"):
                before, counts, after, tj, tc = 0, np.zeros(3, dtype=int), 0, 0.0, 0.0
                for maps in runs:
                    b, c, a, j, t, _ = measure(maps, mode, strategy)
                    before, counts, after, tj, tc = before + b, counts + c, after + a, tj + j, tc + t
                simulated.append(f"| 200 maps, {laps:g} laps, seeds 0-4 | {mode} | {strategy} | {before} | "
                                 f"{' / '.join(map(str, counts.tolist()))} | {after} | {tj:.2f} | {tc:.2f} |")
    text = "\n".join([f"Default gate {DEFAULT_GATE:g}; `python benchmarks/confirmation.py`; load average {load:.1f} "
                      "(2 cores shared; times are one run each, in-process).", "", *clean, "",
                      "`mapjoin simulate` runs (consistent maps):", "", *simulated, "",
                      "Corrupted copies (map N/2), sequential join holding the corrupted value:", "", *bad])
    print(text)
    write_section("confirmation", text)


if __name__ == "__main__":
    main()
