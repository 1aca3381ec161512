"""The consistency check of each join: its minimum cost as a chi-square statistic, and the gate.

A join's cost at its optimum (docs/method.md#one-step-problem) is a sum of squared,
variance-weighted residuals: the common features seen from both sides and the odometry.
If the inputs were exactly the spherical model's (independent Gaussian errors with the
given variances), ``min F`` would be chi-square distributed with

- ``dof = 2n`` with the orientation link: 4n + 3 observed scalars (``Z0_j``, ``Z1_j``, the
  odometry's x, y, heading) minus 2n + 3 unknowns (``f_j``, ``t``, ``phi``);
- ``dof = 2n - 1`` without it (chi = 0, a map joined by its features alone): 4n + 2 observed
  minus 2n + 3 unknowns

(docs/method.md#chi-square-check). Two corrections make the statistic fit that distribution
on real maps (docs/method.md#calibration, measured over all clean joins of the five datasets):

- an a-posteriori variance factor (:func:`variance_factors`): the maps' own variances may be
  too small by a common factor (DLR's exact chi2/dof is 4); each join is tested against
  ``s`` times chi-square(dof), ``s`` the median, over the joins before it, of
  ``cost / median(chi-square(dof))`` (the joins' own minima; at least 1, and 1 during the first
  :data:`WARM_UP` joins; for the tree, :func:`level_variance_factors`: the joins of its own level and
  the levels below);
- the variances of common features last seen many maps away include the chain's odometry
  drift since (:mod:`mapjoin.drift`). That only lowers the minimum, so it is computed only for
  the joins whose own minimum fails the gate (:func:`calibrated`).

``chi2`` is the statistic tested, ``p`` the upper tail probability of ``chi2 / s``; a join is
*flagged* when ``p < gate`` or when its 1-D problem has two minima (Theorem 2: odometry heading
and feature evidence then disagree by more than 72°).

The cost splits into the features' share ``features_cost = c0 - 2 a0`` (the chi = 0
minimum, ``2n - 1`` dof) and the heading link's share ``chi2 - features_cost`` (>= 0). The
``skip`` policy uses it to tell which side of a flagged join is at fault (:func:`blame`).
"""

from __future__ import annotations

import dataclasses
import heapq
import logging
import math
from collections.abc import Callable
from typing import TYPE_CHECKING, Literal

import numpy as np

from .errors import JoinError

if TYPE_CHECKING:
    from .joins import JoinRecord, JoinResult

log = logging.getLogger("mapjoin")

__all__ = ["DEFAULT_GATE", "POLICIES", "WARM_UP", "Calibrated", "Policy", "VarianceFactors", "blame", "calibrated",
           "chi2_median", "chi2_quantile", "degrees_of_freedom", "describe", "enforce", "flags", "level_variance_factors", "p_values",
           "variance_factors"]

#: a join is flagged when its p-value is below this (docs/method.md#chi-square-check, measured)
DEFAULT_GATE = 1e-10
Policy = Literal["warn", "skip", "stop"]
POLICIES: tuple[str, ...] = ("warn", "skip", "stop")
#: tested joins (dof > 0) before the variance factor is estimated; until then it is 1
WARM_UP = 10


def degrees_of_freedom(common: np.ndarray, link: np.ndarray | bool = True) -> np.ndarray:
    """Observed scalars minus unknowns of joins with ``common`` common features: ``2n`` with the
    heading link, ``2n - 1`` without (never below 0: a join without common feature tests nothing)."""
    common = np.asarray(common, dtype=np.int64)
    return np.maximum(2 * common - np.where(link, 0, 1), 0)


def p_values(chi2: np.ndarray, dof: np.ndarray) -> np.ndarray:
    """``P(X >= chi2)`` for ``X ~ chi-square(dof)``; 1 where ``dof`` is 0 (nothing tested).

    For integer ``dof`` the upper regularised gamma function ``Q(dof/2, y)``, ``y = chi2/2``, is a
    finite sum: ``Q(a + 1, y) = Q(a, y) + y^a e^-y / Gamma(a + 1)`` from ``Q(1, y) = e^-y`` (even dof)
    or ``Q(1/2, y) = erfc(sqrt y)`` (odd), i.e. ``dof/2 - 1`` positive terms (no cancellation),
    summed for all joins at once in O(sum of dof) (a join's dof is twice its common features, so
    this is linear in the data). Numpy and :mod:`math` only: a join imports no scipy.
    """
    chi2, dof = np.asarray(chi2, dtype=float), np.asarray(dof, dtype=np.int64)
    y = np.maximum(chi2, 0.0) / 2
    odd = dof % 2 == 1
    first = np.where(odd, 0.5, 1.0)  # the exponent of the first term
    count = np.where(odd, (dof - 1) // 2, np.maximum(dof // 2 - 1, 0))  # terms: exponents first .. dof/2 - 1
    with np.errstate(divide="ignore"):
        log_y = np.log(y)
    base = np.exp(-y)
    base[odd] = [math.erfc(math.sqrt(value)) for value in y[odd].tolist()]  # odd dof: joins without the link
    # the terms more than 50 sqrt(y) + 50 below y are below e^-1250, exactly 0.0 in floating point (the Poisson
    # pmf's lower tail, exp(-(y - e)^2 / 2y)): skipped, they cost nothing and change no bit of the sum
    skip = np.clip(np.floor(y - 50 * np.sqrt(y) - 50 - first), 0, count).astype(np.int64)
    top = int(count.max(initial=0)) + 1
    count = count - skip
    join = np.repeat(np.arange(len(dof)), count)
    step = np.arange(len(join)) - np.repeat(np.cumsum(count) - count, count) + skip[join]  # the term's index
    log_factorial = np.concatenate([[0.0], np.cumsum(np.log(np.arange(1.0, top + 1)))])  # lgamma(k + 1)
    log_half = math.lgamma(1.5) + np.concatenate([[0.0], np.cumsum(np.log(np.arange(1.0, top + 1) + 0.5))])
    odd_term = odd[join]
    exponent = first[join] + step  # each term is y^e e^-y / Gamma(e + 1)
    log_gamma = np.where(odd_term, log_half[step], log_factorial[np.minimum(step + 1, top)])
    terms = np.exp(exponent * log_y[join] - y[join] - log_gamma)
    p = base + np.bincount(join, terms, len(dof))
    return np.where(dof > 0, np.minimum(p, 1.0), 1.0)


#: Newton's steps of :func:`chi2_quantile` at most (it needs 4-8 from its start; bisection's fall-backs more) ...
_QUANTILE_STEPS = 100
#: ... and the relative step below which a quantile has converged (Newton's next error is about its square)
_QUANTILE_TOLERANCE = 1e-15


def chi2_quantile(level: float, dof: np.ndarray | int) -> np.ndarray:
    """The ``level`` quantile of a chi-square with ``dof`` (integer, at least 1) degrees of freedom: the ``x`` whose
    upper tail :func:`p_values` is ``1 - level``, for an array of ``dof`` at once.

    Newton's method on the tail, whose derivative is minus the density ``x^(k-1) e^(-x/2) / (2^k Gamma(k))``,
    ``k = dof / 2``, from the Wilson-Hilferty approximation; a step that leaves the bracket the iterates have
    established is replaced by bisection, so the iteration cannot diverge where the density is steep (few
    degrees of freedom, small ``1 - level``). Numpy and :mod:`math` only: the association's gate and the
    refine's chi^2 check need no scipy (checked against ``scipy.special.chdtri`` in the tests)."""
    from statistics import NormalDist  # with fractions and decimal: ~2 ms a join that asks no quantile is spared

    if not 0.0 < level < 1.0:
        raise ValueError(f"level must be in (0, 1), got {level!r}")
    scalar = np.ndim(dof) == 0
    dof = np.atleast_1d(np.asarray(dof, dtype=np.int64))
    if (dof < 1).any():
        raise ValueError("a chi-square quantile needs at least one degree of freedom")
    tail, n = 1.0 - level, dof.astype(float)
    k = n / 2
    log_scale = -k * math.log(2.0) - np.array([math.lgamma(value) for value in k.tolist()])
    shape = 1 - 2 / (9 * n) + NormalDist().inv_cdf(level) * np.sqrt(2 / (9 * n))
    x = n * np.maximum(shape, 1e-3) ** 3
    low, high = np.zeros_like(x), np.full_like(x, np.inf)
    active = np.arange(len(x))  # the quantiles still moving
    for _ in range(_QUANTILE_STEPS):
        at = x[active]
        upper = p_values(at, dof[active])
        past = upper <= tail  # at or beyond the quantile
        high[active] = np.where(past, np.minimum(high[active], at), high[active])
        low[active] = np.where(past, low[active], np.maximum(low[active], at))
        with np.errstate(divide="ignore", over="ignore"):
            step = at + (upper - tail) / np.exp((k[active] - 1) * np.log(at) - at / 2 + log_scale[active])
        bracket_low, bracket_high = low[active], high[active]
        step = np.where((step > bracket_low) & (step < bracket_high), step,
                        np.where(np.isfinite(bracket_high), (bracket_low + bracket_high) / 2, 2 * at))
        x[active] = step
        active = active[np.abs(step - at) > _QUANTILE_TOLERANCE * at]
        if not len(active):
            break
    return x[0] if scalar else x


def chi2_median(dof: np.ndarray) -> np.ndarray:
    """The median of chi-square(``dof``), by the Wilson-Hilferty approximation ``dof (1 - 2/(9 dof))^3``
    (within 1.4 % for dof >= 2, 3.5 % high at dof 1); 0 where ``dof`` is 0."""
    dof = np.asarray(dof, dtype=float)
    safe = np.where(dof > 0, dof, 1.0)
    return np.where(dof > 0, safe * (1.0 - 2.0 / (9.0 * safe)) ** 3, 0.0)


def variance_factors(chi2: np.ndarray, dof: np.ndarray, warm_up: int = WARM_UP) -> np.ndarray:
    """Each join's a-posteriori variance factor ``s`` (docs/method.md#calibration), from the joins before it.

    If the statistic is ``s`` times a chi-square variable, ``q = chi2 / median(chi-square(dof))``
    has median ``s`` whatever each join's dof, so the running median of ``q`` over the tested
    joins (dof > 0) so far estimates ``s`` robustly: loop closures and bad maps, a minority, do
    not move it. ``s`` is 1 until ``warm_up`` joins have been tested, and never below 1: a factor
    below 1 would sharpen the test where the maps' variances are pessimistic, and then the joins
    the model describes worst (loop closures) would be flagged. Online (join k uses joins before
    k only), so that ``stop`` and ``skip`` decide each join as it happens. O(joins log joins).
    """
    return VarianceFactors(warm_up).extend(chi2, dof)


def level_variance_factors(chi2: np.ndarray, dof: np.ndarray, level: np.ndarray,
                           warm_up: int = WARM_UP) -> np.ndarray:
    """Each tree join's variance factor ``s`` (docs/method.md#calibration): the running median of
    :func:`variance_factors` taken over the joins of the levels up to and including its own.

    A tree level's joins are independent of each other and are solved as one batch before the next
    level (:func:`mapjoin.joining.join_tree`), and the policy acts once the tree is joined, so a level
    can be tested with the whole level known: its first joins then share the level's factor instead of
    being tested before the factor is known (DLR's first tree joins, in the warm-up, were flagged).
    The same rule otherwise: tested joins (dof > 0) only, at least 1, 1 while fewer than ``warm_up``
    joins of these levels are tested. One factor per level: it is the factor :class:`VarianceFactors`
    gives a join placed after the level's last one, in level order. O(joins log joins).
    """
    chi2, dof, level = np.asarray(chi2, dtype=float), np.asarray(dof, dtype=np.int64), np.asarray(level)
    order = np.argsort(level, kind="stable")
    levels = level[order]
    # online factors over the joins in level order, plus one untested join after the last (dof 0): entry i
    # is the factor from the joins before i, so entry ``end`` that of every join of the levels up to its own
    online = VarianceFactors(warm_up).extend(np.append(chi2[order], 0.0), np.append(dof[order], 0))
    factors = np.empty(len(chi2))
    factors[order] = online[np.searchsorted(levels, levels, side="right")]
    return factors


class VarianceFactors:
    """:func:`variance_factors` of a run whose joins come a block at a time (a stream): the running
    median's two halves are kept between blocks (one float per tested join), so each block's factors
    are those of the whole run so far."""

    def __init__(self, warm_up: int = WARM_UP) -> None:
        self._warm_up = max(warm_up, 1)
        self._low: list[float] = []  # max-heap (negated) of the lower half of the q so far
        self._high: list[float] = []  # min-heap of the upper half
        self._median = 1.0  # the median of the q so far (none yet: unused)
        self._tested = 0

    def extend(self, chi2: np.ndarray, dof: np.ndarray) -> np.ndarray:
        """The factors of the next joins (``chi2``, ``dof``: one each), from every join before each."""
        chi2, dof = np.asarray(chi2, dtype=float), np.asarray(dof, dtype=np.int64)
        q = chi2 / np.where(dof > 0, chi2_median(dof), 1.0)
        tested = dof > 0
        low, high = self._low, self._high
        medians = [self._median]  # medians[i]: the median after the first i tested q of this block
        push, pushpop, record = heapq.heappush, heapq.heappushpop, medians.append
        odd = self._tested % 2 == 0  # the count after this value: odd, the lower half holds one more
        for value in q[tested].tolist():
            if odd:
                push(low, -pushpop(high, value))
                record(-low[0])
            else:
                push(high, -pushpop(low, -value))
                record((high[0] - low[0]) / 2)
            odd = not odd
        before = np.cumsum(tested) - tested  # tested joins of this block before each join
        factors = np.where(self._tested + before >= self._warm_up, np.maximum(np.array(medians)[before], 1.0), 1.0)
        self._median, self._tested = medians[-1], self._tested + int(tested.sum())
        return factors


@dataclasses.dataclass(frozen=True)
class Calibrated:
    """The calibrated test of a run's joins (arrays over the joins, docs/method.md#calibration)."""

    chi2: np.ndarray
    features_cost: np.ndarray
    variance_factor: np.ndarray
    p: np.ndarray

    def __post_init__(self) -> None:
        if not self.chi2.shape == self.features_cost.shape == self.variance_factor.shape == self.p.shape:
            raise ValueError("Calibrated: one value per join in each array")


def calibrated(cost: np.ndarray, features_cost: np.ndarray, dof: np.ndarray, link: np.ndarray, gate: float,
               retest: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]] | None,
               variance_factor: np.ndarray | None = None) -> Calibrated:
    """Each join's statistic, variance factor and p-value (docs/method.md#calibration).

    ``cost`` is each join's own minimum (``features_cost``, ``c0 - 2 a0``, where ``link`` is False) and
    ``s`` = :func:`variance_factors` of these. A join whose own ``p`` (of ``cost / s``) is at least
    ``gate`` keeps it: the drift-aware minimum is never larger, so it would pass too. The others are
    tested on the drift-aware minimum ``retest(joins)`` gives (with and without the heading link, the
    latter the new ``features_cost``), all in one call: the drift is computed for them only.
    ``variance_factor``: ``s`` when the joins are a block of a longer run (:class:`VarianceFactors`).
    """
    s = variance_factors(cost, dof) if variance_factor is None else variance_factor
    p = p_values(cost / s, dof)
    chi2, features_cost = cost.copy(), np.asarray(features_cost, dtype=float).copy()
    failing = np.flatnonzero(p < gate)
    if retest is not None and failing.size:
        linked, free = retest(failing)
        chi2[failing] = np.where(link[failing], linked, free)
        features_cost[failing] = free
        p[failing] = p_values(chi2[failing] / s[failing], dof[failing])
    return Calibrated(chi2, features_cost, s, p)


def flags(p: np.ndarray, minima: np.ndarray, gate: float = DEFAULT_GATE) -> np.ndarray:
    """Flagged joins: ``p < gate`` or two minima (always)."""
    if not 0.0 <= gate <= 1.0:
        raise ValueError(f"gate must be a probability in [0, 1], got {gate!r}")
    return (np.asarray(p) < gate) | (np.asarray(minima) == 2)


def blame(features_cost: float, common: int, gate: float = DEFAULT_GATE,
          variance_factor: float = 1.0) -> Literal["odometry", "features"]:
    """Which side of a flagged join contradicts the other.

    ``odometry`` when the features alone fit (the chi = 0 minimum ``features_cost``, divided by the
    join's ``variance_factor``, passes the gate with its ``2n - 1`` degrees of freedom): the heading
    link is what the features disagree with, so the map can be joined by its features. ``features``
    otherwise: the map's features disagree with the map so far whatever the heading.
    """
    dof = degrees_of_freedom(np.array([common]), False)
    if dof[0] > 0 and p_values(np.array([features_cost / variance_factor]), dof)[0] >= gate:
        return "odometry"
    return "features"


def describe(record: JoinRecord, gate: float) -> str:
    """Why ``record`` is flagged, in one clause."""
    template, arguments = _why(record, gate)
    return template % arguments


def _why(record: JoinRecord, gate: float) -> tuple[str, tuple]:
    """:func:`describe`'s message as a logging template and its arguments (one template per kind of
    flag, so that the command line can count repeated warnings of a kind)."""
    if record.minima == 2:
        return ("join %d has two minima (C_phi = %+.3f rad): its odometry heading and its features contradict "
                "each other grossly", (record.join, record.c_phi))
    link = record.chi2 - record.features_cost if record.action == "joined" else 0.0
    return ("join %d is inconsistent: chi^2 = %.6g for %d degrees of freedom, variance factor %.3g (p = %.3g < %g; "
            "heading link's share %.6g, C_phi = %+.3f rad)",
            (record.join, record.chi2, record.dof, record.variance_factor, record.p, gate, link, record.c_phi))


def _warn(flagged: list[JoinRecord], gate: float) -> None:
    """One warning per flagged join, naming its map."""
    for record in flagged:
        template, arguments = _why(record, gate)
        log.warning("%s: " + template, record.map, *arguments)


def enforce(result: JoinResult, policy: Policy, gate: float,
            rejoin: Callable[[frozenset[int], frozenset[int]], JoinResult] | None) -> JoinResult:
    """Apply ``policy`` to the flagged joins of ``result`` (docs/method.md#chi-square-check).

    - ``warn``: one warning per flagged join naming its map (the command line shows the first of
      each kind and counts the rest); ``result`` unchanged.
    - ``stop``: :class:`~mapjoin.errors.JoinError` naming the first flagged join's map.
    - ``skip``: the best map that can still be made. Flagged joins are resolved one at a time, in
      chain order: if the features alone pass the gate (:func:`blame` says ``odometry``), the map is
      joined by its features alone (the chi = 0 solution, phi* = phi0); otherwise, or if that join is
      still flagged, the map is left out: its features are dropped and its end pose kept (placed by
      its odometry from the previous map's end), so the chain continues through it. ``rejoin(unlinked,
      left_out)`` joins the chain again with those join numbers (sequential strategy only: join k
      puts map k+1 onto maps 1..k); each resolved join costs one such join of the whole chain.
    """
    if policy not in POLICIES:
        raise ValueError(f"unknown policy {policy!r}; expected one of {', '.join(POLICIES)}")
    flagged = [r for r in result.report if r.flag]
    if not flagged:
        return result
    if policy == "stop":
        raise JoinError(f"{flagged[0].map}: {describe(flagged[0], gate)}; stopped (policy stop), "
                        f"{len(flagged)} inconsistent joins in all")
    if policy == "warn":
        _warn(flagged, gate)
        return result
    if rejoin is None:
        raise ValueError("the skip policy needs a rejoin (the sequential strategy)")
    unlinked: set[int] = set()
    left_out: set[int] = set()
    while True:
        pending = next((r for r in result.report if r.flag and r.join not in left_out), None)
        if pending is None:
            break
        number = pending.join
        if number not in unlinked and blame(pending.features_cost, pending.common, gate,
                                            pending.variance_factor) == "odometry":
            unlinked.add(number)
            log.warning("%s: %s; its features alone fit, so it is joined by them without the heading link "
                        "(phi* = phi0)", pending.map, describe(pending, gate))
        else:
            unlinked.discard(number)
            left_out.add(number)
            log.warning("%s: %s; left out: its features dropped, its end pose kept (placed by its odometry)",
                        pending.map, describe(pending, gate))
        result = rejoin(frozenset(unlinked), frozenset(left_out))
    report = tuple(dataclasses.replace(r, action="left out") if r.join in left_out else r for r in result.report)
    return dataclasses.replace(result, report=report)
