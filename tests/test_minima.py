"""Theorem 2 (number and position of the minima of the reduced cost) against brute force.

The reference here is an independent, *certified* counter of the strict local minima of

    fbar(varphi) = -a cos(varphi + C) + varphi^2 / 2   on the circle [-pi, pi),

built only from samples of ``h = fbar'`` and ``g = fbar''`` (no use of phi1, phi2 or of the
conditions (16)-(21)):

* a local minimum of fbar is a point where h changes sign from negative to positive
  (fbar is continuous on the circle; at the wrap point h jumps by -2 pi, so it is never
  a minimum);
* on a cell where g does not vanish h is monotone, so the signs of h at the two ends
  of the cell count its minima exactly;
* ``|g'| = a |sin(varphi + C)|`` and ``|h'| = |g|`` bound how far g and h can move inside a
  cell, so a cell in which *both* g and h may vanish is detected from its end values and
  subdivided, recursively, until it is resolved (or is so small that rounding decides:
  the case is then reported as unresolved and never used as evidence). The resolution
  therefore adapts to the distance from a boundary of the two-minima region.

``h`` and ``g`` are evaluated with the addition theorem (``sin x cos C + cos x sin C``),
which keeps full accuracy when ``varphi + C`` is close to a multiple of pi (the
implementation evaluates ``sin(varphi + C)`` directly), with an explicit rounding bound.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from theorem_oracles import _h_g, brute_count

from mapjoin.arithmetic import ARRAYS
from mapjoin.onestep import (
    TOLERANCE,
    _brackets,
    analyse_minima,
    global_orientation,
    minimise_reduced,
)

PI = math.pi
# arcsin(pi / sqrt(pi^2 + 1)) = arctan(pi): the paper's bound on |C| for two minima.
C_STAR = math.atan(math.pi)


# --------------------------------------------------------------------------- brute force


def brute_minima(a: float, c: float, n: int = 20_001):
    """Positions of the local minima of fbar (sign changes of h, refined by bisection).

    Only for well-separated roots (use brute_count for the number of minima).
    """
    x = np.linspace(-PI, PI, n)
    h = _h_g(a, c, x)[0]
    idx = np.nonzero((h[:-1] < 0) & (h[1:] >= 0))[0]
    sc, cc = math.sin(c), math.cos(c)
    slope = lambda v: a * (math.sin(v) * cc + math.cos(v) * sc) + v  # noqa: E731
    roots = []
    for i in idx:
        lo, hi = float(x[i]), float(x[i + 1])
        for _ in range(100):
            mid = 0.5 * (lo + hi)
            if mid in (lo, hi):
                break
            if slope(mid) < 0:
                lo = mid
            else:
                hi = mid
        roots.append(0.5 * (lo + hi))
    return roots


def fbar(a, c, x):
    return -a * np.cos(x + c) + 0.5 * np.asarray(x) ** 2


def implementation_count(a, c):
    return np.array([analyse_minima(float(ai), float(ci)).count for ai, ci in zip(a, c)])


def wrap(x):
    return (np.asarray(x, dtype=float) + PI) % (2 * PI) - PI


def _compare(a, c, min_resolved=0.995):
    """Implementation count == certified brute-force count wherever the latter is resolved."""
    a, c = np.broadcast_arrays(np.asarray(a, float), np.asarray(c, float))
    a, c = a.ravel(), c.ravel()
    expected, resolved = brute_count(a, c)
    assert resolved.mean() >= min_resolved, f"only {resolved.mean():.4f} of the cases resolved"
    got = implementation_count(a[resolved], c[resolved])
    bad = np.nonzero(got != expected[resolved])[0]
    detail = [(float(a[resolved][i]), float(c[resolved][i]), int(got[i]),
               int(expected[resolved][i])) for i in bad[:10]]
    assert not bad.size, f"{bad.size} mismatches (a, C, implementation, brute force): {detail}"
    return int(resolved.sum()), expected[resolved]


# --------------------------------------------------------------------------- 1. counts


def test_count_random_log_uniform_a():
    rng = np.random.default_rng(20130901)
    m = 6000
    a = 10 ** rng.uniform(-3, 6, m)
    c = rng.uniform(-PI, PI, m)
    n, counts = _compare(a, c)
    assert n >= 5970
    assert set(np.unique(counts)) == {1, 2}


def test_count_dense_grid_of_the_two_minima_region():
    a = np.linspace(1.0, 30.0, 117)
    c = np.concatenate([np.linspace(1.2, PI, 40), -np.linspace(1.2, PI, 40)])
    n, counts = _compare(a[:, None], c[None, :])
    assert n >= 0.995 * a.size * c.size
    assert 0.1 < (counts == 2).mean() < 0.9  # the grid really covers the region


ADVERSARIAL = (
    [(1.0 + s * e, c) for s in (-1, 1) for e in (1e-3, 1e-5, 1e-7)
     for c in (-PI, -PI + 1e-3, PI - 1e-3, PI / 2, -PI / 2, 0.0, C_STAR, -C_STAR, 2.0)]
    + [(a, s * (C_STAR + d)) for s in (-1, 1) for d in (-1e-4, -1e-7, 0.0, 1e-7, 1e-4, 1e-2)
       for a in (1.0, 2.0, math.hypot(PI, 1.0), 3.2866, 10.0, 1e3)
       # (sqrt(pi^2+1), +-C_STAR) is the corner of the region: h(pi) = g(pi) = 0, a
       # degenerate root at the wrap point that no float computation resolves.
       if not (d == 0.0 and a == math.hypot(PI, 1.0))]
    + [(a, c) for a in (0.0, 0.5, 1.0, 1.5, 3.0, PI, 10.0, 1e6)
       for c in (PI / 2, -PI / 2, -PI, PI - 1e-15, np.nextafter(-PI, 0.0))]
)


def test_count_adversarial_points():
    a, c = np.array(ADVERSARIAL).T
    n, _ = _compare(a, c, min_resolved=1.0)
    assert n == len(ADVERSARIAL)


@pytest.mark.parametrize("c_phi", [-PI, np.nextafter(-PI, 0.0), PI - 1e-12, -PI + 1e-10],
                         ids=["-pi", "-pi+1ulp", "pi-1e-12", "-pi+1e-10"])
def test_count_just_above_a_equal_one(c_phi):
    """a = 1 + eps, eps = 1e-12 .. 1e-3, C near +-pi: two minima at varphi ~ +-sqrt(6 eps).

    Theorem 2 says at least one minimum, and the brute force resolves most of these points.
    """
    eps = np.logspace(-12, -3, 91)
    a = 1.0 + eps
    c = np.full_like(a, c_phi)
    got = implementation_count(a, c)
    expected, resolved = brute_count(a, c)
    assert resolved.mean() >= 0.5
    wrong = [(float(e), int(g), int(x) if r else "unresolved")
             for e, g, x, r in zip(eps, got, expected, resolved) if g < 1 or (r and g != x)]
    assert not wrong, f"{len(wrong)} wrong counts (a - 1, implementation, brute force): {wrong}"


# ---- boundaries of the two-minima region, found by bisection on the brute-force count


def _boundaries_along(fixed, axis, lo, hi, n=2000):
    """Points where the brute-force count changes, along a (axis='a') or C (axis='c')."""
    xs = np.linspace(lo, hi, n)
    pair = (lambda x: (x, np.full_like(x, fixed))) if axis == "a" else \
           (lambda x: (np.full_like(x, fixed), x))
    counts, resolved = brute_count(*pair(xs))
    assert resolved.all()
    found = []
    for i in np.nonzero(np.diff(counts))[0]:
        left, right = xs[i], xs[i + 1]
        count_left = counts[i]
        for _ in range(80):
            mid = 0.5 * (left + right)
            if mid in (left, right):
                break
            cm, ok = brute_count(*pair(np.array([mid])))
            if not ok[0]:
                break
            if cm[0] == count_left:
                left = mid
            else:
                right = mid
        found.append(0.5 * (left + right))
    return found


# (axis, fixed value, scan from, scan to, number of boundaries on the line)
BOUNDARY_LINES = (
    [("a", c, 0.5, 80.0, 2) for c in (1.5, PI / 2, 2.0, 2.5, 3.0, 3.1, -1.4, -2.2, -3.1)]
    + [("a", 1.3, 3.0, 3.4, 2), ("a", -(C_STAR + 0.01), 3.28, 3.29, 2),  # near the corner
       ("a", 1.25, 0.5, 80.0, 0), ("a", -1.2, 0.5, 80.0, 0)]            # |C| < arctan(pi)
    + [("c", a, -PI, PI, 2) for a in (1.001, 1.5, 2.0, PI, 5.0, 10.0, 30.0, 300.0)]
    # below sqrt(pi^2 + 1) the thin wedge at the corner is a separate piece: |C| in (1.307, 1.312)
    + [("c", 3.25, -PI, PI, 6)]
)


@pytest.mark.parametrize("axis,fixed,lo,hi,expected_boundaries", BOUNDARY_LINES,
                         ids=[f"along-{ax}-at-{'C' if ax == 'a' else 'a'}{f:g}"
                              for ax, f, *_ in BOUNDARY_LINES])
def test_count_on_both_sides_of_each_boundary(axis, fixed, lo, hi, expected_boundaries):
    """Boundaries found by bisection on the brute-force count; both sides at 1e-4 .. 1e-7."""
    boundaries = _boundaries_along(fixed, axis, lo, hi)
    assert len(boundaries) == expected_boundaries
    ends = [lo, hi] + ([lo + 2 * PI, hi - 2 * PI] if axis == "c" else [])  # C is periodic
    checked = 0
    for b in boundaries:
        room = min(abs(b - x) for x in ends + [o for o in boundaries if o != b])
        for d in (1e-4, 1e-5, 1e-6, 1e-7):
            if d > room / 4:
                continue
            checked += 1
            xs = np.array([b - d, b + d])
            a, c = (xs, np.full(2, fixed)) if axis == "a" else (np.full(2, fixed), xs)
            expected, resolved = brute_count(a, c)
            assert resolved.all()
            assert expected[0] != expected[1], "the bisection did not find a boundary"
            assert implementation_count(a, c).tolist() == expected.tolist(), (b, d)
    assert checked >= 2 * len(boundaries)


# --------------------------------------------------------------------------- 2. conditions


def paper_conditions(a: float, c: float):
    """Values of (16)-(21) as the paper states them, computed here (a > 1).

    h(varphi) is evaluated by the addition theorem rather than through sqrt(a^2 - 1).
    """
    alpha = math.acos(-1.0 / a)
    phi1, phi2 = float(wrap(alpha - c)), float(wrap(-alpha - c))
    h = lambda x: float(_h_g(a, c, np.array(x))[0])  # noqa: E731
    return {16: a, 17: h(-PI), 18: h(phi1), 19: h(phi2), 20: h(PI), 21: phi1 - phi2}, phi1, phi2


@settings(max_examples=200, deadline=None)
@given(a=st.floats(1.0 + 1e-6, 1e4), c=st.floats(-PI, PI, exclude_max=True))
def test_conditions_are_16_to_21_and_decide_the_count(a, c):
    analysis = analyse_minima(a, c)
    values, phi1, phi2 = paper_conditions(a, c)
    scale = 1e-10 * (a + PI)
    assert [k.number for k in analysis.conditions] == [16, 17, 18, 19, 20, 21]
    for cond in analysis.conditions:
        assert cond.value == pytest.approx(values[cond.number], abs=scale), cond
        assert cond.bound == (1.0 if cond.number == 16 else 0.0)
        assert cond.relation == (">=" if cond.number in (16, 18, 20) else "<=")
    # phi1, phi2: zeros of g, g going from + to - at phi1 (h has a maximum), - to + at phi2.
    for phi, sign in ((analysis.phi1, -1), (analysis.phi2, 1)):
        assert -PI <= phi < PI
        _, g, _, eg, _ = _h_g(a, c, np.array([phi - 1e-7, phi, phi + 1e-7]))
        assert abs(g[1]) <= 1e-12 * (a + 1)
        assert np.sign(g[2] - g[0]) == sign
    assert analysis.phi1 == pytest.approx(phi1, abs=1e-12)
    assert analysis.phi2 == pytest.approx(phi2, abs=1e-12)
    expected, resolved = brute_count(a, c)
    near_bound = any(abs(k.value - k.bound) <= 1e-9 * (a + PI) for k in analysis.conditions)
    if resolved[0] and not near_bound:
        assert analysis.count == expected[0]
        assert (analysis.count == 2) == all(k.holds for k in analysis.conditions)
        # the paper's non-strict reading agrees away from the boundaries
        paper = (a >= 1 and values[17] <= 0 and values[18] >= 0 and values[19] <= 0
                 and values[20] >= 0 and values[21] <= 0)
        assert paper == (expected[0] == 2)


def test_exact_boundary_a_one_c_minus_pi():
    """a = 1, C = -pi: h = varphi - sin(varphi) has a triple root at 0 (h = g = g' = 0).

    Brute force (h is nondecreasing since g = 1 - cos >= 0): one minimum, at 0. With exact
    values alpha = arccos(-1) = pi, phi1 = wrap(2 pi) = 0 = phi2 and every one of (16)-(21)
    holds with equality in (16), (18), (19), (21): the paper's *non-strict* conditions would
    announce two minima. The implementation reads them strictly and finds one.
    """
    x = np.linspace(-PI, PI, 100_001)
    h = x - np.sin(x)                        # exactly C = -pi
    assert np.all(np.diff(h) >= 0)
    assert ((h[:-1] < 0) & (h[1:] >= 0)).sum() == 1
    assert brute_count(1.0, -PI)[0][0] == 1  # the float C = -pi, 1.2e-16 from -pi
    exact = {16: 1.0 - 1.0, 17: -PI, 18: 0.0 + 0.0, 19: -0.0 + 0.0, 20: PI, 21: 0.0 - 0.0}
    non_strict = (exact[16] >= 0 and exact[17] <= 0 and exact[18] >= 0 and exact[19] <= 0
                  and exact[20] >= 0 and exact[21] <= 0)
    assert non_strict  # the paper's reading: "two minima"
    analysis = analyse_minima(1.0, -PI)
    assert analysis.count == 1
    assert not all(k.holds for k in analysis.conditions)
    (minimum,) = minimise_reduced(analysis)
    assert abs(minimum.varphi) < 1e-4  # (6 * 1.2e-16)^(1/3) ~ 1e-5 for the float C


@pytest.mark.parametrize("c_phi,number", [(-PI / 2, 17), (PI / 2, 20)], ids=["eq17", "eq20"])
def test_exact_boundary_root_at_the_wrap_point(c_phi, number):
    """a = pi, C = -+pi/2: h(-+pi) = 0 exactly, i.e. (17) resp. (20) holds with equality.

    The other five conditions hold strictly, so the paper's non-strict reading announces two
    minima; but the root of h sits on the wrap point, which is never a minimum (fbar
    decreases through it): brute force finds one. ``holds`` must be False there.
    """
    a = PI
    analysis = analyse_minima(a, c_phi)
    by_number = {k.number: k for k in analysis.conditions}
    assert by_number[number].value == 0.0
    assert not by_number[number].holds
    assert all(k.holds for k in analysis.conditions if k.number != number)
    values, _, _ = paper_conditions(a, c_phi)
    assert values[number] == 0.0
    expected, resolved = brute_count(a, c_phi)
    assert resolved[0] and expected[0] == 1
    assert analysis.count == 1
    assert len(minimise_reduced(analysis)) == 1
    # either side of the boundary: two minima inside, one outside
    inside, outside = (a - 1e-6, a + 1e-6)
    assert brute_count([inside, outside], c_phi)[0].tolist() == [2, 1]
    assert [analyse_minima(x, c_phi).count for x in (inside, outside)] == [2, 1]


# --------------------------------------------------------------------------- 3. facts


@settings(max_examples=120, deadline=None)
@given(a=st.floats(0.0, 1.0, exclude_max=True), c=st.floats(-PI, PI, exclude_max=True))
def test_a_below_one_gives_one_minimum(a, c):
    assert analyse_minima(a, c).count == 1
    expected, resolved = brute_count(a, c)
    assert resolved[0] and expected[0] == 1


@settings(max_examples=120, deadline=None)
@given(log_a=st.floats(-3, 6), fraction=st.floats(-1, 1, exclude_min=True, exclude_max=True))
def test_small_contradiction_gives_one_minimum(log_a, fraction):
    """|C| < arcsin(pi / sqrt(pi^2 + 1)) = arctan(pi) ~ 72.3 deg: one minimum, whatever a."""
    a, c = 10.0**log_a, fraction * C_STAR
    assert analyse_minima(a, c).count == 1
    expected, resolved = brute_count(a, c)
    assert not resolved[0] or expected[0] == 1


def test_c_star_is_arcsin_pi_over_sqrt_pi2_plus_1():
    assert C_STAR == pytest.approx(math.asin(PI / math.sqrt(PI**2 + 1)), rel=1e-15)
    assert math.degrees(C_STAR) == pytest.approx(72.34, abs=0.01)
    assert C_STAR == pytest.approx(1.2626, abs=1e-4)


@pytest.mark.parametrize("solver", ["bisection", "golden"])
def test_victoria_park_two_maps(solver):
    """The paper's check: a = 203570, C_phi = -0.0028: one minimum, near varphi = 0.0028."""
    a, c = 203570.0, -0.0028
    analysis = analyse_minima(a, c)
    assert analysis.count == 1
    assert brute_count(a, c)[0][0] == 1
    (minimum,) = minimise_reduced(analysis, solver)
    assert minimum.varphi == pytest.approx(0.0028, abs=1e-7)
    (reference,) = brute_minima(a, c)
    assert minimum.varphi == pytest.approx(reference, abs=1e-9 if solver == "bisection" else 1e-7)


# --------------------------------------------------------------------------- 4. minimise_reduced

BISECTION_MAX = math.ceil(math.log2(2 * PI / 1e-12)) + 2
GOLDEN_MAX = math.ceil(math.log(2 * PI / 1e-12) / math.log((1 + math.sqrt(5)) / 2)) + 2


def _check_minima(a, c, solver):
    expected, resolved = brute_count(a, c)
    if not resolved[0]:
        return False
    analysis = analyse_minima(a, c)
    minima = minimise_reduced(analysis, solver)
    assert len(minima) == expected[0] == analysis.count
    fb = [m.fbar for m in minima]
    assert fb == sorted(fb)
    reference, samples = brute_minima(a, c), 20_001
    while len(reference) < expected[0] and samples < 2_000_000:  # minima closer than the grid step
        samples *= 10
        reference = brute_minima(a, c, samples)
    assert len(reference) == len(minima)
    size = a + PI**2
    for m in minima:
        assert -PI <= m.varphi < PI
        assert m.fbar == pytest.approx(float(fbar(a, c, m.varphi)), rel=1e-12, abs=1e-15 * size)
        h, g, err_h, _, _ = _h_g(a, c, np.array(m.varphi))
        # root of h: bisection to rounding; golden section to ~sqrt(eps * |fbar| * g)
        h_tol = 1e-10 * (a + 1) if solver == "bisection" else 1e-6 * (a + 1)
        assert abs(h) <= h_tol
        assert g >= -1e-6 * (a + 1)
        step = 1e-3
        here = fbar(a, c, m.varphi)
        for x in (m.varphi - step, m.varphi + step):
            if -PI < x < PI:
                assert here <= fbar(a, c, x) + 1e-12 * size
        nearest = min(reference, key=lambda r: abs(r - m.varphi))
        g_ref = float(_h_g(a, c, np.array(nearest))[1])
        if g_ref > 1e-3 * (a + 1):  # well-conditioned root
            x_tol = 1e-9 if solver == "bisection" else 1e-6
            assert m.varphi == pytest.approx(nearest, abs=x_tol)
        assert m.iterations > 0
        assert m.iterations <= (BISECTION_MAX if solver == "bisection" else GOLDEN_MAX)
    # the first is the global minimum of fbar: a fine grid, refined locally
    x = np.linspace(-PI, PI, 20_001)
    values = fbar(a, c, x)
    best = float(values.min())
    refined = min(float(fbar(a, c, r)) for r in reference)
    assert minima[0].fbar <= min(best, refined) + 1e-11 * size
    return True


@pytest.mark.parametrize("solver", ["bisection", "golden"])
@settings(max_examples=100, deadline=None)
@given(log_a=st.floats(-3, 6), c=st.floats(-PI, PI, exclude_max=True))
def test_minimise_reduced_random(log_a, c, solver):
    _check_minima(10.0**log_a, c, solver)


TWO_REGION = ([(a, c) for a in (1.2, 40.0) for c in (-3.13, PI - 0.05, -PI)]
              + [(a, c) for a in (2.0, 3.2, 12.0) for c in (2.9, -3.0, -PI)] + [(3.17, 1.4)])


@pytest.mark.parametrize("solver", ["bisection", "golden"])
@pytest.mark.parametrize("a,c", TWO_REGION, ids=[f"a{a:g}-C{c:+.3f}" for a, c in TWO_REGION])
def test_minimise_reduced_two_minima(a, c, solver):
    assert _check_minima(a, c, solver)
    assert analyse_minima(a, c).count == 2


@pytest.mark.parametrize("tolerance", [1e-3, 1e-6, 1e-9])
def test_bisection_iterations_follow_the_tolerance(tolerance):
    analysis = analyse_minima(2.0, 0.5)
    (m,) = minimise_reduced(analysis, "bisection", tolerance)
    width = analysis.brackets[0][1] - analysis.brackets[0][0]
    assert abs(m.iterations - math.log2(width / tolerance)) <= 1.5
    (ref,) = brute_minima(2.0, 0.5)
    assert abs(m.varphi - ref) <= tolerance


# --------------------------------------------------------------------------- 5. arguments


@pytest.mark.parametrize("a,c", [(math.nan, 0.0), (math.inf, 0.0), (-math.inf, 0.0), (-1.0, 0.0),
                                 (-1e-300, 0.0), (1.0, math.nan), (1.0, math.inf)],
                         ids=["a-nan", "a-inf", "a--inf", "a-negative", "a-tiny-negative", "c-nan",
                              "c-inf"])
def test_bad_arguments_raise(a, c):
    with pytest.raises(ValueError):
        analyse_minima(a, c)


def test_unknown_solver_raises():
    with pytest.raises(ValueError):
        minimise_reduced(analyse_minima(2.0, 1.0), "newton")


# --------------------------------------------------------------------------- 6. many problems at once

def _boundary_points(a: np.ndarray, offset: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(a, C) on the boundaries of the two-minima region, moved by ``offset`` (in C, or in a for a = 1):
    h(-+pi) = 0 (17, 20), h(phi1) = 0 (18), h(phi2) = 0 (19), a = 1 (16), C = +-arctan(pi), C = +-pi."""
    root = np.sqrt(np.maximum(a * a - 1, 0.0))
    alpha = np.arccos(-1 / np.maximum(a, 1.0))
    families = [
        (a, np.arcsin(np.minimum(PI / a, 1.0)) + offset), (a, -np.arcsin(np.minimum(PI / a, 1.0)) + offset),
        (a, wrap(alpha + root + offset)), (a, wrap(-alpha - root + offset)),
        (1.0 + offset, wrap(a)), (a, C_STAR + offset), (a, -C_STAR + offset), (a, wrap(PI + offset)),
    ]
    a_all = np.concatenate([np.broadcast_to(x, np.shape(a)) for x, _ in families])
    c_all = np.concatenate([np.broadcast_to(c, np.shape(a)) for _, c in families])
    keep = (a_all >= 0) & (c_all >= -PI) & (c_all < PI)
    return a_all[keep], c_all[keep]


def _special_points() -> tuple[np.ndarray, np.ndarray]:
    """Random, adversarial, two-minima and boundary (a, C) pairs: a few thousand."""
    rng = np.random.default_rng(2013)
    a = [10 ** rng.uniform(-3, 6, 3000), np.array([p[0] for p in ADVERSARIAL + TWO_REGION])]
    c = [rng.uniform(-PI, PI, 3000), np.array([p[1] for p in ADVERSARIAL + TWO_REGION])]
    grid_a, grid_c = np.meshgrid(np.linspace(1.0, 30.0, 30), np.concatenate([np.linspace(1.2, PI, 20),
                                                                             -np.linspace(1.2, PI, 20)]))
    a.append(grid_a.ravel())
    c.append(grid_c.ravel())
    for offset in (0.0, 1e-12, -1e-12, 1e-7, -1e-7):
        boundary = _boundary_points(np.linspace(1.0, 12.0, 60), np.full(60, offset))
        a.append(boundary[0])
        c.append(boundary[1])
    return np.concatenate(a), np.concatenate(c)


def _scalar_orientations(a0, phi0, z_phi, p_phi, solver, tolerance=TOLERANCE):
    found = [global_orientation(*args, solver, tolerance)
             for args in zip(a0.tolist(), phi0.tolist(), z_phi.tolist(), p_phi.tolist())]
    assert all(type(value) in (float, int) for f in found for value in f)  # Python numbers: no numpy call
    return {field: np.array([getattr(f, field) for f in found]) for field in found[0]._fields}


def _assert_batch_is_scalar(a0, phi0, z_phi, p_phi, solver, tolerance=TOLERANCE):
    """global_orientation of a batch (arrays) gives exactly the numbers of each problem alone (floats)."""
    batch = global_orientation(a0, phi0, z_phi, p_phi, solver, tolerance)
    for field, expected in _scalar_orientations(a0, phi0, z_phi, p_phi, solver, tolerance).items():
        got = getattr(batch, field)
        same = (got == expected) | (np.isnan(got) & np.isnan(expected))
        assert same.all(), (field, np.flatnonzero(~same)[:5], got[~same][:5], expected[~same][:5])
    return batch


def test_batch_brackets_are_those_of_analyse_minima():
    """Theorem 2 as array expressions: the same brackets, bit for bit, on random, adversarial,
    two-minima and boundary points (each boundary exactly and 1e-12, 1e-7 either side)."""
    a, c = _special_points()
    found = _brackets(ARRAYS, a, c)
    for i, (ai, ci) in enumerate(zip(a.tolist(), c.tolist())):
        analysis = analyse_minima(ai, ci)
        assert found.two[i] == (analysis.count == 2), (ai, ci)
        assert (found.low[i], found.high[i]) == analysis.brackets[0], (ai, ci)
        if found.two[i]:
            assert (found.second_low[i], PI) == analysis.brackets[1], (ai, ci)
        assert found.steep[i] == (ai > 1)
        if found.steep[i]:
            assert (found.phi1[i], found.phi2[i], found.h1[i], found.h2[i]) == (
                analysis.phi1, analysis.phi2, analysis.h1, analysis.h2), (ai, ci)
    assert 0.05 < found.two.mean() < 0.5  # the points do cover the two-minima region


@pytest.mark.parametrize("solver", ["bisection", "golden"])
@pytest.mark.parametrize("tolerance", [1e-3, TOLERANCE, 1e-17])
def test_batch_orientation_is_global_orientation(solver, tolerance):
    """The lockstep searches (bisection with its sure steps, golden section) against the scalar
    ones on thousands of problems: the same minima, values and steps, bit for bit; a tolerance
    below the rounding of the angles makes the midpoint rule stop the bisection."""
    a, c = _special_points()
    rng = np.random.default_rng(7)
    phi0 = rng.uniform(-4, 4, len(a))
    p_phi = 10 ** rng.uniform(-4, 1, len(a))
    _assert_batch_is_scalar(a / p_phi, phi0, phi0 + c, p_phi, solver, tolerance)


@pytest.mark.parametrize("solver", ["bisection", "golden"])
@settings(max_examples=60, deadline=None)
@given(problems=st.lists(st.tuples(st.floats(0, 1e6), st.floats(-10, 10), st.floats(-10, 10), st.floats(1e-6, 10)),
                         min_size=1, max_size=72),
       near=st.lists(st.tuples(st.floats(1, 40), st.floats(-1e-6, 1e-6)), max_size=48))
def test_batch_orientation_is_global_orientation_property(problems, near, solver):
    """Any problems, with boundary points of the two-minima region mixed in, batches of any size
    (one included): the same numbers as one by one."""
    a0, phi0, z_phi, p_phi = (np.array(column, dtype=float) for column in zip(*problems))
    if near:
        a, c = _boundary_points(*(np.array(column) for column in zip(*near)))
        a0, phi0 = np.concatenate([a0, a]), np.concatenate([phi0, np.zeros(len(a))])
        z_phi, p_phi = np.concatenate([z_phi, c]), np.concatenate([p_phi, np.ones(len(a))])
    _assert_batch_is_scalar(a0, phi0, z_phi, p_phi, solver)


def test_batch_orientation_against_brute_force():
    """Independent of the scalar path: the number of minima is the certified brute-force count, and
    the minimum found is a root of h where fbar is lowest on a fine grid (the global minimum)."""
    a, c = _special_points()
    batch = global_orientation(a, np.zeros(len(a)), c, np.ones(len(a)))
    expected, resolved = brute_count(batch.a, batch.c_phi)
    assert resolved.mean() > 0.95
    assert (batch.count[resolved] == expected[resolved]).all()
    varphi = wrap(batch.phi - c)
    h = _h_g(batch.a, batch.c_phi, varphi)[0]
    assert (np.abs(h) <= 1e-9 * (batch.a + 1)).all()
    grid = np.linspace(-PI, PI, 4001)
    for chunk in np.array_split(np.arange(len(a)), 8):
        lowest = fbar(batch.a[chunk, None], batch.c_phi[chunk, None], grid).min(axis=1)
        found = fbar(batch.a[chunk], batch.c_phi[chunk], varphi[chunk])
        assert (found <= lowest + 1e-11 * (batch.a[chunk] + PI**2)).all()
    two = batch.count == 2
    other = wrap(batch.other_phi[two] - c[two])
    assert (np.abs(_h_g(batch.a[two], batch.c_phi[two], other)[0]) <= 1e-9 * (batch.a[two] + 1)).all()
    higher = fbar(batch.a[two], batch.c_phi[two], other) - fbar(batch.a[two], batch.c_phi[two], varphi[two])
    assert (higher >= -1e-12 * (batch.a[two] + PI**2)).all()  # the other minimum is not lower (up to a tie)


@pytest.mark.parametrize("a0,phi0", [(math.nan, 0.0), (-1.0, 0.0), (1.0, math.inf)])
def test_batch_orientation_bad_arguments_raise(a0, phi0):
    with pytest.raises(ValueError, match="finite a >= 0"), np.errstate(invalid="ignore"):
        global_orientation(np.full(24, a0), np.full(24, phi0), np.zeros(24), np.ones(24))
    with pytest.raises(ValueError, match="unknown solver"):
        global_orientation(np.ones(3), np.zeros(3), np.zeros(3), np.ones(3), "newton")
