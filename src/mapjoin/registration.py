"""Which features of two maps are the same, with no ids and no initial guess (docs/method.md#merging).

Two point sets A and B (features of two maps, each in its own frame, with spherical
variances) are related by an unknown SE(2) transform. The search is a consensus over pairs:

1. **Pairs.** Each feature is paired with its nearest neighbours (``A_NEIGHBOURS`` in A,
   ``B_NEIGHBOURS`` in B; at most ``B_PAIRS`` of B's pairs, taken evenly, so that the
   candidates grow with A's size, not with the product of both). The distance within a
   pair does not change under SE(2), so a B pair can only be an A pair whose distance
   agrees within the gate
   ``|d_A - d_B|^2 <= gate (var_i + var_j + var_k + var_l)``.
2. **Candidates.** Each agreeing (A pair, B pair) fixes a transform in two ways (the B
   pair's ends matched straight or crossed): ``phi = arg(v_A conj(v_B))`` from the pairs'
   vectors, ``t`` moving the B pair's midpoint onto the A pair's.
3. **Votes.** The candidates vote in a grid over ``(phi, u)``, ``u = t + R(phi) c_B`` the
   image of B's centroid (so that a small error of phi moves u by at most phi's error times
   B's radius); two grids shifted by half a cell, so that no cluster is cut in two.
4. **Verification.** The ``HYPOTHESES`` fullest cells seed a hypothesis each: the
   correspondences its candidates stand for (a feature given two partners left out) give a
   first transform (the chi = 0 solution below); B's features are placed with it and
   matched to the nearest A feature within the gate (Mahalanobis, the variances of both
   features and of the transform). A B feature with two A features in its gate, or an A
   feature claimed twice, is left unmatched (ambiguous). The chi = 0
   one-step problem over the matches (closed form, Theorem 1 with phi* = phi0) gives the
   next transform and its variances; this repeats until the matches stop changing. When
   the matches' residuals show the variances too wide (their median squared normalised
   residual below its chi-square expectation ``2 ln 2``), the gates shrink by that ratio
   (at most 10^4 times): chance neighbours inside a gate far wider than the true errors
   would otherwise be matched. They never widen.

5. **Growth.** One rigid transform fits only a part of two maps that drift apart beyond
   their variances: the best hypothesis' matches (its core) are grown over the whole
   overlap with local rigid transforms, and the other hypotheses that continue them (parts
   beyond a kink of the maps) are joined (:mod:`mapjoin.growing`).

**When the answer is sure** (:func:`consensus`): the best hypothesis' core has

- at least ``min_common`` matches, and so has the grown correspondence,
- at least twice as many as the strongest rival: the most matches of a hypothesis that
  differs from it (turns B by more than three vote cells in phi, or moves the mean of the
  core's B features by more than three cells in u: closer hypotheses are the same transform
  with its gates' chance neighbours) that the grown correspondence does not hold (a B
  feature given another A feature, or left unmatched). A hypothesis that agrees with the
  correspondence on the pairs both hold is the same answer, however far it turns B (another
  part of two drifted maps); one whose matches lie where the correspondence has none (a
  chance transform in clutter) is a rival, as is one that contradicts it. So is the best hypothesis shifted by
  a translation under which A repeats about its matched features (a lattice's vector: one that at least
  ``MIN_COMMON`` of their vectors to their two nearest neighbours share within the gates' reach), counted by
  its matches the best one does not make: in a lattice it matches as many features, while the vote cells, as
  wide as the turn's error times B's radius, would hold it as the same transform (the 8240 simulation's halves,
  features on a 3 m lattice along streets, merged 157 m and 1.7 rad from the truth before), and
- at least ``chance + 4 sqrt(chance)`` matches, where ``chance`` is how many matches chance
  alone would give: the sum over B's features of the probability that one of A's features,
  spread uniformly over A's bounding box, falls in the feature's gate (A's density times the
  gate's area, at most 1). Wide gates in a dense map match anything; this says so.

Otherwise the caller must refuse: the overlap is too small, the gates too wide for the
features' spacing, or the maps too self-similar, to tell the transform.

Everything is vectorised over features, pairs and candidates; the only loop is over the
few hypotheses and their iterations.

**Limits.** Maps that drift apart beyond their variances are matched over the overlap by
local transforms, but where one of them is kinked (a loop closed with a jump, the
simulated robots' start and crossing) the local transform jumps: features at the kink stay
unmatched, and beyond it the correspondence continues only from another hypothesis found
there. Simulated robots (2 and 3 of 20-100 maps, default noise, seeds 0-15): 73-91 % of the
common features matched, about 1 false match in 400 (one whose neighbours are across a kink
places it confidently wrong), 1 real overlap of 128 refused (docs/method.md#merging). The test
for sureness assumes maps consistent with their variances locally. The one chi = 0
transform fitted over the grown overlap is the best rigid fit of drifted maps, not the
relation of their start poses (metres apart after 100 maps).

``scipy.spatial`` (k-d trees) is imported here only, on use.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .covariance import squared_norm, translation_variance
from .growing import whole_overlap
from .onestep import OneStepProblem, OneStepSolution, solve
from .se2 import wrap

__all__ = ["A_NEIGHBOURS", "B_NEIGHBOURS", "B_PAIRS", "GATE_PROBABILITY", "HYPOTHESES", "MIN_COMMON", "Consensus",
           "chi_square_2", "consensus", "registration_problem", "transform_variances"]

A_NEIGHBOURS = 8      # pairs per A feature (A may hold features B did not see among B's neighbours)
B_NEIGHBOURS = 4      # pairs per B feature
B_PAIRS = 512         # at most this many B pairs vote (evenly taken): the candidates grow with A, not A x B
HYPOTHESES = 8        # cells of each vote grid verified
MIN_COMMON = 5        # fewest matches a found transform needs
GATE_PROBABILITY = 0.999
_ITERATIONS = 10
_SAME_CELLS = 3       # hypotheses closer than this many vote cells are one transform


def chi_square_2(probability: float) -> float:
    """The ``probability`` quantile of a chi-square with 2 degrees of freedom: ``-2 ln(1 - p)``."""
    return -2.0 * math.log1p(-probability)


def registration_problem(z0: np.ndarray, var0: np.ndarray, z1: np.ndarray, var1: np.ndarray) -> OneStepProblem:
    """The chi = 0 one-step problem of matched points (docs/method.md#without-the-orientation-link) with no
    odometry: its pair gets weight ``1/var_o = 0`` (variance infinity), so only the features count."""
    return OneStepProblem(z0, var0, z1, var1, np.zeros(3), np.array([math.inf, math.inf]), link=False)


def transform_variances(solution: OneStepSolution) -> tuple[float, float]:
    """``(var_t, var_phi)`` of a chi = 0 solution: ``var_phi = 1/a0`` (the heading's information is ``a0``)
    and ``var_t = 1/W + |m1|^2 var_phi / 2`` (docs/method.md#variance-propagation)."""
    phi_variance = 1.0 / solution.phi_information
    m1 = solution.constants.mean1
    return float(translation_variance(solution.constants.weight, complex(m1[0], m1[1]), phi_variance)), phi_variance


@dataclass(frozen=True)
class Consensus:
    """The outcome of the search: the matches ``(index in A, index in B)`` grown over the overlap from the best
    hypothesis, their chi = 0 solution, how many they are (``best``), how many the best hypothesis' rigid
    transform matched (``core``), how many matches of the strongest rival the correspondence does not hold,
    how many chance would give, and whether that is sure."""

    a: np.ndarray
    b: np.ndarray
    solution: OneStepSolution | None
    best: int
    core: int
    runner_up: int
    chance: float
    sure: bool


def _neighbour_pairs(tree, points: np.ndarray, count: int) -> np.ndarray:
    """Unordered pairs (i < j) of each point with its ``count`` nearest neighbours, each pair once."""
    k = min(count + 1, len(points))
    neighbours = tree.query(points, k=k)[1][:, 1:].ravel()
    owner = np.repeat(np.arange(len(points)), k - 1)
    pairs = np.stack([np.minimum(owner, neighbours), np.maximum(owner, neighbours)], axis=1)
    return np.unique(pairs, axis=0)


def _candidates(za: np.ndarray, va: np.ndarray, pairs_a: np.ndarray, zb: np.ndarray, vb: np.ndarray,
                pairs_b: np.ndarray, gate: float) -> tuple[np.ndarray, ...]:
    """Transforms ``(phi, t)`` (t complex) of every A pair and B pair whose lengths agree, both ways round,
    and the two correspondences each stands for (``ends_a[c, i]`` is ``ends_b[c, i]``)."""
    vec_a = za[pairs_a[:, 1]] - za[pairs_a[:, 0]]
    vec_b = zb[pairs_b[:, 1]] - zb[pairs_b[:, 0]]
    length_a, length_b = np.abs(vec_a), np.abs(vec_b)
    spread_a = va[pairs_a].sum(axis=1)
    spread_b = vb[pairs_b].sum(axis=1)
    order = np.argsort(length_a)
    widest = np.sqrt(gate * (spread_b + spread_a.max()))
    low = np.searchsorted(length_a, length_b - widest, sorter=order)
    high = np.searchsorted(length_a, length_b + widest, side="right", sorter=order)
    count = high - low
    which_b = np.repeat(np.arange(len(pairs_b)), count)
    which_a = order[np.repeat(low, count) + np.arange(count.sum()) - np.repeat(np.cumsum(count) - count, count)]
    agree = ((length_a[which_a] - length_b[which_b]) ** 2 <= gate * (spread_a[which_a] + spread_b[which_b])) \
        & (length_a[which_a] > 0) & (length_b[which_b] > 0)  # a pair of coincident points has no direction
    which_a, which_b = which_a[agree], which_b[agree]
    turn = vec_a[which_a] * vec_b[which_b].conj()
    turn = turn / np.abs(turn)
    middle_a = za[pairs_a[which_a]].mean(axis=1)
    middle_b = zb[pairs_b[which_b]].mean(axis=1)
    turns = np.concatenate([turn, -turn])  # straight, crossed
    t = np.concatenate([middle_a, middle_a]) - turns * np.concatenate([middle_b, middle_b])
    ends_a = np.concatenate([pairs_a[which_a], pairs_a[which_a][:, ::-1]])
    ends_b = np.concatenate([pairs_b[which_b], pairs_b[which_b]])
    return np.angle(turns), t, ends_a, ends_b


def _seeds(phi: np.ndarray, t: np.ndarray, centre: complex, phi_cell: float, xy_cell: float) -> list[np.ndarray]:
    """The candidates (indices) of the ``HYPOTHESES`` fullest cells of two shifted (phi, u) grids."""
    u = t + np.exp(1j * phi) * centre
    seeds = []
    for shift in (0.0, 0.5):
        keys = (np.floor(u.imag / xy_cell + shift), np.floor(u.real / xy_cell + shift),
                np.floor(phi / phi_cell + shift))
        order = np.lexsort(keys)  # candidates sorted by cell; a cell is a run of equal keys
        new_cell = np.zeros(len(order), dtype=bool)
        new_cell[0] = True
        for key in keys:
            new_cell[1:] |= key[order[1:]] != key[order[:-1]]
        starts = np.append(np.flatnonzero(new_cell), len(order))
        votes = np.diff(starts)
        for cell in np.argsort(-votes, kind="stable")[:HYPOTHESES]:
            seeds.append(order[starts[cell]:starts[cell + 1]])
    return seeds


def _voted(ends_a: np.ndarray, ends_b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The correspondences that a cell's candidates stand for, each once; a feature given two partners by
    different candidates is left out (as :func:`_matches` leaves out ambiguous ones)."""
    pairs = np.unique(np.column_stack([ends_a.ravel(), ends_b.ravel()]), axis=0)
    once_a = np.bincount(pairs[:, 0])[pairs[:, 0]] == 1
    once_b = np.bincount(pairs[:, 1])[pairs[:, 1]] == 1
    keep = once_a & once_b
    return pairs[keep, 0], pairs[keep, 1]


def _placement_variances(solution: OneStepSolution, zb: np.ndarray) -> np.ndarray:
    """The spherical variance that the transform's uncertainty adds to each placed point ``t + R(phi) z``, to
    first order: ``1/W + |z - m1|^2 var_phi / 2`` (docs/method.md#variance-propagation; about the matched
    points' mean ``m1``, where t and phi are uncorrelated)."""
    k = solution.constants
    return 1.0 / k.weight + squared_norm(zb - complex(k.mean1[0], k.mean1[1])) / (2 * solution.phi_information)


def _variance_scale(residuals: np.ndarray, variances: np.ndarray) -> float:
    """How much narrower the gates may be than the variances say: the median squared normalised residual of the
    matches over its expected value ``2 ln 2`` (chi-square, 2 degrees of freedom), within [1e-4, 1]; 1 (the
    variances as declared) below ``MIN_COMMON`` matches. Never wider: matches that disagree more than their
    variances say are not let in more easily."""
    if len(residuals) < MIN_COMMON:
        return 1.0
    normalised = squared_norm(residuals) / variances
    return min(1.0, max(1e-4, float(np.median(normalised)) / (2 * math.log(2))))


def _matches(tree, va: np.ndarray, zb: np.ndarray, gate_variances: np.ndarray, gate: float
             ) -> tuple[np.ndarray, np.ndarray]:
    """Unambiguous nearest-neighbour matches (index in A, index in B) of placed B points ``zb``: one A
    feature in the gate, and no other B point matched to it."""
    k = min(2, tree.n)
    distance, nearest = tree.query(np.column_stack([zb.real, zb.imag]), k=k)
    distance, nearest = distance.reshape(len(zb), k), nearest.reshape(len(zb), k)
    inside = distance**2 <= gate * (va[nearest] + gate_variances[:, None])
    single = inside[:, 0] & ~(inside[:, 1] if k == 2 else False)
    b = np.flatnonzero(single)
    a = nearest[b, 0]
    claimed = np.bincount(a, minlength=len(va))
    keep = claimed[a] == 1
    return a[keep], b[keep]


def consensus(za: np.ndarray, va: np.ndarray, zb: np.ndarray, vb: np.ndarray, *,
              min_common: int = MIN_COMMON, probability: float = GATE_PROBABILITY) -> Consensus:
    """The features of B that are features of A, searched for globally (see the module docstring).

    ``za``, ``zb``: complex points ``x + iy``; ``va``, ``vb``: their spherical variances;
    ``probability``: the gates' chi-square level. ``sure`` tells whether the answer may be used.
    """
    from scipy.spatial import cKDTree  # only the search without ids needs k-d trees

    empty = np.zeros(0, dtype=np.intp)
    if len(za) < 2 or len(zb) < 2:
        return Consensus(empty, empty, None, 0, 0, 0, math.inf, False)
    gate = chi_square_2(probability)
    xy_a, xy_b = np.column_stack([za.real, za.imag]), np.column_stack([zb.real, zb.imag])
    tree_a, tree_b = cKDTree(xy_a), cKDTree(xy_b)
    pairs_a = _neighbour_pairs(tree_a, xy_a, A_NEIGHBOURS)
    pairs_b = _neighbour_pairs(tree_b, xy_b, B_NEIGHBOURS)
    if len(pairs_b) > B_PAIRS:
        pairs_b = pairs_b[np.linspace(0, len(pairs_b) - 1, B_PAIRS).astype(np.intp)]
    phi, t, ends_a, ends_b = _candidates(za, va, pairs_a, zb, vb, pairs_b, gate)
    if not len(phi):
        return Consensus(empty, empty, None, 0, 0, 0, math.inf, False)
    # cells: a candidate's phi is good to ~ its pair's position error over its length; u to that error
    # plus phi's error times B's radius
    sigma = math.sqrt(float(np.median(va)) + float(np.median(vb)))
    length = float(np.median(np.abs(zb[pairs_b[:, 1]] - zb[pairs_b[:, 0]])))
    centre = complex(zb.mean())
    radius = math.sqrt(float(squared_norm(zb - centre).mean()))
    phi_cell = min(max(4 * sigma / length, 0.01), 0.5) if length > 0 else 0.5
    xy_cell = 4 * sigma + phi_cell * radius
    found = []
    for members in _seeds(phi, t, centre, phi_cell, xy_cell):
        # the first matches: the correspondences the cell's votes stand for
        a, b = _voted(ends_a[members], ends_b[members])
        previous, solution, scale = None, None, 1.0
        for _ in range(_ITERATIONS):
            if len(a) < 2 or (previous is not None and np.array_equal(previous, b)):
                break
            previous = b
            candidate = solve(registration_problem(xy_a[a], va[a], xy_b[b], vb[b]))
            if candidate.constants.a0 == 0.0:
                break
            solution = candidate
            turn, shift = np.exp(1j * solution.phi), complex(solution.t[0], solution.t[1])
            spread = _placement_variances(solution, zb)
            scale = _variance_scale(za[a] - (turn * zb[b] + shift), va[a] + vb[b] + spread[b])
            a, b = _matches(tree_a, va, turn * zb + shift, vb + spread, gate * scale)
        if solution is not None:
            a, b = _matches(tree_a, va, turn * zb + shift, vb + spread, gate * scale)
            found.append((len(b), -solution.cost, a, b, solution, vb + spread, gate * scale))
    if not found:
        return Consensus(empty, empty, None, 0, 0, 0, math.inf, False)
    found.sort(key=lambda entry: entry[:2], reverse=True)
    count, _, _, _, core, gate_variances, best_gate = found[0]
    a, b, unheld = whole_overlap(tree_a, za, va, zb, vb, [(entry[2], entry[3]) for entry in found], best_gate,
                                 min_common)
    solution = solve(registration_problem(xy_a[a], va[a], xy_b[b], vb[b])) if len(b) >= 2 else core
    centre = complex(core.constants.mean1[0], core.constants.mean1[1])

    def image(s: OneStepSolution) -> complex:  # where a hypothesis puts the core's matched B features' mean
        return np.exp(1j * s.phi) * centre + complex(s.t[0], s.t[1])

    runner_up = max((int(held_not) for entry, held_not in zip(found[1:], unheld[1:])
                     if abs(wrap(entry[4].phi - core.phi)) > _SAME_CELLS * phi_cell
                     or abs(image(entry[4]) - image(core)) > _SAME_CELLS * xy_cell), default=0)
    runner_up = max(runner_up, _shifted_rival(tree_a, za, va, zb, found[0]))
    chance = _chance(xy_a, float(np.median(va)), gate_variances, best_gate)
    sure = (min(count, len(b)) >= min_common and count >= 2 * runner_up
            and count >= chance + 4 * math.sqrt(chance))
    return Consensus(a, b, solution, len(b), count, runner_up, chance, sure)


def _repeats(tree_a, za: np.ndarray, a: np.ndarray, reach: float) -> np.ndarray:
    """Translations under which A repeats about the features ``a`` (a lattice's vectors): the vectors from each of
    them to its two nearest A features, longer than ``reach``, that at least ``MIN_COMMON`` of those vectors share
    within ``reach``; one per cluster (the best shared first), at most ``HYPOTHESES``. None in a world of scattered
    features (a vector shared by five features to within a gate is a pattern, not chance)."""
    if len(a) < MIN_COMMON or len(za) < 3:
        return np.zeros(0, dtype=complex)
    nearest = tree_a.query(np.column_stack([za[a].real, za[a].imag]), k=3)[1][:, 1:]
    vectors = (za[nearest] - za[a][:, None]).ravel()
    vectors = vectors[np.abs(vectors) > reach]
    if len(vectors) < MIN_COMMON:
        return np.zeros(0, dtype=complex)
    from scipy.spatial import cKDTree

    shared = cKDTree(np.column_stack([vectors.real, vectors.imag])).query_ball_point(
        np.column_stack([vectors.real, vectors.imag]), reach, return_length=True)
    repeats: list[complex] = []
    for i in np.argsort(-shared, kind="stable")[:np.count_nonzero(shared >= MIN_COMMON)]:
        if len(repeats) == HYPOTHESES:
            break
        if all(abs(vectors[i] - other) > reach for other in repeats):
            repeats.append(complex(vectors[i]))
    return np.array(repeats, dtype=complex)


def _shifted_rival(tree_a, za: np.ndarray, va: np.ndarray, zb: np.ndarray, best: tuple) -> int:
    """The most matches that the best hypothesis (``best``: its entry of :func:`consensus`) shifted by a translation
    under which A repeats (:func:`_repeats`, within the reach of its gates) makes and does not share with it: in a
    lattice the shifted transform matches about as many features as the best one, a rival as strong, so the search
    refuses; in scattered features there is no such translation."""
    _, _, a, b, solution, gate_variances, gate = best
    reach = math.sqrt(gate * float(np.median(va[a] + gate_variances[b]))) if len(b) else 0.0
    placed = np.exp(1j * solution.phi) * zb + complex(solution.t[0], solution.t[1])
    partner = np.full(len(zb), -1)
    partner[b] = a
    rival = 0
    for shift in _repeats(tree_a, za, a, reach):
        shifted_a, shifted_b = _matches(tree_a, va, placed + shift, gate_variances, gate)
        rival = max(rival, int(np.count_nonzero(partner[shifted_b] != shifted_a)))
    return rival


def _chance(xy_a: np.ndarray, typical_va: float, gate_variances: np.ndarray, gate: float) -> float:
    """Matches expected by chance: A's features spread uniformly over A's bounding box, the probability that
    one falls in each B feature's gate (area ``pi gate (var_a + var_b)``), at most 1 each, summed."""
    extent = xy_a.max(axis=0) - xy_a.min(axis=0)
    area = float(extent[0] * extent[1])
    density = len(xy_a) / area if area > 0 else math.inf
    return float(np.minimum(1.0, density * math.pi * gate * (typical_va + gate_variances)).sum())
