"""The hooks :mod:`mapjoin.joining` calls before and after each join of a data association, and the state they keep
between joins (docs/method.md#data-association).

:class:`_Associator` is the ``associate=`` argument of :func:`mapjoin.joining.join` (its ``Associate`` protocol).
Before each sequential join (:meth:`~_Associator.next`) or tree level (:meth:`~_Associator.level`) it associates the
right piece's features with the left piece's (:func:`~mapjoin.association.drifted.match_with_drift`; a tree level
also by step 2's junction rule, :mod:`mapjoin.association.junction`) and names them by the ids of their matches, the
others by new ids; after each join it records what the later joins' drift needs
(:class:`~mapjoin.association.feature_drift.SightingDrift`: the junctions' posteriors, each feature's sightings, the
chain's ties of step 7). Between joins it keeps each feature's fused covariance and the maps that saw it.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING

import numpy as np

from ..maps import locate
from .covariance_blocks import fused, rotated
from .drift_evidence import drifting
from .drift_scale import DriftScale
from .drifted import _corrected, _pair_noise, match_with_drift, with_drift
from .feature_drift import SightingDrift
from .gate import sighting_bits
from .guard import Solve, Solved, inconsistent, kept_majority, outlying, widened
from .junction import free_pairs, own_link_variances, undrifted
from .junction_drift import fit_variances
from .link_frame import LinkFrame
from .link_pairs import linked_again
from .loop_scope import voters_drift
from .rounds import Matches, _median, _same, match_features

if TYPE_CHECKING:
    from ..joins import _Pieces

__all__ = ["TIE_SUPPORT"]

#: a join ties its map to the map that last saw its drifted pairs' features when it has at least this many (step 7):
#: one, since a chain of small maps meets its old features one to three a join (VicPark 6898: with 4, as a loop
#: closure's support, the chain was tied almost nowhere and D summed every junction since; benchmarks/README.md)
TIE_SUPPORT = 1


def _asked_once(pair_drift: Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray]
                ) -> Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray]:
    """``pair_drift`` remembering its last pairs and answers: step 7 asks it for a join's pairs, the chain's ties ask
    it again after step 6, which mostly changed few pairs. A pair's answer is its own (its left row, right row and
    noise decide it, elementwise), so only the pairs not asked last time are asked (a tree level's step 6 adds its
    loop closures' and junctions' pairs to thousands)."""
    last: list = []

    def remembered(i: np.ndarray, j: np.ndarray, noise: np.ndarray) -> np.ndarray:
        if last and _same(last[0], i) and _same(last[1], j) and _same(last[3], noise):
            return last[2]
        if not (last and len(last[0])):
            last[:] = [i, j, pair_drift(i, j, noise), noise]
            return last[2]
        before_i, before_j, before, before_noise = last
        span = np.int64(max(int(i.max(initial=0)), int(before_i.max(initial=0))) + 1)
        keys = before_j.astype(np.int64) * span + before_i
        order = np.argsort(keys)
        position, known = locate(keys, j.astype(np.int64) * span + i, order)
        known &= before_noise[position] == noise
        answer = np.empty(len(i))
        answer[known] = before[position[known]]
        fresh = ~known
        if fresh.any():
            answer[fresh] = pair_drift(i[fresh], j[fresh], noise[fresh])
        last[:] = [i, j, answer, noise]
        return answer

    return remembered


class _Associator:
    """The hooks :mod:`mapjoin.joining` calls before each join (``associate=``), numbering features as they are
    matched, and after each sequential join (:meth:`placed`: its posterior, for the drift; the tree's are read
    from the pieces at the next level). Compact ids (indices of the joins' arrays) are handed out in order of
    first sighting; the tree renames a right piece's features to the left piece's ids, so each input row's
    current id is kept. ``points``: each map's feature positions (sorted by id, complex), ``end_poses`` the
    maps' end poses, for :class:`mapjoin.association.feature_drift.SightingDrift`; ``full_covariances`` each map's
    full covariance or None, ``orders`` the positions of its sorted ids in it, for the junctions' own drift
    (:mod:`mapjoin.association.junction_drift`); ``pose_variances`` the maps' marginal end-pose variances (their own
    dead reckoning, for the tree joins that drifted); ``end_relatives`` each map's features relative to its end pose
    (:func:`mapjoin.association.covariance_blocks.end_relative`; None for a map without a full covariance or whose
    are not read), which the next join (a sequential one, or the tree's first level's) compares in the link's frame
    (:mod:`mapjoin.association.link_frame`)."""

    def __init__(self, covariances: Sequence[np.ndarray], points: Sequence[np.ndarray], end_poses: np.ndarray,
                 gate: float, margin: float, full_covariances: Sequence[np.ndarray | None],
                 orders: Sequence[np.ndarray], pose_variances: np.ndarray | None = None,
                 end_relatives: Sequence[tuple[np.ndarray, np.ndarray] | None] | None = None):
        self.gate, self.margin = gate, margin
        self.full_covariances = full_covariances
        self.feature_index = np.concatenate([np.zeros(0, np.intp), *orders])  # each row's feature in its map
        self.drift_scale = DriftScale(gate)  # the share of the junctions' excess drift the data bear out
        self.offsets = np.concatenate([[0], np.cumsum([len(c) for c in covariances])]).astype(np.intp)
        self.row_ids = np.full(self.offsets[-1], -1, dtype=np.int64)  # input rows in _prepare's order
        self.row_covariances = np.concatenate([np.zeros((0, 3)), *covariances])  # in each map's frame
        self.row_maps = np.repeat(np.arange(len(covariances)), np.diff(self.offsets))
        ends = end_relatives if end_relatives is not None else [None] * len(covariances)
        self.end_known = np.array([end is not None for end in ends], dtype=bool)  # each map's, if read and known
        self.row_end_points = np.concatenate([np.zeros(0, complex), *(end[0] for end in ends if end is not None)])
        self.row_end_covariances = np.concatenate([np.zeros((0, 3)), *(end[1] for end in ends if end is not None)])
        # each row's place among those (the maps without them have none)
        self.row_end_index = np.cumsum(self.end_known[self.row_maps]) - 1
        # the chain's drift between sightings and links (each map's rows' positions in its frame: their sightings)
        self.drift = SightingDrift.of(end_poses, len(self.row_ids), pose_variances)
        self.row_points = np.concatenate([np.zeros(0, complex), *points])
        self.links = np.zeros(0, np.intp)  # the tree's last level's junctions (left pieces' end pose rows)
        self.end_points = end_poses[:, 0] + 1j * end_poses[:, 1]  # each map's end position in its frame
        self.own_pose_variances = np.zeros((0, 2))  # each map's end-pose variance in its frame (the tree's first level)
        self.count = 0
        # each compact id's 2 x 2 covariance relative to the maps that saw it (rows [xx, xy, yy]), in its piece's
        # frame: the sightings' marginal covariances fused as independent (their common drift is the link's error)
        self.covariances = np.zeros((max(len(self.row_ids), 1), 3))
        self.row_sightings = sighting_bits(np.repeat(np.arange(len(covariances)), np.diff(self.offsets)))
        self.sightings = np.zeros((len(self.covariances), 2), dtype=np.uint64)  # each compact id's maps (bits)
        self.counts: list[tuple[int, int, int]] = []  # (ambiguous, rejected, guarded) per join, in the report's order
        #: a sequential join's guard left pairs out (step 9): the chain's drift is too small, and every later join
        #: associates with it widened (:func:`mapjoin.association.guard.widened`)
        self.drift_too_small = False

    def _fresh(self, number: int) -> np.ndarray:
        ids = np.arange(self.count, self.count + number)
        self.count += number
        if self.count > len(self.covariances):  # the tree hands out new ids at every level
            more = max(self.count, len(self.covariances))
            self.covariances = np.concatenate([self.covariances, np.zeros((more, 3))])
            self.sightings = np.concatenate([self.sightings, np.zeros((more, 2), dtype=np.uint64)])
        self.drift = self.drift.grown(self.count)
        return ids

    def _sighted(self, ids: np.ndarray, covariances: np.ndarray, sightings: np.ndarray, matched: np.ndarray | slice,
                 new: np.ndarray | slice) -> None:
        """Features ``ids`` seen with ``covariances`` (in their frame) by maps ``sightings``: fused into the
        ``matched`` ones, the ``new`` ones (the others; a mask and its negation, or two slices) new."""
        self.covariances[ids[matched]] = fused(self.covariances[ids[matched]], covariances[matched])
        self.covariances[ids[new]] = covariances[new]
        self.sightings[ids[matched]] |= sightings[matched]
        self.sightings[ids[new]] = sightings[new]

    # sequential strategy -----------------------------------------------------------------
    def first(self, size: int) -> np.ndarray:
        """Compact ids of the first map's rows: all new."""
        ids = self._fresh(size)
        self.row_ids[:size] = ids
        self.covariances[ids] = self.row_covariances[:size]
        self.sightings[ids] = self.row_sightings[:size]
        self.drift.seen(ids, self.row_maps[:size], self.row_points[:size])
        return ids

    def placed(self, k: int, t_variance: float, phi_variance: float) -> None:
        """Join ``k`` placed map ``k``'s start (junction ``k``) with these posterior variances (the drift's sums),
        and the excess of the junction's own drift over them (:meth:`_junction_excess`)."""
        excess = self._junction_excess(np.array([k]), np.array([t_variance]), np.array([phi_variance]))
        self.drift.placed(k, t_variance, phi_variance, (float(excess[0, 0]), float(excess[0, 1])))

    def _rows_of(self, maps: np.ndarray) -> np.ndarray:
        """The input rows of ``maps`` (ascending map indices), in order: their offsets' ranges concatenated (one map, a
        sequential junction's: its range, one call instead of seven)."""
        if len(maps) == 1:
            return np.arange(self.offsets[maps[0]], self.offsets[maps[0] + 1])
        starts, lengths = self.offsets[maps], self.offsets[maps + 1] - self.offsets[maps]
        within = np.arange(lengths.sum()) - np.repeat(np.cumsum(lengths) - lengths, lengths)
        return np.repeat(starts, lengths) + within

    def _junction_excess(self, junctions: np.ndarray, t_variances: np.ndarray, phi_variances: np.ndarray
                         ) -> np.ndarray:
        """How much more each junction ``k`` of ``junctions`` (ascending) may be off than its posterior variances
        say (rows: translation, turn; 0 when not): the variance of a rigid fit of the features maps ``k - 1`` and
        ``k`` share, as map ``k - 1``'s covariance (its full one; else its features' blocks) knows them relative to
        its start (:func:`mapjoin.association.junction_drift.fit_variances`; docs/method.md#data-association,
        step 6). The shared rows of all the junctions are found at once, by (map, id) keys sorted once: a tree level
        places up to half the maps' junctions, and a set test (``np.isin``) each cost more than their fits."""
        fits = np.zeros((len(junctions), 2))
        before = self._rows_of(junctions - 1)
        after = self._rows_of(junctions)
        span = np.int64(self.count + 1)  # ids are below count (-1: a row not yet associated)
        keys = (self.row_maps[before] + 1) * span + self.row_ids[before]  # each row as map k's would be keyed
        shared = before[locate(np.sort(self.row_maps[after] * span + self.row_ids[after]), keys)[1]]
        bounds = ([[0], [len(shared)]] if len(junctions) == 1  # one junction (sequential): every shared row is its
                  else np.searchsorted(self.row_maps[shared], np.stack([junctions - 1, junctions])).tolist())
        for n, (k, start, stop) in enumerate(zip(junctions.tolist(), *bounds)):
            if start == stop:
                continue
            rows = shared[start:stop]
            full = self.full_covariances[k - 1]
            if full is None:
                covariance = np.zeros((len(rows), 2, len(rows), 2))
                diagonal = np.arange(len(rows))
                covariance[diagonal, :, diagonal, :] = self.row_covariances[rows][:, [[0, 1], [1, 2]]]
                covariance = covariance.reshape(2 * len(rows), 2 * len(rows))
            else:
                index = (3 + 2 * self.feature_index[rows][:, None] + np.arange(2)).ravel()
                covariance = full[np.ix_(index, index)]
            fits[n] = fit_variances(covariance, self.row_points[rows], complex(self.end_points[k - 1]))
        return np.maximum(fits - np.column_stack([t_variances, phi_variances]), 0.0)

    def _link_frame(self, link_map: int) -> LinkFrame | None:
        """The left features map ``link_map`` saw (compact ids: the rows of the map so far), relative to its end pose,
        the next join's link (:mod:`mapjoin.association.link_frame`); None when the map has no full covariance."""
        if not self.end_known[link_map]:
            return None
        rows = np.arange(self.offsets[link_map], self.offsets[link_map + 1])
        ids, at = self.row_ids[rows], self.row_end_index[rows]
        order = np.argsort(ids)
        return LinkFrame(ids[order], self.row_end_points[at[order]], self.row_end_covariances[at[order]])

    def _first_level_frame(self, left: np.ndarray) -> LinkFrame:
        """The tree's first level's left features (``left``: the level's rows, at this level the input rows,
        ascending) relative to their map's end pose, their join's link, for the maps with them (a full covariance;
        :meth:`_link_frame`'s for a sequential join; :mod:`mapjoin.association.link_frame`)."""
        known = np.flatnonzero(self.end_known[self.row_maps[left]])
        at = self.row_end_index[left[known]]
        return LinkFrame(known, self.row_end_points[at], self.row_end_covariances[at])

    def next(self, k: int, positions: np.ndarray, variances: np.ndarray, link_xy: complex, link_phi: float,
             link_variances: tuple[float, float], z: np.ndarray, var: np.ndarray, solve: Solve
             ) -> tuple[np.ndarray, np.ndarray, int, Solved]:
        """Map ``k`` (rows ``z``, ``var``) against the global map so far (compact ids 0 .. count-1): the order of
        its rows (matched first, then new, each in input order), their compact ids in that order, how many are
        matched and their join (``solve(left ids, right rows)``: the one-step join of these pairs, which step 9
        reads, :mod:`mapjoin.association.guard`)."""
        used = self.count
        rows = slice(self.offsets[k], self.offsets[k + 1])
        right_covariances = rotated(self.row_covariances[rows], link_phi)
        nothing = np.zeros(len(z))  # map k's own features: no drift relative to its start
        drift = (*self.drift.before(slice(None, used), k - 1), nothing, nothing)
        pair_drift = _asked_once(lambda i, j, noise: self.drift.settled(i, k - 1, level=noise, direct=drift[0][i]))
        if self.drift_too_small:
            drift, pair_drift = widened(drift, pair_drift)

        def associated(drift: tuple[np.ndarray, ...], pair_drift: Callable) -> Matches:
            return match_with_drift(positions[:used], self.covariances[:used], np.zeros(used, np.intp),
                                    np.array([link_xy]), np.array([link_phi]), np.array([link_variances]), z,
                                    right_covariances, np.zeros(len(z), np.intp), drift, self.gate, self.margin,
                                    self.sightings[:used], self.row_sightings[rows], pair_drift,
                                    voters_drift(self.drift, None, None),
                                    lambda pair_left, pair_right: self.drift.across_link(pair_left, k - 1,
                                                                                         z[pair_right]),
                                    self._link_frame(k - 1))

        found = associated(drift, pair_drift)
        solved, guarded = solve(found.left, found.right), 0
        if inconsistent(solved.cost, len(found.right)) and outlying(  # step 9
                np.abs(positions[found.left] - (solved.t + solved.turn * z[found.right])) ** 2
                / (variances[found.left] + var[found.right]), self.gate):
            again = associated(*widened(drift, pair_drift))
            left_out = kept_majority(found.left, found.right, again.left, again.right)
            if left_out is not None:
                found, solved, guarded = again, solve(again.left, again.right), left_out
                self.drift_too_small |= left_out > 0
        self.counts.append((int(found.ambiguous[0]), int(found.rejected[0]), guarded))
        left_ids = found.left
        noise = _pair_noise(self.covariances, right_covariances, left_ids, found.right)
        drifts = pair_drift(found.left, found.right, noise)
        strain = self._tie(found, positions[:used], left_ids, np.array([link_xy]), np.array([link_phi]), z,
                           np.zeros(len(z), np.intp), noise, drifts, np.array([k]))
        if not self.drift_too_small:  # once step 9 widened the drift, the scale it had is moot
            self._drift_observed(found, positions, np.array([link_xy]), np.array([link_phi]),
                                 np.array([link_variances]), z, np.zeros(len(z), np.intp), noise, drifts,
                                 drift[0][left_ids] + self.drift.strain[left_ids],
                                 lambda along: self.drift.excess_before(left_ids[along], k - 1))
        matched = np.zeros(len(z), dtype=bool)
        matched[found.right] = True
        order = np.concatenate([found.right, np.flatnonzero(~matched)])  # found.right is sorted
        ids = np.empty(len(z), dtype=np.int64)
        ids[:len(found.right)] = found.left
        ids[len(found.right):] = self._fresh(len(z) - len(found.right))
        self._sighted(ids, right_covariances[order], self.row_sightings[rows][order], slice(None, len(found.right)),
                      slice(len(found.right), None))
        self.row_ids[self.offsets[k] + order] = ids
        points, matched_count = self.row_points[rows][order], len(found.right)
        self.drift.seen_again(ids[:matched_count], k, points[:matched_count], strain)
        self.drift.seen(ids[matched_count:], k, points[matched_count:])
        return order, ids, len(found.right), solved

    def _drift_observed(self, found: Matches, left: np.ndarray, link_xy: np.ndarray, link_phi: np.ndarray,
                        link_variances: np.ndarray, right: np.ndarray, right_join: np.ndarray, noise: np.ndarray,
                        drift: np.ndarray, direct: np.ndarray, excess: Callable[[np.ndarray], np.ndarray],
                        read: np.ndarray | None = None) -> None:
        """A join's or a tree level's pairs (``found``: left rows of ``left``, right rows of ``right`` by
        ``right_join``; ``noise`` and ``drift``, each pair's, :func:`_pair_noise` and the join's ``pair_drift``, as
        :meth:`_tie` takes them) that drifted along the chain tell the drift's scale: those whose ``D`` reaches their
        noise and is the direct way's plus the features' strain (``direct``, each pair's: no tie shortened it), their
        squared offsets around the uncorrected link against their noise and the link's spread
        (``sigma_o^2 + p_phi |z|^2 / 2``) and their drift's posterior and ``excess`` parts (``excess(mask)``: the
        masked pairs', at scale 1; :class:`mapjoin.association.drift_scale.DriftScale`, each join one observation);
        once the estimate moves, the drift's sums take its share of the excess (docs/method.md#data-association, step
        6). ``read`` (None: all): the pairs whose join read the excess in its drift (a tree's drifted joins); the
        others tell nothing of it. A join without such pairs (most) is done here: the estimate observes nothing
        (:meth:`~mapjoin.association.drift_scale.DriftScale.observe` of no pair changes nothing, as it estimates
        only after pairs that grew its joins), so neither their excess nor their offsets are computed."""
        along = (drift >= noise) & (drift == direct) & (True if read is None else read)
        if not along.any():
            return
        join = right_join[found.right[along]]
        right_points = right[found.right[along]]
        offset2 = np.abs(left[found.left[along]] - link_xy[join] - np.exp(1j * link_phi[join]) * right_points) ** 2
        spread = noise[along] + link_variances[join, 0] + link_variances[join, 1] * np.abs(right_points) ** 2 / 2
        excess = excess(along)
        if self.drift_scale.observe(offset2, spread, drift[along] - self.drift.scale[0] * excess, excess, drift[along],
                                    join):
            self.drift.rescaled(self.drift_scale.scale)

    def _tie(self, found: Matches, left: np.ndarray, left_ids: np.ndarray, link_xy: np.ndarray, link_phi: np.ndarray,
             right: np.ndarray, right_join: np.ndarray, noise: np.ndarray, drift: np.ndarray, junctions: np.ndarray
             ) -> np.ndarray:
        """The strain of each of ``found``'s pairs (a quarter of its squared residual around the link as the join's
        pairs corrected it: a fused feature sits about halfway), and the chain's ties: a join whose pairs include
        :data:`TIE_SUPPORT` drifted ones (``drift``: each pair's before the join, at least its ``noise``; both asked
        once per join, by the join's ``pair_drift`` and :func:`_pair_noise`, for this and :meth:`_drift_observed`)
        measured its link, at ``junctions[join]``, relative to the map that last saw their left features
        (``left_ids``, compact; the median), strained by their strains' median
        (:meth:`mapjoin.association.feature_drift.SightingDrift.tie`)."""
        pair_join = right_join[found.right]
        strain = np.abs(left[found.left] - _corrected(found, link_xy, link_phi, right, right_join)) ** 2 / 4
        drifted = drift >= noise
        for tying in np.flatnonzero(np.bincount(pair_join[drifted], minlength=len(junctions)) >= TIE_SUPPORT).tolist():
            pairs = drifted & (pair_join == tying)
            self.drift.tie(int(_median(self.drift.last_map[left_ids[pairs]])), int(junctions[tying]),
                           float(_median(strain[pairs])))
        return strain

    # tree strategy -----------------------------------------------------------------------
    def level(self, pieces: _Pieces, level: int) -> _Pieces:
        """Before a level of the tree: each right piece's features renamed to the ids of their matches in the left
        piece, the others to new ids (``level`` joins have merged pieces of ``2^(level-1)`` maps; at level 1, single
        maps, step 2's link rule as well: :func:`mapjoin.association.link_pairs.linked_again`)."""
        if self.count == 0:  # the maps' own (compact local) ids are not global: every row new
            ids = self.first(len(pieces.feature_ids))
            self.row_ids[:] = ids
            pieces = dataclasses.replace(pieces, feature_ids=ids)
            self.own_pose_variances = pieces.pose_variances.copy()
        count = pieces.count // 2
        ends = np.searchsorted(pieces.pose_piece, np.arange(pieces.count), side="right") - 1
        link = ends[0:2 * count:2]  # each left piece's end pose
        # the last level's junctions (pose row m: map m's end, pose m + 1) hold their joins' posteriors until moved
        # (and the excess of each junction's own drift over its posterior: the same junction as the sequential join's)
        posterior = pieces.pose_variances[self.links]
        excess = self._junction_excess(self.links + 1, posterior[:, 0], posterior[:, 1])
        self.drift.placed(self.links + 1, posterior[:, 0], posterior[:, 1], (excess[:, 0], excess[:, 1]))
        self.links = link
        joined = pieces.feature_piece < 2 * count
        left = np.flatnonzero(joined & (pieces.feature_piece % 2 == 0))
        right = np.flatnonzero(joined & (pieces.feature_piece % 2 == 1))
        right_join = pieces.feature_piece[right] // 2
        right_covariances = rotated(self.covariances[pieces.feature_ids[right]], pieces.pose_phi[link][right_join])
        left_join = pieces.feature_piece[left] // 2
        link_map = pieces.last[0:2 * count:2]  # each join's left piece's last map
        start = pieces.first[0:2 * count:2]  # ... and its first: the ties inside it
        left_ids = pieces.feature_ids[left]
        end = pieces.last[1:2 * count:2]  # each join's right piece's last map
        right_ids = pieces.feature_ids[right]
        arguments = (pieces.features[left], self.covariances[left_ids], left_join, pieces.pose_xy[link],
                     pieces.pose_phi[link], pieces.pose_variances[link], pieces.features[right], right_covariances,
                     right_join)
        sightings = (self.sightings[left_ids], self.sightings[right_ids])
        found = match_features(*arguments, self.gate, self.margin, *sightings)
        if level == 1:  # each left piece is one map, whose end pose is the link: step 2's link rule
            found = linked_again(found, *arguments, self._first_level_frame(left), self.gate, self.margin, *sightings)
        # the joins whose pieces drifted beyond the junctions' posteriors take the maps' own dead reckoning as well
        far = drifting(found, *arguments, self.drift.first_map[right_ids] > link_map[right_join] + 1, self.gate)
        # (and the share of the junctions' excess the drifted joins bore out; the others the posteriors alone)
        plain = self.drift.posterior()
        sources = (plain, self.drift.dead_reckoned()) if far.any() else (plain,)
        left_far, right_far = far[left_join], far[right_join]
        drift = [(*source.before(left_ids, link_map[left_join]), *source.after(right_ids, link_map[right_join]))
                 for source in sources]
        drift = tuple(np.where(rows_far, reckoned, plain) for rows_far, plain, reckoned in
                      zip((left_far, left_far, right_far, right_far), drift[0], drift[-1]))

        def way_drift(source: SightingDrift, i: np.ndarray, j: np.ndarray, noise: np.ndarray) -> np.ndarray:
            # compared with the pairs' noise only: the ties are searched for the pairs whose direct ways reach it
            left_way = (left_ids[i], link_map[left_join[i]], start[left_join[i]])
            right_way = (right_ids[j], link_map[right_join[j]], end[right_join[j]])
            value = source.settled(*left_way, level=np.inf) + source.settled_after(*right_way, level=np.inf)
            reach = np.flatnonzero(value >= noise)
            if len(reach):
                value[reach] = (source.settled(*(part[reach] for part in left_way))
                                + source.settled_after(*(part[reach] for part in right_way)))
            return value

        @_asked_once
        def pair_drift(i: np.ndarray, j: np.ndarray, noise: np.ndarray) -> np.ndarray:
            value, pairs_far = np.empty(len(i)), far[left_join[i]]
            for source, rows in ((sources[0], ~pairs_far), (sources[-1], pairs_far)):
                if rows.any():
                    value[rows] = way_drift(source, i[rows], j[rows], noise[rows])
            return value

        scopes = [voters_drift(source, left_ids, right_ids) for source in sources]

        def scope(pair_left: np.ndarray, pair_right: np.ndarray, join: np.ndarray, *voters: np.ndarray) -> np.ndarray:
            value, pairs_far = np.empty(len(pair_left)), far[join]
            for relative, rows in ((scopes[0], ~pairs_far), (scopes[-1], pairs_far)):
                if rows.any():
                    value[rows] = relative(pair_left[rows], pair_right[rows], join[rows], *voters)
            return value

        found = with_drift(found, *arguments, drift, self.gate, self.margin, *sightings, pair_drift, scope, far)
        if level > 1:  # the junction's own features, under the link's variance relative to its own map (step 2)
            found = self._junction_pairs(found, pieces.features[left], left_ids, left_join, pieces.pose_xy[link],
                                         pieces.pose_phi[link], link_map, pieces.features[right], right_ids,
                                         right_covariances, right_join)
        pair_left, pair_right = left_ids[found.left], right_ids[found.right]
        pair_map = link_map[right_join[found.right]]
        noise = _pair_noise(self.covariances, right_covariances, pair_left, found.right)
        drifts = pair_drift(found.left, found.right, noise)
        self._drift_observed(found, pieces.features[left], pieces.pose_xy[link], pieces.pose_phi[link],
                             pieces.pose_variances[link], pieces.features[right], right_join, noise, drifts,
                             (drift[0][found.left] + self.drift.strain[pair_left])
                             + (drift[2][found.right] + self.drift.strain[pair_right]),
                             lambda along: self.drift.excess_before(pair_left[along], pair_map[along])
                             + self.drift.excess_after(pair_right[along], pair_map[along]),
                             far[right_join[found.right]])
        self.counts += [(ambiguous, rejected, 0) for ambiguous, rejected in zip(found.ambiguous.tolist(),
                                                                                found.rejected.tolist())]
        strain = self._tie(found, pieces.features[left], pair_left, pieces.pose_xy[link], pieces.pose_phi[link],
                           pieces.features[right], right_join, noise, drifts, link_map + 1)
        ids = pieces.feature_ids.copy()
        renamed = self._fresh(len(right))
        renamed[found.right] = ids[left[found.left]]
        ids[right] = renamed
        matched = np.zeros(len(right), dtype=bool)
        matched[found.right] = True
        self._sighted(renamed, right_covariances, self.sightings[pieces.feature_ids[right]], matched, ~matched)
        # a match's last sighting is its right feature's; a new id has its old one's sightings
        self.drift.merged(renamed[matched], pieces.feature_ids[right][matched])
        self.drift.strain[renamed[found.right]] = strain
        self.drift.copied(renamed[~matched], pieces.feature_ids[right][~matched])
        # every input row of a right piece follows its feature's new id
        shift = level - 1
        piece_of_row = np.repeat(np.arange(len(self.offsets) - 1), np.diff(self.offsets)) >> shift
        moved = np.flatnonzero((piece_of_row % 2 == 1) & (piece_of_row // 2 < count))
        span = int(max(self.count, 1))
        keys = pieces.feature_piece.astype(np.int64) * span + pieces.feature_ids
        position, found_all = locate(keys, piece_of_row[moved].astype(np.int64) * span + self.row_ids[moved])
        assert found_all.all()
        self.row_ids[moved] = ids[position]
        return dataclasses.replace(pieces, feature_ids=ids)

    def _junction_pairs(self, found: Matches, left: np.ndarray, left_ids: np.ndarray, left_join: np.ndarray,
                        link_xy: np.ndarray, link_phi: np.ndarray, link_map: np.ndarray, right: np.ndarray,
                        right_ids: np.ndarray, right_covariances: np.ndarray, right_join: np.ndarray) -> Matches:
        """``found`` (a tree level's association) with the pairs of its joins' undrifted features
        (:mod:`mapjoin.association.junction`): steps 2-5 among them under each link's variance relative to its own
        map, a pair kept when ``found`` left both its features unpaired."""
        lefts, rights = undrifted(self.drift.last_map[left_ids], link_map[left_join], self.drift.first_map[right_ids],
                                  link_map[right_join])
        if not len(lefts) or not len(rights):
            return found
        junction = self.drift.sums[link_map + 1] - self.drift.sums[link_map]
        own = own_link_variances(self.own_pose_variances[link_map], junction, self.end_points[link_map])
        near = match_features(left[lefts], self.covariances[left_ids[lefts]], left_join[lefts], link_xy, link_phi,
                              own, right[rights], right_covariances[rights], right_join[rights], self.gate,
                              self.margin, self.sightings[left_ids[lefts]], self.sightings[right_ids[rights]])
        added = free_pairs(found.left, found.right, lefts[near.left], rights[near.right])
        if not added.any():
            return found
        return found.with_pairs(lefts[near.left[added]], rights[near.right[added]], right_join)

    def global_ids(self) -> tuple[np.ndarray, np.ndarray]:
        """Global ids numbered by first sighting: for each compact id (-1 if unused) and for each input row."""
        final = self.row_ids
        unique, first = np.unique(final, return_index=True)
        numbering = np.full(self.count, -1, dtype=np.int64)
        numbering[unique[np.argsort(first)]] = np.arange(len(unique))
        return numbering, numbering[final]
