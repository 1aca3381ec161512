"""Joining a chain of local maps into a global map, one one-step problem per join.

A join takes two consecutive pieces of the chain, ``left`` (a map or a joined run of maps,
in the frame of its start pose) and ``right`` (the same, starting at left's end pose),
and treats left as map 0 and right as map 1 of the one-step problem (method.md,
"Sequential joining"): only the common features enter it, with left's end pose as the
odometry. The features seen only by right, and right's poses, are placed afterwards,
``x = t* + R(phi*) z``. Two strategies order the joins:

- ``sequential``: the global map so far is left, local map k is right (k = 2 .. N);
- ``tree``: neighbouring pieces are joined pairwise, level by level, until one is left
  (the paper's Remark 8). The joins of a level are independent: they are computed
  together, as arrays, and ``jobs > 1`` splits the lower levels into aligned subtrees
  joined in parallel processes (the result does not depend on ``jobs``).

Spherical variances are propagated so that later joins weigh the estimates correctly
(first order, each 2x2 covariance summarised by half its trace):

- a common feature fuses both estimates: ``1 / (1/var0 + 1/var1)``;
- the joined pose r1 (left's end) gets ``var_phi = 1 / (f''(phi*)/2)`` and
  ``var_t = 1/W + |m1|^2 var_phi / 2`` (W, m1 from Theorem 1's reduction);
- a point ``z`` of right placed in left's frame gets ``var_t + var_z + |z|^2 var_phi / 2``,
  a pose orientation ``var_phi + p_phi``.
"""

from __future__ import annotations

import logging
import math
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from typing import Literal

import numpy as np

from .errors import JoinError
from .maps import CovarianceMode, GlobalMap, LocalMap, Provenance, batch_spherical_variances
from .onestep import Constants, Solver, batch_constants, global_orientation, linked_cost, wrap

__all__ = ["DEFAULT_COVARIANCE", "STRATEGIES", "JoinRecord", "JoinResult", "Strategy", "certify_pair",
           "check_chain", "join", "join_sequential", "join_tree"]

log = logging.getLogger("mapjoin")

# Measured against the exact least-squares joins (README, "Covariance modes"): closest on
# VicPark 200 and both simulations; "marginal" is closer on DLR 200 only.
DEFAULT_COVARIANCE: CovarianceMode = "information"
Strategy = Literal["sequential", "tree"]
STRATEGIES: tuple[str, ...] = ("sequential", "tree")


@dataclass(frozen=True)
class JoinRecord:
    """One join of the report: what came in, Theorem 2's certificate, and the optimum found.

    ``map`` names the right piece ("first to last" local map when it is a run of them),
    ``start_id``/``end_id`` its first and last pose; ``level`` is the join's depth (the
    join number for the sequential strategy). ``phi`` is phi*, the orientation of right's
    start pose in left's frame, ``cost`` f_1(phi*); ``phi2``/``cost2`` the other local
    minimum when ``minima`` is 2.
    """

    join: int
    map: str
    start_id: int
    end_id: int
    common: int
    new: int
    a: float
    c_phi: float
    minima: int
    phi: float
    cost: float
    phi2: float | None
    cost2: float | None
    iterations: int
    level: int


@dataclass(frozen=True)
class JoinResult:
    """A joined global map and its per-join report."""

    global_map: GlobalMap
    report: tuple[JoinRecord, ...]


def check_chain(maps: Sequence[LocalMap]) -> None:
    """Raise JoinError unless each map starts at the end pose of the previous one, with no pose twice."""
    if not maps:
        raise JoinError("no local maps to join")
    seen = {maps[0].start_id}
    for previous, current in zip(maps, maps[1:]):
        if current.start_id != previous.end_id:
            raise JoinError(
                f"the pose chain does not connect: {current.name} starts at pose {current.start_id}, "
                f"but the map before it ({previous.name}) ends at pose {previous.end_id}")
    for local_map in maps:
        if local_map.end_id in seen:
            raise JoinError(f"pose {local_map.end_id} appears twice in the chain (again as the end of "
                            f"{local_map.name}); each map must end at a new pose")
        seen.add(local_map.end_id)


@dataclass
class _Pieces:
    """Consecutive pieces of the chain as flat arrays, each in the frame of its own start pose.

    Points are complex numbers ``x + iy`` (a rotation is one product). Feature rows are
    grouped by piece (``feature_piece`` non-decreasing) and sorted by compact id within a
    piece; pose rows are the end poses of the piece's maps, in chain order, so a piece's
    last pose row is its end pose. ``first``/``last`` are the indices of each piece's first
    and last local map.
    """

    feature_piece: np.ndarray
    feature_ids: np.ndarray
    features: np.ndarray
    feature_variances: np.ndarray
    pose_piece: np.ndarray
    pose_xy: np.ndarray
    pose_phi: np.ndarray
    pose_variances: np.ndarray
    first: np.ndarray
    last: np.ndarray

    @property
    def count(self) -> int:
        return len(self.first)

    def block(self, start: int, stop: int) -> _Pieces:
        """Pieces ``start .. stop-1``, renumbered from 0."""
        f = slice(*np.searchsorted(self.feature_piece, [start, stop]))
        p = slice(*np.searchsorted(self.pose_piece, [start, stop]))
        return _Pieces(self.feature_piece[f] - start, self.feature_ids[f], self.features[f],
                       self.feature_variances[f], self.pose_piece[p] - start, self.pose_xy[p], self.pose_phi[p],
                       self.pose_variances[p], self.first[start:stop], self.last[start:stop])


@dataclass(frozen=True)
class _Joins:
    """The outcome of ``count`` independent joins (left i + right i), as arrays over the joins.

    ``turn`` is ``exp(i phi*)`` and ``t`` the translation (complex); ``rows`` are the joins'
    report entries: JoinRecord's fields after ``join``, which is numbered once all joins are known.
    """

    phi: np.ndarray
    turn: np.ndarray
    t: np.ndarray
    phi_variance: np.ndarray
    t_variance: np.ndarray
    rows: list[tuple]


def _solve_joins(pair: np.ndarray, count: int, z0: np.ndarray, var0: np.ndarray, z1: np.ndarray,
                 var1: np.ndarray, odometry_xy: np.ndarray, odometry_phi: np.ndarray,
                 odometry_variances: np.ndarray, solver: Solver,
                 describe: Callable[[int], tuple[str, int, int, int]], level: int) -> _Joins:
    """Algorithm 1 for ``count`` joins at once: Theorem 1's constants as arrays, then the 1-D solve of each.

    Common feature j belongs to join ``pair[j]``; ``odometry_*`` are the end pose of each left
    piece and its spherical variances. ``describe(i)`` names join i's right piece (name,
    start id, end id, its number of features) for the report.
    """
    k = batch_constants(pair, count, z0, var0, z1, var1, odometry_xy, odometry_variances[:, 0])
    p_phi = odometry_variances[:, 1]
    found = [global_orientation(*args, solver) for args in zip(k.a0.tolist(), k.phi0.tolist(),
                                                                 odometry_phi.tolist(), p_phi.tolist())]
    phi = np.array([f.phi for f in found])
    information = k.a0 * np.cos(phi - k.phi0) + 1.0 / p_phi  # f_1''(phi*) / 2
    positive = information > 0
    phi_variance = np.where(positive, 1.0 / np.where(positive, information, 1.0), p_phi)
    turn = np.exp(1j * phi)
    t = k.mean0 - turn * k.mean1
    t_variance = 1.0 / k.weight + _squared(k.mean1) * phi_variance / 2
    costs = linked_cost(k, odometry_phi, p_phi, phi).tolist()
    common = np.bincount(pair, minlength=count).tolist()
    rows = []
    for i, f in enumerate(found):
        name, start_id, end_id, size = describe(i)
        if not common[i]:
            log.warning("%s shares no feature with the maps it is joined onto: it is placed by its "
                        "start pose alone (no correction of the map so far)", name)
        other_cost = None
        if f.other_phi is not None:
            other_cost = float(linked_cost(_one(k, i), odometry_phi[i], p_phi[i], f.other_phi))
        rows.append((name, start_id, end_id, common[i], size - common[i], f.minima.a, f.minima.c_phi,
                     f.minima.count, f.phi, costs[i], f.other_phi, other_cost, f.iterations, level))
    return _Joins(phi, turn, t, phi_variance, t_variance, rows)


def _report(rows: Sequence[tuple]) -> tuple[JoinRecord, ...]:
    """The report: the joins' rows numbered from 1."""
    return tuple(JoinRecord(number, *row) for number, row in enumerate(rows, start=1))


def _one(k: Constants, i: int) -> Constants:
    """Join i's constants out of a batch."""
    return Constants(k.c0[i], k.a0[i], k.phi0[i], k.mean0[i], k.mean1[i], k.weight[i])


def _squared(points: np.ndarray) -> np.ndarray:
    """|z|^2 of complex points."""
    return points.real**2 + points.imag**2


def _place(joins: _Joins, pair: np.ndarray | int, points: np.ndarray, variances: np.ndarray
           ) -> tuple[np.ndarray, np.ndarray]:
    """Points of right pieces (join ``pair[j]``) in left's frame, ``t + R(phi) z``, with their spherical variances."""
    placed = joins.turn[pair] * points + joins.t[pair]
    return placed, joins.t_variance[pair] + variances + _squared(points) * joins.phi_variance[pair] / 2


def _move_poses(joins: _Joins, pair: np.ndarray | int, rows: np.ndarray | slice, pose_xy: np.ndarray,
                pose_phi: np.ndarray, pose_variances: np.ndarray) -> None:
    """Poses ``rows`` of right pieces (join ``pair``) into left's frame, with their (var_xy, var_phi), in place."""
    pose_xy[rows], pose_variances[rows, 0] = _place(joins, pair, pose_xy[rows], pose_variances[rows, 0])
    pose_phi[rows] = wrap(joins.phi[pair] + pose_phi[rows])
    pose_variances[rows, 1] += joins.phi_variance[pair]


def _set_junctions(joins: _Joins, rows: np.ndarray | slice, pose_xy: np.ndarray, pose_phi: np.ndarray,
                   pose_variances: np.ndarray) -> None:
    """Each left piece's end pose (``rows``, one per join) becomes the joined pose r1 = (t*, phi*), in place."""
    pose_xy[rows], pose_phi[rows] = joins.t, joins.phi
    pose_variances[rows, 0], pose_variances[rows, 1] = joins.t_variance, joins.phi_variance


def _fuse(z0: np.ndarray, var0: np.ndarray, placed: np.ndarray, var1: np.ndarray
          ) -> tuple[np.ndarray, np.ndarray]:
    """Theorem 1's X_L: each common feature as the information-weighted mean of both estimates."""
    w0, w1 = 1.0 / var0, 1.0 / var1
    return (w0 * z0 + w1 * placed) / (w0 + w1), 1.0 / (w0 + w1)


def _complex(xy: np.ndarray) -> np.ndarray:
    """(n, 2) x/y rows as complex numbers."""
    return xy[:, 0] + 1j * xy[:, 1]


def _prepare(maps: Sequence[LocalMap], covariance: CovarianceMode) -> tuple[np.ndarray, _Pieces]:
    """Check the chain; every map as a piece, with compact feature ids (and the global ids they stand for)."""
    check_chain(maps)
    feature_variances, pose_variances = batch_spherical_variances(maps, covariance)
    sizes = np.array([m.size for m in maps], dtype=np.intp)
    ids = np.concatenate([m.feature_ids for m in maps])
    feature_ids, compact = np.unique(ids, return_inverse=True)
    piece = np.repeat(np.arange(len(maps)), sizes)
    order = np.lexsort((compact, piece))  # maps' ids are unique but not necessarily sorted
    index = np.arange(len(maps))
    end_poses = np.array([m.end_pose for m in maps])
    pieces = _Pieces(piece, compact[order], _complex(np.concatenate([m.features for m in maps]))[order],
                     feature_variances[order], index, _complex(end_poses), end_poses[:, 2], pose_variances,
                     index, index)
    return feature_ids, pieces


def _global_map(maps: Sequence[LocalMap], feature_ids: np.ndarray, pieces: _Pieces, covariance: str,
                solver: str, strategy: str) -> GlobalMap:
    return GlobalMap(
        feature_ids=feature_ids[pieces.feature_ids],
        features=np.column_stack([pieces.features.real, pieces.features.imag]),
        feature_variances=pieces.feature_variances, pose_ids=np.array([m.end_id for m in maps]),
        poses=np.column_stack([pieces.pose_xy.real, pieces.pose_xy.imag, pieces.pose_phi]),
        pose_variances=pieces.pose_variances,
        provenance=Provenance(tuple(m.name for m in maps), covariance, solver, strategy))


@dataclass(frozen=True)
class _Labels:
    """What the report says about the local maps (the workers get this, not the maps)."""

    names: list[str]
    start_ids: list[int]
    end_ids: list[int]

    @classmethod
    def of(cls, maps: Sequence[LocalMap]) -> _Labels:
        return cls([m.name for m in maps], [m.start_id for m in maps], [m.end_id for m in maps])

    def run(self, first: int, last: int) -> str:
        """The name of maps first .. last."""
        return self.names[first] if first == last else f"{self.names[first]} to {self.names[last]}"


def join_sequential(maps: Sequence[LocalMap], covariance: CovarianceMode = DEFAULT_COVARIANCE,
                    solver: Solver = "bisection",
                    progress: Callable[[int], None] | None = None) -> JoinResult:
    """Join ``maps`` (a connected chain) one after the other; the global frame is the first map's start.

    The global map lives in arrays indexed by compact feature id, so join k reads and
    writes only the rows of map k. ``progress`` is called with the number of maps joined.
    """
    feature_ids, pieces = _prepare(maps, covariance)
    offsets = np.searchsorted(pieces.feature_piece, np.arange(len(maps) + 1))
    # a feature is common in join k iff a map before k saw it: its first row is in an earlier map
    first_row = np.unique(pieces.feature_ids, return_index=True)[1]  # compact ids are 0 .. n-1
    seen_before = first_row[pieces.feature_ids] < offsets[pieces.feature_piece]

    positions = np.zeros(len(feature_ids), dtype=complex)
    position_variances = np.zeros(len(feature_ids))
    pose_xy, pose_phi = pieces.pose_xy.copy(), pieces.pose_phi.copy()
    pose_variances = pieces.pose_variances.copy()
    rows = pieces.feature_ids[:offsets[1]]
    positions[rows], position_variances[rows] = pieces.features[:offsets[1]], pieces.feature_variances[:offsets[1]]
    report: list[tuple] = []
    if progress:
        progress(1)
    for k in range(1, len(maps)):
        span = slice(offsets[k], offsets[k + 1])
        ids, z, var = pieces.feature_ids[span], pieces.features[span], pieces.feature_variances[span]
        common = seen_before[span]
        shared, new = ids[common], ~common
        local_map = maps[k]
        joins = _solve_joins(np.zeros(len(shared), dtype=np.intp), 1, positions[shared],
                             position_variances[shared], z[common], var[common], pose_xy[k - 1:k],
                             pose_phi[k - 1:k], pose_variances[k - 1:k], solver,
                             lambda _: (local_map.name, local_map.start_id, local_map.end_id, local_map.size), k)
        placed, spread = _place(joins, 0, z, var)
        positions[shared], position_variances[shared] = _fuse(positions[shared], position_variances[shared],
                                                              placed[common], var[common])
        positions[ids[new]], position_variances[ids[new]] = placed[new], spread[new]
        _move_poses(joins, 0, slice(k, k + 1), pose_xy, pose_phi, pose_variances)
        _set_junctions(joins, slice(k - 1, k), pose_xy, pose_phi, pose_variances)
        report += joins.rows
        if progress:
            progress(k + 1)
    pieces = replace(pieces, feature_piece=np.zeros(len(feature_ids), dtype=np.intp),
                     feature_ids=np.arange(len(feature_ids)), features=positions,
                     feature_variances=position_variances, pose_xy=pose_xy, pose_phi=pose_phi,
                     pose_variances=pose_variances)
    return JoinResult(_global_map(maps, feature_ids, pieces, covariance, solver, "sequential"), _report(report))


def _join_level(pieces: _Pieces, labels: _Labels, solver: Solver, level: int
                ) -> tuple[_Pieces, list[tuple]]:
    """Join pieces 2i and 2i+1 for every i (an odd last piece passes through): one level of the tree."""
    count = pieces.count // 2
    parent = pieces.feature_piece // 2
    right = (pieces.feature_piece % 2 == 1) & (parent < count)
    left_rows, right_rows = np.flatnonzero(~right), np.flatnonzero(right)
    span = int(pieces.feature_ids.max(initial=0)) + 1
    left_keys = parent[left_rows] * span + pieces.feature_ids[left_rows]  # sorted: pieces in order, ids sorted
    right_keys = parent[right_rows] * span + pieces.feature_ids[right_rows]
    position = np.minimum(np.searchsorted(left_keys, right_keys), max(len(left_keys) - 1, 0))
    common = left_keys[position] == right_keys if len(left_keys) else np.zeros(len(right_keys), dtype=bool)
    lc, rc = left_rows[position[common]], right_rows[common]

    ends = np.searchsorted(pieces.pose_piece, np.arange(pieces.count), side="right") - 1  # each piece's end row
    left_end = ends[0:2 * count:2]
    sizes = np.bincount(pieces.feature_piece, minlength=pieces.count)

    def describe(i: int) -> tuple[str, int, int, int]:
        first, last = int(pieces.first[2 * i + 1]), int(pieces.last[2 * i + 1])
        return labels.run(first, last), labels.start_ids[first], labels.end_ids[last], int(sizes[2 * i + 1])

    joins = _solve_joins(parent[rc], count, pieces.features[lc], pieces.feature_variances[lc],
                         pieces.features[rc], pieces.feature_variances[rc], pieces.pose_xy[left_end],
                         pieces.pose_phi[left_end], pieces.pose_variances[left_end], solver, describe, level)

    features, feature_variances = pieces.features.copy(), pieces.feature_variances.copy()
    placed, spread = _place(joins, parent[right_rows], pieces.features[right_rows],
                            pieces.feature_variances[right_rows])
    features[right_rows], feature_variances[right_rows] = placed, spread
    features[lc], feature_variances[lc] = _fuse(features[lc], feature_variances[lc], placed[common],
                                                pieces.feature_variances[rc])
    keep = np.ones(len(features), dtype=bool)
    keep[rc] = False  # common features live on in the left piece's rows
    kept = np.flatnonzero(keep)
    order = kept[np.argsort(parent[kept] * span + pieces.feature_ids[kept], kind="stable")]

    pose_xy, pose_phi, pose_variances = pieces.pose_xy.copy(), pieces.pose_phi.copy(), pieces.pose_variances.copy()
    moved = np.flatnonzero((pieces.pose_piece % 2 == 1) & (pieces.pose_piece < 2 * count))
    _move_poses(joins, pieces.pose_piece[moved] // 2, moved, pose_xy, pose_phi, pose_variances)
    _set_junctions(joins, left_end, pose_xy, pose_phi, pose_variances)
    joined = _Pieces(parent[order], pieces.feature_ids[order], features[order], feature_variances[order],
                     pieces.pose_piece // 2, pose_xy, pose_phi, pose_variances, pieces.first[0::2],
                     np.append(pieces.last[1::2], pieces.last[-1:]) if pieces.count % 2 else pieces.last[1::2])
    return joined, joins.rows


def _join_levels(pieces: _Pieces, labels: _Labels, solver: Solver, level: int,
                 progress: Callable[[int], None] | None = None) -> tuple[_Pieces, list[tuple]]:
    """Join levels from ``level`` on until one piece is left; the joins' report rows."""
    records: list[tuple] = []
    while pieces.count > 1:
        level += 1
        pieces, joined = _join_level(pieces, labels, solver, level)
        records += joined
        if progress:
            progress(len(records) + 1)
    return pieces, records


def _subtree(job: tuple[_Pieces, _Labels, Solver]) -> tuple[_Pieces, list[tuple]]:
    """A worker process's share: one aligned block of pieces joined into one."""
    pieces, labels, solver = job
    return _join_levels(pieces, labels, solver, 0)


def join_tree(maps: Sequence[LocalMap], covariance: CovarianceMode = DEFAULT_COVARIANCE,
              solver: Solver = "bisection", jobs: int = 1,
              progress: Callable[[int], None] | None = None) -> JoinResult:
    """Join ``maps`` pairwise, level by level (Remark 8); ``jobs`` processes share the lower levels.

    With ``jobs > 1`` the maps are cut into aligned blocks of 2^L maps (at least ``jobs``
    of them), each joined to one piece in a worker, exactly as the single-process tree
    would; the parent joins the blocks' results. Join numbers follow the levels.
    """
    if jobs < 1:
        raise ValueError(f"jobs must be at least 1, got {jobs}")
    feature_ids, pieces = _prepare(maps, covariance)
    labels = _Labels.of(maps)
    records: list[tuple] = []
    depth = 0
    if jobs > 1 and len(maps) >= 2 * jobs:
        depth = int(math.floor(math.log2(len(maps) / jobs)))
        size = 2**depth
        blocks = [pieces.block(start, min(start + size, len(maps))) for start in range(0, len(maps), size)]
        from concurrent.futures import ProcessPoolExecutor  # multiprocessing: imported only when used

        with ProcessPoolExecutor(max_workers=min(jobs, os.cpu_count() or jobs)) as pool:
            results = list(pool.map(_subtree, [(b, labels, solver) for b in blocks]))
        for _, block_records in results:
            records += block_records
        pieces = _concatenate([(start // size, block) for start, (block, _) in
                               zip(range(0, len(maps), size), results)])
        if progress:
            progress(len(records) + 1)
    pieces, upper = _join_levels(pieces, labels, solver, depth,
                                 (lambda done: progress(done + len(records))) if progress else None)
    records += upper
    records.sort(key=lambda row: row[-1])  # by level, stable: chain order within a level
    return JoinResult(_global_map(maps, feature_ids, pieces, covariance, solver, "tree"), _report(records))


def _concatenate(blocks: list[tuple[int, _Pieces]]) -> _Pieces:
    """Single pieces (block b's result becomes piece b) as one _Pieces."""
    def stack(name: str) -> np.ndarray:
        return np.concatenate([getattr(p, name) for _, p in blocks])

    return _Pieces(np.concatenate([np.full(len(p.feature_ids), b) for b, p in blocks]), stack("feature_ids"),
                   stack("features"), stack("feature_variances"),
                   np.concatenate([np.full(len(p.pose_phi), b) for b, p in blocks]), stack("pose_xy"),
                   stack("pose_phi"), stack("pose_variances"), stack("first"), stack("last"))


def join(maps: Sequence[LocalMap], covariance: CovarianceMode = DEFAULT_COVARIANCE, solver: Solver = "bisection",
         strategy: Strategy = "sequential", jobs: int = 1,
         progress: Callable[[int], None] | None = None) -> JoinResult:
    """Join ``maps`` with ``strategy`` (``jobs`` only matters for the tree)."""
    if strategy == "sequential":
        return join_sequential(maps, covariance, solver, progress)
    if strategy == "tree":
        return join_tree(maps, covariance, solver, jobs, progress)
    raise ValueError(f"unknown strategy {strategy!r}; expected one of {', '.join(STRATEGIES)}")


def certify_pair(first: LocalMap, second: LocalMap, covariance: CovarianceMode = DEFAULT_COVARIANCE,
                 solver: Solver = "bisection") -> JoinRecord:
    """The report of joining ``second`` onto ``first``: a, C_phi, the minima and the optimum."""
    if not np.isin(second.feature_ids, first.feature_ids).any():
        raise JoinError(
            f"{first.name} and {second.name} share no feature: the join would rest on the end pose "
            f"of {first.name} alone, so there is no feature evidence whose minima could be counted")
    return join_sequential([first, second], covariance, solver).report[0]
