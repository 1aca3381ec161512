"""Data association on the real datasets with ids local to each map: recall, false matches, and its cost.

For each dataset (ids replaced by ids local to each map, mapjoin.association.local_ids) and strategy:
the true links (a feature seen again by a later map), how many the association missed and how many
false links it made (input features given one global id that are different features), the ambiguous
and rejected counts, and the time of the associating join against the known-id join of the same maps
(medians of --repeat runs of each, the two run in turn, in one process, maps loaded): the *ratio* is the
associating join over the known-id join, *association alone* the association's own cost over the join's
(the ratio less one: issue 13's target, "the association costs at most 3x the join itself").
Writes the 'association' section of benchmarks/README.md. ``--non-target NAME`` adds a dataset that is no
target of issue 13 (VicPark's 6898 small maps, say: the same run in far more maps, a check on data the rules
were not chosen on), sequential only, one run however many --repeat, its rows labelled so.

``--commands`` adds a second table, of whole commands as a user runs them (a fresh interpreter each: start-up,
imports, reading the maps and writing the global map included): `mapjoin join DATASET -o g.csv` against `mapjoin join
LOCAL --associate -o g.csv`, LOCAL being the dataset's maps with ids local to each map (local_ids) written to a
temporary folder as MAT files, the two run in turn --repeat times (medians).

A third table, always, is the case a user (or an outside check) tries first: `mapjoin simulate --local-ids` at its
defaults, ``--seeds`` seeds (``--first-seed``, 0 by default, and on) of 30, 50 and 100 maps, both strategies, against
the simulation's true correspondence: totals of the links, the missed and the false ones, and how many runs made a
false link. The false-link counts of eight seeds move by several links with any change of one join's pairs: judge a
change on a sample no rule was chosen on too (``--first-seed 16 --seeds 32``). ``--long-maps`` adds the same tables
for local maps of 15, 20 and 30 steps (30 and 50 maps), where the association is weaker (docs/joining.md, limits).

    PYTHONPATH=src python benchmarks/association.py [DATASETS...] [--repeat N] [--non-target NAME ...] [--commands]
        [--seeds K] [--first-seed S] [--long-maps]
"""

from __future__ import annotations

import os
import statistics
import sys
import tempfile
from pathlib import Path

import numpy as np


sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import compile_mapjoin, dataset_arguments, median_seconds, whole_command, write_section  # noqa: E402

from mapjoin import io as mapio  # noqa: E402
from mapjoin.association import DEFAULT_GATE, AssociatedJoin, join_associated, link_errors, local_ids  # noqa: E402
from mapjoin.joining import join  # noqa: E402
from mapjoin.maps import LocalMap  # noqa: E402
from mapjoin.simulation import simulate  # noqa: E402

DATASETS = ("VicPark_200_local_maps", "DLR_200_local_maps", "8240_data_50_local_maps")
#: the simulations' sizes (maps) of the third table
SIMULATED_MAPS = (30, 50, 100)
#: ``--long-maps``: poses a local map (the simulator's default is 10) and the sizes of those runs
LONG_MAP_STEPS = (15, 20, 30)
LONG_MAP_SIZES = (30, 50)



def alternated(local: list[LocalMap], maps: list[LocalMap], strategy: str, repeat: int
               ) -> tuple[float, float, AssociatedJoin]:
    """Median wall seconds of the associating join of ``local`` and of the known-id join of ``maps``, run in turn
    (``repeat`` times each), so that the shared machine's load falls on both alike; and the association found."""
    associating, known, found = [], [], None
    for _ in range(repeat):
        seconds, found = median_seconds(lambda: join_associated(local, strategy=strategy), 1)
        associating.append(seconds)
        known.append(median_seconds(lambda: join(maps, strategy=strategy), 1)[0])
    return statistics.median(associating), statistics.median(known), found


def commands_table(data: Path, datasets: list[str], repeat: int) -> list[str]:
    """The whole commands' table (``--commands``): per dataset and strategy, the median wall seconds of `mapjoin join`
    of the dataset with its ids and of `mapjoin join --associate` of its maps with local ids, run in turn."""
    lines = ["", f"Whole commands ({compile_mapjoin()}; fresh interpreters, start-up and reading included; "
             f"medians of {repeat}, run in turn; load average {os.getloadavg()[0]:.2f} at their start):", "",
             "| dataset | strategy | `join` (s) | `join --associate`, local ids (s) | ratio | association alone |",
             "|---|---|---:|---:|---:|---:|"]
    with tempfile.TemporaryDirectory() as folder:
        for name in datasets:
            local_folder = os.path.join(folder, name)
            os.mkdir(local_folder)
            mapio.write_maps(local_ids(mapio.read_maps(str(data / name)))[0], os.path.join(local_folder, ""), "mat")
            output = os.path.join(folder, "g.csv")
            for strategy in ("sequential", "tree"):
                known_args = ["join", str(data / name), "--strategy", strategy, "-o", output]
                associating_args = ["join", local_folder, "--associate", "--strategy", strategy, "-o", output]
                known, associating = [], []
                for _ in range(repeat):
                    known.append(whole_command(known_args, 1)[0])
                    associating.append(whole_command(associating_args, 1)[0])
                known_s, associating_s = statistics.median(known), statistics.median(associating)
                row = (f"| {name} | {strategy} | {known_s:.2f} | {associating_s:.2f} | {associating_s / known_s:.1f}× | "
                       f"{(associating_s - known_s) / known_s:.1f}× |")
                print(row, flush=True)
                lines.append(row)
    return lines


def simulations_table(seeds: int, first: int = 0, steps_per_map: int | None = None,
                      sizes: tuple[int, ...] = SIMULATED_MAPS) -> list[str]:
    """A table of simulations: per size and strategy, the association of seeded runs ``first .. first + seeds - 1``
    of :func:`mapjoin.simulation.simulate` (its defaults, or ``steps_per_map`` poses a local map; ids made local)
    against their true ids, summed."""
    setting = "" if steps_per_map is None else f", steps_per_map={steps_per_map}"
    title = "Default simulations" if steps_per_map is None else f"Longer local maps, {steps_per_map} steps each"
    lines = ["", f"{title} (`simulate(maps, seed=s{setting})`, s = {first}..{first + seeds - 1}, ids local to each "
             "map; totals over the seeds):", "",
             "| maps | strategy | true links | missed | recall | false links | runs with a false link |",
             "|---:|---|---:|---:|---:|---:|---:|"]
    options = {} if steps_per_map is None else {"steps_per_map": steps_per_map}
    for count in sizes:
        runs = [local_ids(simulate(count, seed=seed, **options).maps) for seed in range(first, first + seeds)]
        for strategy in ("sequential", "tree"):
            errors = np.array([link_errors(local, truth, join_associated(local, strategy=strategy))
                               for local, truth in runs])
            links, missed, false = errors.sum(axis=0).tolist()
            row = (f"| {count} | {strategy} | {links} | {missed} | {100 * (links - missed) / links:.2f} % | {false} | "
                   f"{int((errors[:, 2] > 0).sum())} of {seeds} |")
            print(row, flush=True)
            lines.append(row)
    return lines


def main() -> None:
    def options(parser) -> None:
        parser.add_argument("--non-target", action="append", default=[], metavar="NAME",
                            help="a dataset that is no target, sequential only, one run (repeatable)")
        parser.add_argument("--commands", action="store_true",
                            help="also time the whole commands, `join` against `join --associate` (a second table)")
        parser.add_argument("--seeds", type=int, default=8, metavar="K",
                            help="seeds of each default simulation in the third table (default 8)")
        parser.add_argument("--first-seed", type=int, default=0, metavar="S",
                            help="the simulations' seeds are S .. S + K - 1 (default 0; a sample no rule was "
                                 "chosen on: 16)")
        parser.add_argument("--long-maps", action="store_true",
                            help="also tables of longer local maps: 15, 20 and 30 steps each, 30 and 50 maps")

    args = dataset_arguments(__doc__, DATASETS, options)
    also = "".join(f" --non-target {name}" for name in args.non_target)
    also += " --commands" if args.commands else ""
    also += f" --seeds {args.seeds}" if args.seeds != 8 else ""
    also += f" --first-seed {args.first_seed}" if args.first_seed else ""
    also += " --long-maps" if args.long_maps else ""
    lines = [f"Measured with `PYTHONPATH=src python benchmarks/association.py --repeat {args.repeat}{also}` "
             f"(load average {os.getloadavg()[0]:.2f} at the start; gate {DEFAULT_GATE}, default covariance mode).", "",
             "In one process, maps loaded (the association's own cost):", "",
             "| dataset | strategy | true links | missed | recall | false links | ambiguous | rejected | "
             "associating join (ms) | known-id join (ms) | ratio | association alone |",
             "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    cases = [(name, strategy, args.repeat, name) for name in args.datasets for strategy in ("sequential", "tree")]
    cases += [(name, "sequential", 1, f"{name} (not a target)") for name in args.non_target]
    for name, strategy, repeat, label in cases:
        maps = mapio.read_maps(str(args.data / name))
        local, truth = local_ids(maps)
        join(maps, strategy=strategy)
        if repeat > 1:
            join_associated(local, strategy=strategy)  # warm-up: imports and caches
        associating, known, found = alternated(local, maps, strategy, repeat)
        links, missed, false = link_errors(local, truth, found)
        ambiguous = sum(r.ambiguous for r in found.report)
        rejected = sum(r.rejected for r in found.report)
        row = (f"| {label} | {strategy} | {links} | {missed} | {100 * (links - missed) / links:.2f} % | {false} | "
               f"{ambiguous} | {rejected} | {1e3 * associating:.1f} | {1e3 * known:.1f} | "
               f"{associating / known:.1f}× | {(associating - known) / known:.1f}× |")
        print(row, flush=True)
        lines.append(row)
    if args.commands:
        lines += commands_table(args.data, list(args.datasets), args.repeat)
    lines += simulations_table(args.seeds, args.first_seed)
    if args.long_maps:
        for steps in LONG_MAP_STEPS:
            lines += simulations_table(args.seeds, args.first_seed, steps, LONG_MAP_SIZES)
    write_section("association", "\n".join(lines))


if __name__ == "__main__":
    main()
