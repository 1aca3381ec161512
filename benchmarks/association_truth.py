"""The truth's own joint test: how much of each dataset's true correspondence a joint compatibility test admits.

Issue 13 asks the association to recover at least 99 % of the true links with no false one. Its joint test (step 4,
docs/method.md#data-association) accepts a join's pairs when the one-step cost of the join with them is within the
chi-square quantile of the gate level on 2 x pairs degrees of freedom. This script asks that test of the *true*
pairs: per dataset and strategy it joins the maps with their known ids and counts the joins whose cost fails the
test at the gate level (and at 1 - 1e-5, 1 - 1e-12). An association that tests its pairs with the maps' own
covariances leaves out at least one true pair of each such join (if its map so far is the known-id join's), so
*bound* = the links less those joins, over the links, bounds its recall; *level for 99 %* is the level at which at
most 1 % of the links' joins fail (the truth kept at 99 % needs a test at least that lax).

``--fewest`` (sequential joins): for each join that fails at the gate, the fewest true pairs that must be left out for
the rest to pass, found by brute force over subsets (the join re-run with those features' ids made new), up to
``--max-subsets`` subsets a join ("at least" when the search stops there); their sum is the least number of links
such a test refuses, given the map so far. Writes the 'association-truth' section of benchmarks/README.md.

    PYTHONPATH=src python benchmarks/association_truth.py [DATASETS...] [--fewest] [--max-subsets N]
"""

from __future__ import annotations

import dataclasses
import itertools
import os
import sys
from collections.abc import Sequence
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import dataset_arguments, write_section  # noqa: E402

from mapjoin import io as mapio  # noqa: E402
from mapjoin.association import DEFAULT_GATE  # noqa: E402
from mapjoin.consistency import chi2_quantile, p_values  # noqa: E402
from mapjoin.joining import join  # noqa: E402
from mapjoin.maps import LocalMap  # noqa: E402

DATASETS = ("VicPark_200_local_maps", "DLR_200_local_maps", "8240_data_50_local_maps")
#: the stricter levels reported beside the gate's (as 1 - level)
TAILS = (1e-5, 1e-12)


def true_links(maps: Sequence[LocalMap]) -> int:
    """The links of the true correspondence: every sighting of a feature after its first."""
    ids = np.concatenate([m.feature_ids for m in maps])
    return int(len(ids) - len(np.unique(ids)))


def join_p_values(maps: Sequence[LocalMap], strategy: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The known-id join's joins that have common features: their numbers, common counts and the p-value of their
    cost on 2 x common degrees of freedom (the joint test's statistic for the true pairs)."""
    report = [r for r in join(maps, strategy=strategy).report if r.common]
    numbers = np.array([r.join for r in report])
    common = np.array([r.common for r in report])
    return numbers, common, p_values(np.array([r.cost for r in report]), 2 * common)


def fewest_left_out(maps: Sequence[LocalMap], number: int, level: float, max_subsets: int) -> tuple[int, bool]:
    """The fewest of sequential join ``number``'s true pairs that must be left out (their features' ids made new in
    the incoming map) for the rest to pass the joint test at ``level``, by brute force over subsets, smallest first;
    and whether that count is exact (False: ``max_subsets`` tried before a passing subset was found, the count is a
    lower bound)."""
    before, incoming = list(maps[:number]), maps[number]
    common = np.intersect1d(incoming.feature_ids, np.concatenate([m.feature_ids for m in before]))
    fresh = int(max(m.feature_ids.max(initial=0) for m in maps)) + 1
    tried = 0
    for out in range(1, len(common)):  # all of them out: nothing left to test
        for dropped in itertools.combinations(common, out):
            ids = incoming.feature_ids.copy()
            ids[np.isin(ids, dropped)] = fresh + np.arange(out)
            record = join(before + [dataclasses.replace(incoming, feature_ids=ids)]).report[-1]
            if record.cost <= float(chi2_quantile(level, 2 * record.common)):
                return out, True
            tried += 1
            if tried >= max_subsets:
                return out, False
    return len(common), True


def main() -> None:
    def options(parser) -> None:
        parser.add_argument("--fewest", action="store_true",
                            help="also the fewest true pairs each failing sequential join must leave out (brute force)")
        parser.add_argument("--max-subsets", type=int, default=1000, metavar="N",
                            help="subsets tried a join by --fewest at most (default 1000)")

    args = dataset_arguments(__doc__, DATASETS, options)
    gate = DEFAULT_GATE
    also = (f" --fewest --max-subsets {args.max_subsets}" if args.fewest else "")
    lines = [f"Measured with `PYTHONPATH=src python benchmarks/association_truth.py{also}` (gate {gate}, default "
             f"covariance mode; load average {os.getloadavg()[0]:.2f}). *Fail* counts the known-id join's joins whose "
             "true pairs fail the joint test at that level (of the joins with common features); *bound* is the links "
             "less one a join failing at the gate, over the links: a test at the maps' own covariances leaves at least "
             "one true pair of each out, given the known-id join's map so far.", "",
             "| dataset | strategy | true links | joins | fail at gate | their common features | "
             + " | ".join(f"fail at 1 - {t:g}" for t in TAILS) + " | bound | level for 99 % |",
             "|---|---|---:|---:|---:|---:|" + "---:|" * len(TAILS) + "---:|---:|"]
    fewest_rows = []
    for name in args.datasets:
        maps = mapio.read_maps(str(args.data / name))
        links = true_links(maps)
        for strategy in ("sequential", "tree"):
            numbers, common, p = join_p_values(maps, strategy)
            failing = p < 1 - gate
            allowed = int(0.01 * links)
            needed = np.sort(p)[allowed] if allowed < len(p) else 1.0
            row = (f"| {name} | {strategy} | {links} | {len(p)} | {int(failing.sum())} | "
                   f"{int(common[failing].sum())} | " + " | ".join(str(int((p < t).sum())) for t in TAILS)
                   + f" | {100 * (links - failing.sum()) / links:.2f} % | 1 - {needed:.2g} |")
            print(row, flush=True)
            lines.append(row)
            if args.fewest and strategy == "sequential":
                counts = [fewest_left_out(maps, int(n), gate, args.max_subsets) for n in numbers[failing]]
                least = sum(c for c, _ in counts)
                exact = all(e for _, e in counts)
                fewest_rows.append(f"| {name} | {int(failing.sum())} | {'' if exact else 'at least '}{least} | "
                                   f"{100 * (links - least) / links:.2f} % |")
                print(fewest_rows[-1], flush=True)
    if fewest_rows:
        lines += ["", "The fewest true pairs the sequential joins failing at the gate must leave out (brute force over "
                  f"subsets, at most {args.max_subsets} a join; given the known-id join's map so far):", "",
                  "| dataset | joins failing at the gate | true pairs left out, fewest | "
                  "recall at most, given that map so far |",
                  "|---|---:|---:|---:|", *fewest_rows]
    write_section("association-truth", "\n".join(lines))


if __name__ == "__main__":
    main()
