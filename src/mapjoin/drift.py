"""The drift of the fast join's chain that a join's consistency statistic allows for (docs/method.md#drift).

The spherical variances a fast join carries describe each feature next to the maps that
saw it: they are not its uncertainty *relative to* a pose many maps further along the chain,
where a join next meets it (a loop closure). Between the last map that saw a feature and the
join's junction pose (or, for a right piece, between the junction and the first map that
saw it) the chain is held together by the joins in between: join ``i`` placed the map starting
at junction pose ``i`` with pose variances ``(v_i, p_i)`` (its posterior, ``t_variance`` and
``phi_variance``), and these errors add up. To first order a feature at ``f`` moves relative to
the junction by ``sum_i u_i + e_i R(pi/2) (f - x_i)`` over those junctions ``i`` (``x_i`` the
junction's position, ``u_i``, ``e_i`` the join's translation and heading errors), whose
covariance has half-trace

    D(f) = sum_i v_i + p_i |f - x_i|^2 / 2.

:class:`ChainDrift` holds the chain dead-reckoned (the end poses composed: lever arms only
need its local shape) and the prefix sums ``V``, ``P``, ``PX``, ``PXX`` of ``v_i``, ``p_i``,
``p_i x_i``, ``p_i |x_i|^2`` over the junctions, so that ``D`` of any feature over any run of
junctions costs O(1).

A sequential join's fused estimate of a feature is off the map's own estimate by a share of the join's
residual, which at a loop closure is the drift since the feature was last seen: :func:`fusion_bias` keeps
the excess for the next joins that meet the feature, where ``D`` (from this sighting on) is 0.

The drift-aware statistic is the join's minimum cost with ``D`` (and the bias) added to its common features'
variances (the one-step problem solved again, Algorithm 1, by the one implementation
:func:`mapjoin.joining._solve_joins`). Adding variance lowers every weighted residual, so it
is never above the join's own cost: a join whose own cost passes the gate passes with the
drift too (docs/method.md#calibration). Hence the statistic is computed lazily, only for the
joins whose own cost fails: :class:`SequentialRecord` and :class:`TreeRecord` record, as the joins are made,
references to what each join's problem was (no copy, no arithmetic: O(1) per join or per tree
level), and :meth:`SequentialRecord.retest` / :meth:`TreeRecord.retest` give the callable that computes the
statistic of the joins asked for, all at once as one batch.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from .joins import _Pieces

__all__ = ["BIAS_LEVEL", "ChainDrift", "Retest", "SequentialRecord", "SolveWidened", "TreeRecord", "drift_variance",
           "fusion_bias"]

#: ``retest(joins)``: for these report indices (ascending), the drift-aware minimum with and without the heading link
Retest = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]
#: ``solve(problems)``: the minima, with the heading link and without, of one-step problems
#: ``(z0, var0, z1, var1, odometry_xy, odometry_phi, var_o, p_phi)`` whose variances carry the drift
#: (:func:`mapjoin.joining.solve_widened`, passed in: the join strategies use this module)
SolveWidened = Callable[[list[tuple]], tuple[np.ndarray, np.ndarray]]
#: a fused estimate keeps its join's residual beyond this many times the residual's own half-trace variance
BIAS_LEVEL = 10.0


@dataclass(frozen=True)
class ChainDrift:
    """A chain of ``N`` maps dead-reckoned, with the posteriors of its joins.

    ``poses``/``headings``: poses 0 .. N (complex positions; pose 0 the origin, pose m+1 map m's
    end), composed from the maps' end poses (each in its map's start frame). ``sums`` (N+2 x 5):
    row ``i`` the sums of ``v, p, p Re x, p Im x, p |x|^2`` over junctions ``< i`` (Section 1's ``D``).
    """

    poses: np.ndarray
    headings: np.ndarray
    sums: np.ndarray

    def __post_init__(self) -> None:
        n = len(self.poses)
        if len(self.headings) != n or self.sums.shape != (n + 1, 5):
            raise ValueError("ChainDrift: poses and headings need one row per pose, sums one more")

    @classmethod
    def of(cls, end_poses: np.ndarray, junctions: np.ndarray, t_variance: np.ndarray, phi_variance: np.ndarray
           ) -> ChainDrift:
        """The chain of maps with these end poses (N x 3, each in its map's start frame) whose joins at
        ``junctions`` (pose indices 1 .. N-1, each once) placed their pose with these posterior variances."""
        end_poses = np.asarray(end_poses, dtype=float).reshape(-1, 3)
        headings = np.concatenate([[0.0], np.cumsum(end_poses[:, 2])])
        steps = np.exp(1j * headings[:-1]) * (end_poses[:, 0] + 1j * end_poses[:, 1])
        poses = np.concatenate([[0j], np.cumsum(steps)])
        v, p = np.zeros(len(poses)), np.zeros(len(poses))
        v[junctions], p[junctions] = t_variance, phi_variance
        terms = np.column_stack([v, p, p * poses.real, p * poses.imag, p * (poses.real ** 2 + poses.imag ** 2)])
        sums = np.zeros((len(poses) + 1, 5))
        sums[1:] = np.cumsum(terms, axis=0)
        return cls(poses, headings, sums)

    def dead_reckoned(self, start: np.ndarray, points: np.ndarray) -> np.ndarray:
        """Points (complex) given in the frame of pose ``start`` (a map's start pose index), dead-reckoned."""
        return self.poses[start] + np.exp(1j * self.headings[start]) * points

    def variance(self, low: np.ndarray | int, high: np.ndarray | int, points: np.ndarray) -> np.ndarray:
        """``D`` at the dead-reckoned ``points`` over the junctions ``low .. high - 1`` (``low <= high``, the
        callers' invariant; 0 when equal): the half-trace variance the joins in between add."""
        return drift_variance(self.sums[high] - self.sums[low], points)


def drift_variance(sums: np.ndarray, points: np.ndarray) -> np.ndarray:
    """``D`` at the dead-reckoned ``points`` (one each) from the sums (rows of ``v, p, p Re x, p Im x, p |x|^2``)
    over the junctions in between (Section 1)."""
    v, p, px, py, pxx = sums.T
    lever = (points.real ** 2 + points.imag ** 2) * p - 2.0 * (points.real * px + points.imag * py) + pxx
    return v + np.maximum(lever, 0.0) / 2.0


def fusion_bias(z0: np.ndarray, var0: np.ndarray, placed: np.ndarray, var1: np.ndarray) -> np.ndarray:
    """The error a sequential join's fused estimate of each common feature keeps relative to its junction, as a
    half-trace variance (docs/method.md#drift): ``w^2 max(0, |r|^2 / 2 - BIAS_LEVEL (var0 + var1))``.

    The join fuses ``z0`` (the map so far) and ``placed`` (the map's own estimate, rigid with its junction) as
    ``w z0 + (1 - w) placed``, ``w = var1 / (var0 + var1)`` (:func:`mapjoin.covariance.fuse`), so the fused
    estimate is off the placed one by ``w r``, ``r = z0 - placed`` the join's residual, which the join has
    observed. Where ``r`` is noise the fused variance already holds it; at a loop closure ``r`` is the
    chain's drift since the feature was last seen (kilometres on long runs), and the feature's last
    sighting is now this map, so the drift since it (:meth:`ChainDrift.variance`) is 0 at the next join while
    the estimate is ``w r`` off. Only the excess over :data:`BIAS_LEVEL` times the residual's own variance is
    kept (``P(chi2(2) / 2 > 10) = 4.5e-5`` under the model), so a consistent join keeps nothing."""
    weight = var1 / (var0 + var1)
    residual = (z0.real - placed.real) ** 2 + (z0.imag - placed.imag) ** 2
    return weight ** 2 * np.maximum(residual / 2.0 - BIAS_LEVEL * (var0 + var1), 0.0)


@dataclass(frozen=True)
class _Sightings:
    """The input rows of the chain that saw some features: each row's map and position (in that map's
    frame), sorted by ``(id, map)`` so that the last map up to ``m`` (or the first from ``m``) that saw a
    feature is one search."""

    maps: np.ndarray
    points: np.ndarray
    keys: np.ndarray
    width: int
    rows: np.ndarray  # the input row of each entry
    bias: np.ndarray | None = None  # per entry: what its fused estimate keeps (:func:`fusion_bias`)

    @classmethod
    def of(cls, maps: np.ndarray, ids: np.ndarray, points: np.ndarray, width: int, needed: np.ndarray
           ) -> _Sightings:
        """The rows (``maps``, ``ids``, ``points``: one entry each) of the features ``needed`` (``width``:
        more than any map index)."""
        rows = np.flatnonzero(np.isin(ids, needed))
        keys = ids[rows].astype(np.int64) * width + maps[rows]
        order = np.argsort(keys, kind="stable")
        rows = rows[order]
        return cls(maps[rows], points[rows], keys[order], width, rows)

    def last(self, ids: np.ndarray, up_to: int) -> np.ndarray:
        """The row of the last map ``<= up_to`` that saw each feature (one exists: the callers' invariant)."""
        return np.searchsorted(self.keys, ids * self.width + up_to, side="right") - 1

    def first(self, ids: np.ndarray, from_: int) -> np.ndarray:
        """The row of the first map ``>= from_`` that saw each feature (one exists)."""
        return np.searchsorted(self.keys, ids * self.width + from_, side="left")


def _end_poses(chain: _Pieces) -> np.ndarray:
    """The maps' end poses (N x 3, each in its map's start frame) of a chain of single-map pieces."""
    return np.column_stack([chain.pose_xy.real, chain.pose_xy.imag, chain.pose_phi])


def _statistic(end_poses: np.ndarray, posteriors: tuple[np.ndarray, np.ndarray, np.ndarray],
               problems: list[tuple], solve: SolveWidened) -> tuple[np.ndarray, np.ndarray]:
    """The drift-aware minima (with the heading link, and without: ``c0 - 2 a0``) of ``problems``, one per join:
    ``(sightings, ids, left_last, right_first, z0, var0, z1, var1, odometry_xy, odometry_phi, var_o, p_phi)``
    with the common features' ``ids`` (as ``sightings`` numbers them), the left piece's last map and the right
    piece's first map; ``solve`` solves them with the drift in their variances (:data:`SolveWidened`)."""
    drift = ChainDrift.of(end_poses, *posteriors)
    widened = []
    for sightings, ids, m, first, z0, var0, z1, var1, *odometry in problems:
        ids = np.asarray(ids, dtype=np.int64)
        left = sightings.last(ids, m)
        right = sightings.first(ids, first)
        junction = m + 1  # the left piece's end pose, where the right piece starts
        seen = sightings.maps[left]
        var0 = var0 + drift.variance(seen + 1, junction, drift.dead_reckoned(seen, sightings.points[left]))
        if sightings.bias is not None:
            var0 = var0 + sightings.bias[left]
        seen = sightings.maps[right]
        reckoned = drift.dead_reckoned(seen, sightings.points[right])
        widened.append((z0, var0, z1, var1 + drift.variance(junction + 1, seen + 1, reckoned), *odometry))
    return solve(widened)


@dataclass
class SequentialRecord:
    """The sequential join's problems as they are made (filled join by join, hence not frozen): for join
    ``k`` (map k onto maps 0 .. k-1), the map so far's common features ``z0``, ``var0`` (fresh arrays the
    join does not change), its odometry and the posterior of the pose it places. ``chain``: every map as a
    piece, as the join starts (:func:`mapjoin.joining._prepare`; its end poses)."""

    chain: _Pieces
    joins: list[tuple] = field(default_factory=list)

    def joined(self, z0: np.ndarray, var0: np.ndarray, odometry_xy: complex, odometry_phi: float, var_o: float,
               p_phi: float, t_variance: float, phi_variance: float) -> None:
        """Join ``len(joins) + 1`` is made: O(1), references only."""
        self.joins.append((z0, var0, odometry_xy, odometry_phi, var_o, p_phi, t_variance, phi_variance))

    def biases(self, z: np.ndarray, var: np.ndarray, piece: np.ndarray, starts: list[int], ends_common: list[int],
               pose_xy: list[complex], pose_phi: list[float]) -> np.ndarray:
        """Per input row (``z``, ``var``, ``piece`` its map; map ``k``'s common rows ``starts[k] .. ends_common[k]``,
        join ``k`` the ``k``-th recorded; ``pose_xy``, ``pose_phi`` each map's start pose once joined, i.e. its
        join's ``(t*, phi*)``): :func:`fusion_bias` of its join's fusion, 0 for a first sighting."""
        bias = np.zeros(len(z))
        if not self.joins:
            return bias
        offsets = np.asarray(starts, dtype=np.int64)
        counts = np.asarray(ends_common, dtype=np.int64) - offsets[:-1]
        rows = np.flatnonzero(np.arange(len(z)) - offsets[piece] < counts[piece])  # common rows, map after map
        start = piece[rows] - 1  # map k starts at pose k - 1, where its join placed it
        t = np.asarray(pose_xy, dtype=complex)[start]
        turn = np.exp(1j * np.asarray(pose_phi, dtype=float)[start])
        z0 = np.concatenate([join[0] for join in self.joins])
        var0 = np.concatenate([join[1] for join in self.joins])
        bias[rows] = fusion_bias(z0, var0, t + turn * z[rows], var[rows])
        return bias

    def retest(self, ids: np.ndarray, z: np.ndarray, var: np.ndarray, piece: np.ndarray, starts: list[int],
               ends_common: list[int], solve: SolveWidened, pose_xy: list[complex], pose_phi: list[float]) -> Retest:
        """The drift-aware statistic of the joins asked for, once the chain is joined: ``ids``, ``z``, ``var``,
        ``piece`` the input rows in the order the joins read them (each map's common rows
        ``starts[k] .. ends_common[k]`` first), as numbered at the end; ``pose_xy``, ``pose_phi`` the maps'
        start poses once joined (:meth:`biases`)."""
        def retest(joins: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            end_poses = _end_poses(self.chain)
            needed = np.concatenate([ids[starts[k]:ends_common[k]] for k in (joins + 1).tolist()])
            sightings = _Sightings.of(piece, ids, z, len(end_poses) + 1, needed)
            bias = self.biases(z, var, piece, starts, ends_common, pose_xy, pose_phi)
            sightings = replace(sightings, bias=bias[sightings.rows])
            posteriors = (np.arange(1, len(self.joins) + 1), np.array([j[6] for j in self.joins]),
                          np.array([j[7] for j in self.joins]))
            problems = []
            for number in joins.tolist():
                k = number + 1  # join k puts map k onto maps 0 .. k-1
                z0, var0, *odometry, _, _ = self.joins[number]
                common = slice(starts[k], ends_common[k])
                problems.append((sightings, ids[common], k - 1, k, z0, var0, z[common], var[common], *odometry))
            return _statistic(end_poses, posteriors, problems, solve)

        return retest


@dataclass
class TreeRecord:
    """The tree join's problems as its levels are made (filled level by level): per level, the arrays its
    batch of joins read. The report lists the joins level by level, in chain order within a level, which
    is the order of these records sorted (stably) by level: worker processes' blocks come in chain order."""

    levels: list[tuple] = field(default_factory=list)

    def level(self, number: int, pair: np.ndarray, ids: np.ndarray, row_ids: np.ndarray | None,
              left_last: np.ndarray, z0: np.ndarray, var0: np.ndarray, z1: np.ndarray, var1: np.ndarray,
              odometry: tuple, t_variance: np.ndarray, phi_variance: np.ndarray) -> None:
        """Level ``number``'s joins are made: common feature ``j`` (id ``ids[j]``) belongs to join ``pair[j]``
        (sorted), whose left piece ends with map ``left_last``; ``row_ids`` the input rows' ids as the level
        numbers them (None: the ids the chain came with). O(1): references only."""
        self.levels.append((number, pair, ids, row_ids, left_last, z0, var0, z1, var1, odometry, t_variance,
                            phi_variance))

    def extend(self, other: TreeRecord) -> None:
        """Append the levels a worker process made (its block follows the blocks recorded so far)."""
        self.levels += other.levels

    def retest(self, chain: _Pieces, solve: SolveWidened) -> Retest:
        """The drift-aware statistic of the joins asked for (report indices); ``chain``: every map as a piece,
        as the join started (:func:`mapjoin.joining._prepare`)."""
        def retest(joins: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            end_poses, row_maps, row_ids = _end_poses(chain), chain.feature_piece, chain.feature_ids
            width = len(end_poses) + 1
            levels = sorted(self.levels, key=lambda level: level[0])  # stable: the report's order
            starts = np.cumsum([0] + [len(level[4]) for level in levels])
            posteriors = (np.concatenate([np.asarray(level[4]) + 1 for level in levels]),  # junction: left end
                          np.concatenate([level[10] for level in levels]),
                          np.concatenate([level[11] for level in levels]))
            at = np.searchsorted(starts, joins, side="right") - 1  # each join's level record
            chosen = []  # (level, join there, its common rows there), in the order of ``joins``
            for number, level in zip(joins.tolist(), at.tolist()):
                i = number - int(starts[level])
                chosen.append((level, i, slice(*np.searchsorted(levels[level][1], [i, i + 1]))))  # pair sorted
            tables: dict[int, _Sightings] = {}  # by the level whose ids they use (-1: the chain's own)
            for key in {-1 if levels[level][3] is None else level for level, _, _ in chosen}:
                needed = np.concatenate([levels[level][2][rows] for level, _, rows in chosen
                                         if key == (-1 if levels[level][3] is None else level)])
                tables[key] = _Sightings.of(row_maps, row_ids if key == -1 else levels[key][3], chain.features,
                                            width, needed)
            problems = []
            for level, i, rows in chosen:
                _, _, ids, snapshot, left_last, z0, var0, z1, var1, odometry, *_ = levels[level]
                m = int(left_last[i])
                problems.append((tables[-1 if snapshot is None else level], ids[rows], m, m + 1, z0[rows],
                                 var0[rows], z1[rows], var1[rows], *(o[i] for o in odometry)))
            return _statistic(end_poses, posteriors, problems, solve)

        return retest
