"""Data association on the real datasets with ids local to each map: recall, false matches, and its cost.

For each dataset (ids replaced by ids local to each map, mapjoin.association.local_ids) and strategy:
the true links (a feature seen again by a later map), how many the association missed and how many
false links it made (input features given one global id that are different features), the ambiguous
and rejected counts, and the time of the associating join against the known-id join of the same maps
(medians of --repeat runs, in one process, maps loaded). Writes the 'association' section of
benchmarks/README.md. ``--non-target NAME`` adds a dataset that is no target of issue 13 (VicPark's 6898 small
maps, say: the same run in far more maps, a check on data the rules were not chosen on), sequential only, one run
however many --repeat, its rows labelled so.

    PYTHONPATH=src python benchmarks/association.py [DATASETS...] [--repeat N] [--non-target NAME ...]
"""

from __future__ import annotations

import os
import sys
from pathlib import Path


sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import dataset_arguments, median_seconds, write_section  # noqa: E402

from mapjoin import io as mapio  # noqa: E402
from mapjoin.association import DEFAULT_GATE, join_associated, link_errors, local_ids  # noqa: E402
from mapjoin.joining import join  # noqa: E402

DATASETS = ("VicPark_200_local_maps", "DLR_200_local_maps", "8240_data_50_local_maps")



def main() -> None:
    args = dataset_arguments(__doc__, DATASETS, lambda parser: parser.add_argument(
        "--non-target", action="append", default=[], metavar="NAME",
        help="a dataset that is no target, sequential only, one run (repeatable)"))
    also = "".join(f" --non-target {name}" for name in args.non_target)
    lines = [f"Measured with `PYTHONPATH=src python benchmarks/association.py --repeat {args.repeat}{also}` "
             f"(load average {os.getloadavg()[0]:.2f} at the start; gate {DEFAULT_GATE}, default covariance mode).", "",
             "| dataset | strategy | true links | missed | recall | false links | ambiguous | rejected | "
             "associating join (ms) | known-id join (ms) | ratio |",
             "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    cases = [(name, strategy, args.repeat, name) for name in args.datasets for strategy in ("sequential", "tree")]
    cases += [(name, "sequential", 1, f"{name} (not a target)") for name in args.non_target]
    for name, strategy, repeat, label in cases:
        maps = mapio.read_maps(str(args.data / name))
        local, truth = local_ids(maps)
        join(maps, strategy=strategy)
        if repeat > 1:
            join_associated(local, strategy=strategy)  # warm-up: imports and caches
        associating, found = median_seconds(lambda: join_associated(local, strategy=strategy), repeat)
        known, _ = median_seconds(lambda: join(maps, strategy=strategy), repeat)
        links, missed, false = link_errors(local, truth, found)
        ambiguous = sum(r.ambiguous for r in found.report)
        rejected = sum(r.rejected for r in found.report)
        row = (f"| {label} | {strategy} | {links} | {missed} | {100 * (links - missed) / links:.2f} % | {false} | "
               f"{ambiguous} | {rejected} | {1e3 * associating:.1f} | {1e3 * known:.1f} | "
               f"{associating / known:.1f}× |")
        print(row, flush=True)
        lines.append(row)
    write_section("association", "\n".join(lines))


if __name__ == "__main__":
    main()
