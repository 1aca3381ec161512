"""The drift the fast consistency statistic allows for, against the fast map's true errors (issue 14 follow-up).

    python benchmarks/drift_truth.py [MAPS ...]     (default: 200 1000 2000 6000)

For each ``mapjoin simulate`` run (MAPS maps, two laps, seed 0, spherical variances, the default
``information`` mode) the sequential join is made in memory, and at every join ``k`` each common feature's
fast estimate ``z0`` (the map so far, as the join read it) is compared with the truth relative to the
junction pose (the map so far's last pose, as the join read it): ``e = R(phi_k)^T (z0 - x_k)`` against the
same for the true feature and pose. ``|e|^2 / 2`` (the error's half-trace) is divided by the variance the
statistic allows: the feature's own ``var0``, ``var0 + D`` with ``D`` the chain's drift since the
feature's last sighting (:class:`mapjoin.drift.ChainDrift`, docs/method.md#drift), and ``var0 + D + bias``
with what the estimate kept of its last join's residual (:func:`mapjoin.drift.fusion_bias`, since
2026-11-26). Under the model these
ratios are about chi-square(2) / 2 (median 0.69, 99 % 4.6). The rows are split by the sighting ``D`` starts
from: the map just before (``D = 0``) for a feature never re-seen after a gap, the map just before for a
feature that was (its estimate was fused at a loop closure since), or an earlier map (``D > 0``). Written
between the ``drift-truth`` markers of benchmarks/README.md.

What the joins read is internal (:class:`mapjoin.drift.SequentialRecord`, kept for the statistic): the
benchmark wraps its ``retest`` to keep a reference, and changes nothing.
"""

from __future__ import annotations

import logging
import sys
from unittest import mock

import numpy as np
from common import write_section

from mapjoin.drift import ChainDrift, SequentialRecord, _end_poses, _Sightings
from mapjoin.joining import join_sequential
from mapjoin.simulation import simulate

RUNS = (200, 1000, 2000, 6000)
GROUPS = ("last seen by the map before, never re-seen after a gap",
          "last seen by the map before, re-seen after a gap before (fused at a loop closure)",
          "last seen maps before (D > 0)")


def recorded_join(maps: list) -> tuple:
    """The sequential join of ``maps`` and what its joins read (the record and the rows as ``retest`` got them)."""
    kept: dict = {}
    original = SequentialRecord.retest

    def keep(record, ids, z, var, piece, starts, ends_common, solve, pose_xy, pose_phi):
        kept.update(record=record, ids=ids, z=z, var=var, piece=piece, starts=starts, ends_common=ends_common,
                    poses=(pose_xy, pose_phi))
        return original(record, ids, z, var, piece, starts, ends_common, solve, pose_xy, pose_phi)

    with mock.patch.object(SequentialRecord, "retest", keep):
        result = join_sequential(maps)
    return result, kept


def ratios(count: int) -> tuple[int, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, int]:
    """Per common-feature row of every join of a ``count``-map run: ``|e|^2/2``, ``var0``, ``D``, the bias and
    its group (0, 1, 2 as :data:`GROUPS`); and the joins the fast statistic flags."""
    sim = simulate(count, seed=0, laps=2.0, full_covariance=False)
    result, kept = recorded_join(list(sim.maps))
    record, ids, starts, ends = kept["record"], kept["ids"], kept["starts"], kept["ends_common"]
    end_poses = _end_poses(record.chain)
    drift = ChainDrift.of(end_poses, np.arange(1, len(record.joins) + 1),
                          np.array([j[6] for j in record.joins]), np.array([j[7] for j in record.joins]))
    sightings = _Sightings.of(kept["piece"], ids, kept["z"], len(end_poses) + 1, ids)
    bias = record.biases(kept["z"], kept["var"], kept["piece"], starts, ends, *kept["poses"])[sightings.rows]
    feature = sightings.keys // sightings.width
    new = np.r_[True, feature[1:] != feature[:-1]]
    after_gap = np.r_[False, ~new[1:] & (sightings.maps[1:] > sightings.maps[:-1] + 1)]
    group = np.cumsum(new)  # a feature re-seen after a gap at or before each of its sightings
    first_gap = np.full(group[-1] + 1, len(feature))
    np.minimum.at(first_gap, group[after_gap], np.flatnonzero(after_gap))
    gapped = np.arange(len(feature)) >= first_gap[group]
    truth = dict(zip(sim.truth.feature_ids.tolist(), sim.truth.features[:, 0] + 1j * sim.truth.features[:, 1]))
    error, var0s, drifts, biases, groups = [], [], [], [], []
    for k in range(1, len(record.joins) + 1):
        z0, var0, junction, heading = record.joins[k - 1][:4]
        common = ids[starts[k]:ends[k]]
        if not len(common):
            continue
        last = sightings.last(common, k - 1)
        seen = sightings.maps[last]
        x, y, phi = sim.truth.poses[k]
        true = np.exp(-1j * phi) * (np.array([truth[i] for i in common.tolist()]) - complex(x, y))
        error.append(np.abs(np.exp(-1j * heading) * (z0 - junction) - true) ** 2 / 2)
        var0s.append(var0)
        drifts.append(drift.variance(seen + 1, k, drift.dead_reckoned(seen, sightings.points[last])))
        biases.append(bias[last])
        groups.append(np.where(seen < k - 1, 2, np.where(gapped[last], 1, 0)))
    flagged = sum(r.flag for r in result.report)
    return count, *map(np.concatenate, (error, var0s, drifts, biases, groups)), flagged


def main(counts: tuple[int, ...]) -> None:
    logging.getLogger("mapjoin").disabled = True  # the loop closures' warnings
    lines = [("Two laps, seed 0, information mode, sequential in memory; `python benchmarks/drift_truth.py`. "
              "Per common-feature row: |e|²/2 over the variance allowed (model: median 0.69, 99 % 4.6)."), "",
             ("| maps | fast flags | rows | sighting D starts from | over var0: median | 99 % | "
              "over var0 + D: median | 99 % | max | over var0 + D + bias: median | 99 % | max |"),
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for count in counts:
        count, error, var0, drift, bias, group, flagged = ratios(count)
        for number, name in enumerate(GROUPS):
            chosen = group == number
            cells = [f"{count}", f"{flagged}", f"{chosen.sum()}", name]
            for allowed in (var0, var0 + drift, var0 + drift + bias):
                ratio = error[chosen] / allowed[chosen]
                cells += [f"{np.median(ratio):.3g}", f"{np.quantile(ratio, 0.99):.3g}"] + \
                    ([f"{ratio.max():.3g}"] if allowed is not var0 else [])
            lines.append("| " + " | ".join(cells) + " |")
    text = "\n".join(lines)
    print(text)
    write_section("drift-truth", text)


if __name__ == "__main__":
    main(tuple(int(a) for a in sys.argv[1:]) or RUNS)
