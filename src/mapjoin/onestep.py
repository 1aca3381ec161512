"""The one-step problem with spherical covariances: Theorem 1, Theorem 2 and Algorithm 1.

Notation follows ``method.md``. Pose r0 is the origin, the unknowns are the pose
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
from typing import Literal

import numpy as np

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
    "minimise_reduced",
    "summarise_minima",
    "recover",
    "reduced_cost",
    "solve",
    "wrap",
]

Solver = Literal["bisection", "golden"]
SOLVERS: tuple[str, ...] = ("bisection", "golden")
_PI_LOW = 1.2246467991473532e-16  # pi - float(pi)
TOLERANCE = 1e-12  # bracket width (rad) at which bisection and golden-section stop


def wrap(angle):
    """Map angles (a float or an array) into [-pi, pi)."""
    wrapped = (angle + math.pi) % (2 * math.pi) - math.pi
    # (angle + pi) % 2pi can round up to exactly 2pi for angles just below -pi
    if isinstance(wrapped, float):
        return wrapped - 2 * math.pi if wrapped >= math.pi else wrapped
    return np.where(wrapped >= math.pi, wrapped - 2 * math.pi, wrapped)


def rotation(phi: float) -> np.ndarray:
    """R(phi)."""
    c, s = math.cos(phi), math.sin(phi)
    return np.array([[c, -s], [s, c]])


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


def constants(problem: OneStepProblem) -> Constants:
    """c0, a0, phi0 of Theorem 1 in O(n) (see the module docstring for the derivation)."""
    def points(xy: np.ndarray) -> np.ndarray:
        return xy[..., 0] + 1j * xy[..., 1]

    k = batch_constants(np.zeros(len(problem.z0), dtype=np.intp), 1, points(problem.z0), problem.var0,
                        points(problem.z1), problem.var1, points(problem.odometry[None, :2]),
                        problem.odometry_variances[:1])
    mean0, mean1 = complex(k.mean0[0]), complex(k.mean1[0])
    return Constants(float(k.c0[0]), float(k.a0[0]), float(k.phi0[0]), np.array([mean0.real, mean0.imag]),
                     np.array([mean1.real, mean1.imag]), float(k.weight[0]))


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


def _inflections(a: float, c_phi: float) -> tuple[float, float, float, float]:
    """phi1, phi2 (the zeros of g) and h(phi1), h(phi2) for a > 1, free of cancellation near a = 1.

    With ``root = sqrt(a^2 - 1)`` and ``delta = atan(root)``, ``arccos(-1/a) = pi - delta`` and
    ``h(phi1) = root + phi1 = (root - delta) + (phi1 + delta)``; ``root - delta`` is taken
    from its series when small, where both terms nearly cancel.
    """
    root = math.sqrt((a - 1.0) * (a + 1.0))
    delta = math.atan(root)
    excess = (root**3 / 3 - root**5 / 5 + root**7 / 7) if root < 1e-2 else root - delta  # root - atan(root)
    # phi1 = wrap(pi - c_phi - delta) = shift1 - delta with shift1 = pi - c_phi - 2 pi k; the
    # subtraction of 2 pi k is exact when it nearly cancels, which is where precision matters,
    # and pi's rounding error (_PI_LOW) is added back so that c_phi = float(-pi) is exact too
    two_pi = 2 * math.pi
    k1 = math.floor((two_pi - c_phi - delta) / two_pi)
    k2 = math.floor((delta - c_phi) / two_pi)
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
