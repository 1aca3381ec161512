"""Growing a merge's correspondence over the whole overlap with local rigid transforms (docs/method.md#merging).

Two maps that drift apart beyond their variances are related by no one rigid transform: the
search of :mod:`mapjoin.registration` finds the part that one transform fits (its core
matches), and, in long runs, other hypotheses that fit other parts. Locally the maps still
agree, so the correspondence is grown from the core:

1. **Local transform.** Each B feature is placed by the rigid fit (the chi = 0 solution in
   closed form, weights ``1/(var_a + var_b)``) of its ``NEIGHBOURS`` nearest matched B
   features (in B's frame; a matched feature leaves itself out) onto their A partners.
2. **Gate.** The fit's residuals say how far the maps bend there: their per-axis variance
   ``sum |r|^2 / (2k - 3)`` (k pairs, 3 parameters) is added to each pair's variances and
   the fit is solved again; a placed point's gate variance is ``var_a + var_b`` of the two
   features, plus that spread, plus the fit's placement variance
   ``1/W + |z - m_1|^2 var_phi / 2`` (docs/method.md#variance-propagation). The gate is the
   chi-square one of the search, shrunk as its best hypothesis' residuals say (variances
   declared far wider than the errors would let chance neighbours in).
3. **Matches.** As in the search: the nearest A feature inside the gate, unless a second A
   feature is inside too, or another B feature claims the same A feature (ambiguous: left
   unmatched). A gate that chance would fill is no evidence: a match needs
   ``density * pi * gate * variance <= MATCH_CHANCE``, A's density taken from its features'
   spacing (the median distance to the third nearest). Without that, a fit spoilt by a kink
   of the maps (a loop closed in one of them) gives a gate of metres that off the features'
   band holds one A feature, and a patch of false matches grows from it.
4. **Rounds.** Every B feature is decided again in each round, the matched ones too (a core
   match that its neighbours' transform denies is dropped), from the last round's matches;
   the correspondence grows outward until it stops changing. When it cycles instead (features
   at a kink taken and dropped in turn), the pairs that every state of the cycle holds are kept.

A kink stops the growth: beyond it the local transform jumps (by a metre in the simulated
runs). :func:`whole_overlap` then grows the search's other hypotheses (parts beyond the kinks)
and joins those that continue the correspondence (step 5 of docs/method.md#merging).

Everything is vectorised over features; the only loops are over rounds and hypotheses.
"""

from __future__ import annotations

import functools

import numpy as np

from .covariance import squared_norm
from .onestep import point_constants

__all__ = ["CLOSE", "DRIFT", "GROWTH", "MATCH_CHANCE", "NEIGHBOURS", "ROUNDS", "grow", "whole_overlap"]

NEIGHBOURS = 6       # matched neighbours that fix a feature's local transform (3 parameters: at least 2)
MATCH_CHANCE = 0.25  # a gate that holds an A feature by chance with a larger probability matches nothing
ROUNDS = 1000        # at most this many rounds (each adds the features next to the matched ones)
DRIFT = 0.5          # another part joins when its transform turns B by at most this (rad) from the local one ...
GROWTH = 2.0         # ... and grown alone, it holds at least this many times its own matches,
CLOSE = 0.1          # or when it turns B by at most this


def _local_placement(za: np.ndarray, va: np.ndarray, zb: np.ndarray, vb: np.ndarray, a: np.ndarray,
                     b: np.ndarray, count: int) -> tuple[np.ndarray, np.ndarray]:
    """Every B feature placed in A's frame by the rigid fit of its ``count`` nearest matched neighbours
    (leaving itself out), and the variance that the fit adds to the placed point (its residual spread plus
    its placement variance)."""
    from scipy.spatial import cKDTree

    xy = np.column_stack([zb[b].real, zb[b].imag])
    k = min(count + 1, len(b))
    neighbours = cKDTree(xy).query(np.column_stack([zb.real, zb.imag]), k=k)[1].reshape(len(zb), k)
    itself = b[neighbours] == np.arange(len(zb))[:, None]
    # the first k - 1 neighbours that are not the feature itself (a matched feature appears at most once)
    order = np.argsort(itself, axis=1, kind="stable")[:, :k - 1]
    chosen = np.take_along_axis(neighbours, order, axis=1)
    fit = _Fit(za[a[chosen]], zb[b[chosen]], va[a[chosen]] + vb[b[chosen]])
    return fit.place(zb), fit.added_variance(zb)


class _Fit:
    """Row-wise rigid fits of B points ``pb`` onto A points ``pa`` (the chi = 0 solution in closed form, weights
    1/variance), refitted once with the residual spread added to every pair's variance."""

    def __init__(self, pa: np.ndarray, pb: np.ndarray, pair_variance: np.ndarray) -> None:
        self._pb = pb
        self._solve(pa, pb, pair_variance)
        residual = pa - self.place(pb.T).T
        self.spread = squared_norm(residual).sum(axis=1) / max(2 * pa.shape[1] - 3, 1)
        self._solve(pa, pb, pair_variance + self.spread[:, None])

    def _solve(self, pa: np.ndarray, pb: np.ndarray, variance: np.ndarray) -> None:
        """Each row's chi = 0 fit: Theorem 1's constants of the rows as a batch of problems without odometry
        (:func:`mapjoin.onestep.point_constants`; phi* = phi0)."""
        rows, count = pa.shape
        k = point_constants(pa.ravel(), variance.ravel(), pb.ravel(), np.zeros(rows * count),
                            np.zeros(rows, dtype=complex), np.full(rows, np.inf), np.repeat(np.arange(rows), count))
        self._weight = 1.0 / variance
        self.total, self.mean_a, self.mean_b, self.turn = k.weight, k.mean0, k.mean1, np.exp(1j * k.phi0)

    def place(self, z: np.ndarray) -> np.ndarray:
        """``z`` (one point per row, or a row of points per fit) placed by each row's fit."""
        return self.mean_a + self.turn * (z - self.mean_b)

    def added_variance(self, z: np.ndarray) -> np.ndarray:
        """The variance a row's fit adds at ``z``: its spread + 1/W + |z - m_1|^2 var_phi / 2."""
        information = (self._weight * squared_norm(self._pb - self.mean_b[:, None])).sum(axis=1)
        with np.errstate(divide="ignore", invalid="ignore"):  # coincident points: no rotation information
            return self.spread + 1.0 / self.total + squared_norm(z - self.mean_b) / (2 * information)


def grow(tree_a, za: np.ndarray, va: np.ndarray, zb: np.ndarray, vb: np.ndarray, a: np.ndarray, b: np.ndarray,
         gate: float, neighbours: int = NEIGHBOURS) -> tuple[np.ndarray, np.ndarray]:
    """The correspondence ``(a, b)`` (indices in A, in B) grown over the overlap with local transforms (steps
    1-4 of the module docstring); ``tree_a`` a k-d tree of A's points, ``gate`` the chi-square gate."""
    spacing = tree_a.query(tree_a.data, k=min(4, tree_a.n))[0][:, -1]
    density = (min(4, tree_a.n) - 1) / (np.pi * float(np.median(spacing)) ** 2)
    seen: dict[bytes, int] = {}
    states: list[np.ndarray] = []
    for round_ in range(ROUNDS):
        if len(b) < 3:
            break
        state = a.astype(np.int64) * len(zb) + b  # each pair as one number, sorted by b
        key = state.tobytes()
        if key in seen:  # a cycle: keep the pairs that every state of it holds
            kept = functools.reduce(np.intersect1d, states[seen[key]:])
            return kept // len(zb), kept % len(zb)
        seen[key] = len(states)
        states.append(state)
        placed, extra = _local_placement(za, va, zb, vb, a, b, neighbours)
        k = min(2, tree_a.n)
        distance, nearest = tree_a.query(np.column_stack([placed.real, placed.imag]), k=k)
        distance, nearest = distance.reshape(len(zb), k), nearest.reshape(len(zb), k)
        gate_variance = va[nearest] + (vb + extra)[:, None]
        trusted = density * np.pi * gate * gate_variance[:, 0] <= MATCH_CHANCE
        inside = distance**2 <= gate * gate_variance
        single = trusted & inside[:, 0] & ~(inside[:, 1] if k == 2 else False)
        new_b = np.flatnonzero(single)
        new_a = nearest[new_b, 0]
        keep = np.bincount(new_a, minlength=len(za))[new_a] == 1
        a, b = new_a[keep], new_b[keep]
    return a, b


def _partners(a: np.ndarray, b: np.ndarray, size_a: int, size_b: int) -> tuple[np.ndarray, np.ndarray]:
    """Each A feature's B partner and each B feature's A partner in ``(a, b)`` (-1: none)."""
    partner_of_a, partner_of_b = np.full(size_a, -1), np.full(size_b, -1)
    partner_of_a[a], partner_of_b[b] = b, a
    return partner_of_a, partner_of_b


def _continuous(za: np.ndarray, va: np.ndarray, zb: np.ndarray, vb: np.ndarray, a: np.ndarray, b: np.ndarray,
                part_a: np.ndarray, part_b: np.ndarray, neighbours: int) -> tuple[float, float]:
    """How far another part ``(part_a, part_b)`` is from continuing the correspondence ``(a, b)``: the angle
    between its rigid transform and the local one (the fit of the ``neighbours`` matched B features nearest the
    part's centre), and the distance between where the two put that centre, over the neighbours' mean distance
    from it (a part beyond a kink: a few tenths; a chance part: anything)."""
    from scipy.spatial import cKDTree

    centre = zb[part_b].mean()
    k = min(neighbours, len(b))
    distance, nearest = cKDTree(np.column_stack([zb[b].real, zb[b].imag])).query([centre.real, centre.imag], k=k)
    nearest = np.atleast_1d(nearest)
    local = _Fit(za[a[nearest]][None, :], zb[b[nearest]][None, :], (va[a[nearest]] + vb[b[nearest]])[None, :])
    own = _Fit(za[part_a][None, :], zb[part_b][None, :], (va[part_a] + vb[part_b])[None, :])
    turn = float(np.abs(np.angle(own.turn[0] / local.turn[0])))
    offset = float(np.abs(own.place(centre)[0] - local.place(centre)[0])) / float(np.mean(distance))
    return turn, offset


def whole_overlap(tree_a, za: np.ndarray, va: np.ndarray, zb: np.ndarray, vb: np.ndarray,
                  hypotheses: list[tuple[np.ndarray, np.ndarray]], gate: float, min_common: int,
                  neighbours: int = NEIGHBOURS) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The correspondence grown over the whole overlap, and how many matches of each hypothesis it does not hold.

    ``hypotheses``: the search's matches per hypothesis, the best first. The best is grown
    (:func:`grow`); then each other hypothesis with at least ``min_common`` matches that the
    correspondence leaves free (neither feature matched) joins when it continues the
    correspondence: it turns B by at most ``CLOSE`` rad from the local transform near it and
    puts its centre within ``2 CLOSE`` times the local neighbours' distance of where that
    transform does (a part beyond a kink), or by at most ``DRIFT`` and ``2 DRIFT`` if, grown
    alone, it holds at least ``GROWTH`` times its free matches (chance matches do not grow).
    Its grown matches that the correspondence leaves free are added and the whole is grown
    again. Last, each hypothesis' matches that the final correspondence does not hold (a B
    feature given another A feature, or one it leaves unmatched): the caller's rivals (a
    transform that agrees with the correspondence on the pairs both hold is the same answer,
    however far from the best it turns B).
    """
    a, b = grow(tree_a, za, va, zb, vb, *hypotheses[0], gate, neighbours)
    for part_a, part_b in hypotheses[1:]:
        if len(b) < 3:
            break
        partner_of_a, partner_of_b = _partners(a, b, len(za), len(zb))
        free = (partner_of_b[part_b] < 0) & (partner_of_a[part_a] < 0)
        if free.sum() < min_common:
            continue
        turn, offset = _continuous(za, va, zb, vb, a, b, part_a[free], part_b[free], neighbours)
        if turn > DRIFT or offset > 2 * DRIFT:
            continue
        alone_a, alone_b = grow(tree_a, za, va, zb, vb, part_a[free], part_b[free], gate, neighbours)
        if (turn > CLOSE or offset > 2 * CLOSE) and len(alone_b) < GROWTH * free.sum():
            continue
        keep = (partner_of_b[alone_b] < 0) & (partner_of_a[alone_a] < 0)
        a, b = grow(tree_a, za, va, zb, vb, np.concatenate([a, alone_a[keep]]), np.concatenate([b, alone_b[keep]]),
                    gate, neighbours)
    partner_of_a, partner_of_b = _partners(a, b, len(za), len(zb))
    unheld = np.array([int((partner_of_b[part_b] != part_a).sum()) for part_a, part_b in hypotheses])
    return a, b, unheld

