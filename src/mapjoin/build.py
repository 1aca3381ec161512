"""Local maps from raw data (``mapjoin build``): cut the odometry chain into consecutive
local maps and solve each one's full nonlinear least-squares problem.

Local map j runs from chain pose ``a_j`` to ``b_j``. Its unknowns are the poses after
``a_j`` up to ``b_j`` and the features observed from its poses, all in the frame of pose
``a_j`` (held fixed at the origin); its residuals are every odometry step in it
(``(R(phi_i)^T (t_k - t_i), wrap(phi_k - phi_i)) - z``) and every observation made from
its poses except ``b_j`` (``R(phi_i)^T (f - t_i) - z``), each whitened by its
covariance. Observations from ``b_j`` belong to the next map, which sees them from its
origin, so each is used once; the last map also takes those from the last pose.

The problem is refine's exact joining problem (:class:`mapjoin.refine.problem.ExactProblem`),
solved by the same sparse Gauss-Newton/LM code (:func:`mapjoin.refine.solver.minimise`): one
measurement block per odometry step, its relative pose plus the observations made from
its start pose with their block-diagonal covariance (I-SLSJF's one-step local maps are
exactly these blocks). Observations from the last pose of the data form one more block
whose end pose is virtual: measured as (0, 0, 0) with unit covariance from the last
pose, it has zero residual at every optimum and changes nothing else, estimate or
covariance (3 residuals, 3 unknowns: the degrees of freedom are unchanged). All local
maps are solved at once, one fixed origin each: independent blocks of one sparse system.

Initial values, so that each solve lands in its global minimum by construction rather
than from long dead reckoning (which can stall in a local minimum, as GTSAM's batch
Levenberg-Marquardt does on Victoria Park): stretches of at most ``piece_steps`` steps
start from dead reckoning; a longer local map is first built as such pieces, which are
joined with the certified one-step join (:func:`mapjoin.joining.join_sequential`), and
refined from there.

Covariance of each local map: the block of ``(J^T J)^-1`` over its end pose and features
at the optimum, i.e. the inverse of the Schur complement that marginalises its interior
poses out of the sparse information matrix ``J^T J`` (see :func:`_covariance_blocks`);
only each map's own (3 + 2m)^2 Schur complement is inverted.

:func:`batch` is the full batch SLAM problem: the whole chain as one local map.
"""

from __future__ import annotations

import dataclasses
import itertools
import logging
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import scipy.linalg

from .errors import InputError, counted
from .covariance import spherical_summary
from .joining import join_sequential
from .maps import GlobalMap, LocalMap, Provenance, StackedMaps, first_invalid_map, marginal_variances, size_groups, unstack
from .raw import RawData
from .se2 import compose, relative
from .refine import TOLERANCE, RefineResult
from .refine.problem import Blocks, ExactProblem
from .refine.solver import Minimum, minimise

__all__ = ["PIECE_STEPS", "BuildResult", "batch", "build", "cut"]

log = logging.getLogger("mapjoin")

#: longest stretch of odometry solved from dead reckoning; longer maps are joined from pieces
PIECE_STEPS = 50
_PROBES = 256  # right-hand sides per solve for the covariances (memory: unknowns x this)


@dataclass(frozen=True)
class BuildResult:
    """The local maps built and how well their problems fit.

    ``costs[j]``: chi^2 of map j at its optimum, with ``residuals[j]`` and ``unknowns[j]``.
    ``iterations``, ``converged``, ``reason``: of the final solve (all maps at once).
    ``pieces``: small maps solved from dead reckoning and joined first (0 when every map
    was short enough to solve directly). ``seconds``: the solves (pieces, joins, final);
    ``covariance_seconds``: the maps' covariances. ``batch``: the full batch solution
    started from these maps (see :func:`batch`), when asked for.
    """

    maps: tuple[LocalMap, ...]
    costs: np.ndarray
    residuals: np.ndarray
    unknowns: np.ndarray
    iterations: int
    converged: bool
    reason: str
    seconds: float
    covariance_seconds: float
    pieces: int = 0
    batch: RefineResult | None = None

    @property
    def cost(self) -> float:
        """chi^2 of all maps together."""
        return float(self.costs.sum())

    @property
    def degrees_of_freedom(self) -> np.ndarray:
        """Residuals minus unknowns of each map: the expected value of its chi^2."""
        return self.residuals - self.unknowns


def cut(steps: int, maps: int | None = None, poses_per_map: int | None = None, source: str | None = None
        ) -> np.ndarray:
    """Chain indices ``0 = b_0 < b_1 < ... < b_N = steps`` of N consecutive local maps:
    ``maps`` of (nearly) equal length, or ``poses_per_map`` steps each (the last map takes
    what is left). Exactly one of the two. ``source`` (the raw data's file) is named in errors."""
    if (maps is None) == (poses_per_map is None):
        raise ValueError("give exactly one of maps and poses_per_map")
    if maps is not None:
        if not 1 <= maps <= steps:
            raise InputError(f"cannot cut {steps} odometry steps into {maps} local maps: expected 1 to {steps} maps "
                             "(each map needs at least one step)", source)
        return np.round(np.linspace(0, steps, maps + 1)).astype(np.int64)
    if poses_per_map < 1:
        raise InputError(f"expected at least 1 pose per map, got {poses_per_map}")
    return np.unique(np.append(np.arange(0, steps, poses_per_map), steps)).astype(np.int64)


def build(raw: RawData, bounds: Sequence[int], *, jobs: int = 1, piece_steps: int = PIECE_STEPS,
          max_iterations: int = 100, tolerance: float = TOLERANCE, progress: Callable[[int, float], None] | None = None,
          with_batch: bool = False) -> BuildResult:
    """Solve the local maps between consecutive chain indices ``bounds`` (see :func:`cut`)
    and return them with their full covariances; ``progress(iteration, chi^2)`` follows the
    final solves (with one job). ``jobs > 1``: the maps, independent problems, are cut into
    that many runs of consecutive maps, each built in a worker process exactly as one job
    builds all (the solver stops per run, so results agree to rounding, not bit for bit).
    ``with_batch``: also the batch solution (:func:`batch`), started from these maps joined.
    Whether chi^2 is plausible: :func:`mapjoin.evaluation.chi2_verdict` of ``costs`` and
    ``degrees_of_freedom``."""
    if jobs < 1:
        raise ValueError(f"jobs must be at least 1, got {jobs}")
    bounds = np.asarray(bounds, dtype=np.int64)
    runs = np.round(np.linspace(0, len(bounds) - 1, min(jobs, len(bounds) - 1) + 1)).astype(np.int64)
    if len(runs) == 2:
        *part, solved = _build_run(raw, bounds, 0, piece_steps, max_iterations, tolerance, progress)
        parts = [tuple(part)]
    else:
        # multiprocessing: imported only when used
        from concurrent.futures import ProcessPoolExecutor

        work = [(_stretch(raw, bounds[i], bounds[k]), bounds[i:k + 1] - bounds[i], int(i), piece_steps,
                 max_iterations, tolerance) for i, k in itertools.pairwise(runs)]
        with ProcessPoolExecutor(max_workers=len(work)) as pool:
            parts = list(pool.map(_run_in_worker, work))
    poses = np.concatenate([p for _, p in parts])
    parts = [part for part, _ in parts]
    maps = [m for part in parts for m in part.maps]
    empty = [m.name for m in maps if not m.size]
    if empty:
        log.warning("%s without a feature (first: %s): written with the end pose only; a join places "
                    "each by its start pose alone", counted(len(empty), "local map"), empty[0])
    result = BuildResult(maps=tuple(maps), costs=np.concatenate([p.costs for p in parts]),
                         residuals=np.concatenate([p.residuals for p in parts]),
                         unknowns=np.concatenate([p.unknowns for p in parts]),
                         iterations=max(p.iterations for p in parts), converged=all(p.converged for p in parts),
                         reason=next((p.reason for p in parts if not p.converged), parts[0].reason),
                         seconds=max(p.seconds for p in parts),
                         covariance_seconds=max(p.covariance_seconds for p in parts),
                         pieces=sum(p.pieces for p in parts))
    if with_batch:
        start = time.perf_counter()
        pieces = _Pieces(bounds, poses, maps)
        whole = solved if len(bounds) == 2 else _solve(raw, bounds[[0, -1]], piece_steps, max_iterations, tolerance,
                                                       progress, pieces=pieces)
        result = dataclasses.replace(result, batch=_batch_result(whole, bounds, time.perf_counter() - start))
    return result


def _build_run(raw: RawData, bounds: np.ndarray, first: int, piece_steps: int, max_iterations: int,
               tolerance: float, progress: Callable[[int, float], None] | None = None
               ) -> tuple[BuildResult, np.ndarray, _Solved]:
    """Solve the maps between ``bounds`` of ``raw`` together, numbered from map ``first``: the
    result (no batch), each measurement block's end pose in its map's frame, the solve."""
    start = time.perf_counter()
    solved = _solve(raw, bounds, piece_steps, max_iterations, tolerance, progress)
    seconds = time.perf_counter() - start
    start = time.perf_counter()
    maps = solved.local_maps(raw.name, first)
    covariance_seconds = time.perf_counter() - start
    found, layout = solved.minimum, solved.layout
    run = BuildResult(tuple(maps), solved.segment_costs(), layout.segment_residuals, layout.segment_unknowns,
                      found.iterations, found.converged, found.reason, seconds, covariance_seconds, solved.pieces)
    return run, solved.block_poses(), solved


def _run_in_worker(job: tuple) -> tuple[BuildResult, np.ndarray]:
    """A worker process's share of :func:`build`: one run of maps (see :func:`_build_run`)."""
    return _build_run(*job)[:2]


def _stretch(raw: RawData, a: int, b: int) -> RawData:
    """The raw data of chain poses ``a`` to ``b`` (pose a the origin): the steps between them
    and the observations made from poses a to b - 1, and from b when it is the last pose
    (else they belong to the next map)."""
    keep = (raw.observers >= a) & ((raw.observers < b) | (b == raw.steps))
    return dataclasses.replace(
        raw, pose_ids=raw.pose_ids[a:b + 1], odometry=raw.odometry[a:b], odometry_covariances=raw.odometry_covariances[a:b],
        observers=raw.observers[keep] - a, feature_ids=raw.feature_ids[keep], observations=raw.observations[keep],
        observation_covariances=raw.observation_covariances[keep], odometry_lines=raw.odometry_lines[a:b],
        observation_lines=raw.observation_lines[keep])


def batch(raw: RawData, bounds: Sequence[int] | None = None, *, piece_steps: int = PIECE_STEPS,
          max_iterations: int = 100, tolerance: float = TOLERANCE, covariances: bool = True,
          progress: Callable[[int, float], None] | None = None) -> RefineResult:
    """The full batch SLAM solution, built as one local map (so from pieces, certified joins
    and refinement): every feature and the poses at chain indices ``bounds[1:]`` (default:
    every pose), pose k labelled k as the k-th built map's end pose is, in the frame of the
    first pose, with marginal covariances (else unit variances)."""
    bounds = np.arange(raw.steps + 1) if bounds is None else np.asarray(bounds, dtype=np.int64)
    start = time.perf_counter()
    solved = _solve(raw, np.array([0, raw.steps]), piece_steps, max_iterations, tolerance, progress)
    return _batch_result(solved, bounds, time.perf_counter() - start, covariances)


def _batch_result(solved: _Solved, bounds: np.ndarray, seconds: float, covariances: bool = True) -> RefineResult:
    """The global map of a solved single map (the whole chain) at the poses ``bounds[1:]``."""
    problem, found, layout = solved.problem, solved.minimum, solved.layout
    poses, features = problem.unpack(found.x)
    kept = bounds[1:] - 1                                   # blocks ending at those poses
    start = time.perf_counter()
    if covariances:
        pose_covariances, feature_covariances = problem.marginals(found.final_factor(problem))
        pose_covariances = pose_covariances[kept]
        pose_variances, feature_variances = spherical_summary(pose_covariances, feature_covariances)
    else:
        pose_covariances = feature_covariances = None
        pose_variances, feature_variances = np.ones((len(kept), 2)), np.ones(len(features))
    covariance_seconds = time.perf_counter() - start
    name = layout.raw.name
    global_map = GlobalMap(
        feature_ids=layout.distinct[problem.feature_ids % layout.n_distinct], features=features,
        feature_variances=feature_variances, pose_ids=np.arange(1, len(kept) + 1), poses=poses[kept],
        pose_variances=pose_variances, provenance=Provenance((name,), "full", "gauss-newton", "batch"),
        feature_covariances=feature_covariances, pose_covariances=pose_covariances, name=f"{name} (batch)")
    return RefineResult.of(problem, found, global_map, seconds, covariance_seconds)


# ---------------------------------------------------------------------------------------
# The problem of consecutive local maps


class _Layout:
    """The measurement blocks of the local maps between chain indices ``bounds``.

    Block k < P is odometry step k+1 (chain pose k to k+1) with the observations made from
    chain pose k; block P, present when the last pose observed anything, holds those with
    the virtual end pose. Internal pose ids: chain index for the steps' end poses, P + 1
    for the virtual one, P + 2 + j for the origin of map j. Feature unknowns are per map:
    id ``j * n_distinct + compact id``.
    """

    def __init__(self, raw: RawData, bounds: np.ndarray):
        self.raw, self.bounds = raw, bounds
        P = raw.steps
        self.segments = S = len(bounds) - 1
        virtual = bool((raw.observers == P).any())
        self.n_blocks = K = P + virtual
        self.segment = _segment_of_blocks(bounds, K, P)
        first = np.arange(K) == bounds[self.segment]            # the map's first step: it starts at the origin
        first[P:] = False
        self.base = np.where(first, -1, np.arange(K) - 1)      # block holding the base pose (-1: the origin)
        start_ids = np.where(first, P + 2 + self.segment, np.arange(K))
        end_ids = np.arange(1, K + 1)
        # observations: block of the observing pose, features per map
        block = np.minimum(raw.observers, P)
        order = np.argsort(block, kind="stable")
        self.order = order
        self.distinct, compact = np.unique(raw.feature_ids, return_inverse=True)
        self.n_distinct = len(self.distinct)
        self.observation_block = block[order]
        self.unknown_ids = self.segment[block[order]] * self.n_distinct + compact.ravel()[order]
        sizes = np.bincount(block, minlength=K)
        self.first_observation = np.concatenate([[0], np.cumsum(sizes)])
        pose_covariances = np.concatenate([raw.odometry_covariances, np.eye(3)[None].repeat(K - P, axis=0)])
        observation_covariances = raw.observation_covariances[order]
        measured = np.concatenate([raw.odometry, np.zeros((K - P, 3))])

        def covariances(ks: np.ndarray) -> np.ndarray:
            m = int(sizes[ks[0]])
            stacked = np.zeros((len(ks), 3 + 2 * m, 3 + 2 * m))
            stacked[:, :3, :3] = pose_covariances[ks]
            if m:
                rows = 3 + 2 * np.arange(m)[:, None] + np.arange(2)
                which = self.first_observation[ks][:, None] + np.arange(m)
                stacked[:, rows[:, :, None], rows[:, None, :]] = observation_covariances[which]
            return stacked

        def name(k: int) -> str:
            if k < P:
                return f"{raw.name}, odometry at {raw.where(raw.odometry_lines[k])}"
            return f"{raw.name}, observations from the last pose"

        self.blocks = Blocks(start_ids=start_ids, end_ids=end_ids, end_poses=measured, sizes=sizes,
                             feature_ids=self.unknown_ids, features=raw.observations[order],
                             covariances=covariances, names=name)
        self.origins = P + 2 + np.arange(S)
        # per map: residuals, unknowns
        residuals_of_block = 3 + 2 * sizes
        self.segment_residuals = np.bincount(self.segment, residuals_of_block, minlength=S).astype(np.int64)
        features_of_map = np.bincount(np.unique(self.unknown_ids) // self.n_distinct, minlength=S)
        self.segment_unknowns = (3 * np.bincount(self.segment, minlength=S) + 2 * features_of_map).astype(np.int64)

    def dead_reckoning(self) -> np.ndarray:
        """Each block's end pose in its map's frame by composing the odometry from the map's origin."""
        raw = self.raw
        heading = np.concatenate([[0.0], np.cumsum(raw.odometry[:, 2])])
        c, s = np.cos(heading[:-1]), np.sin(heading[:-1])
        dx, dy = raw.odometry[:, 0], raw.odometry[:, 1]
        position = np.concatenate([[[0.0, 0.0]], np.cumsum(np.stack([c * dx - s * dy, s * dx + c * dy], 1), 0)])
        chain = np.concatenate([position, heading[:, None]], axis=1)
        ends = chain[np.minimum(np.arange(1, self.n_blocks + 1), raw.steps)]
        return relative(chain[self.bounds[self.segment]], ends)

    def initial(self, poses: np.ndarray) -> np.ndarray:
        """The unknowns from each block's end pose in its map's frame, each feature at the mean
        of its observations placed from their observing (base) poses."""
        base = self.base[self.observation_block]
        observer = np.where(base[:, None] >= 0, poses[np.maximum(base, 0)], 0.0)
        z = self.raw.observations[self.order]
        c, s = np.cos(observer[:, 2]), np.sin(observer[:, 2])
        placed = observer[:, :2] + np.stack([c * z[:, 0] - s * z[:, 1], s * z[:, 0] + c * z[:, 1]], axis=1)
        _, which, count = np.unique(self.unknown_ids, return_inverse=True, return_counts=True)
        which = which.ravel()
        features = np.stack([np.bincount(which, placed[:, i]) for i in range(2)], axis=1) / count[:, None]
        return np.concatenate([poses.ravel(), features.ravel()])

    def selected(self, problem: ExactProblem) -> list[np.ndarray]:
        """Per map, the unknowns of its state [end pose, features (ascending id)]."""
        end_block = self.bounds[1:] - 1
        feature_map = problem.feature_ids // self.n_distinct
        starts = np.searchsorted(feature_map, np.arange(self.segments + 1))
        base = 3 * problem.n_maps
        return [np.concatenate([3 * end_block[j] + np.arange(3),
                                base + np.arange(2 * starts[j], 2 * starts[j + 1])]) for j in range(self.segments)]


def _segment_of_blocks(bounds: np.ndarray, blocks: int, steps: int) -> np.ndarray:
    """The map (between ``bounds``) of each of ``blocks`` measurement blocks of a chain of ``steps``."""
    end_step = np.minimum(np.arange(1, blocks + 1), steps)     # chain index of each block's end pose
    return np.searchsorted(bounds, end_step, side="left") - 1


@dataclass
class _Solved:
    """A solved layout: the problem, where the solver stopped, and how many pieces led there."""

    layout: _Layout
    problem: ExactProblem
    minimum: Minimum
    pieces: int = 0

    def segment_costs(self) -> np.ndarray:
        r = self.problem.residual(self.minimum.x)
        block = np.repeat(np.arange(self.layout.n_blocks), np.diff(self.problem.row0))
        return np.bincount(self.layout.segment[block], r * r, minlength=self.layout.segments)

    def block_poses(self) -> np.ndarray:
        """Each measurement block's end pose in its map's frame."""
        return self.problem.unpack(self.minimum.x)[0]

    def local_maps(self, label: str, first: int = 0) -> list[LocalMap]:
        """The maps, map j from pose j to pose j + 1 (I-SLSJF's numbering, which every map
        format holds, counted from ``first``; the name gives the raw pose ids): end pose,
        features (raw ids) and the full covariance over both."""
        layout, problem = self.layout, self.problem
        raw = layout.raw
        selected = layout.selected(problem)
        covariances = _covariance_blocks(problem, self.minimum.data, selected)
        x = self.minimum.x
        names = [f"{label} poses {raw.pose_ids[a]}-{raw.pose_ids[b]}" for a, b in itertools.pairwise(layout.bounds)]
        sizes = np.array([(len(chosen) - 3) // 2 for chosen in selected])
        stacks = []
        for group in size_groups(sizes):                   # the maps of each size as one stack, checked at once
            m = int(sizes[group[0]])
            chosen = np.stack([selected[j] for j in group])
            end_pose = x[chosen[:, :3]]
            end_pose[:, 2] = [math.remainder(phi, 2 * math.pi) for phi in end_pose[:, 2].tolist()]
            ids = layout.distinct[problem.feature_ids[(chosen[:, 3::2] - 3 * problem.n_maps) // 2] % layout.n_distinct]
            covariance = np.stack([covariances[j] for j in group])
            feature_variances, pose_variances = marginal_variances(covariance)     # as LocalMap.from_covariance
            stacks.append((group, StackedMaps([names[j] for j in group], end_pose, ids.astype(np.int64),
                                              x[chosen[:, 3:]].reshape(len(group), m, 2), feature_variances,
                                              pose_variances, covariance)))
        invalid = first_invalid_map(stacks)
        if invalid:
            raise invalid[1]      # the first map's, as constructing them in turn
        places = first + np.arange(len(selected))
        return unstack(stacks, places.tolist(), (places + 1).tolist())


def _solve(raw: RawData, bounds: np.ndarray, piece_steps: int, max_iterations: int, tolerance: float,
           progress: Callable[[int, float], None] | None = None, pieces: _Pieces | None = None) -> _Solved:
    """Solve the maps between ``bounds``: from dead reckoning when each has at most
    ``piece_steps`` steps, else from pieces of at most that many (``pieces``: solved maps
    whose bounds refine ``bounds``, and their local maps), joined map by map."""
    layout = _Layout(raw, bounds)
    problem = ExactProblem(layout.blocks, origins=layout.origins)
    if pieces is None and np.diff(bounds).max() > piece_steps:
        counts = -(-np.diff(bounds) // piece_steps)
        split = np.unique(np.concatenate([np.round(np.linspace(a, b, n + 1))
                                          for a, b, n in zip(bounds[:-1], bounds[1:], counts)])).astype(np.int64)
        solved = _solve(raw, split, piece_steps, max_iterations, tolerance)
        pieces = _Pieces(split, solved.block_poses(), solved.local_maps(f"piece of {raw.name}"))
    poses = layout.dead_reckoning() if pieces is None else _joined(pieces, bounds, raw.steps)
    found = minimise(problem, layout.initial(poses), max_iterations=max_iterations, tolerance=tolerance,
                     progress=progress)
    if not found.converged:
        log.warning("%s: the local maps' solve did not converge (%s after %d iterations): chi^2 = %.10g",
                    raw.name, found.reason, found.iterations, found.cost)
    return _Solved(layout, problem, found, 0 if pieces is None else len(pieces.maps))


@dataclass(frozen=True)
class _Pieces:
    """Solved maps between ``bounds`` (map i from pose i to i + 1) and each measurement
    block's end pose in its map's frame, to start a solve of coarser maps from."""

    bounds: np.ndarray
    block_poses: np.ndarray
    maps: list[LocalMap]


def _joined(pieces: _Pieces, bounds: np.ndarray, steps: int) -> np.ndarray:
    """Each block's end pose in the frame of its map between ``bounds`` (a chain of ``steps``),
    from the solved ``pieces``, joined map by map with the certified one-step join."""
    piece_bounds, local = pieces.bounds, pieces.block_poses
    start_of_piece = np.zeros((len(pieces.maps), 3))         # each piece's start in its map's frame
    owner = np.searchsorted(bounds, piece_bounds[:-1], side="right") - 1
    for j in range(len(bounds) - 1):
        members = np.flatnonzero(owner == j)
        if len(members) > 1:     # no warnings: they would name pieces the user never sees
            joined = join_sequential([pieces.maps[i] for i in members], warn=False).global_map
            start_of_piece[members[1:]] = joined.poses[np.searchsorted(joined.pose_ids, members[1:])]
    return compose(start_of_piece[_segment_of_blocks(piece_bounds, len(local), steps)], local)


def _covariance_blocks(problem: ExactProblem, data: np.ndarray, selected: list[np.ndarray]) -> list[np.ndarray]:
    """The covariance of each set of unknowns in ``selected`` (one set per local map; every
    unknown not in a set is a pose inside a map), from J^T J at the optimum (``data``).

    With the interior poses I and the selected unknowns S, the information of S with I
    marginalised is the Schur complement ``A_SS - A_SI A_II^-1 A_IS``; A_II is banded (each
    pose couples with its neighbours in the chain only), so it is factorised as a band
    matrix. The maps are independent, so one right-hand side carries the i-th unknown of
    every map at once. Each map's covariance is the inverse of its Schur complement.
    """
    chosen = np.concatenate(selected)
    sizes = np.array([len(s) for s in selected])
    interior = np.setdiff1d(np.arange(problem.n_unknowns), chosen, assume_unique=True)
    order = problem.position[np.concatenate([interior, chosen])]
    A = problem.normal_matrix(data).tocsr()[order][:, order].tocsc()
    n = len(interior)
    inner, outer, own = A[:n, :n].tocoo(), A[:n, n:].tocsr(), A[n:, n:].tocsr()
    if n:
        upper = inner.col >= inner.row
        width = int((inner.col - inner.row)[upper].max())
        band = np.zeros((width + 1, n))
        band[width + inner.row[upper] - inner.col[upper], inner.col[upper]] = inner.data[upper]
        factor = scipy.linalg.cholesky_banded(band, check_finite=False)
    probe_row = np.arange(len(chosen))
    probe_column = np.concatenate([np.arange(k) for k in sizes])
    first = np.concatenate([[0], np.cumsum(sizes)])
    schur = [np.empty((k, k)) for k in sizes]
    for low in range(0, int(sizes.max()), _PROBES):
        high = min(low + _PROBES, int(sizes.max()))
        probes = np.zeros((len(chosen), high - low))
        inside = (probe_column >= low) & (probe_column < high)
        probes[probe_row[inside], probe_column[inside] - low] = 1.0
        block = own @ probes
        if n:
            block -= outer.T @ scipy.linalg.cho_solve_banded((factor, False), outer @ probes, check_finite=False)
        for j, k in enumerate(sizes):
            if k > low:
                schur[j][:, low:high] = block[first[j]:first[j + 1], :min(k, high) - low]
    covariances = [np.linalg.inv((s + s.T) / 2) for s in schur]
    return [(c + c.T) / 2 for c in covariances]     # exactly symmetric (LocalMap then takes it as is)
