"""Whether two versions of mapjoin associate alike: every input feature's global id and each join's ambiguous and
rejected counts of `join --associate`, compared between this checkout and another version's source folder.

The cases: the association benchmark's three datasets with local ids, sequential and tree, also with a narrower
gate and margin; simulated runs with local ids (as `simulate --local-ids` makes them) of 20 and 40 maps over
--seeds seeds, with and without the maps' full covariances, and noiseless runs of 13 maps. A change meant to make
the association faster must leave every id as it was (then every output of `join --associate` is the same, byte
for byte).

    git archive main src | tar -x -C /tmp/before
    PYTHONPATH=src python benchmarks/association_same.py --before /tmp/before/src [--seeds 8]
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import DATA, ROOT

DATASETS = ("VicPark_200_local_maps", "DLR_200_local_maps", "8240_data_50_local_maps")


def cases(data: Path, seeds: int):
    """(name, maps with local ids, options of join_associated), lazily."""
    from mapjoin import io as mapio
    from mapjoin.association import local_ids
    from mapjoin.simulation import simulate

    for name in DATASETS:
        local, _ = local_ids(mapio.read_maps(str(data / name)))
        for strategy in ("sequential", "tree"):
            yield f"{name} {strategy}", local, {"strategy": strategy}
            yield f"{name} {strategy} gate 0.99 margin 3", local, {"strategy": strategy, "gate": 0.99, "margin": 3.0}
    for seed in range(1, seeds + 1):
        for count in (20, 40):
            local, _ = local_ids(simulate(count, seed=seed).maps)
            spherical = tuple(dataclasses.replace(m, covariance=None) for m in local)
            for strategy in ("sequential", "tree"):
                yield f"simulation {count} seed {seed} {strategy}", local, {"strategy": strategy}
                yield f"simulation {count} seed {seed} {strategy} no covariances", spherical, {"strategy": strategy}
        noiseless, _ = local_ids(simulate(13, seed=seed + 112, noiseless=True).maps)  # seed 119: a false link
        for strategy in ("sequential", "tree"):
            yield f"noiseless simulation 13 seed {seed + 112} {strategy}", noiseless, {"strategy": strategy}


def dump(path: str, data: Path, seeds: int) -> None:
    """Each case's global ids and per-join (ambiguous, rejected) counts, by the mapjoin on the path, to ``path``."""
    from mapjoin.association import join_associated

    logging.getLogger("mapjoin").setLevel(logging.CRITICAL)
    found = {}
    for name, maps, options in cases(data, seeds):
        result = join_associated(maps, **options)
        found[name + " ids"] = np.concatenate(result.global_ids)
        found[name + " counts"] = np.array([(r.ambiguous, r.rejected) for r in result.report]).reshape(-1, 2)
    np.savez(path, **found)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--before", type=Path, help="the other version's source folder (holding mapjoin/)")
    parser.add_argument("--seeds", type=int, default=8, help="simulated runs per size (default: %(default)s)")
    parser.add_argument("--data", type=Path, default=DATA, help="folder of the datasets (default: %(default)s)")
    parser.add_argument("--dump", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.dump:
        dump(args.dump, args.data, args.seeds)
        return
    if args.before is None:
        parser.error("--before DIR is required")
    with tempfile.TemporaryDirectory() as folder:
        results = []
        for source in (args.before.resolve(), ROOT / "src"):
            path = os.path.join(folder, f"{len(results)}.npz")
            subprocess.run([sys.executable, __file__, "--dump", path, "--seeds", str(args.seeds), "--data",
                            str(args.data)], check=True, env={**os.environ, "PYTHONPATH": str(source)})
            results.append(dict(np.load(path)))
    before, after = results
    different = sorted(key for key in before.keys() | after.keys()
                       if key not in before or key not in after or not np.array_equal(before[key], after[key]))
    for key in different:
        print(f"DIFFERENT: {key}")
    print(f"{len(before) // 2} cases, {len(different)} arrays different")
    sys.exit(1 if different else 0)


if __name__ == "__main__":
    main()
