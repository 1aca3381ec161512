"""Stage 2 of the consistency test: a join that fails the fast statistic, confirmed on the exact problem.

The fast statistic of a join (:mod:`mapjoin.consistency`, docs/method.md#calibration) treats the
map so far as known up to its spherical summary and the chain's drift; after loop closures that
summary understates its uncertainty, and consistent joins fail. The exact statistic has no such
summary: joining piece B onto piece A (each a run of consecutive local maps) raises the optimum
of the exact least-squares problem (docs/method.md#exact-joining) by

    chi2 = chi2*(A u B) - chi2*(A) - chi2*(B),
    dof  = (residuals(A u B) - unknowns(A u B)) - (residuals(A) - unknowns(A)) - (residuals(B) - unknowns(B)),

which for a correct model is chi-square distributed with ``dof`` degrees of freedom (the
increment of a linear least-squares problem by a block of measurements: Cochran). The residuals
add up, the unknowns of A u B are A's and B's less the features they share (B's start pose is A's
end pose, fixed at B's own origin), so ``dof = 2n`` for ``n`` shared features: the one-step join's
dof (docs/method.md#each-join). A sequential join is B = one map, whose own optimum is 0.

Each piece is solved by :func:`mapjoin.refine.solver.minimise` from its own tree join (the start
``refine`` takes by default, :data:`mapjoin.refine.DEFAULT_START`), and the union from the two pieces' optima
(with a one-map right piece, by extending the left piece's optimum: :mod:`mapjoin.refine.extension`). Cost:
two exact solves of at most the whole chain per confirmed join; only joins failing stage 1 are confirmed, and
a piece's optimum is computed once however many joins read it (docs/method.md#confirmation).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING

import numpy as np

from .consistency import p_values
from .errors import JoinError
from .joining import JoinRecord, JoinResult, Strategy, join_tree
from .maps import GlobalMap, LocalMap, locate, span
from .se2 import compose, relative, to_frame, transform, wrap
from .streaming import CompactReport

if TYPE_CHECKING:
    from .refine.dense import Backend
    from .refine.problem import ExactProblem

__all__ = ["BUDGET", "MAX_SOLVED", "REREAD_LIMIT", "Estimate", "Increment", "Optimum",
           "Pieces", "chain_backend", "confirm", "confirm_streamed", "increment", "piece_bounds", "variance_factor"]

#: the exact solves of a run's confirmations stop once they have solved this many times the chain's maps
BUDGET = 20.0
#: ... and a join is confirmed only while its exact problems fit in this many maps solved in all: a sequential
#: loop closure after 25 000 maps would need three solves of the whole chain (minutes, where its join took
#: seconds; benchmarks/README.md, "Confirmation")
MAX_SOLVED = 20_000
#: a streamed join's maps are read again for its confirmation only up to this many maps (a longer stream
#: keeps its memory bound, and its fast flags)
REREAD_LIMIT = 100_000


@dataclasses.dataclass(frozen=True)
class Optimum:
    """The exact optimum of a run of maps: ``cost`` chi^2, ``dof`` residuals minus unknowns, ``converged``
    whether the solver says so."""

    cost: float
    dof: int
    converged: bool


@dataclasses.dataclass(frozen=True)
class Increment:
    """The exact statistic of one join: ``chi2`` the optimum's increase, ``dof`` its degrees of freedom;
    ``union``, ``left``, ``right`` the three optima it is made of."""

    chi2: float
    dof: int
    union: Optimum
    left: Optimum
    right: Optimum

    @property
    def converged(self) -> bool:
        return self.union.converged and self.left.converged and self.right.converged


@dataclasses.dataclass(frozen=True)
class Estimate:
    """Poses (by id, x y phi) and features (by id, x y) in one frame: where an exact solve starts or ended."""

    pose_ids: np.ndarray
    poses: np.ndarray
    feature_ids: np.ndarray
    features: np.ndarray

    def __post_init__(self) -> None:
        if self.poses.shape != (len(self.pose_ids), 3) or self.features.shape != (len(self.feature_ids), 2):
            raise ValueError("Estimate: one pose (x, y, phi) per pose id and one point (x, y) per feature id")

    @classmethod
    def of(cls, global_map: GlobalMap) -> Estimate:
        return cls(global_map.pose_ids, global_map.poses, global_map.feature_ids, global_map.features)

    def pose(self, pose_id: int) -> np.ndarray:
        """Pose ``pose_id`` (the frame's origin when it is not held: the chain's first start pose)."""
        at = np.flatnonzero(self.pose_ids == pose_id)
        return self.poses[at[0]] if at.size else np.zeros(3)

    def values(self, problem: ExactProblem, origin_id: int) -> np.ndarray:
        """The unknowns of ``problem`` (which must all be held here), moved into the frame of pose ``origin_id``
        (the problem's fixed origin)."""
        origin = self.pose(origin_id)
        index, _ = locate(self.pose_ids, problem.pose_ids, np.argsort(self.pose_ids, kind="stable"))
        poses = relative(origin, self.poses[index])
        index, _ = locate(self.feature_ids, problem.feature_ids, np.argsort(self.feature_ids, kind="stable"))
        return np.concatenate([poses.ravel(), to_frame(origin, self.features[index]).ravel()])

    def then(self, other: Estimate, junction: int) -> Estimate:
        """This estimate and ``other`` (given in the frame of this one's pose ``junction``) in this frame; a
        feature both hold keeps this one's position."""
        at = self.pose(junction)
        # a search, not np.isin: its np.unique imports numpy.ma (7 ms of a confirming join's start-up)
        extra = ~locate(self.feature_ids, other.feature_ids, np.argsort(self.feature_ids, kind="stable"))[1]
        return Estimate(np.concatenate([self.pose_ids, other.pose_ids]),
                        np.concatenate([self.poses, compose(at, other.poses)]),
                        np.concatenate([self.feature_ids, other.feature_ids[extra]]),
                        np.concatenate([self.features, transform(at, other.features[extra])]))


class Pieces:
    """Exact optima of runs ``maps[first:stop]`` of one chain, each solved once (a join's pieces are
    shared: sequential join k's union is join k+1's left piece).

    A union whose right piece is one map (every sequential join's) is first extended from the left piece's optimum
    (:func:`mapjoin.refine.extension.extend`: chord steps with the factor of the left piece's Hessian, where a solve
    of the union costs a factorisation per step; DLR 200's join 181: one factorisation and 6 solves against 3
    factorisations and 4 solves), and solved whole as below only where that gives up (a loop closure that moves the
    map by metres). A piece is solved from its own tree join, as ``refine`` starts by default: measured, the fast
    sequential map of a long run with loop closures leaves the solve far from the optimum after 100 iterations (a
    2-lap simulation of 1000 maps, maps 0..744: chi^2 8962 against 5712, reached from the tree join in 7), so that
    joins were kept flagged as unconverged. The union of a join's two pieces is solved from the two pieces' optima
    put together (the right one placed at the left one's end): measured, the fast sequential map after a loop
    closure can lead the union's solve into another, higher minimum (docs/method.md#confirmation), the pieces'
    optima do not; the fast join's ``global_map`` is the second start of a union whose increment fails
    (:meth:`from_fast_join`).
    """

    def __init__(self, maps: Sequence[LocalMap], global_map: GlobalMap, max_iterations: int = 100,
                 backend: Backend = "auto") -> None:
        self._maps, self._fast, self._max_iterations = list(maps), Estimate.of(global_map), max_iterations
        self._backend = backend  # the linear algebra of every solve (:func:`chain_backend`)
        self._optima: dict[tuple[int, int], tuple[Optimum, Estimate]] = {}
        # the last piece solved, its problem and optimum's unknowns, until the next solve: a union of it and one
        # map starts from its problem (:meth:`_extended`)
        self._last: tuple[tuple[int, int], ExactProblem, np.ndarray] | None = None
        self.solved = 0  # maps in the exact problems solved so far

    def optimum(self, first: int, stop: int, start: Estimate | None = None) -> Optimum:
        """The exact optimum of maps ``first .. stop - 1``, solved from ``start`` (default: the run's own tree
        join) if not known yet."""
        key = (first, stop)
        if key not in self._optima:
            if start is None and stop - first > 1:
                start = Estimate.of(join_tree(self._maps[first:stop]).global_map)
            self._optima[key] = self._solve(first, stop, start or self._fast)
        return self._optima[key][0]

    def union(self, first: int, middle: int, stop: int) -> Optimum:
        """The exact optimum of maps ``first .. stop - 1``, solved from those of ``first .. middle - 1`` and
        ``middle .. stop - 1`` put together."""
        if (first, stop) not in self._optima:
            if stop - middle == 1 and middle - first > 1:
                extended = self._extended(first, middle)
                if extended is not None:
                    self._optima[first, stop] = extended
                    return extended[0]
            left, right = self._optima[first, middle][1], self._optima[middle, stop][1]
            return self.optimum(first, stop, left.then(right, self._maps[middle].start_id))
        return self.optimum(first, stop)

    def _extended(self, first: int, middle: int) -> tuple[Optimum, Estimate] | None:
        """The exact optimum of maps ``first .. middle``, the run ``first .. middle - 1`` (solved) and one map,
        from the run's own optimum and the factor of its Hessian there (:func:`mapjoin.refine.extension.extend`:
        chord steps, no factorisation of the union's); None where that gives up. Counted in :attr:`solved` as
        the union's solve (the budget confirms the same joins either way)."""
        from .refine.extension import extend
        from .refine.problem import ExactProblem

        run, added = self._maps[first:middle], self._maps[middle]
        last, self._last = self._last, None
        if last is not None and last[0] == (first, middle):
            problem, x = last[1:]
        else:   # the run was solved before another piece: its problem made again
            problem = ExactProblem(run, backend=self._backend)
            x = self._optima[first, middle][1].values(problem, run[0].start_id)
        found = extend(problem, x, added)
        if found is None:
            return None
        self.solved += middle + 1 - first
        left = self._optima[first, middle][0]
        poses, features = problem.unpack(found.x)
        end_pose = found.end_pose.copy()
        end_pose[2] = wrap(end_pose[2])
        return (Optimum(found.cost, left.dof + 2 * found.shared, True),
                Estimate(np.append(problem.pose_ids, added.end_id), np.concatenate([poses, end_pose[None, :]]),
                         np.concatenate([problem.feature_ids, found.feature_ids]),
                         np.concatenate([features, found.features])))

    def from_fast_join(self, first: int, stop: int) -> Optimum:
        """The exact optimum of maps ``first .. stop - 1`` solved again from the fast join's map; the lower of
        the two is kept (a solve can end in a higher local minimum from either start)."""
        solved = self._solve(first, stop, self._fast)
        if (first, stop) not in self._optima or solved[0].cost < self._optima[first, stop][0].cost:
            self._optima[first, stop] = solved
        return self._optima[first, stop][0]

    def _solve(self, first: int, stop: int, start: Estimate) -> tuple[Optimum, Estimate]:
        run = self._maps[first:stop]
        if stop - first == 1:  # one map fits its own measurements exactly
            m = run[0]
            return Optimum(0.0, 0, True), Estimate(np.array([m.end_id]), m.end_pose[None, :], m.feature_ids,
                                                   m.features)
        from .refine.problem import ExactProblem  # scipy.sparse: only when a join is confirmed
        from .refine.solver import Singular, minimise

        self.solved += stop - first
        self._last = None   # the last problem released before the next is made
        problem = ExactProblem(run, backend=self._backend)
        try:
            found = minimise(problem, start.values(problem, run[0].start_id), max_iterations=self._max_iterations)
        except Singular as error:  # the solver knows no map names
            raise JoinError(f"{span([m.name for m in run])}: {error}") from None
        self._last = (first, stop), problem, found.x
        poses, features = problem.unpack(found.x)
        return (Optimum(found.cost, problem.n_residuals - problem.n_unknowns, found.converged),
                Estimate(problem.pose_ids, poses, problem.feature_ids, features))


def chain_backend(maps: Sequence[LocalMap]) -> Backend:
    """The linear algebra of every exact solve of a confirmation: the one the whole chain's problem would take
    (:func:`mapjoin.refine.dense.backend_for`: by the dense work of its partition, from the maps' pose and
    feature ids alone), the largest a confirmation can solve and the one ``refine`` solves after it. By their own sizes, pieces below the dense backend's crossover would be solved densely
    and a larger piece, or the refine, would import scipy all the same: measured, ``join`` of DLR 200 then
    took 2.3 times the CPU (its 71-map pieces, 680 unknowns, dense; its 180-map ones sparse)."""
    from .refine.dense import Partition, backend_for

    distinct, compact = np.unique(np.concatenate([m.feature_ids for m in maps]), return_inverse=True)
    owner = np.repeat(np.arange(len(maps)), [m.size for m in maps])
    return backend_for("auto", 3 * len(maps) + 2 * len(distinct), lambda: Partition.of(
        owner, compact, np.arange(len(maps)) - 1, len(distinct)))[0]


def increment(pieces: Pieces, first: int, middle: int, stop: int) -> Increment:
    """The exact statistic of joining maps ``middle .. stop - 1`` onto maps ``first .. middle - 1``."""
    left, right = pieces.optimum(first, middle), pieces.optimum(middle, stop)
    union = pieces.union(first, middle, stop)
    return Increment(union.cost - left.cost - right.cost, union.dof - left.dof - right.dof, union, left, right)


def variance_factor(exact: Increment, fallback: float) -> float:
    """The a-posteriori variance factor the exact statistic is divided by: the pieces' own exact
    ``chi2 / dof`` pooled, at least 1 (docs/method.md#confirmation); ``fallback`` (the fast statistic's
    running factor) when the pieces have no degrees of freedom (two single maps)."""
    dof = exact.left.dof + exact.right.dof
    if dof <= 0:
        return fallback
    return max(1.0, (exact.left.cost + exact.right.cost) / dof)


def piece_bounds(maps: Sequence[LocalMap], record: JoinRecord, strategy: Strategy) -> tuple[int, int, int]:
    """``(first, middle, stop)``: the maps of the left piece (``first .. middle - 1``) and the right one
    (``middle .. stop - 1``) of ``record``. Sequential join k puts map k onto maps 0 .. k-1; a tree join
    at level L joins two aligned runs, the left one of 2^(L-1) maps (docs/method.md#tree-joining)."""
    if strategy == "sequential":
        return 0, record.join, record.join + 1
    starts = np.fromiter((m.start_id for m in maps), np.int64, len(maps))
    ends = np.fromiter((m.end_id for m in maps), np.int64, len(maps))
    middle = int(np.flatnonzero(starts == record.start_id)[0])
    stop = int(np.flatnonzero(ends == record.end_id)[0]) + 1
    return middle - 2 ** (record.level - 1), middle, stop


def confirm(maps: Sequence[LocalMap], result: JoinResult, strategy: Strategy, gate: float,
            budget: float = BUDGET) -> JoinResult:
    """``result`` with each join that fails the fast test confirmed on the exact statistic (stage 2).

    A join is confirmed when its ``p`` is below ``gate``, it has one minimum (two are flagged always),
    it was joined with the heading link and tests something (``dof > 0``). Its ``exact_chi2`` is
    :func:`increment`, its ``exact_p`` the upper tail of ``exact_chi2 / s`` (:func:`variance_factor`)
    under chi-square(dof). It stays flagged only if ``exact_p < gate`` with the union solved from both
    starts (its pieces' optima, then the fast join's map; the lower optimum counts), or if a solve did not
    converge (nothing is then confirmed either way). In report order (chain order; the tree's level by
    level), while the exact problems solved so far hold fewer than ``budget`` times the chain's maps, and
    only joins whose union fits, with them, in :data:`MAX_SOLVED` maps; the others keep the fast test's
    flag (``exact_p`` None).
    """
    chosen = [r for r in result.report if r.p < gate and r.minima == 1 and r.action == "joined" and r.dof > 0]
    if not chosen:
        return result
    pieces = Pieces(maps, result.global_map, backend=chain_backend(maps))
    limit = budget * len(maps)
    confirmed: dict[int, JoinRecord] = {}
    for record in chosen:
        if pieces.solved >= limit:
            break
        first, middle, stop = piece_bounds(maps, record, strategy)
        if pieces.solved + stop - first > MAX_SOLVED:
            continue
        exact = increment(pieces, first, middle, stop)
        s = variance_factor(exact, record.variance_factor)
        p = float(p_values(np.array([exact.chi2 / s]), np.array([exact.dof]))[0])
        if p < gate:  # a flag must not come from a higher local minimum: the union from the other start too
            pieces.from_fast_join(first, stop)
            exact = increment(pieces, first, middle, stop)
            p = float(p_values(np.array([exact.chi2 / s]), np.array([exact.dof]))[0])
        confirmed[record.join] = dataclasses.replace(record, exact_chi2=exact.chi2, exact_p=p,
                                                     flag=bool(p < gate) or not exact.converged)
    report = tuple(confirmed.get(r.join, r) for r in result.report)
    return dataclasses.replace(result, report=report)


def confirm_streamed(result: JoinResult, read: Callable[[], Sequence[LocalMap]] | None, gate: float,
                     source: str = "stdin") -> tuple[JoinResult, str | None]:
    """:func:`confirm` for a streamed sequential join, whose maps are gone: when it flags joins, ``read()``
    reads them again (``None``: they cannot be, as they came from ``source``, e.g. stdin or a FIFO), unless
    the chain has more than :data:`REREAD_LIMIT` maps. Returns the result and, when its flags stay
    unconfirmed, why (a sentence)."""
    report = result.report
    count = int(report.flagged.sum()) if isinstance(report, CompactReport) else sum(r.flag for r in report)
    if not count:
        return result, None
    first = (int(np.flatnonzero(report.flagged)[0]) + 1 if isinstance(report, CompactReport)
             else min(r.join for r in report if r.flag))   # a sequential join k's union: maps 1..k+1
    why = (f"its maps came from {source}" if read is None else
           f"it has more than {REREAD_LIMIT} maps" if len(report) + 1 > REREAD_LIMIT else
           f"the first one's exact problem would hold more than {MAX_SOLVED} maps" if first + 1 > MAX_SOLVED
           else None)
    if why is None:
        maps = read()
        if [m.name for m in maps[1:]] == [r.map for r in report]:
            return confirm(maps, result, "sequential", gate), None
        why = "its input changed since it was read"
    joins = "join" if count == 1 else "joins"
    return result, (f"{count} flagged {joins} tested by the fast statistic only: the streamed join's maps are not "
                    f"read again for the exact confirmation ({why}; docs/method.md#confirmation)")
