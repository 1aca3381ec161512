"""Joining a chain of local maps into a global map, one one-step problem per join.

A join takes two consecutive pieces of the chain, ``left`` (a map or a joined run of maps,
in the frame of its start pose) and ``right`` (the same, starting at left's end pose),
and treats left as map 0 and right as map 1 of the one-step problem
(docs/method.md#sequential-joining): only the common features enter it, with left's end pose as the
odometry. The features seen only by right, and right's poses, are placed afterwards,
``x = t* + R(phi*) z``. Two strategies order the joins:

- ``sequential``: the global map so far is left, local map k is right (k = 2 .. N);
- ``tree``: neighbouring pieces are joined pairwise, level by level, until one is left
  (the paper's Remark 8). The joins of a level are independent: they are computed
  together, as arrays, and ``jobs > 1`` splits the lower levels into aligned subtrees
  joined in parallel processes (the result does not depend on ``jobs``).

Spherical variances are propagated so that later joins weigh the estimates correctly, as
:mod:`mapjoin.covariance` describes (the joined pose r1 is left's end pose).
"""

from __future__ import annotations

import dataclasses
import logging
import math
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from functools import partial
from typing import Protocol

import numpy as np

from .arithmetic import backend
from .consistency import DEFAULT_GATE, Policy, calibrated, degrees_of_freedom, enforce, flags, level_variance_factors
from .errors import JoinError
from .covariance import (DEFAULT_COVARIANCE, CovarianceMode, batch_spherical_variances, fuse, placed_variances,
                         squared_norm, translation_variance)
from .drift import Retest, SequentialRecord, TreeRecord
from .joins import STRATEGIES, JoinRecord, JoinResult, Strategy, _Pieces
from .maps import GlobalMap, LocalMap, Provenance, first_duplicate, joined_map, locate
from .onestep import Solver, as_complex, global_orientation, linked_cost, point_constants
from .se2 import wrap

__all__ = ["STRATEGIES", "JoinRecord", "JoinResult", "Strategy", "certify_pair",
           "check_chain", "join", "join_sequential", "join_tree", "without_features"]

log = logging.getLogger("mapjoin")

#: stage 2 of the consistency test, passed in by the callers above (:func:`mapjoin.confirmation.confirm`):
#: ``(maps, result, strategy, gate)`` -> ``result`` with its failing joins confirmed on the exact problem; called
#: only for a result with a flagged join (so that a caller may import it then: cli/common.confirm)
Confirm = Callable[[Sequence[LocalMap], "JoinResult", Strategy, float], "JoinResult"]
#: the tree's hook between levels, ``(pieces, level)`` -> the pieces the next level joins (:func:`join_tree`)
Settle = Callable[[_Pieces, int], _Pieces]


class Associate(Protocol):
    """The hooks a join calls when the maps' feature ids are local to each map (the associator of
    :mod:`mapjoin.association`, docs/method.md#data-association): which rows are features joined already.
    ``count``: the compact ids handed out so far; ``row_ids``: each input row's (-1 before it is seen)."""

    count: int
    row_ids: np.ndarray

    def first(self, size: int) -> np.ndarray:
        """Compact ids of the first map's rows."""

    def next(self, k: int, positions: np.ndarray, variances: np.ndarray, link_xy: complex, link_phi: float,
             link_variances: tuple[float, float], z: np.ndarray, var: np.ndarray,
             solve: Callable[[np.ndarray, np.ndarray], _Joins]) -> tuple[np.ndarray, np.ndarray, int, _Joins]:
        """Map ``k`` against the map so far: its rows' order (matched first), their compact ids, how many match, and
        the join of those (``solve(compact ids, rows of z)``: the join reads the association's own statistic)."""

    def placed(self, k: int, t_variance: float, phi_variance: float) -> None:
        """Join ``k`` placed map ``k``'s start with these posterior variances."""

    def level(self, pieces: _Pieces, level: int) -> _Pieces:
        """The right pieces of a tree level's joins with their features renamed to their matches' ids."""


_ROW = [field.name for field in dataclasses.fields(JoinRecord)][1:]  # a report row: the fields after ``join``
_COMMON, _MINIMA, _COST, _LEVEL, _FEATURES = (_ROW.index(name) for name in
                                              ("common", "minima", "cost", "level", "features_cost"))


def check_chain(maps: Sequence[LocalMap]) -> None:
    """Raise JoinError unless each map starts at the end pose of the previous one, with no pose twice."""
    if not maps:
        raise JoinError("no local maps to join")
    starts = np.fromiter((m.start_id for m in maps), np.int64, len(maps))
    ends = np.fromiter((m.end_id for m in maps), np.int64, len(maps))
    broken = np.flatnonzero(starts[1:] != ends[:-1])
    if broken.size:
        previous, current = maps[broken[0]], maps[broken[0] + 1]
        raise JoinError(
            f"the pose chain does not connect: {current.name} starts at pose {current.start_id}, "
            f"but the map before it ({previous.name}) ends at pose {previous.end_id}")
    again = first_duplicate(np.concatenate([starts[:1], ends]))  # the chain's poses in order
    if again is not None:
        raise pose_twice(maps[again - 1])


def pose_twice(local_map: LocalMap) -> JoinError:
    """The error for ``local_map``, whose end pose is already in the chain before it."""
    return JoinError(f"pose {local_map.end_id} appears twice in the chain (again as the end of "
                     f"{local_map.name}); each map must end at a new pose")


@dataclass(frozen=True)
class _Joins:
    """The outcome of ``count`` independent joins (left i + right i), as arrays over the joins (numbers for one).

    ``turn`` is ``exp(i phi*)`` and ``t`` the translation (complex); ``rows`` are the joins'
    report entries: JoinRecord's fields after ``join``, which is numbered once all joins are known.
    """

    phi: np.ndarray
    turn: np.ndarray
    t: np.ndarray
    phi_variance: np.ndarray
    t_variance: np.ndarray
    rows: list[tuple]

    @property
    def cost(self) -> float:
        """The first join's minimum f_1(phi*) (the sequential strategy's one join)."""
        return self.rows[0][_COST]


def _solve_joins(pair: np.ndarray | None, count: int, z0: np.ndarray, var0: np.ndarray, z1: np.ndarray,
                 var1: np.ndarray, odometry_xy, odometry_phi, var_o, p_phi, solver: Solver,
                 labels: list[tuple[str, int, int, int]], level: int, warn: bool = True, link: bool = True) -> _Joins:
    """Algorithm 1 for one join on Python numbers (``pair`` None: the sequential strategy's step) or for
    ``count`` joins at once as arrays (a tree level): Theorem 1's constants, then the 1-D solve.

    Common feature j belongs to join ``pair[j]``; ``odometry_*`` are the end pose of each left piece
    and ``var_o``, ``p_phi`` its spherical variances. ``labels[i]`` names join i's right piece (name,
    start id, end id, its number of features) for the report (``warn``: as :func:`_row`).
    ``link=False`` joins by the features alone: phi* = phi0, the chi = 0 solution
    (docs/method.md#without-the-orientation-link), reported with one minimum.
    """
    k = point_constants(z0, var0, z1, var1, odometry_xy, var_o, pair)
    found = global_orientation(k.a0, k.phi0, odometry_phi, p_phi, solver)
    ops = backend(found.phi)
    where = ops.where
    features_cost = k.c0 - 2.0 * k.a0
    if link:
        phi, minima, iterations = found.phi, found.count, found.iterations
        information = k.a0 * ops.cos(phi - k.phi0) + 1.0 / p_phi  # f_1''(phi*) / 2
        cost, second = linked_cost(k, odometry_phi, p_phi, phi), found.count == 2
    else:
        phi, minima, iterations = wrap(k.phi0), ops.full(found.phi, 1), ops.full(found.phi, 0)
        information, cost, second = k.a0, features_cost, ops.full(found.phi, False)
    positive = information > 0
    phi_variance = where(positive, 1.0 / where(positive, information, 1.0), p_phi)
    turn = ops.cos(phi) + 1j * ops.sin(phi)
    # the other minimum's cost, where ``second`` (rarely any: most joins have one minimum)
    other_cost = linked_cost(k, odometry_phi, p_phi, found.other_phi) if ops.any(second) else found.other_phi
    common = [len(z0)] if pair is None else np.bincount(pair, minlength=count).tolist()
    solutions = ops.rows((found.a, found.c_phi, minima, phi, cost, where(second, found.other_phi, None),
                          where(second, other_cost, None), iterations, ops.full(phi, level), features_cost))
    rows = [_row(*label[:3], common, label[3], *solution, warn=warn)
            for label, common, solution in zip(labels, common, solutions)]
    return _Joins(phi, turn, k.mean0 - turn * k.mean1, phi_variance,
                  translation_variance(k.weight, k.mean1, phi_variance), rows)


def _row(name: str, start_id: int, end_id: int, common: int, size: int, *solution, warn: bool = True) -> tuple:
    """A join's report entry (JoinRecord's fields after ``join``); with ``warn``, warns when the join has
    no common feature."""
    if warn:
        _warn_if_unlinked(name, common)
    return (name, start_id, end_id, common, size - common, *solution)


def _warn_if_unlinked(name: str, common: int) -> None:
    """Warn that the map(s) ``name`` share no feature with what they are joined onto."""
    if not common:
        log.warning("%s shares no feature with the maps it is joined onto: it is placed by its "
                    "start pose alone (no correction of the map so far)", name)


def solve_widened(problems: list[tuple], solver: Solver) -> tuple[np.ndarray, np.ndarray]:
    """The minima (with the heading link, and without: ``c0 - 2 a0``) of ``problems``, one per join:
    ``(z0, var0, z1, var1, odometry_xy, odometry_phi, var_o, p_phi)`` with the drift already in the
    variances. One batch of Algorithm 1 (:func:`_solve_joins`): :data:`mapjoin.drift.SolveWidened`."""
    pair = [np.full(len(problem[0]), number) for number, problem in enumerate(problems)]
    z0, var0, z1, var1 = ([problem[i] for problem in problems] for i in range(4))
    count = len(problems)
    if count == 1:  # one problem on Python numbers (the same numbers as in a batch, at a fraction of its cost)
        odometry = [complex(problems[0][4]), *(float(value) for value in problems[0][5:8])]
        together = None
    else:
        odometry = [np.array([problem[4 + i] for problem in problems], dtype=complex if i == 0 else float)
                    for i in range(4)]
        together = np.concatenate(pair)
    joins = _solve_joins(together, count, np.concatenate(z0), np.concatenate(var0), np.concatenate(z1),
                         np.concatenate(var1), *odometry, solver, [("", 0, 0, 0)] * count, 0, warn=False)
    return (np.array([row[_COST] for row in joins.rows], dtype=float),
            np.array([row[_FEATURES] for row in joins.rows], dtype=float))


def _report(rows: Sequence[tuple], unlinked: frozenset[int] = frozenset(),
            gate: float = DEFAULT_GATE, retest: Retest | None = None, by_level: bool = False) -> tuple[JoinRecord, ...]:
    """The report: the joins' rows numbered from 1, each with its consistency check
    (:mod:`mapjoin.consistency`); ``unlinked`` are the numbers of the joins made by features alone;
    ``retest`` (:mod:`mapjoin.drift`) the drift-aware statistic of the joins whose own cost fails;
    ``by_level`` (the tree): each join's variance factor from its own level and the levels below
    (:func:`mapjoin.consistency.level_variance_factors`), else from the joins before it."""
    if not rows:
        return ()
    link = np.array([number not in unlinked for number in range(1, len(rows) + 1)])
    common, minima = np.array([row[_COMMON] for row in rows]), np.array([row[_MINIMA] for row in rows])
    dof = degrees_of_freedom(common, link)
    cost = np.array([row[_COST] for row in rows], dtype=float)
    factors = level_variance_factors(cost, dof, np.array([row[_LEVEL] for row in rows])) if by_level else None
    test = calibrated(cost, np.array([row[_FEATURES] for row in rows], dtype=float), dof, link, gate, retest, factors)
    flagged = flags(test.p, minima, gate)
    return tuple(JoinRecord(number, *row[:_FEATURES], fc, c, d, s, q, f, "joined" if ln else "features only")
                 for number, (row, fc, c, d, s, q, f, ln) in enumerate(zip(
                     rows, test.features_cost.tolist(), test.chi2.tolist(), dof.tolist(),
                     test.variance_factor.tolist(), test.p.tolist(), flagged.tolist(), link.tolist()), start=1))


def _place(turn, t, t_variance, phi_variance, points, variances, squared):
    """Points ``z`` of a right piece in left's frame, ``t + R(phi) z``, with their spherical variances.

    ``turn = exp(i phi)``; ``squared`` is ``|z|^2``. Numbers or arrays (broadcast).
    """
    return turn * points + t, placed_variances(t_variance, phi_variance, variances, squared)


def _move_poses(joins: _Joins, pair: np.ndarray, rows: np.ndarray, pose_xy: np.ndarray,
                pose_phi: np.ndarray, pose_variances: np.ndarray) -> None:
    """Poses ``rows`` of right pieces (join ``pair``) into left's frame, with their (var_xy, var_phi), in place."""
    xy = pose_xy[rows]
    pose_xy[rows], pose_variances[rows, 0] = _place(joins.turn[pair], joins.t[pair], joins.t_variance[pair],
                                                    joins.phi_variance[pair], xy, pose_variances[rows, 0],
                                                    squared_norm(xy))
    pose_phi[rows] = wrap(joins.phi[pair] + pose_phi[rows])
    pose_variances[rows, 1] += joins.phi_variance[pair]


def _set_junctions(joins: _Joins, rows: np.ndarray, pose_xy: np.ndarray, pose_phi: np.ndarray,
                   pose_variances: np.ndarray) -> None:
    """Each left piece's end pose (``rows``, one per join) becomes the joined pose r1 = (t*, phi*), in place."""
    pose_xy[rows], pose_phi[rows] = joins.t, joins.phi
    pose_variances[rows, 0], pose_variances[rows, 1] = joins.t_variance, joins.phi_variance


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
    pieces = _Pieces(piece, compact[order], as_complex(np.concatenate([m.features for m in maps]))[order],
                     feature_variances[order], index, as_complex(end_poses), end_poses[:, 2], pose_variances,
                     index, index)
    return feature_ids, pieces


def _global_map(maps: Sequence[LocalMap], feature_ids: np.ndarray, pieces: _Pieces, covariance: str,
                solver: str, strategy: str) -> GlobalMap:
    return joined_map(
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
                    progress: Callable[[int], None] | None = None, *, warn: bool = True,
                    gate: float = DEFAULT_GATE, unlinked: frozenset[int] = frozenset(),
                    associate: Associate | None = None) -> JoinResult:
    """Join ``maps`` (a connected chain) one after the other; the global frame is the first map's start.

    The global map lives in arrays indexed by compact feature id, so join k reads and writes
    only the rows of map k (its common features first, then its new ones: two slices); the
    1-D problem and the poses are Python numbers. ``progress`` is called with the number of maps joined.
    ``warn``: warn about each map that shares no feature with those before it (callers joining
    pieces of their own, which the user never sees, say False). ``gate``: the report's flags
    (:mod:`mapjoin.consistency`); ``unlinked``: the joins (numbers k, map k+1 onto maps 1..k) made by
    the features alone, without the heading link.
    ``associate`` (:mod:`mapjoin.association`): the maps' ids are local to each map; it numbers
    each map's features before its join.
    """
    feature_ids, pieces = _prepare(maps, covariance)
    # a feature is common in join k iff a map before k saw it: its first row is in an earlier map
    first_row = np.unique(pieces.feature_ids, return_index=True)[1]  # compact ids are 0 .. n-1
    offsets = np.searchsorted(pieces.feature_piece, np.arange(len(maps) + 1))
    seen_before = first_row[pieces.feature_ids] < offsets[pieces.feature_piece]
    if associate is not None:  # local ids say nothing: each map's rows stay in _prepare's order, as the associator's
        seen_before[:] = False
    segment = _Segment.of(pieces, seen_before, len(maps))
    if associate is not None:  # compact ids are handed out as features are matched: at most one per row
        first = segment.starts[1]
        segment.ids[:first], feature_ids = associate.first(first), np.zeros(len(segment.ids), dtype=np.int64)
    positions = np.zeros(len(feature_ids), dtype=complex)
    position_variances = np.zeros(len(feature_ids))
    record = SequentialRecord(pieces)
    report = _join_segment(segment, maps, positions, position_variances, solver, 1, progress, warn=warn,
                           unlinked=unlinked, associate=associate, record=record)
    retest = record.retest(segment.ids, segment.z, segment.var, pieces.feature_piece, segment.starts,
                           segment.ends_common, partial(solve_widened, solver=solver), segment.pose_xy, segment.pose_phi)
    if associate is not None:
        feature_ids = np.arange(associate.count)
        positions, position_variances = positions[:associate.count], position_variances[:associate.count]
    pieces = replace(pieces, feature_piece=np.zeros(len(feature_ids), dtype=np.intp),
                     feature_ids=np.arange(len(feature_ids)), features=positions,
                     feature_variances=position_variances, pose_xy=np.array(segment.pose_xy, dtype=complex),
                     pose_phi=np.array(segment.pose_phi), pose_variances=np.column_stack([segment.var_xy,
                                                                                          segment.var_phi]))
    return JoinResult(_global_map(maps, feature_ids, pieces, covariance, solver, "sequential"),
                      _report(report, unlinked, gate, retest))


@dataclass
class _Segment:
    """Maps 0 .. n-1 of a chain laid out for the sequential joins of maps 1 .. n-1 onto the map so far.

    Feature rows go map after map, each map's common features (seen by an earlier map) first,
    then its new ones, each part in the order given (by id): map k's rows are
    ``starts[k] .. starts[k+1]``, its common ones end at ``ends_common[k]``. ``ids`` are compact
    ids (indices into the global map's arrays). The end poses are Python numbers, as join k
    reads pose k-1 and moves pose k. A stream (:mod:`mapjoin.streaming`) lays out each chunk of
    maps as a segment whose map 0 is the previous chunk's last map, without feature rows.
    """

    ids: np.ndarray
    z: np.ndarray
    var: np.ndarray
    information: np.ndarray
    squared: np.ndarray
    starts: list[int]
    ends_common: list[int]
    pose_xy: list[complex]
    pose_phi: list[float]
    var_xy: list[float]
    var_phi: list[float]

    @classmethod
    def of(cls, pieces: _Pieces, seen_before: np.ndarray, count: int) -> _Segment:
        """The segment of ``count`` single-map pieces (rows grouped by piece, by id within one); ``seen_before``:
        each row's feature was seen by an earlier map."""
        offsets = np.searchsorted(pieces.feature_piece, np.arange(count + 1))
        order = np.lexsort((~seen_before, pieces.feature_piece))  # stable: the given order within each part
        z, var = pieces.features[order], pieces.feature_variances[order]
        ends_common = offsets[:-1] + np.bincount(pieces.feature_piece[seen_before], minlength=count)
        return cls(pieces.feature_ids[order], z, var, 1.0 / var, squared_norm(z), offsets.tolist(),
                   ends_common.tolist(), pieces.pose_xy.tolist(), pieces.pose_phi.tolist(),
                   pieces.pose_variances[:, 0].tolist(), pieces.pose_variances[:, 1].tolist())


def _join_segment(segment: _Segment, maps: Sequence[LocalMap], positions: np.ndarray, position_variances: np.ndarray,
                  solver: Solver, number: int, progress: Callable[[int], None] | None = None, *, warn: bool = True,
                  unlinked: frozenset[int] = frozenset(), associate: Associate | None = None,
                  record: SequentialRecord | None = None) -> list[tuple]:
    """Join maps 1 .. n-1 of ``segment`` (``maps`` are its maps) onto the global map so far, in place: its
    ``positions`` and ``position_variances`` (by compact id) and the segment's poses; map 0's own feature
    rows, if any, are placed first (the chain's first map). ``number`` is the join number of map 1. The joins'
    report rows (:func:`_report` numbers them). ``record`` keeps what each join read (:mod:`mapjoin.drift`)."""
    ids, z, var, information, squared = segment.ids, segment.z, segment.var, segment.information, segment.squared
    starts, ends_common = segment.starts, segment.ends_common
    pose_xy, pose_phi, var_xy, var_phi = segment.pose_xy, segment.pose_phi, segment.var_xy, segment.var_phi
    positions[ids[:starts[1]]], position_variances[ids[:starts[1]]] = z[:starts[1]], var[:starts[1]]
    report: list[tuple] = []
    if progress:
        progress(number)
    for k in range(1, len(maps)):
        join_number = number + k - 1
        rows = slice(starts[k], starts[k + 1])
        local_map = maps[k]
        # the join's arguments after its common features' (its link and report label)
        given = (pose_xy[k - 1], pose_phi[k - 1], var_xy[k - 1], var_phi[k - 1], solver,
                 [(local_map.name, local_map.start_id, local_map.end_id, local_map.size)], join_number, warn,
                 join_number not in unlinked)
        if associate is not None:  # map k's rows: its matches of the map so far first, then its new features
            z_k, var_k = z[rows], var[rows]
            order_k, ids[rows], common, joins = associate.next(
                k, positions, position_variances, pose_xy[k - 1], pose_phi[k - 1], (var_xy[k - 1], var_phi[k - 1]),
                z_k, var_k, lambda left, right: _solve_joins(None, 1, positions[left], position_variances[left],
                                                             z_k[right], var_k[right], *given))
            for array in (z, var, information, squared):
                array[rows] = array[rows][order_k]
            ends_common[k] = starts[k] + common
        common = ends_common[k] - starts[k]
        shared = ids[starts[k]:ends_common[k]]
        z0, var0 = positions[shared], position_variances[shared]
        if associate is None:
            joins = _solve_joins(None, 1, z0, var0, z[rows][:common], var[rows][:common], *given)
        if record is not None:
            record.joined(z0, var0, pose_xy[k - 1], pose_phi[k - 1], var_xy[k - 1], var_phi[k - 1],
                          joins.t_variance, joins.phi_variance)
        move = (joins.turn, joins.t, joins.t_variance, joins.phi_variance)
        placed, spread = _place(*move, z[rows], var[rows], squared[rows])
        positions[shared], position_variances[shared] = fuse(z0, var0, placed[:common], information[rows][:common])
        fresh = ids[ends_common[k]:starts[k + 1]]
        positions[fresh], position_variances[fresh] = placed[common:], spread[common:]
        pose_xy[k], var_xy[k] = _place(*move, pose_xy[k], var_xy[k], squared_norm(pose_xy[k]))
        pose_phi[k], var_phi[k] = wrap(joins.phi + pose_phi[k]), var_phi[k] + joins.phi_variance
        pose_xy[k - 1], pose_phi[k - 1], var_xy[k - 1], var_phi[k - 1] = move[1], joins.phi, move[2], move[3]
        if associate is not None:  # the junction's posterior: the chain's drift the next associations allow for
            associate.placed(k, move[2], move[3])
        report += joins.rows
        if progress:
            progress(join_number + 1)
    return report


def _join_level(pieces: _Pieces, labels: _Labels, solver: Solver, level: int, associate: Associate | None = None,
                record: TreeRecord | None = None) -> tuple[_Pieces, list[tuple]]:
    """Join pieces 2i and 2i+1 for every i (an odd last piece passes through): one level of the tree.
    ``associate`` first renames right pieces' features to the ids of their matches in the left ones;
    ``record`` keeps what the joins read (:mod:`mapjoin.drift`)."""
    if associate is not None:
        pieces = associate.level(pieces, level)
    count = pieces.count // 2
    parent = pieces.feature_piece // 2
    right = (pieces.feature_piece % 2 == 1) & (parent < count)
    left_rows, right_rows = np.flatnonzero(~right), np.flatnonzero(right)
    span = int(pieces.feature_ids.max(initial=0)) + 1
    left_keys = parent[left_rows] * span + pieces.feature_ids[left_rows]  # sorted: pieces in order, ids sorted
    right_keys = parent[right_rows] * span + pieces.feature_ids[right_rows]
    position, common = locate(left_keys, right_keys)
    lc, rc = left_rows[position[common]], right_rows[common]

    ends = np.searchsorted(pieces.pose_piece, np.arange(pieces.count), side="right") - 1  # each piece's end row
    left_end = ends[0:2 * count:2]
    sizes = np.bincount(pieces.feature_piece, minlength=pieces.count)[1:2 * count:2].tolist()
    rights = zip(pieces.first[1:2 * count:2].tolist(), pieces.last[1:2 * count:2].tolist(), sizes)
    problem = (pieces.features[lc], pieces.feature_variances[lc], pieces.features[rc], pieces.feature_variances[rc])
    odometry = (pieces.pose_xy[left_end], pieces.pose_phi[left_end], pieces.pose_variances[left_end, 0],
                pieces.pose_variances[left_end, 1])
    joins = _solve_joins(parent[rc], count, *problem, *odometry, solver,
                         [(labels.run(first, last), labels.start_ids[first], labels.end_ids[last], size)
                          for first, last, size in rights], level)
    if record is not None:
        record.level(level, parent[rc], pieces.feature_ids[lc], None if associate is None else associate.row_ids.copy(),
                     pieces.last[0:2 * count:2], *problem, odometry, joins.t_variance, joins.phi_variance)

    features, feature_variances = pieces.features.copy(), pieces.feature_variances.copy()
    pair, z = parent[right_rows], pieces.features[right_rows]
    placed, spread = _place(joins.turn[pair], joins.t[pair], joins.t_variance[pair], joins.phi_variance[pair], z,
                            pieces.feature_variances[right_rows], squared_norm(z))
    features[right_rows], feature_variances[right_rows] = placed, spread
    features[lc], feature_variances[lc] = fuse(features[lc], feature_variances[lc], placed[common],
                                                1.0 / pieces.feature_variances[rc])
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
                 progress: Callable[[int], None] | None = None, associate: Associate | None = None,
                 record: TreeRecord | None = None, settle: Settle | None = None) -> tuple[_Pieces, list[tuple]]:
    """Join levels from ``level`` on until one piece is left; the joins' report rows. ``settle``: see
    :func:`join_tree`."""
    records: list[tuple] = []
    while pieces.count > 1:
        level += 1
        pieces, joined = _join_level(pieces, labels, solver, level, associate, record)
        if settle is not None:
            pieces = settle(pieces, level)
        records += joined
        if progress:
            progress(len(records) + 1)
    return pieces, records


def _subtree(job: tuple[_Pieces, _Labels, Solver]) -> tuple[_Pieces, list[tuple], TreeRecord]:
    """A worker process's share: one aligned block of pieces joined into one, and what its joins read
    (:mod:`mapjoin.drift`). It does not warn: the parent (:func:`join_tree`) warns for its rows, so that one
    process's logging says (and counts) everything."""
    pieces, labels, solver = job
    log.disabled = True
    record = TreeRecord()
    return (*_join_levels(pieces, labels, solver, 0, record=record), record)


def join_tree(maps: Sequence[LocalMap], covariance: CovarianceMode = DEFAULT_COVARIANCE,
              solver: Solver = "bisection", jobs: int = 1,
              progress: Callable[[int], None] | None = None, associate: Associate | None = None, *,
              gate: float = DEFAULT_GATE, settle: Settle | None = None) -> JoinResult:
    """Join ``maps`` pairwise, level by level (Remark 8); ``jobs`` processes share the lower levels.

    With ``jobs > 1`` the maps are cut into aligned blocks of 2^L maps (at least ``jobs``
    of them), each joined to one piece in a worker, exactly as the single-process tree
    would; the parent joins the blocks' results. Join numbers follow the levels. ``associate``: as for
    :func:`join_sequential` (in one process only). ``settle(pieces, level)`` (in one process only) is given
    each level's joined pieces and returns the pieces the next level joins (the hierarchical start of the
    exact solve, :mod:`mapjoin.refine.hierarchy`, solves them exactly).
    """
    if jobs < 1:
        raise ValueError(f"jobs must be at least 1, got {jobs}")
    if associate is not None and jobs > 1:
        raise ValueError("data association runs the tree in one process (jobs=1)")
    if settle is not None and jobs > 1:
        raise ValueError("settling the tree's pieces runs the tree in one process (jobs=1)")
    feature_ids, pieces = _prepare(maps, covariance)
    labels = _Labels.of(maps)
    records: list[tuple] = []
    record, chain = TreeRecord(), pieces
    depth = 0
    if jobs > 1 and len(maps) >= 2 * jobs:
        depth = int(math.floor(math.log2(len(maps) / jobs)))
        size = 2**depth
        blocks = [pieces.block(start, min(start + size, len(maps))) for start in range(0, len(maps), size)]
        from concurrent.futures import ProcessPoolExecutor  # multiprocessing: imported only when used

        with ProcessPoolExecutor(max_workers=min(jobs, os.cpu_count() or jobs)) as pool:
            results = list(pool.map(_subtree, [(b, labels, solver) for b in blocks]))
        for _, block_records, block_record in results:
            records += block_records
            record.extend(block_record)
        for row in records:
            _warn_if_unlinked(row[0], row[3])
        pieces = _concatenate([(start // size, block) for start, (block, *_) in
                               zip(range(0, len(maps), size), results)])
        if progress:
            progress(len(records) + 1)
    pieces, upper = _join_levels(pieces, labels, solver, depth,
                                 (lambda done: progress(done + len(records))) if progress else None, associate, record,
                                 settle)
    records += upper
    records.sort(key=lambda row: row[_LEVEL])  # by level, stable: chain order within a level
    retest = record.retest(chain, partial(solve_widened, solver=solver))
    if associate is not None:  # the compact ids the associator handed out
        feature_ids = np.arange(associate.count)
    return JoinResult(_global_map(maps, feature_ids, pieces, covariance, solver, "tree"),
                      _report(records, gate=gate, retest=retest, by_level=True))


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
         progress: Callable[[int], None] | None = None, *, gate: float = DEFAULT_GATE,
         on_inconsistent: Policy = "warn", associate: Associate | None = None,
         confirm: Confirm | None = None, settle: Settle | None = None) -> JoinResult:
    """Join ``maps`` with ``strategy`` (``jobs`` only matters for the tree; ``associate``: see
    :func:`join_sequential`, used by :func:`mapjoin.association.join_associated`).

    Every join is checked (:mod:`mapjoin.consistency`): a join whose chi-square p-value is below
    ``gate``, or that has two minima, is flagged in the report, and ``on_inconsistent`` says what
    happens then: ``warn`` (one warning per flagged map), ``stop`` (:class:`JoinError` naming the
    map) or ``skip`` (sequential only: such a map is joined by its features alone or left out; see
    :func:`mapjoin.consistency.enforce`). ``confirm`` (:func:`mapjoin.confirmation.confirm`, passed in
    by the callers above this module): the joins that fail the gate are confirmed on the exact problem
    before the policy acts (not with ``associate``: the maps' ids are local); it is called only when a join
    is flagged. ``settle``: the tree's hook between levels (:func:`join_tree`).
    """
    if associate is not None:
        confirm = None
    if on_inconsistent == "skip" and associate is not None:
        raise ValueError("on_inconsistent='skip' re-joins the chain with the maps' own ids: not with association")
    if on_inconsistent == "skip" and strategy != "sequential":
        raise ValueError("on_inconsistent='skip' re-joins the chain map by map: it needs strategy='sequential'")
    if strategy == "sequential":
        result = join_sequential(maps, covariance, solver, progress, gate=gate, associate=associate)
    elif strategy == "tree":
        result = join_tree(maps, covariance, solver, jobs, progress, associate, gate=gate, settle=settle)
    else:
        raise ValueError(f"unknown strategy {strategy!r}; expected one of {', '.join(STRATEGIES)}")
    def confirmed(chain: Sequence[LocalMap], joined: JoinResult, joined_by: Strategy) -> JoinResult:
        flagged = confirm is not None and any(record.flag for record in joined.report)
        return confirm(chain, joined, joined_by, gate) if flagged else joined

    result = confirmed(maps, result, strategy)

    def rejoin(unlinked: frozenset[int], left_out: frozenset[int]) -> JoinResult:
        chain = [without_features(m) if k in left_out else m for k, m in enumerate(maps)]
        rejoined = join_sequential(chain, covariance, solver, warn=False, gate=gate, unlinked=unlinked)
        return confirmed(chain, rejoined, "sequential")

    return enforce(result, on_inconsistent, gate, rejoin if strategy == "sequential" else None)


def without_features(local_map: LocalMap) -> LocalMap:
    """``local_map`` with its end pose only (a map the skip policy leaves out: its odometry stays in the chain)."""
    return LocalMap(local_map.name, local_map.start_id, local_map.end_id, local_map.end_pose,
                    np.zeros(0, dtype=np.int64), np.zeros((0, 2)), np.zeros(0), local_map.pose_variances,
                    None if local_map.covariance is None else local_map.covariance[:3, :3])


def certify_pair(first: LocalMap, second: LocalMap, covariance: CovarianceMode = DEFAULT_COVARIANCE,
                 solver: Solver = "bisection") -> JoinRecord:
    """The report of joining ``second`` onto ``first``: a, C_phi, the minima and the optimum."""
    if not np.isin(second.feature_ids, first.feature_ids).any():
        raise JoinError(
            f"{first.name} and {second.name} share no feature: the join would rest on the end pose "
            f"of {first.name} alone, so there is no feature evidence whose minima could be counted")
    return join_sequential([first, second], covariance, solver).report[0]
