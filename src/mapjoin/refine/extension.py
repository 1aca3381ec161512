"""The exact optimum of a chain extended by one local map, from the factor at the chain's own optimum.

A sequential join's confirmation (docs/method.md#confirmation) needs the exact optima of maps
``1..k`` (A) and ``1..k+1`` (A u B). The union adds one map, B, to A's problem
(docs/method.md#exact-joining); of its unknowns, B's end pose and the features B sees first are
measured by B alone. Minimised over them (they can take any value in B's frame), B's term
``e^T P^-1 e`` becomes the term of the features B shares with A (the Schur complement of the rest of
``P``: a Gaussian's marginal):

    chi2*(A u B) = min_a  chi2_A(a) + e_s(a)^T P_ss^-1 e_s(a),   e_s = s_s - R(phi_b)^T (p_s - t_b),

``a`` A's unknowns, ``(t_b, phi_b)`` B's start pose (A's last end pose), ``p_s`` the ``s`` shared
features, ``s_s`` B's estimates of them and ``P_ss`` their block of B's covariance. The shared term
touches ``k = 3 + 2s`` of A's unknowns. So the union is solved on A's unknowns alone, by steps whose
matrix is A's Hessian (``J^T J`` plus the second-order term) at A's optimum, factorised once, plus the
shared term's ``J^T J`` at the current point, a rank-``2s`` update applied by the Woodbury identity:
each step costs one solve with A's factor (and a ``k``-column one once), where a solve of the union
costs a factorisation per step. It is a chord method: A's part of the matrix is that of A's optimum,
which the union's moves away from, so it converges linearly (DLR 200's join 181: steps of 6e-2,
2e-3, 3e-3, 2e-5, 1e-5 m or rad: one factorisation and 6 solves, one of them of 21 columns, against the
union solve's 3 factorisations and 4 solves on a problem of its own; with the shared term's second-order
part it took 7 steps). The shared term's ``J^T J`` keeps the matrix positive definite,
so each step is a descent direction. B's own unknowns follow from ``a`` in closed form (the
conditional mean of B's state given the shared part). Stops as :func:`.solver.minimise` does
(docs/method.md#solver); gives up (None) where a step raises chi^2, where the steps do not shrink
fourfold every two steps (a loop closure that moves the map far, where A's Hessian no longer fits: on
simulations, steps of metres that raise chi^2, or of 0.3 m that stall) or after :data:`MAX_STEPS`: the
caller then solves the union whole, having spent a factorisation and a few solves.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..covariance import state_covariance
from ..maps import LocalMap, locate
from ..se2 import compose, to_frame, transform
from .dense import DenseFactor
from .problem import ExactProblem
from .solver import TOLERANCE

__all__ = ["MAX_STEPS", "Extension", "SharedTerm", "extend"]

#: chord steps before the extension gives up (DLR 200's join 181 takes 5)
MAX_STEPS = 20


@dataclass(frozen=True)
class Extension:
    """The exact optimum of a chain's problem extended by one map: ``cost`` chi^2, ``x`` the chain's
    unknowns there (its problem's order), ``end_pose`` the new map's end pose and ``feature_ids``,
    ``features`` the features it sees first (global frame); ``steps`` taken; ``shared`` the features it
    shares with the chain."""

    cost: float
    x: np.ndarray
    end_pose: np.ndarray
    feature_ids: np.ndarray
    features: np.ndarray
    steps: int
    shared: int


class SharedTerm:
    """The term ``e_s^T P_ss^-1 e_s`` of the features map ``local_map`` shares with the chain of
    ``problem``, B's other unknowns minimised out (see the module docstring), on the ``k`` unknowns it
    touches (``columns``: B's start pose, then each shared feature's x and y)."""

    def __init__(self, problem: ExactProblem, local_map: LocalMap):
        base, found = locate(problem.pose_ids, np.array([local_map.start_id]))
        if not found[0]:
            raise ValueError(f"{local_map.name} does not start at an end pose of the chain")
        at, shared = locate(problem.feature_ids, local_map.feature_ids)
        self.map, self.shared = local_map, shared
        self.columns = np.concatenate([3 * int(base[0]) + np.arange(3),
                                       (3 * problem.n_maps + 2 * at[shared][:, None] + np.arange(2)).ravel()])
        P = state_covariance(local_map)
        state = np.concatenate([[False] * 3, np.repeat(shared, 2)])       # B's state entries that are shared
        rows, rest = np.flatnonzero(state), np.flatnonzero(~state)
        self._rows, self._rest = rows, rest
        self.whitening = np.linalg.inv(np.linalg.cholesky(P[np.ix_(rows, rows)]))   # L^-1, P_ss = L L^T
        # the conditional mean of B's other entries given the shared ones: s_rest - P_rs P_ss^-1 e_s
        self._gain = P[np.ix_(rest, rows)] @ self.whitening.T @ self.whitening
        self._measured = np.concatenate([local_map.end_pose, local_map.features.ravel()])

    def _local(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """B's start pose at ``x`` and the shared features seen from it (s, 2)."""
        base = x[self.columns[:3]]
        return base, to_frame(base, x[self.columns[3:]].reshape(-1, 2))

    def residual(self, x: np.ndarray) -> np.ndarray:
        """The whitened residual ``L^-1 e_s`` (2s) at ``x``."""
        return self.whitening @ (self._measured[self._rows] - self._local(x)[1].ravel())

    def cost(self, x: np.ndarray) -> float:
        r = self.residual(x)
        return float(r @ r)

    def linearise(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
        """``(J^T J (k, k), J^T r (k), chi^2)`` at ``x`` (the halves of the Gauss-Newton matrix and the
        gradient of chi^2, as :meth:`.problem.ExactProblem.linearise` gives them), with ``J = -L^-1 dh/dx``,
        ``h`` the shared features seen from the start pose ``(t, phi)``: ``dh/dt = -R^T``, ``dh/dp = R^T``,
        ``dh/dphi = (h_y, -h_x)``."""
        base, h = self._local(x)
        s = len(h)
        c, n = math.cos(base[2]), math.sin(base[2])
        Rt = np.array([[c, n], [-n, c]])
        dh = np.zeros((2 * s, 3 + 2 * s))
        rows = np.arange(2 * s).reshape(s, 2)
        dh[:, :2] = np.tile(-Rt, (s, 1))
        dh[:, 2] = np.stack([h[:, 1], -h[:, 0]], axis=1).ravel()
        dh[rows[:, :, None], 3 + rows[:, None, :]] = Rt
        r = self.whitening @ (self._measured[self._rows] - h.ravel())
        J = -self.whitening @ dh
        return J.T @ J, J.T @ r, float(r @ r)

    def placed(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """B's end pose and the features it sees first, ``(pose (3), ids, points (q, 2))`` in the global
        frame, where they minimise B's term given the shared features at ``x``."""
        base, h = self._local(x)
        e = self._measured[self._rows] - h.ravel()
        state = np.empty(len(self._measured))
        state[self._rows] = h.ravel()
        state[self._rest] = self._measured[self._rest] - self._gain @ e
        new = ~self.shared
        points = state[3:].reshape(-1, 2)[new]
        return compose(base, state[:3]), self.map.feature_ids[new], transform(base, points)


def extend(problem: ExactProblem, x: np.ndarray, local_map: LocalMap, *, tolerance: float = TOLERANCE,
           max_steps: int = MAX_STEPS) -> Extension | None:
    """The exact optimum of ``problem``'s chain extended by ``local_map`` (starting at one of its end poses),
    from ``x``, the chain's own optimum: chord steps on the chain's unknowns with the shared term
    minimised over the new map's own (see the module docstring). Converged as :func:`.solver.minimise`
    judges (a step at most ``tolerance * (1 + max |x|)`` in every unknown, or a step predicted to change
    chi^2 by at most ``tolerance`` relative that changed it by at most that); None if a step raises chi^2
    beyond rounding, a step is more than a quarter of the one two steps before, the factor of the chain's Hessian (or
    the update's I + W C) is singular, or ``max_steps`` steps do not settle."""
    term = SharedTerm(problem, local_map)
    columns = term.columns
    relative = max(tolerance, math.sqrt(problem.n_residuals + len(columns)) * np.finfo(float).eps)
    x = np.array(x, dtype=float)
    data, gradient, cost, second = problem.linearise(x, curvature=True)
    try:
        factor = problem.factorise(data, second=second)
        if isinstance(factor, DenseFactor) and not factor.cholesky:
            # not positive definite (the chain not at a minimum): the dense backend would solve each step by LU of
            # the whole matrix; Gauss-Newton's matrix is positive definite
            factor = problem.factorise(data)
        unit = np.zeros((problem.n_unknowns, len(columns)))
        unit[columns, np.arange(len(columns))] = 1.0
        Z = problem.solve(factor, unit)                          # A^-1 E: the update's columns
    except RuntimeError:
        return None
    del data, second
    W = Z[columns]                                               # E^T A^-1 E
    identity = np.eye(len(columns))
    matrix, shared_gradient, shared_cost = term.linearise(x)
    cost += shared_cost
    gradient[columns] += shared_gradient
    lengths: list[float] = []                                    # each step's largest component
    for steps in range(max_steps):
        # (A + E C E^T)^-1 b = y - Z C d, with y = A^-1 b and (I + W C) d = y's rows of E
        y = problem.solve(factor, -gradient)
        try:
            correction = np.linalg.solve(identity + W @ matrix, y[columns])
        except np.linalg.LinAlgError:  # I + W C singular to rounding: no extension, as for a singular factor
            return None
        step = y - Z @ (matrix @ correction)
        lengths.append(float(np.max(np.abs(step), initial=0.0)))
        if not math.isfinite(lengths[-1]):
            return None
        if lengths[-1] <= tolerance * (1.0 + np.max(np.abs(x), initial=0.0)):
            return _extension(problem, term, x, cost, steps)
        predicted = -(step @ gradient)
        negligible = 0 <= predicted <= relative * cost
        if steps >= 2 and lengths[-1] > lengths[-3] / 4 and not negligible:
            return None                                          # not converging: A's Hessian no longer fits
        trial = x + step
        trial_cost = problem.cost(trial) + term.cost(trial)
        if trial_cost > cost * (1.0 + relative):   # at the optimum to rounding if the step was negligible
            return _extension(problem, term, x, cost, steps) if negligible else None
        done = negligible and abs(cost - trial_cost) <= relative * cost
        x = trial
        if done:
            return _extension(problem, term, x, trial_cost, steps + 1)
        _, gradient, cost = problem.linearise(x)
        matrix, shared_gradient, shared_cost = term.linearise(x)
        cost += shared_cost
        gradient[columns] += shared_gradient
    return None


def _extension(problem: ExactProblem, term: SharedTerm, x: np.ndarray, cost: float, steps: int) -> Extension:
    end_pose, feature_ids, features = term.placed(x)
    return Extension(cost, x, end_pose, feature_ids, features, steps, int(term.shared.sum()))
