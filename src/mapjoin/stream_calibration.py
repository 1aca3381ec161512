"""The consistency calibration of a streamed join, tested a block of joins at a time (docs/method.md#calibration).

The in-memory sequential join tests its joins once the chain is joined
(:func:`mapjoin.consistency.calibrated` with :class:`mapjoin.drift.SequentialRecord`): each join's
variance factor comes from the joins before it, and the drift-aware minimum of a join whose own cost
fails reads each common feature's last sighting before the join and the chain's drift sums between
that sighting and the junction (docs/method.md#drift). Both look back only, so a stream
(:mod:`mapjoin.streaming`) can test each block's joins at the block's end, without the history:
:class:`StreamCalibration` keeps the running median's halves (a float per join), the chain's
dead-reckoned pose and drift sums at its end, and per feature (bounded by the global map) its last
sighting: the map, its dead-reckoned position, the drift sums there and what its fused estimate kept of
that join's residual (:func:`mapjoin.drift.fusion_bias`). The cumulative sums are
continued from their carried values, so every number equals the in-memory join's, bit for bit.
"""

from __future__ import annotations

import numpy as np

from .consistency import VarianceFactors, calibrated, degrees_of_freedom
from .drift import SequentialRecord, _Sightings, drift_variance
from .joining import _Segment, solve_widened
from .onestep import Solver

__all__ = ["StreamCalibration"]


class StreamCalibration:
    """What the calibration of a streamed join keeps between blocks (module docstring)."""

    def __init__(self) -> None:
        self._factors = VarianceFactors()
        self._heading = 0.0  # heading and position of the chain's next pose (dead-reckoned, drift.ChainDrift)
        self._pose = 0j
        self._sums = np.zeros(5)  # the drift sums over the junctions before that pose
        self._seen = np.zeros(0, dtype=np.int64)  # by compact id: the last map that saw the feature ...
        self._reckoned = np.zeros(0, dtype=complex)  # ... its position there, dead-reckoned ...
        self._seen_sums = np.zeros((0, 5))  # ... and the drift sums over the junctions up to that map ...
        self._bias = np.zeros(0)  # ... and what its fused estimate kept there (drift.fusion_bias)

    def block(self, segment: _Segment, piece: np.ndarray, end_poses: np.ndarray, first: int, number: int,
              record: SequentialRecord, cost: np.ndarray, features_cost: np.ndarray, gate: float, solver: Solver
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Test the joins of a block (``segment``'s maps 1 .. n-1, join ``number`` the first; ``piece``: its
        rows' maps, ``end_poses`` its maps' end poses as pieces hold them, complex and headings; its maps from
        ``first`` on are new to the chain; ``record`` what the joins read; ``cost``, ``features_cost`` their
        own minima). The joins' ``chi2``, ``features_cost``, variance factor and ``p``, as
        :func:`mapjoin.consistency.calibrated` of the whole run gives them."""
        pose_xy, pose_phi = end_poses
        offset = number - 1  # the chain's index of the segment's map 0
        low = offset + first  # the first new map: poses low .. high + 1 are made here
        headings = np.cumsum(np.concatenate([[self._heading], pose_phi[first:]]))
        steps = np.exp(1j * headings[:-1]) * (pose_xy.real[first:] + 1j * pose_xy.imag[first:])
        poses = np.cumsum(np.concatenate([[self._pose], steps]))
        v, p = np.zeros(len(steps)), np.zeros(len(steps))  # the posteriors of the joins at these poses
        v[1 - first:] = [join[6] for join in record.joins]
        p[1 - first:] = [join[7] for join in record.joins]
        at = poses[:-1]
        terms = np.column_stack([v, p, p * at.real, p * at.imag, p * (at.real ** 2 + at.imag ** 2)])
        sums = np.cumsum(np.concatenate([self._sums[None, :], terms]), axis=0)  # sums[i - low]: over junctions < i
        maps = offset + piece  # the rows' maps in the chain
        reckoned = poses[maps - low] + np.exp(1j * headings[maps - low]) * segment.z
        row_sums = sums[maps + 1 - low]
        bias = record.biases(segment.z, segment.var, piece, segment.starts, segment.ends_common, segment.pose_xy,
                             segment.pose_phi)

        dof = degrees_of_freedom(np.array([join[0].size for join in record.joins], dtype=np.int64))
        factors = self._factors.extend(cost, dof)

        def retest(joins: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            starts, ends_common, ids = segment.starts, segment.ends_common, segment.ids
            needed = np.concatenate([ids[starts[j]:ends_common[j]] for j in (joins + 1).tolist()])
            needed = np.unique(needed, return_index=True)[0]   # sorted; without the hash path, which imports numpy.ma
            known = needed[needed < len(self._seen)]
            carried = known[self._seen[known] >= 0]
            table_maps = np.concatenate([self._seen[carried], maps])
            table = _Sightings.of(table_maps, np.concatenate([carried, ids]), np.arange(len(table_maps)),
                                  offset + len(segment.starts), needed)
            table_reckoned = np.concatenate([self._reckoned[carried], reckoned])
            table_sums = np.concatenate([self._seen_sums[carried], row_sums])
            table_bias = np.concatenate([self._bias[carried], bias])
            problems = []
            for j in (joins + 1).tolist():
                common = slice(starts[j], ends_common[j])
                row = table.points[table.last(ids[common], offset + j - 1)]
                z0, var0, *odometry, _, _ = record.joins[j - 1]
                widened = (var0 + drift_variance(sums[offset + j - low] - table_sums[row], table_reckoned[row])
                           + table_bias[row])
                problems.append((z0, widened, segment.z[common], segment.var[common], *odometry))
            return solve_widened(problems, solver)

        test = calibrated(cost, features_cost, dof, np.ones(len(cost), dtype=bool), gate, retest, factors) \
            if len(cost) else None
        self._heading, self._pose, self._sums = float(headings[-1]), complex(poses[-1]), sums[-1]
        self._keep(segment.ids, maps, reckoned, row_sums, bias)
        if test is None:  # no joins: the chain's first map alone
            return cost, features_cost, cost, cost
        return test.chi2, test.features_cost, test.variance_factor, test.p

    def _keep(self, ids: np.ndarray, maps: np.ndarray, reckoned: np.ndarray, row_sums: np.ndarray,
              bias: np.ndarray) -> None:
        """Each feature's last sighting among these rows (grouped by map, in chain order) as its carried one."""
        if len(ids) == 0:
            return
        size = int(ids.max()) + 1
        if size > len(self._seen):
            size = max(size, 2 * len(self._seen))
            grown = len(self._seen)
            self._seen = np.concatenate([self._seen, np.full(size - grown, -1, dtype=np.int64)])
            self._reckoned = np.resize(self._reckoned, size)
            self._seen_sums = np.concatenate([self._seen_sums, np.zeros((size - grown, 5))])
            self._bias = np.concatenate([self._bias, np.zeros(size - grown)])
        unique, backwards = np.unique(ids[::-1], return_index=True)
        last = len(ids) - 1 - backwards
        self._seen[unique], self._reckoned[unique], self._seen_sums[unique] = maps[last], reckoned[last], row_sums[last]
        self._bias[unique] = bias[last]
