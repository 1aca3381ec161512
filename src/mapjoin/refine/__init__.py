"""Exact least-squares map joining (the problem I-SLSJF solves): sparse Gauss-Newton.

The problem (docs/method.md#exact-joining): the global end poses of all maps and the
global positions of all features minimising ``sum_k e_k^T P_k^-1 e_k`` over the local
maps k, each weighted by its full covariance (:mod:`.problem`). It is solved by
Gauss-Newton with Levenberg-Marquardt and Newton safeguards (:mod:`.solver`) from a fast
join (:func:`join_and_refine`; the tree join by default, :data:`DEFAULT_START`), on normal
equations of fixed sparse pattern factorised by SuperLU (:mod:`.factor`); the marginal covariances at the optimum
come by selected inversion of that factor (:mod:`.sparse`). A small problem takes the same equations dense instead
(:mod:`.dense`: numpy only, as importing scipy would cost the command more than the solve).

:func:`join_and_refine` is the whole pipeline, fast join then refinement, that ``mapjoin
join --refine`` and ``mapjoin refine`` run; :func:`refine` starts from a given map.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np

from ..covariance import DEFAULT_COVARIANCE, CovarianceMode, spherical_summary
from ..consistency import DEFAULT_GATE, Policy
from ..joining import STRATEGIES, Confirm, JoinResult, Strategy, without_features, join
from ..errors import JoinError
from ..maps import GlobalMap, LocalMap, Provenance, joined_map, span
from ..onestep import Solver
from .hierarchy import HIERARCHICAL, Settle
from .problem import ExactProblem
from .solver import TOLERANCE, Minimum, Singular, minimise

__all__ = ["DEFAULT_START", "STARTS", "TOLERANCE", "RefineResult", "Start", "default_start", "exact_cost",
           "join_and_refine", "refine"]

log = logging.getLogger("mapjoin")

#: the starts of the exact solve: a fast join's strategy, or the tree join with its top levels' pieces solved
#: exactly (:mod:`.hierarchy`, docs/method.md#hierarchical-start)
Start = Literal["sequential", "tree", "hierarchical"]
STARTS: tuple[str, ...] = (*STRATEGIES, HIERARCHICAL)

#: the fast join the exact solve starts from unless told: measured to lead it to the optimum (the one a start
#: at the ground truth reaches) on the real datasets and on 1000- and 10^4-map simulations, where the
#: sequential join's drift left it creeping for 100 iterations (benchmarks/README.md, "Which start refine
#: defaults to")
DEFAULT_START: Strategy = "tree"


def default_start(on_inconsistent: Policy = "warn") -> Strategy:
    """The start of :func:`join_and_refine` when none is given: :data:`DEFAULT_START`, except under the
    ``skip`` policy, which re-joins the chain map by map and so needs the sequential join."""
    return "sequential" if on_inconsistent == "skip" else DEFAULT_START


@dataclass(frozen=True)
class RefineResult:
    """The exact join and how it was found.

    ``global_map``: poses and features at the optimum; with covariances, its
    ``feature_covariances`` (n, 2, 2) and ``pose_covariances`` (p, 3, 3) are the marginal
    blocks of ``(J^T J)^-1`` and its spherical variances their summary (see
    :func:`~mapjoin.covariance.spherical_summary`); without, the variances of the initial map are kept.
    ``cost``: chi^2 at the optimum. ``costs``: chi^2 before the first iteration and after
    each accepted one (decreasing; the last may rise by rounding, see
    :func:`.solver.minimise`). ``seconds``: time of the solve (problem set-up and
    iterations; neither the initial join nor the covariances), ``covariance_seconds``: time
    of the marginal covariances, ``initial_seconds``: time of the fast join that gave the
    initial value (with the hierarchical start, its pieces' solves too; 0 when one was given), ``fast_join``:
    that join (None when an initial
    map was given). ``gradient_norm``: max |J^T r| at the optimum (r whitened residuals).
    ``rejected``: steps computed but not taken (they did not lower chi^2, or a Newton step
    was no descent). ``start``: the start the solve started from (:data:`STARTS`; None when an initial
    map was given). ``abandoned``: the default start whose solve did not converge, when this is the
    hierarchical start's solve tried after it (:func:`join_and_refine`); its whole time is in
    ``initial_seconds``.
    """

    global_map: GlobalMap
    cost: float
    costs: tuple[float, ...]
    iterations: int
    converged: bool
    reason: str
    seconds: float
    covariance_seconds: float = 0.0
    initial_seconds: float = 0.0
    residuals: int = 0
    unknowns: int = 0
    gradient_norm: float = math.nan
    rejected: int = 0
    fast_join: JoinResult | None = None
    start: Start | None = None
    abandoned: Start | None = None

    @property
    def degrees_of_freedom(self) -> int:
        """Residuals minus unknowns: the expected value of chi^2 at the optimum."""
        return self.residuals - self.unknowns

    @classmethod
    def of(cls, problem: ExactProblem, found: Minimum, global_map: GlobalMap, seconds: float,
           covariance_seconds: float) -> RefineResult:
        """The result of ``problem`` solved to ``found``, its solution ``global_map``."""
        return cls(global_map=global_map, cost=found.cost, costs=tuple(found.costs), iterations=found.iterations,
                   converged=found.converged, reason=found.reason, seconds=seconds,
                   covariance_seconds=covariance_seconds, residuals=problem.n_residuals,
                   unknowns=problem.n_unknowns, gradient_norm=float(np.max(np.abs(found.gradient), initial=0.0)),
                   rejected=found.rejected)


def join_and_refine(maps: Sequence[LocalMap], *, start: Start | None = None,
                    covariance: CovarianceMode = DEFAULT_COVARIANCE, solver: Solver = "bisection", jobs: int = 1,
                    join_progress: Callable[[int], None] | None = None, max_iterations: int = 100,
                    tolerance: float = TOLERANCE, covariances: bool = True,
                    progress: Callable[[int, float], None] | None = None, gate: float = DEFAULT_GATE,
                    on_inconsistent: Policy = "warn", confirm: Confirm | None = None) -> RefineResult:
    """Join the chain ``maps`` fast (:func:`mapjoin.joining.join` with strategy ``start``, by default
    :func:`default_start`,
    ``covariance``, ``solver``, ``jobs``, ``join_progress``, ``gate`` and ``on_inconsistent``: a map
    the skip policy leaves out keeps only its end pose in the refinement too; ``confirm``: see
    :func:`mapjoin.joining.join`), then refine that to the
    exact least-squares join (:func:`refine` with the other arguments). The result holds
    the fast join (``fast_join``) and its time (``initial_seconds``). ``start="hierarchical"``: the tree
    join with its top levels' pieces solved exactly (:class:`.hierarchy.Settle`; in one process, ``jobs=1``),
    for long runs where the tree's start leaves the solve creeping (docs/method.md#hierarchical-start).
    With no ``start`` given, a solve from the default tree start that does not converge (or stalls:
    :func:`.solver.minimise`'s ``stall``) is tried again from the hierarchical start (one process), and the
    result says so (``abandoned``)."""
    maps = list(maps)
    given, start = start, start or default_start(on_inconsistent)
    if start not in STARTS:
        raise ValueError(f"unknown start {start!r}; expected one of {', '.join(STARTS)}")

    def solved_from(start: Start, jobs: int, stall: bool) -> RefineResult:
        began = time.perf_counter()
        settle = Settle(maps) if start == HIERARCHICAL else None
        try:  # the exact solves (the hierarchical start's, a confirmation's, the refinement) know no map names
            fast = join(maps, covariance, solver, "tree" if settle else start, jobs, join_progress, gate=gate,
                        on_inconsistent=on_inconsistent, confirm=confirm, settle=settle)
            left_out = {r.join for r in fast.report if r.action == "left out"}
            chain = [without_features(m) if k in left_out else m for k, m in enumerate(maps)]
            initial_seconds = time.perf_counter() - began
            result = refine(chain, fast.global_map, max_iterations=max_iterations, tolerance=tolerance,
                            covariances=covariances, progress=progress, stall=stall)
        except Singular as error:
            raise JoinError(f"{span([m.name for m in maps])}: {error}") from None
        return dataclasses.replace(result, initial_seconds=initial_seconds, fast_join=fast, start=start)

    began = time.perf_counter()
    fallback = given is None and start == "tree"
    result = solved_from(start, jobs, stall=fallback)
    if result.converged or not fallback:
        return result
    log.warning("the exact join from the tree join did not converge (%s after %d iterations, chi^2 = %.10g): "
                "trying the hierarchical start", result.reason, result.iterations, result.cost)
    spent = time.perf_counter() - began
    retried = solved_from(HIERARCHICAL, 1, stall=False)
    return dataclasses.replace(retried, initial_seconds=spent + retried.initial_seconds, abandoned=start)


def refine(maps: Sequence[LocalMap], initial: GlobalMap | None = None, *, max_iterations: int = 100,
           tolerance: float = TOLERANCE, covariances: bool = True,
           progress: Callable[[int, float], None] | None = None, stall: bool = False) -> RefineResult:
    """Solve the exact least-squares joining problem of the chain ``maps``.

    Starts from ``initial`` (which must hold every pose and feature; extra ones are
    ignored) or else from the fast join :data:`DEFAULT_START` (:func:`join_and_refine`, which
    needs a chain); the steps and the stopping rules are those of :func:`.solver.minimise`.
    ``covariances``: compute the marginal covariances (else the initial map's variances
    are kept). ``stall``: give up on a creep (:func:`.solver.minimise`).
    """
    if initial is None:
        return join_and_refine(maps, max_iterations=max_iterations, tolerance=tolerance, covariances=covariances,
                               progress=progress)
    maps = list(maps)
    start = time.perf_counter()
    problem = ExactProblem(maps)
    found = minimise(problem, problem.pack(initial), max_iterations=max_iterations, tolerance=tolerance,
                     progress=progress, stall=stall)
    seconds = time.perf_counter() - start

    poses, features = problem.unpack(found.x)
    start = time.perf_counter()
    if covariances:
        pose_covariances, feature_covariances = problem.marginals(found.final_factor(problem))
        pose_variances, feature_variances = spherical_summary(pose_covariances, feature_covariances)
    else:
        pose_covariances = feature_covariances = None
        pose_variances, feature_variances = problem.variances(initial)
    covariance_seconds = time.perf_counter() - start if covariances else 0.0
    global_map = joined_map(
        feature_ids=problem.feature_ids, features=features, feature_variances=feature_variances,
        pose_ids=problem.pose_ids, poses=poses, pose_variances=pose_variances,
        provenance=Provenance(tuple(m.name for m in maps), "full", "gauss-newton", "exact"),
        feature_covariances=feature_covariances, pose_covariances=pose_covariances)
    return RefineResult.of(problem, found, global_map, seconds, covariance_seconds)


def exact_cost(maps: Sequence[LocalMap], global_map: GlobalMap) -> float:
    """chi^2 of ``global_map`` in the exact joining problem of ``maps``."""
    problem = ExactProblem(maps)
    return problem.cost(problem.pack(global_map))
