"""The solver of the exact join: Gauss-Newton with safeguards (:func:`minimise`).

An overshooting Gauss-Newton step is first halved (a line search along it), then
Levenberg-Marquardt damping (Marquardt's ``lambda diag(J^T J)``, steps accepted only if they
lower the cost, lambda adapted by the gain ratio as in Nielsen's rule) takes over; it
switches to Newton's method (the exact Hessian: ``J^T J`` plus the second-order term, which
only touches the base angles) once steps are good, for quadratic convergence. The damping
alone would cut the directions ``J^T J`` hardly constrains (long chains of maps) by orders
of magnitude and creep; the halving keeps Gauss-Newton's direction. Only full undamped steps
can stop the solver as converged (docs/method.md#solver): a shortened or damped step's small
gain says nothing about the distance to the optimum.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ..errors import JoinError
from .problem import ExactProblem

__all__ = ["STALL_ITERATIONS", "TOLERANCE", "Minimum", "Singular", "minimise"]

#: default stopping tolerance: relative chi^2 change, and step size relative to (1 + largest |unknown|);
#: 1e-12 puts the solution within ~1e-7 m of the optimum on the real datasets from either fast join
TOLERANCE = 1e-12
_MAX_DAMPING = 1e16  # Marquardt lambda at which the solver gives up looking for a decrease
_HALVINGS = 10       # an overshooting Gauss-Newton step is tried at 1/2 ... 1/2^10 of its length before damping
_NEWTON_FAILURES = 3  # Newton steps that may fail (no descent, no decrease) before Gauss-Newton for good
_NEAR = 1e-3          # Newton's steps only after a step that gained at most this (relative): near the optimum
_WITHIN = 9.0         # ... and lowered chi^2 by at most this (absolute): a step of at most three standard deviations
#: a solve asked to watch for stalling (:func:`minimise`'s ``stall``) gives up when its last this many accepted steps
#: lowered chi^2 by less than :data:`_WITHIN` in all
STALL_ITERATIONS = 10
_RESOLVED = 1e-4      # a full Gauss-Newton step predicted to gain at most this (absolute) lands within a hundredth of a
                      # standard deviation in every unknown: if it raises chi^2, the solver stops (:func:`minimise`)


class Singular(JoinError):
    """Normal equations singular to rounding (e.g. variances 60 orders of magnitude apart). The solver knows no
    map names; :func:`mapjoin.refine.join_and_refine` names the maps."""


@dataclass
class Minimum:
    """Where :func:`minimise` stopped: the unknowns ``x``, the data of J^T J, J^T r and chi^2
    there, chi^2 before the first step and after each accepted one (``costs``), why it
    stopped, and ``factor``: the undamped Gauss-Newton factor of J^T J at ``x`` when the
    last one computed was that (else None)."""

    x: np.ndarray
    data: np.ndarray
    gradient: np.ndarray
    cost: float
    costs: list[float]
    iterations: int
    converged: bool
    reason: str
    rejected: int
    factor: object = None

    def final_factor(self, problem: ExactProblem):
        """The undamped factor of J^T J at the optimum (for covariances)."""
        return self.factor if self.factor is not None else problem.factorise(self.data)


@dataclass
class _Mode:
    """Which step comes next: Gauss-Newton, undamped (``damping`` 0) or with Marquardt's
    ``damping`` (multiplied by ``growth`` after each rejected step), or Newton's while
    ``newton`` (after a good undamped step near the optimum; never again once Newton's model
    has failed :data:`_NEWTON_FAILURES` times: ``failures``)."""

    damping: float = 0.0
    growth: float = 2.0
    newton: bool = False
    failures: int = 0

    @property
    def plain(self) -> bool:
        """An undamped Gauss-Newton step: its factor is that of J^T J."""
        return self.damping == 0.0 and not self.newton

    def abandon_newton(self) -> None:
        """Newton's step was no descent or did not lower chi^2: Gauss-Newton until the next good
        undamped step. A failure far from the optimum, where the second-order term misleads, must
        not cost the quadratic convergence near it: Gauss-Newton alone converges linearly on these
        non-zero-residual problems and stopped 1e-4 m short of the optimum on a 1000-map simulation."""
        self.newton = False
        self.failures += 1

    def accept(self, ratio: float, gain: float, lowered: float) -> None:
        """After an accepted step of gain ratio ``ratio`` that lowered chi^2 by ``gain`` (relative) and by
        ``lowered`` (absolute): less damping (Nielsen), and near the optimum (a good undamped step that gained at
        most :data:`_NEAR` and at most :data:`_WITHIN`) Newton's quadratic convergence. Far from it the
        second-order term misleads: Newton's steps taken after every good step led the tree's start of a
        1000-map simulation (seed 6) into a local minimum 10 % above the optimum that Gauss-Newton reaches from
        there. The absolute bound makes "near" mean the same on every problem size: chi^2 is the squared
        Mahalanobis distance, so a step that lowered it by at most 9 moved the estimate by about three of its
        standard deviations or less, whereas 1e-3 of chi^2 is 284 (17 standard deviations) at 10^4 maps; there
        the first Newton step, taken after a Gauss-Newton step that gained 20.7, moved the estimate 2.3 m along
        the chain's flattest directions where Gauss-Newton's lands within 0.14 m of the optimum, and cost an
        iteration (docs/method.md#solver)."""
        self.damping *= max(1.0 / 3.0, 1.0 - (2.0 * ratio - 1.0) ** 3)
        if self.damping < 1e-12:
            self.damping = 0.0
        self.growth = 2.0
        self.newton = (self.damping == 0.0 and ratio > 0.5 and self.failures < _NEWTON_FAILURES and gain <= _NEAR
                       and lowered <= _WITHIN)

    def damp(self) -> bool:
        """After a rejected Gauss-Newton step: more damping; False past the limit."""
        self.damping = 1e-6 if self.damping == 0.0 else self.damping * self.growth
        self.growth *= 2.0
        return self.damping <= _MAX_DAMPING


def minimise(problem: ExactProblem, x: np.ndarray, *, max_iterations: int = 100, tolerance: float = TOLERANCE,
             progress: Callable[[int, float], None] | None = None, stall: bool = False) -> Minimum:
    """Minimise chi^2 of ``problem`` from ``x``: Gauss-Newton (``J^T J``), undamped while steps
    lower the cost (an overshooting one is first halved up to ten times: a backtracking line
    search along it), with Marquardt damping ``lambda diag(J^T J)`` adapted by the gain ratio
    (Nielsen) after one that does not; after a good undamped step, Newton's (``J^T J`` plus
    the second-order term, for quadratic convergence on these non-zero-residual problems)
    once steps gain at most 1e-3 of chi^2 and at most 9 (near the optimum; farther away its steps can jump to
    another basin), falling back to Gauss-Newton until the next such step if a Newton step is
    not a descent or does not lower the cost (for good after three such failures). An undamped step
    predicted to lower chi^2 by at most ``tolerance`` relative is accepted unless chi^2 rises
    by more than that: comparing the costs is rounding there, and it would make the stopping
    point random; a damped step that small hands over to the undamped one (once at each point).

    Stops, converged, only on what the undamped model says about the current point: when an
    accepted full undamped step (neither halved nor damped) lowered chi^2 by at most
    ``tolerance`` relative and was predicted to; when an undamped step is at most
    ``tolerance * (1 + max |x|)`` in every unknown; or when an undamped step predicted to lower
    chi^2 by at most ``tolerance`` relative raises it by more (these two not taken); or when a full
    Gauss-Newton step predicted to lower chi^2 by at most 1e-4 (and at most ``sqrt(tolerance)``
    relative) raises it (not taken): the predicted decrease is the squared Mahalanobis distance to
    the model's optimum, so that optimum is within a hundredth of a standard deviation in every unknown, and
    the halved steps that would follow only creep along directions the data leave flat (on 10^5 simulated
    maps, 21 iterations of gains about 5e-7 each after the optimum was reached). A halved
    or damped step gains little because it is short, not because the optimum is near: its
    cost change never stops the solver (it used to, 1e-4 m short on a 1000-map simulation).
    After a full undamped step that gained at most ``sqrt(tolerance)`` (near the optimum, where
    convergence is quadratic), the next step is first the chord step of that step's factor (:func:`_chord`,
    a solve instead of a factorisation): taken if predicted, and found, to change chi^2 by at most
    ``tolerance`` and if its length times that step's is at most ``tolerance * (1 + max |x|)`` (how far it
    lands from Newton's), and the last if the chord step after it is at most that in every unknown (else
    the solver goes on as usual). On the real datasets this saves the factorisation of the step that only
    confirms convergence.
    Stops unconverged after ``max_iterations`` accepted steps or at the damping limit; with ``stall``, also
    when the last :data:`STALL_ITERATIONS` accepted steps lowered chi^2 by less than 9 in all (three standard
    deviations: a creep the data cannot tell from standing still, e.g. towards a worse local minimum; for a
    caller that has another start to try). The
    relative tolerances on chi^2 are at least its rounding, ``sqrt(residuals)`` machine
    epsilons, so that ``tolerance=0`` means "to rounding" rather than a damped search for what
    rounding hides. ``progress(iteration, cost)`` is called with the initial chi^2 (iteration
    0) and after each accepted step.
    """
    if max_iterations < 0:
        raise ValueError(f"max_iterations must be >= 0, got {max_iterations}")
    if not tolerance >= 0:
        raise ValueError(f"tolerance must be >= 0, got {tolerance}")
    # chi^2's own rounding (sqrt(residuals) machine epsilons, relative): comparing costs or predicted
    # decreases below it is noise, so a smaller tolerance (e.g. 0) stops there instead of damping on
    relative = max(tolerance, math.sqrt(problem.n_residuals) * np.finfo(float).eps)
    data, gradient, cost = problem.linearise(x)           # the first step is Gauss-Newton's
    second = None
    costs = [cost]
    if progress:
        progress(0, cost)
    mode = _Mode()
    rejected = 0
    refused_here = False    # an undamped step was refused at the current x
    kept = None             # the last point's undamped factor, kept for the chord test (:func:`_chord`)

    def accepted(at: np.ndarray, newton: bool) -> tuple:
        """The problem linearised at an accepted point (with the second-order term where ``newton``; else
        None), its chi^2 recorded and reported."""
        if newton:
            linear = problem.linearise(at, curvature=True)
        else:
            linear = (*problem.linearise(at), None)
        costs.append(linear[2])
        if progress:
            progress(len(costs) - 1, linear[2])
        return linear

    def stop(reason: str, converged: bool = False, factor: object = None) -> Minimum:
        """Where the solver is now (x and its linearisation), and why it stops there."""
        return Minimum(x, data, gradient, cost, costs, len(costs) - 1, converged, reason, rejected, factor)

    while True:
        if len(costs) - 1 >= max_iterations:
            return stop("max iterations reached")
        if kept is not None:
            chord = _chord(problem, *kept, x, gradient, cost, relative, tolerance)
            if chord is not None:   # a full undamped step of negligible gain, taken
                x, data, second = chord, None, None
                # should it not settle, Newton's step follows: with its second-order term
                data, gradient, cost, second = accepted(x, mode.newton)
                after = problem.solve(kept[0], -gradient)
                kept = None
                if np.max(np.abs(after), initial=0.0) <= tolerance * (1.0 + np.max(np.abs(x), initial=0.0)):
                    return stop("relative cost change below tolerance", True)
                continue
            kept = None
        factor = None   # the previous step's factor is freed before the next is made
        factor, step = _step(problem, data, second if mode.newton else None, gradient, mode)
        finite = step is not None and bool(np.all(np.isfinite(step)))
        undamped = mode.damping == 0.0          # the model's own minimiser: the only step that measures the optimum
        scale = 1.0 + np.max(np.abs(x), initial=0.0)
        if undamped and finite and np.max(np.abs(step), initial=0.0) <= tolerance * scale:
            return stop("step below tolerance", True, factor if mode.plain else None)
        if mode.newton and (not finite or step @ gradient >= 0):
            mode.abandon_newton()       # not a descent direction: Gauss-Newton for now
            rejected += 1
            continue
        if not finite:
            raise Singular("the normal equations of the exact join are singular")
        # the model's decrease, -g.step + damping step.D.step (the gain ratio's denominator)
        predicted = -(step @ gradient) + mode.damping * (step * step) @ problem.diagonal(data)
        small = 0 <= predicted <= relative * cost
        if small and not undamped and not refused_here:
            # damping has shrunk the step to nothing: it says nothing about the optimum, and near it (to
            # rounding) there is nothing left to guard; the undamped step decides (once at each point)
            mode.damping = 0.0
            rejected += 1
            continue
        trial = x + step
        trial_cost = problem.cost(trial)
        negligible = small and undamped
        shortened = False
        if (mode.plain and not negligible and trial_cost >= cost
                and predicted <= min(_RESOLVED, math.sqrt(relative) * cost)):
            # the model's optimum is within a hundredth of a standard deviation and its full step does not reach
            # it: halved steps would only creep along directions the data leave flat
            return stop("predicted decrease below the data's resolution", True, factor)
        if trial_cost >= cost and not negligible and mode.plain:
            shorter = _halved(problem, x, step, cost)
            if shorter is not None:
                rejected += 1
                trial, trial_cost, fraction = shorter
                predicted *= fraction * (2 - fraction)     # the model's decrease along it
                shortened = True
        if negligible and trial_cost > cost * (1.0 + relative):
            # at the optimum to within rounding, and the model no longer holds: damped retries would only
            # shrink the step
            return stop("predicted decrease below tolerance", True, factor if mode.plain else None)
        if trial_cost < cost or negligible:
            # a step of negligible predicted decrease is taken however chi^2 compares: at that level the
            # comparison is rounding noise (it would make where the solver stops random), and the model's
            # minimiser is the better estimate
            mode.accept((cost - trial_cost) / predicted if predicted > 0 else 1.0,
                        (cost - trial_cost) / cost if cost > 0 else 0.0, cost - trial_cost)
            x, previous = trial, cost
            # the cost change stops the solver only after a full undamped step that was also predicted to
            # change chi^2 that little: a shortened or damped step gains little because it is short, not
            # because the optimum is near
            done = (undamped and not shortened and previous - trial_cost <= relative * previous
                    and predicted <= relative * previous)
            refused_here = False
            # near the optimum (quadratic convergence: this step gained at most sqrt(tolerance)), the factor is
            # kept for the chord test at the new point
            near = undamped and not shortened and not done and predicted <= math.sqrt(relative) * previous
            kept = (factor, float(np.max(np.abs(step), initial=0.0))) if near else None
            data = second = factor = None    # the last point's normal matrix freed before the new one is made
            # the second-order term only where a Newton step follows
            data, gradient, cost, second = accepted(x, mode.newton and not done)
            if done:
                return stop("relative cost change below tolerance", True)
            if stall and len(costs) > STALL_ITERATIONS and costs[-STALL_ITERATIONS - 1] - cost < _WITHIN:
                return stop(f"stalled (chi^2 lowered by less than {_WITHIN:g} in {STALL_ITERATIONS} iterations)")
        elif mode.newton:
            mode.abandon_newton()       # Newton's model failed here: Gauss-Newton for now
            rejected += 1
        else:
            rejected += 1
            refused_here = refused_here or undamped
            if not mode.damp():
                return stop("no step lowers the cost (damping limit reached)")


def _step(problem: ExactProblem, data: np.ndarray, second: np.ndarray | None, gradient: np.ndarray, mode: _Mode
          ) -> tuple[object, np.ndarray | None]:
    """The factor of the normal matrix ``data`` (plus the second-order term ``second`` for Newton's, damped as
    ``mode`` says) and the step ``-(matrix)^-1 gradient``; a Newton step of a singular matrix is None
    (Gauss-Newton's: an error)."""
    factor = None
    try:
        factor = problem.factorise(data, mode.damping, second)
        return factor, problem.solve(factor, -gradient)
    except RuntimeError:          # SuperLU: exactly singular
        if not mode.newton:
            raise Singular("the normal equations of the exact join are singular") from None
        return factor, None


def _chord(problem: ExactProblem, factor: object, last: float, x: np.ndarray, gradient: np.ndarray, cost: float,
           relative: float, tolerance: float) -> np.ndarray | None:
    """The chord step at ``x``: ``x - A^-1 gradient`` with ``factor``, the undamped (Gauss-Newton's or Newton's)
    factor ``A`` of the point before, if it is predicted to lower chi^2 by at most ``relative`` and changes it
    by at most that (the last step of the stopping rule, docs/method.md#solver); else None. Near the optimum
    ``A`` differs from the matrix at ``x`` by the order of the last step (``last``: its largest component), so
    it predicts the next gain as a new factorisation would, at the cost of a solve; the chord step lands off
    Newton's by about its own length times ``last``, and is taken only if that is within the step tolerance
    (``tolerance * (1 + max |x|)``): on DLR 200's first 181 maps (``last`` 4e-3, the chord step 1e-5) it would
    not settle there and would only add an iteration."""
    step = problem.solve(factor, -gradient)
    predicted = -(step @ gradient)
    reach = float(np.max(np.abs(step), initial=0.0))
    if not (np.isfinite(reach) and 0 <= predicted <= relative * cost
            and reach * last <= tolerance * (1.0 + np.max(np.abs(x), initial=0.0))):
        return None
    trial = x + step
    if abs(problem.cost(trial) - cost) > relative * cost:
        return None
    return trial


def _halved(problem: ExactProblem, x: np.ndarray, step: np.ndarray, cost: float
            ) -> tuple[np.ndarray, float, float] | None:
    """Gauss-Newton's step overshoots: the first of 1/2 ... 1/2^10 of it that lowers chi^2
    below ``cost``, as ``(x, chi^2, fraction)``, else None. Its direction is one of descent;
    shortening it first keeps it, where damping, scaled by diag(J^T J), would cut the
    directions J^T J hardly constrains by orders of magnitude and let the solver creep along
    them (as on long runs with loop closures)."""
    for halving in range(1, _HALVINGS + 1):
        shorter = x + 0.5 ** halving * step
        shorter_cost = problem.cost(shorter)
        if shorter_cost < cost:
            return shorter, shorter_cost, 0.5 ** halving
    return None
