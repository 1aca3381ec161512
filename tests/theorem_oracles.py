"""Independent oracles for the one-step mathematics, shared by several test modules.

- ``Dense``: Theorem 1's dense matrix formulas exactly as ``method.md`` writes them
  (``A``, ``C``, ``z0``, ``z1``, ``Q^-1``), block by block; no code shared with ``onestep.py``.
- ``brute_count``: a certified brute-force counter of the strict local minima of
  ``fbar(varphi) = -a cos(varphi + C) + varphi^2 / 2`` on the circle, from samples of
  ``h = fbar'`` and ``g = fbar''`` with adaptive subdivision (see ``tests/test_minima.py``).
"""

from __future__ import annotations

import math

import numpy as np
from scipy.optimize import brentq, minimize_scalar

from mapjoin.onestep import OneStepProblem

PI = math.pi
EPS = np.finfo(float).eps


def my_wrap(x):
    return (np.asarray(x, dtype=float) + PI) % (2 * PI) - PI


def rot(phi):
    c, s = math.cos(phi), math.sin(phi)
    return np.array([[c, -s], [s, c]])


# --------------------------------------------------------------------------- dense oracle


class Dense:
    """The paper's dense Theorem 1 for a problem, exactly as method.md writes it.

    Unknown ``X_L = (f_1..f_n, t)``; rows: ``Z0_j = f_j`` (n blocks), ``O_xy = t`` (1 block),
    ``R(phi) Z1_j = f_j - t`` (n blocks).
    """

    def __init__(self, p: OneStepProblem):
        z0, z1 = np.asarray(p.z0, float), np.asarray(p.z1, float)
        n = len(z0)
        self.n = n
        rows, cols = 2 * (2 * n + 1), 2 * (n + 1)
        eye = np.eye(2)
        A = np.zeros((rows, cols))
        for j in range(n):
            A[2 * j:2 * j + 2, 2 * j:2 * j + 2] = eye                 # Z0_j = f_j
        A[2 * n:2 * n + 2, 2 * n:2 * n + 2] = eye                     # O_xy = t
        for j in range(n):
            r = 2 * (n + 1 + j)
            A[r:r + 2, 2 * j:2 * j + 2] = eye                         # R Z1_j = f_j - t
            A[r:r + 2, 2 * n:2 * n + 2] = -eye
        variances = np.concatenate([p.var0, [p.odometry_variances[0]], p.var1])
        c_diag = np.repeat(variances, 2)
        Ci = np.diag(1.0 / c_diag)
        self.A, self.Ci, self.c_diag = A, Ci, c_diag
        self.z0 = np.concatenate([z0.ravel(), p.odometry[:2], np.zeros(2 * n)])
        self.z1 = np.concatenate([np.zeros(2 * n), np.zeros(2), z1.ravel()])
        self.normal = A.T @ Ci @ A
        self.Qi = Ci - Ci @ A @ np.linalg.solve(self.normal, A.T @ Ci)
        self.z1perp = self.rbar(PI / 2) @ self.z1
        self.link = p.link
        self.z_phi = float(p.odometry[2])
        self.p_phi = float(p.odometry_variances[1])
        self.scale = float(self.z0 @ Ci @ self.z0 + self.z1 @ Ci @ self.z1)

    def rbar(self, phi):
        return np.kron(np.eye(len(self.z0) // 2), rot(phi))

    def constants(self):
        z0, z1, Qi = self.z0, self.z1, self.Qi
        c0 = z0 @ Qi @ z0 + z1 @ Qi @ z1
        along, across = z0 @ Qi @ z1, z0 @ Qi @ self.z1perp
        return c0, math.hypot(along, across), math.atan2(-across, -along)

    def recover(self, phi):
        x = np.linalg.solve(self.normal, self.A.T @ self.Ci @ (self.z0 + self.rbar(phi) @ self.z1))
        return x[:-2].reshape(-1, 2), x[-2:]

    def _rotated_z1(self, phis):
        """Rbar(phi) z1 for many phi: (N, m)."""
        z1 = self.z1.reshape(-1, 2)
        c, s = np.cos(phis)[:, None], np.sin(phis)[:, None]
        x = c * z1[:, 0] - s * z1[:, 1]
        y = s * z1[:, 0] + c * z1[:, 1]
        return np.stack([x, y], axis=-1).reshape(len(phis), -1)

    def f(self, phis):
        """f_chi(phi) = r^T Q^-1 r + chi wrap(z_phi - phi)^2 / p_phi, for an array of phi."""
        phis = np.atleast_1d(np.asarray(phis, float))
        r = self.z0 + self._rotated_z1(phis)
        value = np.einsum("ij,jk,ik->i", r, self.Qi, r)
        if self.link:
            value = value + my_wrap(self.z_phi - phis) ** 2 / self.p_phi
        return value

    def df(self, phis):
        """d f_chi / d phi (away from the wrap point of the link term)."""
        phis = np.atleast_1d(np.asarray(phis, float))
        r = self.z0 + self._rotated_z1(phis)
        dr = self._rotated_z1(phis + PI / 2)
        value = 2 * np.einsum("ij,jk,ik->i", r, self.Qi, dr)
        if self.link:
            value = value - 2 * my_wrap(self.z_phi - phis) / self.p_phi
        return value

    def lstsq_cost(self, phi):
        """min over (f, t) of F(f, t, phi) by numpy.linalg.lstsq on the whitened system."""
        w = 1.0 / np.sqrt(self.c_diag)
        rhs = self.z0 + self.rbar(phi) @ self.z1
        x, *_ = np.linalg.lstsq(w[:, None] * self.A, w * rhs, rcond=None)
        value = float(np.sum((w * (rhs - self.A @ x)) ** 2))
        if self.link:
            value += float(my_wrap(self.z_phi - phi)) ** 2 / self.p_phi
        return value

    def local_minima(self, n_grid=8192):
        """All local minima of f_chi over [z_phi - pi, z_phi + pi) (or a full turn without link).

        Sign changes - to + of the dense derivative on a grid, then minimize_scalar around
        each, then brentq on the derivative (minimize_scalar alone is only ~sqrt(eps)
        accurate in phi). Returns [(phi, f)] sorted by f.
        """
        start = self.z_phi - PI if self.link else -PI
        grid = start + 2 * PI * np.arange(n_grid + 1) / n_grid  # the last point closes the turn: a minimum
        # just below its end changes sign between the last point and the first, turned by 2 pi
        d = self.df(grid)
        step = 2 * PI / n_grid
        found = []
        for i in np.nonzero((d[:-1] < 0) & (d[1:] >= 0))[0]:
            lo, hi = grid[i], grid[i + 1]
            # never across the window's ends: with the link, f has a cusp (a local maximum) at z_phi +- pi
            res = minimize_scalar(lambda x: float(self.f(x)[0]),
                                  bounds=(max(lo - step, grid[0]), min(hi + step, grid[-1])),
                                  method="bounded", options={"xatol": 1e-12})
            x = res.x
            g = lambda x: float(self.df(x)[0])  # noqa: E731
            if g(lo) < 0 < g(hi):
                x = brentq(g, lo, hi, xtol=1e-15, rtol=4 * np.finfo(float).eps, maxiter=200)
            assert abs(x - res.x) < 1e-4  # the two refinements find the same minimum
            found.append((x, float(self.f(x)[0])))
        return sorted(found, key=lambda m: m[1])


# --------------------------------------------------------------------------- brute force


def _h_g(a, c, x, sx=None, cx=None):
    """h, g and their rounding bounds at x (a, c broadcast against x)."""
    if sx is None:
        sx, cx = np.sin(x), np.cos(x)
    sc, cc = np.sin(c), np.cos(c)
    s1, s2 = sx * cc, cx * sc
    c1, c2 = cx * cc, sx * sc
    h = a * (s1 + s2) + x
    g = a * (c1 - c2) + 1.0
    err_h = 8 * EPS * (a * (np.abs(s1) + np.abs(s2)) + np.abs(x)) + 1e-300
    err_g = 8 * EPS * (a * (np.abs(c1) + np.abs(c2)) + 1.0) + 1e-300
    return h, g, err_h, err_g, np.abs(s1 + s2) + 8 * EPS


def _cells(a, c, x, sx=None, cx=None):
    """Per cell (between consecutive columns of x): minimum indicator and 'ambiguous' flag.

    Ambiguous: both g and h may vanish inside the cell (so h may be non-monotone there and
    cross zero more than once). For a <= 1, g >= 1 - a >= 0 with isolated zeros, so h is
    strictly increasing and no cell is ambiguous.
    """
    h, g, err_h, err_g, sin_abs = _h_g(a, c, x, sx, cx)
    hl, hr, gl, gr = h[:, :-1], h[:, 1:], g[:, :-1], g[:, 1:]
    d = x[:, 1:] - x[:, :-1]
    a_ = np.broadcast_to(a, hl.shape)
    # A minimum in a cell where h is monotone: h(left) < 0 <= h(right); the right end of the
    # whole interval (pi, the wrap point) is never a minimum, so there h(right) > 0 is needed.
    at_end = x[:, 1:] >= PI
    indicator = (hl < 0) & np.where(at_end, hr > 0, hr >= 0)
    eh = np.maximum(err_h[:, :-1], err_h[:, 1:])
    eg = np.maximum(err_g[:, :-1], err_g[:, 1:])
    # Inside the cell |g'| = a |sin(x + C)| <= a (s_min + d) =: dg, |h'| = |g| <= g_min + dg d.
    # A zero of g inside needs g_min <= dg d / 2, a zero of h min(|h_l|, |h_r|) <= (g_min + dg d) d / 2.
    g_min = np.minimum(np.abs(gl), np.abs(gr))
    dg = a_ * (np.minimum(sin_abs[:, :-1], sin_abs[:, 1:]) + d)
    g_may_vanish = (gl * gr <= 0) | (g_min <= dg * d / 2 + eg)
    h_bound = (g_min + eg + dg * d) * d / 2 + eh
    h_may_vanish = (hl * hr <= 0) | (np.minimum(np.abs(hl), np.abs(hr)) <= h_bound)
    return indicator, g_may_vanish & h_may_vanish & (a_ > 1)


def brute_count(a, c, n0: int = 256, split: int = 32, smallest: float = 1e-14):
    """Certified number of strict local minima of fbar on the circle, for arrays a, c.

    Returns ``(count, resolved)``; ``count`` is meaningless where ``resolved`` is False.
    """
    a = np.atleast_1d(np.asarray(a, dtype=float))
    c = np.atleast_1d(np.asarray(c, dtype=float))
    a, c = np.broadcast_arrays(a, c)
    count = np.zeros(a.shape, dtype=int)
    resolved = np.ones(a.shape, dtype=bool)
    grid = np.linspace(-PI, PI, n0 + 1)
    grid[0], grid[-1] = -PI, PI
    chunk = max(1, 2_000_000 // (n0 + 1))
    for start in range(0, a.size, chunk):
        sl = slice(start, start + chunk)
        aa, cc = a[sl][:, None], c[sl][:, None]
        x = np.broadcast_to(grid, (aa.shape[0], n0 + 1))
        ind, amb = _cells(aa, cc, x, np.sin(grid), np.cos(grid))
        count[sl] += (ind & ~amb).sum(axis=1)
        rows, cols = np.nonzero(amb)
        case = rows + start
        left, right = x[rows, cols], x[rows, cols + 1]
        while case.size:
            width = right - left
            tiny = width <= smallest * np.maximum(1.0, np.abs(left))
            # a case whose ambiguous cells multiply is near-degenerate: give up on it
            per_case = np.bincount(case, minlength=a.size)
            tiny |= per_case[case] > 16
            resolved[case[tiny]] = False
            case, left, right = case[~tiny], left[~tiny], right[~tiny]
            if not case.size:
                break
            t = np.linspace(0.0, 1.0, split + 1)
            sub = left[:, None] + (right - left)[:, None] * t
            sub[:, 0], sub[:, -1] = left, right
            ind, amb = _cells(a[case][:, None], c[case][:, None], sub)
            np.add.at(count, case, (ind & ~amb).sum(axis=1))
            rows, cols = np.nonzero(amb)
            case, left, right = case[rows], sub[rows, cols], sub[rows, cols + 1]
    return count, resolved
