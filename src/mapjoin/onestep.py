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
from typing import Literal

import numpy as np

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
    "batch_constants",
    "constants",
    "cost",
    "global_orientation",
    "linked_cost",
    "Orientation",
    "MinimaSummary",
    "Orientations",
    "as_complex",
    "batch_orientation",
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
    For a batch (:func:`batch_constants`) every field has one more leading axis, one entry per problem.
    """

    c0: float
    a0: float
    phi0: float
    mean0: np.ndarray
    mean1: np.ndarray
    weight: float


def as_complex(xy: np.ndarray) -> np.ndarray:
    """x/y pairs (the last axis) as complex numbers ``x + iy``, the form the one-step sums use."""
    return xy[..., 0] + 1j * xy[..., 1]


def constants(problem: OneStepProblem) -> Constants:
    """c0, a0, phi0 of Theorem 1 in O(n) (see the module docstring for the derivation)."""
    k = point_constants(as_complex(problem.z0), problem.var0, as_complex(problem.z1), problem.var1,
                        complex(as_complex(problem.odometry[:2])), float(problem.odometry_variances[0]))
    return Constants(k.c0, k.a0, k.phi0, np.array([k.mean0.real, k.mean0.imag]),
                     np.array([k.mean1.real, k.mean1.imag]), k.weight)


def point_constants(z0: np.ndarray, var0: np.ndarray, z1: np.ndarray, var1: np.ndarray, odometry: complex,
                    odometry_variance: float) -> Constants:
    """Theorem 1's constants of one problem with points as complex numbers ``x + iy``, as Python numbers.

    The same sums as :func:`batch_constants` in a few numpy calls (one join of the sequential
    strategy): with ``s = w q0``, ``sum w |q0|^2 = vdot(q0, s)`` and ``A + iB = vdot(q1, s)``.
    """
    weights = 1.0 / (var0 + var1)
    odometry_weight = 1.0 / odometry_variance
    weight = float(np.add.reduce(weights)) + odometry_weight
    mean0 = (complex(np.dot(weights, z0)) + odometry_weight * odometry) / weight
    mean1 = complex(np.dot(weights, z1)) / weight
    q0, q1 = z0 - mean0, z1 - mean1
    s0 = weights * q0
    o0 = odometry - mean0  # the odometry pair (O_xy, 0), centred
    c0 = (complex(np.vdot(q0, s0) + np.vdot(q1, weights * q1)).real
          + odometry_weight * (o0.real**2 + o0.imag**2 + mean1.real**2 + mean1.imag**2))
    moment = complex(np.vdot(q1, s0)) - odometry_weight * o0 * mean1.conjugate()
    return Constants(c0, abs(moment), math.atan2(moment.imag, moment.real), mean0, mean1, weight)


def batch_constants(problem_of: np.ndarray, count: int, z0: np.ndarray, var0: np.ndarray, z1: np.ndarray,
                    var1: np.ndarray, odometry: np.ndarray, odometry_variance: np.ndarray) -> Constants:
    """Theorem 1's constants of ``count`` one-step problems at once, as arrays of length ``count``.

    Points are complex numbers ``x + iy`` (and so are the means returned). Common feature j
    belongs to problem ``problem_of[j]`` (any order, a problem may have none); ``odometry``
    (the x/y of each problem's O) and ``odometry_variance`` (var_o) give its odometry point
    pair ``(O_xy, 0)`` with weight ``1 / var_o``, appended as one more pair. With complex
    points ``A + iB = sum w q0 conj(q1)``.
    """
    group = np.concatenate([problem_of, np.arange(count)])
    weights = 1.0 / np.concatenate([var0 + var1, odometry_variance])
    p0 = np.concatenate([z0, odometry])
    p1 = np.concatenate([z1, np.zeros(count, dtype=complex)])

    def total(values: np.ndarray) -> np.ndarray:
        return np.bincount(group, weights * values, count)

    def complex_total(values: np.ndarray) -> np.ndarray:
        return total(values.real) + 1j * total(values.imag)

    weight = np.bincount(group, weights, count)
    mean0, mean1 = complex_total(p0) / weight, complex_total(p1) / weight
    q0, q1 = p0 - mean0[group], p1 - mean1[group]
    c0 = total(q0.real**2 + q0.imag**2 + q1.real**2 + q1.imag**2)
    moment = complex_total(q0 * q1.conj())
    return Constants(c0, np.abs(moment), np.angle(moment), mean0, mean1, weight)


def cost(problem: OneStepProblem, phi, consts: Constants | None = None):
    """f_chi(phi) of Theorem 1 (scalar or array ``phi``)."""
    k = consts or constants(problem)
    if problem.link:
        value = linked_cost(k, problem.odometry[2], problem.odometry_variances[1], np.asarray(phi))
    else:
        value = k.c0 - 2.0 * k.a0 * np.cos(np.asarray(phi) - k.phi0)
    return value if np.ndim(phi) else float(value)


def linked_cost(k: Constants, z_phi, p_phi, phi):
    """f_1(phi) = c0 - 2 a0 cos(phi - phi0) + wrap(z_phi - phi)^2 / p_phi (Theorem 1; arrays broadcast)."""
    return k.c0 - 2.0 * k.a0 * np.cos(phi - k.phi0) + wrap(z_phi - phi) ** 2 / p_phi


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


def reduced_cost(a: float, c_phi: float, varphi):
    """fbar(varphi) = -a cos(varphi + c_phi) + varphi^2 / 2 (Theorem 2)."""
    if isinstance(varphi, float):
        return -a * math.cos(varphi + c_phi) + 0.5 * varphi**2
    varphi = np.asarray(varphi, dtype=float)
    value = -a * np.cos(varphi + c_phi) + 0.5 * varphi**2
    return value if value.ndim else float(value)


def analyse_minima(a: float, c_phi: float) -> MinimaAnalysis:
    """Count and bracket the local minima of fbar on [-pi, pi) (Theorem 2, conditions (16)-(21)).

    g = fbar'' vanishes at ``phi1 = wrap(arccos(-1/a) - c_phi)`` and
    ``phi2 = wrap(-arccos(-1/a) - c_phi)``; h decreases between them (going forward from
    phi1 to phi2). When phi1 < phi2 the increasing parts are [-pi, phi1] and [phi2, pi]
    and each holds a minimum iff h changes sign strictly inside it; otherwise h increases
    on one interval (the whole circle when a <= 1) holding the one minimum. A minimum
    never sits at the wrap point: there h jumps down by 2 pi.
    """
    if not (math.isfinite(a) and math.isfinite(c_phi)) or a < 0:
        raise ValueError(f"expected a finite a >= 0 and a finite c_phi, got a={a!r}, c_phi={c_phi!r}")
    pi = math.pi
    h_left = -a * math.sin(c_phi) - pi   # h(-pi)
    h_right = -a * math.sin(c_phi) + pi  # h(pi)
    if a > 1:
        phi1, phi2, h1, h2 = _inflections(a, c_phi)
    else:
        phi1 = phi2 = h1 = h2 = math.nan
    if not a > 1:
        brackets: tuple[tuple[float, float], ...] = ((-pi, pi),)
    elif phi1 >= phi2:
        brackets = ((phi2, phi1),)
    else:
        # margin > 0: h changes sign strictly inside the interval, so it holds a minimum
        candidates = (((-pi, phi1), min(-h_left, h1)), ((phi2, pi), min(-h2, h_right)))
        brackets = tuple(b for b, margin in candidates if margin > 0)
        if not brackets:  # rounding at a boundary; Theorem 2 guarantees one minimum
            brackets = (max(candidates, key=lambda c: c[1])[0],)
    return MinimaAnalysis(a, c_phi, phi1, phi2, h1, h2, brackets)


# the few functions _inflections needs, for one problem (floats) or many at once (arrays); the
# arrays' atan is math.atan too (one call per problem), as numpy's may differ in the last bit
# and so would the brackets: batches then give exactly the scalar results
_FLOATS = SimpleNamespace(sqrt=math.sqrt, atan=math.atan, floor=math.floor, minimum=min,
                          where=lambda condition, x, y: x if condition else y)
_ARRAYS = SimpleNamespace(sqrt=np.sqrt, atan=lambda x: np.array([math.atan(v) for v in x.tolist()]),
                          floor=np.floor, minimum=np.minimum, where=np.where)


def _inflections(a, c_phi, ops: SimpleNamespace = _FLOATS) -> tuple:
    """phi1, phi2 (the zeros of g) and h(phi1), h(phi2) for a > 1, free of cancellation near a = 1.

    With ``root = sqrt(a^2 - 1)`` and ``delta = atan(root)``, ``arccos(-1/a) = pi - delta`` and
    ``h(phi1) = root + phi1 = (root - delta) + (phi1 + delta)``; ``root - delta`` is taken
    from its series when small, where both terms nearly cancel. ``ops`` is ``_FLOATS`` for
    floats, ``_ARRAYS`` for arrays of problems.
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


def _bisection(a: float, c_phi: float, low: float, high: float, tolerance: float) -> tuple[float, int]:
    """The root of h in [low, high], where h increases, by bisection (Algorithm 1, step 2)."""
    sin = math.sin  # h(x) = a sin(x + c_phi) + x, inlined: this loop runs ~42 times a join
    iterations = 0
    while high - low > tolerance:
        middle = 0.5 * (low + high)
        if middle == low or middle == high:
            break
        if a * sin(middle + c_phi) + middle < 0:
            low = middle
        else:
            high = middle
        iterations += 1
    return 0.5 * (low + high), iterations


_INVERSE_GOLDEN = (math.sqrt(5.0) - 1.0) / 2.0


def _golden(a: float, c_phi: float, low: float, high: float, tolerance: float) -> tuple[float, int]:
    """The minimum of fbar on [low, high], where fbar is convex, by golden-section search (Remark 7)."""
    f = lambda x: -a * math.cos(x + c_phi) + 0.5 * x * x  # noqa: E731
    x1 = high - _INVERSE_GOLDEN * (high - low)
    x2 = low + _INVERSE_GOLDEN * (high - low)
    f1, f2 = f(x1), f(x2)
    iterations = 0
    while high - low > tolerance and x1 < x2:
        if f1 <= f2:
            high, x2, f2 = x2, x1, f1
            x1 = high - _INVERSE_GOLDEN * (high - low)
            f1 = f(x1)
        else:
            low, x1, f1 = x1, x2, f2
            x2 = low + _INVERSE_GOLDEN * (high - low)
            f2 = f(x2)
        iterations += 1
    best = min((low, x1, x2, high), key=f)
    return best, iterations


def minimise_reduced(analysis: MinimaAnalysis, solver: Solver = "bisection",
                     tolerance: float = TOLERANCE) -> tuple[Minimum, ...]:
    """Every local minimum of fbar, lowest first (Algorithm 1, steps 2-3)."""
    if solver not in SOLVERS:
        raise ValueError(f"unknown solver {solver!r}; expected one of {', '.join(SOLVERS)}")
    search = _bisection if solver == "bisection" else _golden
    minima = []
    for low, high in analysis.brackets:
        varphi, iterations = search(analysis.a, analysis.c_phi, low, high, tolerance)
        minima.append(Minimum(varphi, reduced_cost(analysis.a, analysis.c_phi, varphi), iterations))
    return tuple(sorted(minima, key=lambda m: m.fbar))


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


@dataclass(frozen=True)
class Orientation:
    """The global minimiser ``phi`` of f_1 (Algorithm 1), the other local minimum if any, and Theorem 2's analysis."""

    phi: float
    other_phi: float | None
    minima: MinimaAnalysis
    iterations: int


def global_orientation(a0: float, phi0: float, z_phi: float, p_phi: float, solver: Solver = "bisection",
                       tolerance: float = TOLERANCE) -> Orientation:
    """Algorithm 1 on f_1: reduce to fbar with ``a = a0 p_phi``, ``C_phi = wrap(z_phi - phi0)``, count, minimise."""
    analysis = analyse_minima(a0 * p_phi, wrap(z_phi - phi0))
    minima = minimise_reduced(analysis, solver, tolerance)
    other = wrap(z_phi + minima[1].varphi) if len(minima) > 1 else None
    return Orientation(wrap(z_phi + minima[0].varphi), other, analysis, sum(m.iterations for m in minima))


@dataclass(frozen=True)
class Orientations:
    """:func:`global_orientation` of many problems (:func:`batch_orientation`), one array entry per problem.

    ``other_phi`` is NaN where f_1 has one minimum; ``a``, ``c_phi`` and ``count`` are Theorem 2's
    reduction and number of minima, ``iterations`` the search steps summed over the minima.
    """

    phi: np.ndarray
    other_phi: np.ndarray
    a: np.ndarray
    c_phi: np.ndarray
    count: np.ndarray
    iterations: np.ndarray


def batch_orientation(a0: np.ndarray, phi0: np.ndarray, z_phi: np.ndarray, p_phi: np.ndarray,
                      solver: Solver = "bisection", tolerance: float = TOLERANCE) -> Orientations:
    """Algorithm 1 on f_1 for many problems at once: :func:`global_orientation` as array operations.

    Theorem 2's analysis is :func:`analyse_minima` as array expressions, and every bracket is
    searched in lockstep with the same steps and stopping rule as the scalar search, so the
    cost is a fixed number of numpy calls per search step, whatever the number of problems.
    """
    if solver not in SOLVERS:
        raise ValueError(f"unknown solver {solver!r}; expected one of {', '.join(SOLVERS)}")
    a, c_phi = a0 * p_phi, wrap(z_phi - phi0)
    bad = ~(np.isfinite(a) & np.isfinite(c_phi) & (a >= 0))
    if bad.any():
        i = int(np.argmax(bad))
        raise ValueError(f"expected a finite a >= 0 and a finite c_phi, got a={float(a[i])!r}, "
                         f"c_phi={float(c_phi[i])!r}")
    low, high, two = _batch_brackets(a, c_phi)
    # the second brackets (problems with two minima) follow the first ones in one flat search
    second = np.flatnonzero(two)
    problem = np.concatenate([np.arange(len(a)), second])
    search = _batch_bisection if solver == "bisection" else _batch_golden
    varphi, iterations = search(a[problem], c_phi[problem], np.concatenate([low[0], low[1, second]]),
                                np.concatenate([high[0], high[1, second]]), tolerance)
    fbar = reduced_cost(a[problem], c_phi[problem], varphi)
    best, other = varphi[:len(a)], np.full(len(a), math.nan)
    other[second] = varphi[len(a):]
    swap = second[fbar[len(a):] < fbar[second]]  # lowest minimum first; a tie keeps the first bracket
    best[swap], other[swap] = other[swap], best[swap]
    steps = iterations[:len(a)].copy()
    steps[second] += iterations[len(a):]
    return Orientations(wrap(z_phi + best), wrap(z_phi + other), a, c_phi, 1 + two, steps)


def _batch_brackets(a: np.ndarray, c_phi: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`analyse_minima`'s brackets as arrays: ``low``, ``high`` (2, n) and ``two`` (n,).

    Row 0 holds each problem's first bracket (its only one with one minimum), row 1 the second
    where ``two`` is True (two minima).
    """
    pi = math.pi
    h_edge = -a * np.sin(c_phi)
    steep = a > 1
    phi1, phi2, h1, h2 = _inflections(np.where(steep, a, 2.0), c_phi, _ARRAYS)  # a <= 1: unused values
    split = steep & (phi1 < phi2)  # h increases on [-pi, phi1] and [phi2, pi]
    margin1, margin2 = np.minimum(pi - h_edge, h1), np.minimum(-h2, h_edge + pi)
    first, second = split & (margin1 > 0), split & (margin2 > 0)
    neither = split & ~first & ~second  # rounding at a boundary: the larger margin, the first on a tie
    first |= neither & (margin1 >= margin2)
    second |= neither & (margin1 < margin2)
    # one bracket: (-pi, pi) when a <= 1, (phi2, phi1) when phi1 >= phi2, else (-pi, phi1) or (phi2, pi)
    low = np.where(steep & ~first, phi2, -pi)
    high = np.where(steep & (~split | first), phi1, pi)
    return np.stack([low, np.where(second, phi2, pi)]), np.stack([high, np.full_like(high, pi)]), first & second


def _batch_bisection(a: np.ndarray, c_phi: np.ndarray, low: np.ndarray, high: np.ndarray, tolerance: float
                     ) -> tuple[np.ndarray, np.ndarray]:
    """:func:`_bisection` of every bracket in lockstep: the roots of h and the steps each took.

    The first :func:`_sure_steps` steps are taken without the stopping rule (no bracket can
    meet it yet), in place; the remaining few test it bracket by bracket.
    """
    low, high = low.copy(), high.copy()
    sure = _sure_steps(low, high, tolerance)
    middle, h = np.empty_like(low), np.empty_like(low)
    below = np.empty(len(low), dtype=bool)
    for _ in range(sure):
        np.add(low, high, out=middle)
        middle *= 0.5
        np.add(middle, c_phi, out=h)
        np.sin(h, out=h)
        h *= a
        h += middle
        np.less(h, 0.0, out=below)  # h(middle) = a sin(middle + c_phi) + middle < 0: the root is above
        np.copyto(low, middle, where=below)
        np.copyto(high, middle, where=~below)
    iterations = np.full(len(low), sure, dtype=np.intp)
    while True:
        middle = 0.5 * (low + high)
        active = (high - low > tolerance) & (middle != low) & (middle != high)
        if not np.count_nonzero(active):
            return middle, iterations
        below = a * np.sin(middle + c_phi) + middle < 0
        low = np.where(active & below, middle, low)
        high = np.where(active & ~below, middle, high)
        iterations += active


def _sure_steps(low: np.ndarray, high: np.ndarray, tolerance: float) -> int:
    """How many bisection steps every bracket takes for certain: all stay wider than the tolerance and 4 ulp.

    A step halves the width up to the rounding of the midpoint, at most ``ulp/2`` of the endpoints'
    sum; over any number of steps the width stays above ``w0 / 2^k - ulp``. While ``w0 / 2^k >=
    4 m`` with ``m = max(tolerance, 4 ulp)`` it is above ``m``: the stopping rule cannot hold.
    """
    if not len(low):
        return 0
    ulp = float(np.spacing(2 * max(np.abs(low).max(), np.abs(high).max())))
    margin = 4 * max(tolerance, 4 * ulp)
    narrowest = float((high - low).min())
    return max(0, math.floor(math.log2(narrowest / margin)) + 1) if narrowest >= margin else 0


def _batch_golden(a: np.ndarray, c_phi: np.ndarray, low: np.ndarray, high: np.ndarray, tolerance: float
                  ) -> tuple[np.ndarray, np.ndarray]:
    """:func:`_golden` of every bracket in lockstep: the minima of fbar and the steps each took."""
    def f(x: np.ndarray) -> np.ndarray:
        return -a * np.cos(x + c_phi) + 0.5 * x * x

    x1 = high - _INVERSE_GOLDEN * (high - low)
    x2 = low + _INVERSE_GOLDEN * (high - low)
    f1, f2 = f(x1), f(x2)
    iterations = np.zeros(len(low), dtype=np.intp)
    while True:
        active = (high - low > tolerance) & (x1 < x2)
        if not active.any():
            break
        left = active & (f1 <= f2)  # the minimum is in [low, x2]
        right = active & ~(f1 <= f2)  # ... in [x1, high]
        high, low = np.where(left, x2, high), np.where(right, x1, low)
        probe = np.where(left, high - _INVERSE_GOLDEN * (high - low), low + _INVERSE_GOLDEN * (high - low))
        f_probe = f(probe)
        x1, x2 = np.where(left, probe, np.where(right, x2, x1)), np.where(left, x1, np.where(right, probe, x2))
        f1, f2 = np.where(left, f_probe, np.where(right, f2, f1)), np.where(left, f1, np.where(right, f_probe, f2))
        iterations += active
    candidates = np.stack([low, x1, x2, high])
    best = np.argmin(f(candidates), axis=0)  # the first of equal values, as min() takes
    return candidates[best, np.arange(len(low))], iterations


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
    features, t = recover(problem, found.phi, k)
    return OneStepSolution(
        phi=found.phi, t=t, features=features, cost=cost(problem, found.phi, k), constants=k,
        minima=found.minima, other_phi=found.other_phi,
        other_cost=cost(problem, found.other_phi, k) if found.other_phi is not None else None,
        iterations=found.iterations, phi_information=k.a0 * math.cos(found.phi - k.phi0) + 1.0 / p_phi,
    )
