"""Calibration of the per-join consistency check: its statistic over every clean join of the real datasets.

    python benchmarks/consistency.py [DATASET ...]     (default: the five local-map folders)

For each dataset and strategy (default covariance mode): the joins tested (dof > 0), the
quantiles of chi2/dof (1 on average for a chi-square), how many joins fall below the p-value
levels 1e-3, 1e-6 and the default gate, and the exact join's chi2/dof (how consistent the
local maps themselves are). Then each dataset with one map corrupted (end heading + 0.6 rad;
a common feature moved by 5 m; two feature ids swapped): the p-value of the sequential join
that contains the corrupted value. Written between the ``consistency`` markers of benchmarks/README.md.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from common import dataset_arguments, write_section

from mapjoin import io as mapio
from mapjoin.consistency import DEFAULT_GATE
from mapjoin.joining import join
from mapjoin.refine import join_and_refine

DATASETS = ("535_data_5_local_maps", "8240_data_50_local_maps", "DLR_200_local_maps", "VicPark_200_local_maps",
            "VicPark_6898_local_maps")
LEVELS = (1e-3, 1e-6, DEFAULT_GATE)


def corrupted(maps: list, k: int, how: str) -> tuple[list, int]:
    """``maps`` with map k corrupted, and the number of the sequential join whose problem holds the value."""
    local_map = maps[k]
    seen = np.isin(local_map.feature_ids, np.concatenate([m.feature_ids for m in maps[:k]]))
    j = int(np.flatnonzero(seen)[0])  # a feature the maps before k saw: it is common in join k
    if how == "heading":
        pose = local_map.end_pose.copy()
        pose[2] += 0.6
        changed, joined = dataclasses.replace(local_map, end_pose=pose), k + 1  # the odometry of join k+1
    elif how == "feature":
        features = local_map.features.copy()
        features[j, 0] += 5.0
        changed, joined = dataclasses.replace(local_map, features=features), k
    else:
        ids = local_map.feature_ids.copy()
        other = (j + 1) % len(ids)
        ids[[j, other]] = ids[[other, j]]
        changed, joined = dataclasses.replace(local_map, feature_ids=ids), k
    return [*maps[:k], changed, *maps[k + 1:]], joined


def main() -> None:
    args = dataset_arguments(__doc__, DATASETS)
    clean = ["| dataset | strategy | joins tested | chi2/dof median | 99 % | max | "
             + " | ".join(f"p < {level:g}" for level in LEVELS) + " | exact chi2/dof |",
             "|---|---|---|---|---|---|" + "---|" * len(LEVELS) + "---|"]
    bad = ["| dataset | corrupted map | heading +0.6 rad | feature +5 m | ids swapped |", "|---|---|---|---|---|"]
    totals = np.zeros(len(LEVELS), dtype=int)
    tested = 0
    for name in args.datasets:
        maps = mapio.read_maps(str(args.data / name))
        exact = join_and_refine(maps, covariances=False)
        for strategy in ("sequential", "tree"):
            report = join(maps, strategy=strategy).report
            chi2 = np.array([r.chi2 for r in report])
            dof = np.array([r.dof for r in report])
            p = np.array([r.p for r in report])
            used = dof > 0
            ratio = chi2[used] / dof[used]
            counts = [int(np.sum(p[used] < level)) for level in LEVELS]
            totals += counts
            tested += int(used.sum())
            q50, q99 = np.quantile(ratio, [0.5, 0.99])
            clean.append(f"| {name} | {strategy} | {used.sum()} | {q50:.3g} | {q99:.3g} | {ratio.max():.3g} | "
                         + " | ".join(map(str, counts)) + f" | {exact.cost / exact.degrees_of_freedom:.3g} |")
        k = len(maps) // 2
        cells = []
        for how in ("heading", "feature", "swap"):
            chain, number = corrupted(maps, k, how)
            record = join(chain).report[number - 1]
            cells.append(f"join {number}: chi2/dof {record.chi2 / record.dof:.3g}, p = {record.p:.2g}")
        bad.append(f"| {name} | {maps[k].name.rsplit('/', 1)[-1]} | " + " | ".join(cells) + " |")
    clean.append(f"| all | both | {tested} | | | | " + " | ".join(
        f"{count} ({count / tested:.2%})" for count in totals) + " | |")
    text = "\n".join(["Default covariance mode; `python benchmarks/consistency.py`.", "", *clean, "",
                      "Corrupted copies, sequential join holding the corrupted value:", "", *bad])
    print(text)
    write_section("consistency", text)


if __name__ == "__main__":
    main()
