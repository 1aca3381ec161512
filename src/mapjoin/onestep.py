"""The one-step problem with spherical covariances: Theorem 1, Theorem 2 and Algorithm 1.

Notation follows docs/method.md (#one-step-problem, #theorem-1, #theorem-2, #algorithm-1). Pose r0 is the origin, the unknowns are the pose
``r1 = (t, phi)`` and the common features ``f_j``; the data are ``Z0_j`` (features in r0,
variance ``var0_j``), the odometry ``O = (O_xy, z_phi)`` (variances ``var_o``, ``p_phi``)
and ``Z1_j`` (features in r1, variance ``var1_j``).

**The O(n) form of Theorem 1.** Eliminating ``f_j`` at fixed ``(t, phi)`` leaves
``s_j |Z0_j - R(phi) Z1_j - t|^2`` with ``s_j = 1 / (var0_j + var1_j)``; the odometry is
one more pair of points ``(O_xy, 0)`` with weight ``1 / var_o``. Eliminating ``t`` then
centres both point sets at their weighted means ``m0, m1`` (``t = m0 - R(phi) m1``), and

    f_chi(phi) = c0 - 2 a0 cos(phi - phi0) + chi wrap(z_phi - phi)^2 / p_phi

with ``q = p - m`` the centred points, ``w`` their weights,
``c0 = sum w (|q0|^2 + |q1|^2)``, ``A = sum w q0.q1``, ``B = sum w (q0 x q1)``
(``q0_y q1_x - q0_x q1_y``), ``a0 = hypot(A, B)``, ``phi0 = atan2(B, A)``. These equal the
dense matrix formulas of the paper's Theorem 1 (``tests/test_onestep.py`` checks it).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from types import SimpleNamespace
from typing import Any, Literal, NamedTuple

import numpy as np

from .arithmetic import ARRAYS, FLOATS, backend
from .se2 import rotation, wrap

__all__ = [
    "Condition",
    "Constants",
    "MinimaAnalysis",
    "Minimum",
    "OneStepProblem",
    "OneStepSolution",
    "Solver",
    "analyse_minima",
    "constants",
    "cost",
    "global_orientation",
    "linked_cost",
    "MinimaSummary",
    "Orientations",
    "as_complex",
    "point_constants",
    "minimise_reduced",
    "summarise_minima",
    "recover",
    "reduced_cost",
    "solve",
]

Solver = Literal["bisection", "golden"]
SOLVERS: tuple[str, ...] = ("bisection", "golden")
_PI_LOW = 1.2246467991473532e-16  # pi - float(pi)
TOLERANCE = 1e-12  # bracket width (rad) at which bisection and golden-section stop


@dataclass(frozen=True)
class OneStepProblem:
    """Data of one join: the common features seen from r0 and from r1, and the odometry.

    ``link=False`` drops the orientation term (chi = 0): point-set registration.
    """

    z0: np.ndarray
    var0: np.ndarray
    z1: np.ndarray
    var1: np.ndarray
    odometry: np.ndarray
    odometry_variances: np.ndarray
    link: bool = True


@dataclass(frozen=True)
class Constants:
    """c0, a0, phi0 of Theorem 1, and the weighted means that recover ``t = m0 - R(phi) m1``.

    ``weight`` is the total weight ``W`` of the point pairs: the information of ``t`` at fixed phi.
    The means are complex numbers ``x + iy`` except in :func:`constants` (x/y arrays); for a batch
    (:func:`point_constants` with ``problem_of``) every field is an array, one entry per problem.
    """

    c0: float | np.ndarray
    a0: float | np.ndarray
    phi0: float | np.ndarray
    mean0: complex | np.ndarray
    mean1: complex | np.ndarray
    weight: float | np.ndarray


def as_complex(xy: np.ndarray) -> np.ndarray:
    """x/y pairs (the last axis) as complex numbers ``x + iy``, the form the one-step sums use."""
    return xy[..., 0] + 1j * xy[..., 1]


def constants(problem: OneStepProblem) -> Constants:
    """c0, a0, phi0 of Theorem 1 in O(n) (see the module docstring for the derivation)."""
    k = point_constants(as_complex(problem.z0), problem.var0, as_complex(problem.z1), problem.var1,
                        complex(as_complex(problem.odometry[:2])), float(problem.odometry_variances[0]))
    return Constants(k.c0, k.a0, k.phi0, np.array([k.mean0.real, k.mean0.imag]),
                     np.array([k.mean1.real, k.mean1.imag]), k.weight)


def point_constants(z0: np.ndarray, var0: np.ndarray, z1: np.ndarray, var1: np.ndarray, odometry, odometry_variance,
                    problem_of: np.ndarray | None = None) -> Constants:
    """Theorem 1's constants with points as complex numbers ``x + iy`` (docs/method.md#weighted-sums).

    One problem (``problem_of`` None): ``odometry`` (the x/y of O) is a complex number and
    ``odometry_variance`` (var_o) a float, and the constants are Python numbers. A batch: they are
    arrays, one entry per problem, and common feature j belongs to problem ``problem_of[j]`` (any
    order, a problem may have none). Either way the features' sums are ``np.bincount``'s, added left
    to right from 0 (one problem is group 0 of one), and the odometry pair ``(O_xy, 0)`` with weight
    ``1 / var_o`` is added after them in real arithmetic, so that a problem's constants are the
    same, bit for bit, alone or in any batch.
    """
    ops = FLOATS if problem_of is None else ARRAYS
    group, count = (np.zeros(len(z0), dtype=np.intp), 1) if problem_of is None else (problem_of, len(odometry))
    total, total_xy, at = ops.total, ops.total_xy, ops.at
    weights = 1.0 / (var0 + var1)
    odometry_weight = 1.0 / odometry_variance
    p0, p1 = weights * z0, weights * z1
    pairs = ops.pairs(group)  # the problems of the x/y pairs of complex values (``values.view(float)``)
    weight = total(group, weights, count) + odometry_weight
    (sum0_x, sum0_y), (sum1_x, sum1_y) = total_xy(pairs, p0.view(float), count), total_xy(pairs, p1.view(float), count)
    o_x, o_y = odometry.real, odometry.imag
    mean0_x, mean0_y = (sum0_x + odometry_weight * o_x) / weight, (sum0_y + odometry_weight * o_y) / weight
    mean1_x, mean1_y = sum1_x / weight, sum1_y / weight
    mean0, mean1 = ops.complex(mean0_x, mean0_y), ops.complex(mean1_x, mean1_y)
    q0, q1 = z0 - at(mean0, group), z1 - at(mean1, group)
    q1_conj = q1.conj()
    spread = weights * (q0 * q0.conj() + q1 * q1_conj).real  # w (|q0|^2 + |q1|^2): its sum is c0
    big_a, big_b = total_xy(pairs, (weights * (q0 * q1_conj)).view(float), count)  # sum w q0 conj(q1) = A + iB
    # the odometry pair: q0 = O_xy - m0, q1 = -m1
    d_x, d_y = o_x - mean0_x, o_y - mean0_y
    c0 = total(group, spread, count) + odometry_weight * (d_x * d_x + d_y * d_y + mean1_x * mean1_x
                                                          + mean1_y * mean1_y)
    big_a = big_a - odometry_weight * (d_x * mean1_x + d_y * mean1_y)
    big_b = big_b - odometry_weight * (d_y * mean1_x - d_x * mean1_y)
    return Constants(c0, ops.hypot(big_a, big_b), ops.atan2(big_b, big_a), mean0, mean1, weight)


def cost(problem: OneStepProblem, phi, consts: Constants | None = None):
    """f_chi(phi) of Theorem 1 (scalar or array ``phi``)."""
    k = consts or constants(problem)
    if problem.link:
        value = linked_cost(k, problem.odometry[2], problem.odometry_variances[1], np.asarray(phi))
    else:
        value = k.c0 - 2.0 * k.a0 * np.cos(np.asarray(phi) - k.phi0)
    return value if np.ndim(phi) else float(value)


def linked_cost(k: Constants, z_phi, p_phi, phi):
    """f_1(phi) = c0 - 2 a0 cos(phi - phi0) + wrap(z_phi - phi)^2 / p_phi (Theorem 1; numbers, or arrays that
    broadcast)."""
    residual = wrap(z_phi - phi)
    return k.c0 - 2.0 * k.a0 * backend(phi).cos(phi - k.phi0) + residual * residual / p_phi


def recover(problem: OneStepProblem, phi: float, consts: Constants | None = None
            ) -> tuple[np.ndarray, np.ndarray]:
    """Theorem 1's X_L at ``phi``: the common features (n x 2) and ``t``, in closed form."""
    k = consts or constants(problem)
    rot = rotation(phi)
    t = k.mean0 - rot @ k.mean1
    w0, w1 = 1.0 / problem.var0, 1.0 / problem.var1
    features = ((w0[:, None] * problem.z0 + w1[:, None] * (problem.z1 @ rot.T + t))
                / (w0 + w1)[:, None])
    return features, t


@dataclass(frozen=True)
class Condition:
    """One of the conditions (16)-(21) of Theorem 2: ``value relation bound``."""

    number: int
    expression: str
    value: float
    relation: str
    bound: float

    @property
    def holds(self) -> bool:
        """Whether the condition holds strictly (equality is a degenerate, non-minimum stationary point)."""
        if math.isnan(self.value):
            return False
        return self.value > self.bound if self.relation == ">=" else self.value < self.bound


@dataclass(frozen=True)
class Minimum:
    """A local minimum of the reduced cost: ``varphi`` (rad, in [-pi, pi)) and ``fbar`` there."""

    varphi: float
    fbar: float
    iterations: int


@dataclass(frozen=True)
class MinimaAnalysis:
    """Theorem 2 for ``fbar(varphi) = -a cos(varphi + c_phi) + varphi^2 / 2`` on [-pi, pi).

    ``brackets`` are the intervals where ``h = fbar'`` increases and changes sign, one per
    local minimum; ``count = len(brackets)``.
    """

    a: float
    c_phi: float
    phi1: float
    phi2: float
    h1: float
    h2: float
    brackets: tuple[tuple[float, float], ...]

    @property
    def count(self) -> int:
        """Number of local minima (1 or 2)."""
        return len(self.brackets)

    @property
    def conditions(self) -> tuple[Condition, ...]:
        """Conditions (16)-(21) with their values (h1, h2 = h(phi1), h(phi2); NaN when a <= 1)."""
        h_edge = -self.a * math.sin(self.c_phi)
        return (
            Condition(16, "a", self.a, ">=", 1.0),
            Condition(17, "-a sin(C_phi) - pi", h_edge - math.pi, "<=", 0.0),
            Condition(18, "sqrt(a^2-1) + phi1", self.h1, ">=", 0.0),
            Condition(19, "-sqrt(a^2-1) + phi2", self.h2, "<=", 0.0),
            Condition(20, "-a sin(C_phi) + pi", h_edge + math.pi, ">=", 0.0),
            Condition(21, "phi1 - phi2", self.phi1 - self.phi2, "<=", 0.0),
        )


def _fbar(ops: SimpleNamespace, a, c_phi, varphi):
    """fbar(varphi) = -a cos(varphi + c_phi) + varphi^2 / 2 (Theorem 2) with ``ops``."""
    return -a * ops.cos(varphi + c_phi) + 0.5 * varphi * varphi


def reduced_cost(a: float, c_phi: float, varphi):
    """fbar(varphi) = -a cos(varphi + c_phi) + varphi^2 / 2 (Theorem 2; a float or an array ``varphi``)."""
    if isinstance(varphi, float):
        return _fbar(FLOATS, a, c_phi, varphi)
    value = _fbar(ARRAYS, a, c_phi, np.asarray(varphi, dtype=float))
    return value if value.ndim else float(value)


class _Brackets(NamedTuple):
    """Theorem 2's analysis of fbar for one problem (numbers) or many (arrays): see :func:`_brackets`."""

    steep: Any  # a > 1: g vanishes at phi1 and phi2 (else phi1, phi2, h1, h2 are meaningless)
    phi1: Any
    phi2: Any
    h1: Any
    h2: Any
    low: Any  # the first bracket (low, high): a problem's only one when it has one minimum
    high: Any
    second_low: Any  # the second bracket (second_low, pi), where ``two``
    two: Any


def _brackets(ops: SimpleNamespace, a, c_phi) -> _Brackets:
    """Count and bracket the local minima of fbar on [-pi, pi) (Theorem 2, conditions (16)-(21)).

    g = fbar'' vanishes at ``phi1 = wrap(arccos(-1/a) - c_phi)`` and
    ``phi2 = wrap(-arccos(-1/a) - c_phi)`` (when a > 1: ``steep``); h decreases between them (going
    forward from phi1 to phi2). When phi1 < phi2 the increasing parts are [-pi, phi1] and
    [phi2, pi] and each holds a minimum iff h changes sign strictly inside it; if rounding leaves
    neither, the one with the larger margin (the first on a tie: Theorem 2 guarantees one minimum).
    Otherwise h increases on one interval (the whole circle when a <= 1) holding the one minimum.
    A minimum never sits at the wrap point: there h jumps down by 2 pi. Written without branches
    (``ops.where``), for one problem or many (docs/method.md#brackets).
    """
    bad = ops.not_(ops.isfinite(a) & ops.isfinite(c_phi) & (a >= 0))
    if ops.any(bad):  # (a NaN is not finite)
        raise ValueError(f"expected a finite a >= 0 and a finite c_phi, got a={float(ops.first(bad, a))!r}, "
                         f"c_phi={float(ops.first(bad, c_phi))!r}")
    pi, where, not_ = math.pi, ops.where, ops.not_
    h_edge = -a * ops.sin(c_phi)  # h(-pi) + pi = h(pi) - pi
    steep = a > 1
    phi1, phi2, h1, h2 = _inflections(where(steep, a, 2.0), c_phi, ops)  # a <= 1: unused values
    split = steep & (phi1 < phi2)  # h increases on [-pi, phi1] and [phi2, pi]
    margin1, margin2 = ops.minimum(pi - h_edge, h1), ops.minimum(-h2, h_edge + pi)  # > 0: h changes sign
    first, second = split & (margin1 > 0), split & (margin2 > 0)
    neither = split & not_(first) & not_(second)  # rounding at a boundary
    first = first | (neither & (margin1 >= margin2))
    second = second | (neither & (margin1 < margin2))
    # one bracket: (-pi, pi) when a <= 1, (phi2, phi1) when phi1 >= phi2, else (-pi, phi1) or (phi2, pi)
    low = where(steep & not_(first), phi2, -pi)
    high = where(steep & (not_(split) | first), phi1, pi)
    return _Brackets(steep, phi1, phi2, h1, h2, low, high, where(second, phi2, pi), first & second)


def analyse_minima(a: float, c_phi: float) -> MinimaAnalysis:
    """Count and bracket the local minima of fbar on [-pi, pi) (Theorem 2, conditions (16)-(21)):
    :func:`_brackets` of one problem."""
    found = _brackets(FLOATS, a, c_phi)
    brackets = ((found.low, found.high), (found.second_low, math.pi)) if found.two else ((found.low, found.high),)
    phi1, phi2, h1, h2 = found[1:5] if found.steep else (math.nan,) * 4
    return MinimaAnalysis(a, c_phi, phi1, phi2, h1, h2, brackets)


def _inflections(a, c_phi, ops: SimpleNamespace) -> tuple:
    """phi1, phi2 (the zeros of g) and h(phi1), h(phi2) for a > 1, free of cancellation near a = 1.

    With ``root = sqrt(a^2 - 1)`` and ``delta = atan(root)``, ``arccos(-1/a) = pi - delta`` and
    ``h(phi1) = root + phi1 = (root - delta) + (phi1 + delta)``; ``root - delta`` is taken
    from its series when small, where both terms nearly cancel (docs/method.md#precision).
    """
    root = ops.sqrt((a - 1.0) * (a + 1.0))
    delta = ops.atan(root)
    small = ops.minimum(root, 1e-2)  # the series is used below 1e-2 only (and must not overflow)
    excess = ops.where(root < 1e-2, small**3 / 3 - small**5 / 5 + small**7 / 7, root - delta)  # root - atan(root)
    # phi1 = wrap(pi - c_phi - delta) = shift1 - delta with shift1 = pi - c_phi - 2 pi k; the
    # subtraction of 2 pi k is exact when it nearly cancels, which is where precision matters,
    # and pi's rounding error (_PI_LOW) is added back so that c_phi = float(-pi) is exact too
    two_pi = 2 * math.pi
    k1 = ops.floor((two_pi - c_phi - delta) / two_pi)
    k2 = ops.floor((delta - c_phi) / two_pi)
    shift1 = (math.pi * (1 - 2 * k1) - c_phi) + _PI_LOW * (1 - 2 * k1)
    shift2 = (-math.pi * (1 + 2 * k2) - c_phi) - _PI_LOW * (1 + 2 * k2)
    return shift1 - delta, shift2 + delta, excess + shift1, -excess + shift2


def _bisection(ops: SimpleNamespace, a, c_phi, low, high, tolerance: float) -> tuple:
    """The root of h in [low, high], where h increases, and the steps taken, by bisection (Algorithm 1,
    step 2; docs/method.md#bisection-and-golden-section).

    Halves the bracket on the sign of h at the midpoint until it is at most ``tolerance`` wide or
    the midpoint equals an end. The first :func:`_sure_steps` steps, which no bracket can stop in,
    are taken without the test; then a finished problem is frozen while the others of its batch go
    on. One problem takes the steps it would take in any batch: its numbers do not depend on it.
    """
    sin, where = ops.sin, ops.where  # looked up once: a join of the sequential strategy takes ~43 steps
    sure = _sure_steps(ops, low, high, tolerance)
    for _ in range(sure):
        middle = 0.5 * (low + high)
        below = a * sin(middle + c_phi) + middle < 0  # h(middle) < 0: the root is above
        low, high = where(below, middle, low), where(below, high, middle)
    iterations = ops.full(low, sure)
    while True:
        middle = 0.5 * (low + high)
        active = (high - low > tolerance) & (middle != low) & (middle != high)
        if not ops.any(active):
            return middle, iterations
        below = a * sin(middle + c_phi) + middle < 0
        low, high = where(active & below, middle, low), where(active & ops.not_(below), middle, high)
        iterations = iterations + active


def _sure_steps(ops: SimpleNamespace, low, high, tolerance: float) -> int:
    """How many bisection steps every bracket takes for certain: all stay wider than the tolerance and 4 ulp.

    A step halves the width up to the rounding of the midpoint, at most ``ulp/2`` of the endpoints'
    sum; over any number of steps the width stays above ``w0 / 2^k - ulp``. While ``w0 / 2^k >=
    4 m`` with ``m = max(tolerance, 4 ulp)`` it is above ``m``: the stopping rule cannot hold.
    """
    if not ops.size(low):
        return 0
    ulp = math.ulp(2 * float(ops.largest(ops.maximum(abs(low), abs(high)))))
    margin = 4 * max(tolerance, 4 * ulp)
    narrowest = float(ops.smallest(high - low))
    return max(0, math.floor(math.log2(narrowest / margin)) + 1) if narrowest >= margin else 0


_INVERSE_GOLDEN = (math.sqrt(5.0) - 1.0) / 2.0


def _golden(ops: SimpleNamespace, a, c_phi, low, high, tolerance: float) -> tuple:
    """The minimum of fbar on [low, high], where fbar is convex, and the steps taken, by golden-section
    search (Remark 7; docs/method.md#bisection-and-golden-section): the best of the four final points,
    the first of equal values. A finished problem is frozen while the others of its batch go on."""
    where = ops.where  # selects tuples of values at once (one call a selection on numbers)
    x1 = high - _INVERSE_GOLDEN * (high - low)
    x2 = low + _INVERSE_GOLDEN * (high - low)
    f1, f2 = _fbar(ops, a, c_phi, x1), _fbar(ops, a, c_phi, x2)
    iterations = ops.full(low, 0)
    while True:
        active = (high - low > tolerance) & (x1 < x2)
        if not ops.any(active):
            break
        left = f1 <= f2  # the minimum is in [low, x2], else in [x1, high]; the inner point kept, its value
        new_low, new_high, kept, f_kept = where(left, (low, x2, x1, f1), (x1, high, x2, f2))
        probe = where(left, new_high - _INVERSE_GOLDEN * (new_high - new_low),
                      new_low + _INVERSE_GOLDEN * (new_high - new_low))
        f_probe = _fbar(ops, a, c_phi, probe)
        new = (new_low, new_high, *where(left, (probe, kept, f_probe, f_kept), (kept, probe, f_kept, f_probe)))
        # a finished problem keeps its state (while every problem goes on there is none to keep)
        low, high, x1, x2, f1, f2 = new if ops.all(active) else where(active, new, (low, high, x1, x2, f1, f2))
        iterations = iterations + active
    best, f_best = low, _fbar(ops, a, c_phi, low)
    for x in (x1, x2, high):
        f_x = _fbar(ops, a, c_phi, x)
        best, f_best = where(f_x < f_best, (x, f_x), (best, f_best))
    return best, iterations


_SEARCHES = {"bisection": _bisection, "golden": _golden}


def _minima(ops: SimpleNamespace, a, c_phi, found: _Brackets, solver: Solver, tolerance: float) -> tuple:
    """(varphi, fbar, iterations) of the minimum in the first bracket and in the second one (NaN, NaN, 0
    where there is none), and ``swap``: whether the second is the lower, so the global minimum (Algorithm 1,
    steps 2-3; on a tie the first bracket's)."""
    if solver not in SOLVERS:
        raise ValueError(f"unknown solver {solver!r}; expected one of {', '.join(SOLVERS)}")
    search = _SEARCHES[solver]
    varphi1, steps1 = search(ops, a, c_phi, found.low, found.high, tolerance)
    varphi2, steps2, fbar2 = ops.full(a, math.nan), ops.full(a, 0), ops.full(a, math.nan)
    if ops.any(found.two):  # rarely: most problems have one minimum
        varphi2, steps2 = ops.apply_where(found.two, search, (ops, a, c_phi, found.second_low,
                                                              ops.full(found.second_low, math.pi), tolerance),
                                          (math.nan, 0))
        fbar2 = _fbar(ops, a, c_phi, varphi2)
    fbar1 = _fbar(ops, a, c_phi, varphi1)
    return (varphi1, fbar1, steps1), (varphi2, fbar2, steps2), fbar2 < fbar1


def minimise_reduced(analysis: MinimaAnalysis, solver: Solver = "bisection",
                     tolerance: float = TOLERANCE) -> tuple[Minimum, ...]:
    """Every local minimum of fbar, lowest first (Algorithm 1, steps 2-3): :func:`_minima` of one problem."""
    (low, high), (second_low, _) = analysis.brackets[0], analysis.brackets[-1]
    found = _Brackets(analysis.a > 1, analysis.phi1, analysis.phi2, analysis.h1, analysis.h2, low, high, second_low,
                      analysis.count == 2)
    first, second, swap = _minima(FLOATS, analysis.a, analysis.c_phi, found, solver, tolerance)
    return tuple(Minimum(*m) for m in ((second, first) if swap else (first, second))[:analysis.count])


@dataclass(frozen=True)
class MinimaSummary:
    """One flat row of Theorem 2's answer for (a, C_phi): count, zeros of g, every minimum."""

    a: float
    c_phi: float
    minima: int
    phi1: float
    phi2: float
    varphi_1: float
    fbar_1: float
    varphi_2: float | None
    fbar_2: float | None


def summarise_minima(a: float, c_phi: float, solver: Solver = "bisection") -> MinimaSummary:
    """Analyse and locate the minima of fbar for (a, C_phi), lowest minimum first."""
    analysis = analyse_minima(a, c_phi)
    minima = minimise_reduced(analysis, solver)
    second = minima[1] if len(minima) > 1 else None
    return MinimaSummary(a, c_phi, len(minima), analysis.phi1, analysis.phi2, minima[0].varphi,
                         minima[0].fbar, second.varphi if second else None, second.fbar if second else None)


@dataclass(frozen=True)
class OneStepSolution:
    """The global optimum of a one-step problem.

    ``phi`` and ``t`` are the pose r1, ``features`` the common features (frame r0),
    ``cost`` is f_chi(phi*). With the orientation link, ``minima`` is Theorem 2's analysis
    and ``other_phi``/``other_cost`` the second local minimum when there is one.
    ``phi_information`` is f_chi''(phi*)/2, the information of phi after eliminating X_L.
    """

    phi: float
    t: np.ndarray
    features: np.ndarray
    cost: float
    constants: Constants
    minima: MinimaAnalysis | None
    other_phi: float | None
    other_cost: float | None
    iterations: int
    phi_information: float


class Orientations(NamedTuple):
    """:func:`global_orientation` of one problem (numbers) or many (arrays, one entry per problem).

    ``phi`` is the global minimiser of f_1, ``other_phi`` the other local minimum (NaN where f_1 has
    one); ``a``, ``c_phi`` and ``count`` are Theorem 2's reduction and number of minima, ``iterations``
    the search steps summed over the minima. (A named tuple: the sequential join makes one a join.)
    """

    phi: Any
    other_phi: Any
    a: Any
    c_phi: Any
    count: Any
    iterations: Any


def global_orientation(a0, phi0, z_phi, p_phi, solver: Solver = "bisection", tolerance: float = TOLERANCE
                       ) -> Orientations:
    """Algorithm 1 on f_1 (docs/method.md#algorithm-1) for one problem (numbers) or many (arrays):
    reduce to fbar with ``a = a0 p_phi``, ``C_phi = wrap(z_phi - phi0)``, bracket, minimise, map back.
    A problem gets the same numbers, bit for bit, alone or in any batch."""
    ops = backend(a0)
    a, c_phi = a0 * p_phi, wrap(z_phi - phi0)
    found = _brackets(ops, a, c_phi)
    (varphi1, _, steps1), (varphi2, _, steps2), swap = _minima(ops, a, c_phi, found, solver, tolerance)
    lowest, other = ops.where(swap, varphi2, varphi1), ops.where(swap, varphi1, varphi2)
    return Orientations(wrap(z_phi + lowest), wrap(z_phi + other), a, c_phi, 1 + found.two, steps1 + steps2)


def solve(problem: OneStepProblem, solver: Solver = "bisection", tolerance: float = TOLERANCE
          ) -> OneStepSolution:
    """Algorithm 1: the global minimum of f_chi over phi, then X_L from Theorem 1.

    Without the orientation link the optimum is ``phi0`` in closed form.
    """
    k = constants(problem)
    if not problem.link:
        if k.a0 == 0.0:
            raise ValueError("without an orientation link the orientation needs two distinct points")
        phi = wrap(k.phi0)
        features, t = recover(problem, phi, k)
        return OneStepSolution(phi, t, features, cost(problem, phi, k), k, None, None, None, 0, k.a0)
    p_phi = float(problem.odometry_variances[1])
    found = global_orientation(k.a0, k.phi0, float(problem.odometry[2]), p_phi, solver, tolerance)
    other_phi = found.other_phi if found.count == 2 else None
    features, t = recover(problem, found.phi, k)
    return OneStepSolution(
        phi=found.phi, t=t, features=features, cost=cost(problem, found.phi, k), constants=k,
        minima=analyse_minima(found.a, found.c_phi), other_phi=other_phi,
        other_cost=cost(problem, other_phi, k) if other_phi is not None else None,
        iterations=found.iterations, phi_information=k.a0 * math.cos(found.phi - k.phi0) + 1.0 / p_phi,
    )
