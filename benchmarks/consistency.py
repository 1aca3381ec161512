"""Calibration of the per-join consistency check: its statistic over every clean join of the real datasets.

    python benchmarks/consistency.py [DATASET ...]     (default: the five local-map folders)

For each dataset and strategy (default covariance mode): the joins tested (dof > 0), the
quantiles of chi2/dof (1 on average for a chi-square), the last join's variance factor, and how
many joins fall below the p-value levels 1e-2, 1e-3, 1e-6 and 1e-10, before the calibration (the
join's own cost against chi-square(dof), as up to 2026-11-25) and after it (``before > after``:
joined at gate 1, so that every join's ``chi2`` is the drift-aware minimum; at a gate g the joins
flagged are exactly those of these below g, docs/method.md#calibration),
and the exact join's chi2/dof (how consistent the local maps themselves are). Then the same counts
on ``mapjoin simulate`` runs (consistent by construction; 200 maps, seeds 0-4; two laps of the
figure-eight, so with loop closures, and half a lap, without), in both modes. Then each dataset
with one map corrupted (end heading + 0.6 rad; a common feature moved by 5 m; two feature ids
swapped): the p-value of the sequential join that contains the corrupted value. Written between
the ``consistency`` markers of benchmarks/README.md.
"""

from __future__ import annotations

import numpy as np
from common import dataset_arguments, write_section

from mapjoin import io as mapio
from mapjoin.consistency import DEFAULT_GATE, p_values
from mapjoin.evaluation import compare
from mapjoin.faults import corrupted
from mapjoin.joining import join
from mapjoin.refine import join_and_refine
from mapjoin.simulation import simulate

DATASETS = ("535_data_5_local_maps", "8240_data_50_local_maps", "DLR_200_local_maps", "VicPark_200_local_maps",
            "VicPark_6898_local_maps")
LEVELS = (1e-2, 1e-3, 1e-6, 1e-10)
SEEDS = range(5)


def flagged(report: tuple) -> tuple[int, np.ndarray, np.ndarray, np.ndarray]:
    """Joins tested, and how many fall below each level: before the calibration (the join's own cost,
    nominal; every join is linked under the default policy), after it; and the tested joins' chi2/dof."""
    used = [r for r in report if r.dof > 0]
    dof = np.array([r.dof for r in used], dtype=np.int64)
    before = p_values(np.array([r.cost for r in used]), dof)
    after = np.array([r.p for r in used])
    ratio = np.array([r.chi2 for r in used]) / np.maximum(dof, 1)
    below = [np.array([np.sum(p < v) for v in LEVELS]) for p in (before, after)]
    return len(used), below[0], below[1], ratio


def before_after(before: np.ndarray, after: np.ndarray) -> str:
    return " | ".join(f"{b} > {a}" for b, a in zip(before.tolist(), after.tolist()))


def main() -> None:
    args = dataset_arguments(__doc__, DATASETS)
    levels = " | ".join(f"p < {level:g}" for level in LEVELS)
    header = (f"| dataset | strategy | joins tested | chi2/dof median | 99 % | max | last factor | {levels} "
              "| exact chi2/dof |")
    clean = [header, "|---|---|---|---|---|---|---|" + "---|" * len(LEVELS) + "---|"]
    bad = ["| dataset | corrupted map | heading +0.6 rad | feature +5 m | ids swapped |", "|---|---|---|---|---|"]
    totals = np.zeros((2, len(LEVELS)), dtype=int)
    tested, skip = 0, ""
    for name in args.datasets:
        maps = mapio.read_maps(str(args.data / name))
        exact = join_and_refine(maps, covariances=False)
        for strategy in ("sequential", "tree"):
            report = join(maps, strategy=strategy, gate=1.0).report  # every join on the drift-aware statistic
            count, before, after, ratio = flagged(report)
            totals += [before, after]
            tested += count
            q50, q99 = np.quantile(ratio, [0.5, 0.99])
            clean.append(f"| {name} | {strategy} | {count} | {q50:.3g} | {q99:.3g} | {ratio.max():.3g} | "
                         f"{report[-1].variance_factor:.3g} | {before_after(before, after)} | "
                         f"{exact.cost / exact.degrees_of_freedom:.3g} |")
        k = len(maps) // 2
        cells = []
        for how in ("heading", "feature", "swap"):
            chain, number = corrupted(maps, k, how)
            record = join(chain).report[number - 1]
            cells.append(f"join {number}: chi2/dof {record.chi2 / record.dof:.3g}, p = {record.p:.2g}")
        bad.append(f"| {name} | {maps[k].name.rsplit('/', 1)[-1]} | " + " | ".join(cells) + " |")
        if name == "VicPark_200_local_maps":  # issue 14: skip within 2x of the clean fast join's distance
            chain, _ = corrupted(maps, 100, "heading")
            distances = [compare(exact.global_map, join(m, on_inconsistent=policy).global_map)
                         for m, policy in ((maps, "warn"), (chain, "skip"), (chain, "warn"))]
            skip = ("VicPark 200, localmap_101's end heading +0.6 rad, distance to the exact join (RMS xy m / "
                    "mean |phi| rad): clean " + ", corrupted with skip ".join(
                        f"{d.rms_xy:.4f} / {d.mean_abs_phi:.5f}" for d in distances[:2])
                    + f", corrupted with warn {distances[2].rms_xy:.4f} / {distances[2].mean_abs_phi:.5f}.")
    clean.append(f"| all | both | {tested} | | | | | " + " | ".join(
        f"{b} > {a} ({a / tested:.2%})" for b, a in zip(*totals.tolist())) + " | |")
    clean.append("| expected at the level | | | | | | | " + " | ".join(f"{tested * v:.3g}" for v in LEVELS) + " | |")
    simulated = [f"| run | mode | strategy | joins tested | {levels} |", "|---|---|---|---|" + "---|" * len(LEVELS)]
    for laps in (2.0, 0.5):
        runs = [list(simulate(200, seed=seed, laps=laps).maps) for seed in SEEDS]
        for mode in ("information", "marginal"):
            for strategy in ("sequential", "tree"):
                sums, count = np.zeros((2, len(LEVELS)), dtype=int), 0
                for maps in runs:
                    n, before, after, _ = flagged(join(maps, mode, strategy=strategy, gate=1.0).report)
                    sums += [before, after]
                    count += n
                simulated.append(f"| 200 maps, {laps:g} laps, seeds 0-4 | {mode} | {strategy} | {count} | "
                                 f"{before_after(*sums)} |")
    text = "\n".join([(f"Default covariance mode, default gate {DEFAULT_GATE:g}; `python benchmarks/consistency.py`. "
                       "Counts: before the calibration > after it."), "", *clean, "",
                      "`mapjoin simulate` runs (consistent maps; expected at the level: joins tested × level):", "",
                      *simulated, "", "Corrupted copies, sequential join holding the corrupted value:", "", *bad,
                      "", skip])
    print(text)
    write_section("consistency", text)


if __name__ == "__main__":
    main()
