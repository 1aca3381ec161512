"""Loop closures in data association: the rigid correction a drifted part of the map so far needs, by votes.

Where a map closes a loop, the features it meets again were last seen many maps before, and the chain's drift
since then (:mod:`mapjoin.association.feature_drift`) moves all of them, relative to the join's link, by nearly one
rigid correction: metres on DLR and 8240, far outside the gate and more than the features' spacing, so that no gate
wide enough to hold the drift can choose partners feature by feature (docs/method.md#data-association, step 6).
Two candidate pairs ``(i1, j1)``, ``(i2, j2)`` of one join (each within the drift's gate) whose distances agree,
``| |f_i1 - f_i2| - |x_j1 - x_j2| |`` within the noise's gate, fix a rigid correction: a turn
``dphi = arg((f_i1 - f_i2) / (x_j1 - x_j2))`` and the offset it gives the right features' centroid ``c``,
``o = f_i1 + e^{i dphi} (c - x_j1) - c`` (a small error of ``dphi`` moves ``o`` by at most it times the map's
extent). :func:`rigid_votes` counts, in a grid over ``(dphi, o)`` (two grids shifted by half a cell, so that no
cluster is cut in two), the distinct right features whose pairs vote in each cell, and gives each join's fullest
cell, the median correction of its votes and the agreement of the fullest cell that stands for another correction
(farther than :data:`DIFFERENT_CELLS` cells in ``dphi`` or in ``o``) by a rival association: among the votes of two
pairs neither of which votes for the best cell. A drifted piece is bent along its length, and its own pairs, far
apart along it, vote beyond the best cell: the same association, no rival (docs/method.md#data-association, step 6).
Distances do not change under the correction, so chance votes are rare even where the drift's gate holds dozens of
features; the caller takes a loop closure only when it is clearly the best, and then chooses and tests its pairs with
the ordinary gate around the corrected link.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ..neighbours import nearest

__all__ = ["DIFFERENT_CELLS", "RigidVotes", "rigid_votes"]

#: every pair of right features votes up to this many features; above, each feature with its nearest ones
ALL_PAIRS = 32
NEIGHBOURS = 8
#: up to this many right features their nearest neighbours are found by brute force: n^2 distances, 27 ms at 1024
#: (measured), a tenth of scipy.spatial's import; beyond, its k-d tree
BRUTE_FORCE = 1024
#: a join's votes are at most about this many (two candidate pairs each)
VOTES = 1 << 16
#: cells whose centres are farther apart than this many cells (in dphi or in o) stand for different corrections
DIFFERENT_CELLS = 2.0


@dataclass(frozen=True)
class RigidVotes:
    """Per join: the best correction (``turn`` dphi, ``offset`` of the centroid, complex; 0 without votes), its
    ``support`` (distinct right features voting for it), its ``agreement`` (distinct pairs of right features voting
    for it: a true correction of n features has n (n - 1) / 2, chance few) and the ``runner_up``'s agreement (a cell
    far from the best, counting the votes of two pairs that are not among the ``voters`` only). The
    ``voters``: the candidate pairs (rows of ``a``, ``b``) whose votes lie within a cell of the best correction, by
    ``voter_join``: where the correction is exact (step 6's scope, :mod:`mapjoin.association.loop_scope`)."""

    turn: np.ndarray
    offset: np.ndarray
    support: np.ndarray
    agreement: np.ndarray
    runner_up: np.ndarray
    voters: np.ndarray = field(default_factory=lambda: np.zeros(0, np.intp))
    voter_join: np.ndarray = field(default_factory=lambda: np.zeros(0, np.intp))


def _fullest(join: np.ndarray, cells: np.ndarray, first: np.ndarray, second: np.ndarray, supported: bool = True
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The occupied cells (``cells``: integer coordinates per vote, a vote being two pairs of right features
    ``first`` < ``second``) with their join, their distinct right features and their distinct right pairs.
    Cells are numbered by one integer key, lexicographic in (join, cell), so that every count is a sort of
    integers: each column offset by its least value, or, were the key too large for that, its values made compact
    (a sort per column). The distinct right features are counted only where the best cell is chosen among them:
    in the cells with their join's most right pairs (0 elsewhere, and everywhere unless ``supported``), since a
    join's best cell has the most pairs first (:func:`rigid_votes`); the other cells' would cost a sort of all the
    votes' ends."""
    columns = [join, *cells.T]
    low = [int(column.min(initial=0)) for column in columns]
    spans = [int(column.max(initial=0)) - least + 1 for column, least in zip(columns, low)]
    compact = float(np.prod(np.array(spans, dtype=float))) >= 2.0 ** 62
    key = np.zeros(len(join), np.int64)
    for column, least, span in zip(columns, low, spans):
        if compact:
            values, offset = np.unique(column, return_inverse=True)
            key = key * len(values) + offset
        else:
            key = key * span + (column - least)
    cell, row, number = np.unique(key, return_index=True, return_inverse=True)  # row: each cell's first vote
    size = np.int64(max(int(first.max(initial=0)), int(second.max(initial=0))) + 1)
    pairs = np.unique((number * size + first) * size + second)  # one vote per right pair and cell
    agreement = np.bincount(pairs // (size * size), minlength=len(cell))
    support = np.zeros(len(cell), np.int64)
    if supported and len(cell):
        owner = join[row]
        most = np.zeros(int(owner.max()) + 1, np.int64)
        np.maximum.at(most, owner, agreement)
        fullest = agreement == most[owner]
        pairs = pairs[fullest[pairs // (size * size)]]
        ends = np.unique(np.concatenate([pairs // (size * size) * size + pairs % (size * size) // size,
                                         pairs // (size * size) * size + pairs % size]))
        support = np.bincount(ends // size, minlength=len(cell))
    return join[row], cells[row], support, agreement  # a vote of each cell: its join and coordinates


def _cells(join: np.ndarray, p: np.ndarray, q: np.ndarray, dphi: np.ndarray, o: np.ndarray, b: np.ndarray,
           turn_cell: np.ndarray, offset_cell: np.ndarray, supported: bool = True
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The occupied cells of the votes (two candidate pairs ``p``, ``q`` each, of ``join``, for the correction
    ``dphi``, ``o``) in both grids (the second shifted by half a cell): each cell's join, centre (dphi, o.real,
    o.imag), agreement and support (:func:`_fullest`: only where it may choose the best cell, and only if
    ``supported``)."""
    found = []
    for shift in (0.0, 0.5):
        cells = np.column_stack([np.floor(dphi / turn_cell[join] + shift), np.floor(o.real / offset_cell[join] + shift),
                                 np.floor(o.imag / offset_cell[join] + shift)]).astype(np.int64)
        owner, coordinates, features, count = _fullest(join, cells, np.minimum(b[p], b[q]), np.maximum(b[p], b[q]),
                                                       supported)
        centres = (coordinates + 0.5 - shift) * np.column_stack([turn_cell[owner], offset_cell[owner],
                                                                   offset_cell[owner]])
        found.append((owner, centres, count, features))
    owner, centres, count, features = (np.concatenate(column) for column in zip(*found))
    return owner, centres, count, features


def _right_pairs(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The pairs ``u < v`` of right features that vote: all of them for up to :data:`ALL_PAIRS` features, else each
    feature with its :data:`NEIGHBOURS` nearest (the votes then grow with the features, not with their square)."""
    n = len(points)
    if n <= ALL_PAIRS:
        return np.triu_indices(n, 1)
    u, v = np.repeat(np.arange(n), NEIGHBOURS), _nearest(points, NEIGHBOURS).ravel()
    pairs = np.unique(np.minimum(u, v) * n + np.maximum(u, v))  # in (u, v) order, as one integer each
    return pairs // n, pairs % n


def _nearest(points: np.ndarray, k: int) -> np.ndarray:
    """Each of the complex ``points``' ``k`` nearest others (one row each, in no order; ties broken either way).
    Up to :data:`BRUTE_FORCE` points by their squared distances (:func:`mapjoin.neighbours.nearest`; a join's free right
    features are tens to hundreds: this spares scipy's import, 0.3 s of a command), beyond by scipy's k-d tree."""
    n = len(points)
    if n > BRUTE_FORCE:
        from scipy.spatial import cKDTree

        xy = np.column_stack([points.real, points.imag])
        return cKDTree(xy).query(xy, k + 1)[1][:, 1:]  # the first: itself
    return nearest(points, points, k, exclude=np.arange(n))[0]  # not itself


def rigid_votes(left: np.ndarray, right_points: np.ndarray, a: np.ndarray, b: np.ndarray, pair_join: np.ndarray,
                centre: np.ndarray, noise: np.ndarray, turning: np.ndarray, turn_cell: np.ndarray,
                offset_cell: np.ndarray, joins: int, closeness: np.ndarray | None = None,
                bent: np.ndarray | None = None) -> RigidVotes:
    """Votes of the candidate pairs ``(a[p], b[p])`` (rows of ``left`` and of ``right_points``, complex, both in
    left's frame; ``pair_join`` sorted; ``noise``: each pair's isotropic variance, the sum of its two features';
    ``turning``: the largest turn the drift allows each pair) for rigid corrections about each join's ``centre``,
    in cells of ``turn_cell`` and ``offset_cell`` (one each per join). A join's votes are at most about
    :data:`VOTES` (memory): where its pairs of right features times their candidates would be more, each right
    feature keeps its candidates of least ``closeness`` (by default all are alike). ``bent`` (a mask over the joins,
    None for none): joins whose right piece is a drifted chain (:mod:`mapjoin.association.drift_evidence`), whose
    regions vote for corrections of their own; there a rival association must pair a right feature of the best
    correction's voters with another left feature: the runner-up counts only the votes with such a pair."""
    turn, offset = np.zeros(joins), np.zeros(joins, complex)
    support, agreement, runner_up = (np.zeros(joins, np.int64) for _ in range(3))
    g2 = 9.0  # distances agree within 3 sigma of their difference
    starts = np.searchsorted(pair_join, np.arange(joins + 1))
    parts = []
    for join in np.flatnonzero(np.diff(starts) >= 2).tolist():
        rows = np.arange(starts[join], starts[join + 1])
        rows = rows[np.lexsort((np.zeros(len(rows)) if closeness is None else closeness[rows], b[rows]))]
        features, first, size = np.unique(b[rows], return_index=True, return_counts=True)
        u, v = _right_pairs(right_points[features])
        if int((size[u] * size[v]).sum()) > VOTES:  # each feature's least close candidates go
            most = max(int(math.sqrt(VOTES / max(len(u), 1))), 2)
            rank = np.arange(len(rows)) - np.repeat(first, size)
            rows = rows[rank < most]
            features, first, size = np.unique(b[rows], return_index=True, return_counts=True)
        per = size[u] * size[v]
        total = int(per.sum())
        if not total:
            continue
        # positions in rows: for each pair (u, v), each of u's rows (p) with each of v's (q), row by row; as ranges
        # (u's rows, then one run of v's rows per row of u) repeated and shifted, without dividing vote indices
        runs, run_first = np.repeat(size[v], size[u]), np.repeat(first[v], size[u])
        own = np.arange(int(size[u].sum())) + np.repeat(first[u] - (np.cumsum(size[u]) - size[u]), size[u])
        q = np.arange(total) + np.repeat(run_first - (np.cumsum(runs) - runs), runs)
        # two different left features whose distance agrees with their right features' (one per pair u, v); the
        # rows' left features, points and noise gathered once, each vote reading them by position (u's side
        # repeated along its runs). Most votes disagree: they are dropped first against the rows' largest noise (a
        # bound on each vote's two), the few left tested with their own noise, each vote's row of u found from its
        # run; then the distinct left features are checked among the votes that agree
        row_left, row_noise = a[rows], noise[rows]
        row_point = left[row_left]
        span_left = np.repeat(row_point[own], runs) - row_point[q]
        span = np.abs(right_points[features[u]] - right_points[features[v]])
        gap = (np.abs(span_left) - np.repeat(span, per)) ** 2
        rough = np.flatnonzero(gap <= g2 * (2 * np.fmax.reduce(row_noise)))  # (fmax: a NaN noise bounds nothing)
        p = own[np.searchsorted(np.cumsum(runs), rough, side="right")]
        agree = gap[rough] <= g2 * (row_noise[p] + row_noise[q[rough]])
        p, q, span_left = p[agree], q[rough[agree]], span_left[rough[agree]]
        distinct = row_left[p] != row_left[q]
        p, q, span_left = rows[p[distinct]], rows[q[distinct]], span_left[distinct]
        dphi = np.angle(span_left / (right_points[b[p]] - right_points[b[q]]))
        allowed = np.abs(dphi) <= np.minimum(turning[p], turning[q])
        p, q, dphi = p[allowed], q[allowed], dphi[allowed]
        o = left[a[p]] + np.exp(1j * dphi) * (centre[join] - right_points[b[p]]) - centre[join]
        parts.append((np.full(len(p), join), p, q, dphi, o))
    if not parts:
        return RigidVotes(turn, offset, support, agreement, runner_up)
    join, p, q, dphi, o = (np.concatenate(column) for column in zip(*parts))
    owner, centres, count, features = _cells(join, p, q, dphi, o, b, turn_cell, offset_cell)
    order = np.lexsort((-features, -count, owner))
    first = np.ones(len(order), dtype=bool)
    first[1:] = owner[order][1:] != owner[order][:-1]
    best = order[first]
    support[owner[best]] = features[best]
    agreement[owner[best]] = count[best]
    best_centre = np.zeros((joins, 3))
    best_centre[owner[best]] = centres[best]
    scale = np.column_stack([turn_cell, offset_cell, offset_cell])
    # the correction: the median of the votes within a cell of the best cell's centre
    near = (np.abs(np.column_stack([dphi, o.real, o.imag]) - best_centre[join]) <= scale[join]).all(axis=1)
    for j in np.unique(join[near]).tolist():
        chosen = near & (join == j)
        turn[j] = np.median(dphi[chosen])
        offset[j] = np.median(o[chosen].real) + 1j * np.median(o[chosen].imag)
    # the runner-up: the fullest cell far from the best among the votes of two pairs that are not the best's voters
    # (a rival association); the best's own pairs voting elsewhere are its association through a bent piece
    voting = np.zeros(len(b), dtype=bool)
    voting[p[near]] = voting[q[near]] = True
    rival = ~(voting[p] | voting[q])
    if bent is not None and bent.any():  # a bent piece's other regions, other right features, are no rival
        claimed = np.zeros(len(right_points), dtype=bool)
        claimed[b[p[near]]] = claimed[b[q[near]]] = True
        rival &= ~bent[join] | claimed[b[p]] | claimed[b[q]]
    owner, centres, count, _ = _cells(join[rival], p[rival], q[rival], dphi[rival], o[rival], b, turn_cell,
                                      offset_cell, supported=False)
    apart = (np.abs(centres - best_centre[owner]) > DIFFERENT_CELLS * scale[owner]).any(axis=1)
    np.maximum.at(runner_up, owner[apart], count[apart])
    voters = np.unique(np.concatenate([join[near] * len(b) + p[near], join[near] * len(b) + q[near]]))
    return RigidVotes(turn, offset, support, agreement, runner_up, voters % len(b), voters // len(b))
