"""Merging maps: accuracy and speed on VicPark 200 cut in two halves, and on simulated robots of growing size.

    python benchmarks/merge.py [--repeat N] [--data DIR]

VicPark 200 (and DLR 200 cut at map 150, the 8240 simulation at map 25, whose lattice of features the search
must refuse: ``HALVES``): the first 100 and the last 100 local maps are joined separately (sequential),
each half in its own frame (the second half's starts at the end pose of map 100); the second
is merged into the first with the shared ids, and with ``associate=True`` after its feature
ids are replaced by fresh ones. The recovered transform is compared with the first half's
end pose (the true relation of the frames, as joined), and the correspondences the search
found with the true ones (ids). Then ``simulate_robots(2, maps)`` (quiet odometry, so that
the joined maps stay consistent with their variances) for growing ``maps``: merge times
with ids and without, the transform's error against the truth, false matches. Times are
medians of ``--repeat`` library calls (the search imports scipy.spatial once, before).
Last, the search over seeds 0 .. ``--seeds`` - 1 of ``simulate_robots(2, maps)`` at the simulator's default noise
(maps that drift apart beyond their variances): the share of the common features matched, false matches, real
overlaps refused, and unrelated pairs (robot 1 of one seed against robot 2 of the next) accepted.
Results are printed and written between the ``merge`` markers of benchmarks/README.md, with
the machine's load (``uptime``).
"""

from __future__ import annotations

import dataclasses
import math
import subprocess

import numpy as np
from common import dataset_arguments, median_seconds, write_section

import mapjoin
from mapjoin import JoinError
from mapjoin import io as mapio
from mapjoin.joining import join
from mapjoin.onestep import as_complex
from mapjoin.registration import consensus
from mapjoin.simulation import simulate_robots

FRESH = 10**9
SIZES = (25, 100, 400)
#: datasets cut in two halves (the maps before ``cut`` and from it), each joined in its own frame; 8240's features lie
#: on a lattice, where the search must refuse
HALVES = (("VicPark_200_local_maps", 100), ("DLR_200_local_maps", 150), ("8240_data_50_local_maps", 25))
SWEEP_SIZES = (20, 30, 50, 100)


def _errors(record, pose) -> tuple[float, float]:
    return (math.hypot(record.x - pose[0], record.y - pose[1]),
            abs((record.phi - pose[2] + math.pi) % (2 * math.pi) - math.pi))


def _case(name: str, first, second, truth_pose, repeat: int) -> list[str]:
    """Rows of one pair: shared ids and without ids."""
    rows = []
    fresh = dataclasses.replace(second, feature_ids=second.feature_ids + FRESH)
    shared = len(np.intersect1d(first.feature_ids, second.feature_ids))
    for label, other, associate in (("ids", second, False), ("search", fresh, True)):
        try:
            seconds, result = median_seconds(lambda: mapjoin.merge([first, other], associate=associate), repeat)
        except JoinError:
            rows.append(f"| {name} | {len(first.feature_ids)} + {len(second.feature_ids)} | {label} | {shared} | "
                        "refused | - | - | - | - |")
            continue
        record = result.report[0]
        distance, angle = _errors(record, truth_pose)
        false = "-"
        if associate:
            found = consensus(as_complex(first.features), first.feature_variances, as_complex(fresh.features),
                              fresh.feature_variances)
            false = str(int(np.sum(first.feature_ids[found.a] != fresh.feature_ids[found.b] - FRESH)))
        rows.append(f"| {name} | {len(first.feature_ids)} + {len(second.feature_ids)} | {label} | {shared} | "
                    f"{record.common} | {false} | {distance:.3f} | {angle:.4f} | {seconds * 1000:.1f} |")
    return rows


def _searched(a, b) -> tuple[int, int, bool]:
    """The search for ``b`` (ids made fresh) in ``a``: matches, false matches (the ids deny them), sure."""
    fresh = b.feature_ids + FRESH
    found = consensus(as_complex(a.features), a.feature_variances, as_complex(b.features), b.feature_variances)
    return len(found.a), int(np.sum(a.feature_ids[found.a] != fresh[found.b] - FRESH)), found.sure


def _sweep(seeds: int) -> list[str]:
    """Rows of the drifted robots: per size, totals over the seeds."""
    rows = [f"| robots × maps | common | matched | false matches | real overlaps refused (of {seeds}) | "
            f"unrelated pairs accepted (of {seeds}) |", "|---|---:|---:|---:|---:|---:|"]
    for size in SWEEP_SIZES:
        pairs = [tuple(join(run.maps).global_map for run in simulate_robots(2, size, seed=seed).robots)
                 for seed in range(seeds)]
        common = matched = false = refused = accepted = 0
        for seed, (a, b) in enumerate(pairs):
            count, wrong, sure = _searched(a, b)
            common += len(np.intersect1d(a.feature_ids, b.feature_ids))
            if sure:
                matched, false = matched + count, false + wrong
            refused += not sure
            accepted += _searched(a, pairs[(seed + 1) % seeds][1])[2]
        rows.append(f"| 2 × {size} | {common} | {matched} ({100 * matched / common:.1f} %) | {false} | {refused} | "
                    f"{accepted} |")
    return rows


def main() -> None:
    args = dataset_arguments(__doc__, ("VicPark_200_local_maps",), lambda parser: parser.add_argument(
        "--seeds", type=int, default=16, help="seeds of the drifted robots' sweep (default: %(default)s)"))
    from scipy.spatial import cKDTree  # noqa: F401  (imported once, outside the timings)

    rows = ["| maps | features (A + B) | common by | true common | matched | false matches | "
            "transform error (m) | (rad) | merge (ms) |", "|---|---:|---|---:|---:|---:|---:|---:|---:|"]
    for name, cut in HALVES:
        maps = mapio.read_maps([str(args.data / name)])
        first, second = join(maps[:cut]).global_map, join(maps[cut:]).global_map
        end = first.poses[first.pose_ids == cut][0]
        rows += _case(f"{name.split('_local')[0].replace('_data', '')} cut at {cut}", first, second, end, args.repeat)
    for size in SIZES:
        world = simulate_robots(2, size, seed=1, odometry_noise=(0.01, 0.005, 0.002), full_covariance=False)
        a, b = (join(run.maps).global_map for run in world.robots)
        rows += _case(f"2 robots x {size}", a, b, world.truth.poses[size], args.repeat)
    load = subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()
    text = "\n".join([f"`python benchmarks/merge.py --repeat {args.repeat} --seeds {args.seeds}`; load: {load}", "",
                      *rows, "",
                      "Transform error: against the first half's end pose as joined (the datasets), against the "
                      "truth (robots). 'false matches': correspondences the search found that the ids deny.", "",
                      "The search on drifted maps (`simulate_robots(2, maps, seed=s)` at the default noise, each "
                      f"robot joined; totals over s = 0..{args.seeds - 1}; matched and false over the accepted "
                      "searches):", "", *_sweep(args.seeds)])
    print(text)
    write_section("merge", text)


if __name__ == "__main__":
    main()
