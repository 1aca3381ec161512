"""The hierarchical start of the exact solve: the tree join with its top levels' pieces solved exactly
(docs/method.md#hierarchical-start).

The tree join (docs/method.md#tree-joining) moves each right piece rigidly and bends neither piece, so each
piece keeps its dead-reckoned heading drift until a top-level join aligns two drifted laps; on long runs the
exact solve from it can creep without converging (``simulate(10000, seed=2)``: 100 iterations, chi^2
464543.7 against the optimum 284904.29). Here the levels of the tree with at most ``2^depth`` pieces have
their pieces solved exactly (:func:`.solver.minimise`, all pieces of a level as one problem of independent
parts, a few iterations) before the next level joins them, so that the join above meets a piece that is
already bent to its own loop closures and the seam left for the whole solve is a single junction.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from ..joins import _Pieces
from ..maps import LocalMap
from .problem import Blocks, ExactProblem
from .solver import minimise

__all__ = ["HIERARCHICAL", "SETTLE_DEPTH", "SETTLE_ITERATIONS", "SETTLE_TOLERANCE", "Settle"]

#: the start's name (``refine --start hierarchical``)
HIERARCHICAL = "hierarchical"
#: the levels settled: those of at most 2^SETTLE_DEPTH pieces (1: the root's two children). Measured on
#: 10^4 maps, seed 2 (benchmarks/README.md, "The hierarchical start"): the children alone settled let the
#: whole solve converge; the levels of 3 pieces too cost more and gained nothing
SETTLE_DEPTH = 1
#: at most this many iterations per settled level: the pieces need to be bent near their optimum, not to
#: the tolerance (5 settle 10^4 maps, seed 2, in 20 iterations with the whole solve's, against 26 to
#: convergence)
SETTLE_ITERATIONS = 5
#: the settled levels' stopping tolerance (relative chi^2 change, :func:`.solver.minimise`)
SETTLE_TOLERANCE = 1e-6


@dataclass(frozen=True)
class Settle:
    """The hook :func:`mapjoin.joining.join_tree` calls after each level (``settle(pieces, level)``): a level
    of at most ``2^depth`` pieces, and more than one (the whole chain is the exact solve's), has all its
    pieces solved exactly, each in the frame of its own start pose, by at most ``iterations`` iterations of
    :func:`.solver.minimise` at ``tolerance``. The pieces keep the tree's spherical variances as the weights
    of the joins above (the marginals of the settled pieces would cost a selected inversion per level).
    ``levels``: per settled level, ``(level, pieces, chi^2 before, chi^2 after, iterations)``."""

    maps: Sequence[LocalMap]
    depth: int = SETTLE_DEPTH
    iterations: int = SETTLE_ITERATIONS
    tolerance: float = SETTLE_TOLERANCE
    levels: list[tuple[int, int, float, float, int]] = field(default_factory=list)

    def __post_init__(self) -> None:
        if self.depth < 0:
            raise ValueError(f"depth must be >= 0, got {self.depth}")
        if self.iterations < 0:
            raise ValueError(f"iterations must be >= 0, got {self.iterations}")

    def __call__(self, pieces: _Pieces, level: int) -> _Pieces:
        if not 1 < pieces.count <= 2 ** self.depth:
            return pieces
        problem, features = _pieces_problem(self.maps, pieces)
        x = np.concatenate([np.column_stack([pieces.pose_xy.real, pieces.pose_xy.imag, pieces.pose_phi]).ravel(),
                            np.column_stack([pieces.features.real, pieces.features.imag])[features].ravel()])
        before = problem.cost(x)
        found = minimise(problem, x, max_iterations=self.iterations, tolerance=self.tolerance)
        self.levels.append((level, pieces.count, before, found.cost, found.iterations))
        poses, settled = problem.unpack(found.x)
        placed = np.empty(len(pieces.features), dtype=complex)
        placed[features] = settled[:, 0] + 1j * settled[:, 1]
        return dataclasses.replace(pieces, pose_xy=poses[:, 0] + 1j * poses[:, 1], pose_phi=poses[:, 2],
                                   features=placed)


def _pieces_problem(maps: Sequence[LocalMap], pieces: _Pieces) -> tuple[ExactProblem, np.ndarray]:
    """The exact problem of every piece at once, its parts independent: each piece's first map starts at a
    fixed origin of its own, and a feature seen by two pieces is one unknown in each (ids ``piece * n +
    compact id``). With it, the feature rows of ``pieces`` in the problem's feature order (its poses are the
    maps', in chain order, as the pieces' pose rows)."""
    blocks = Blocks.of_maps(maps)
    ids = np.unique(blocks.feature_ids)       # the tree's compact ids (joining._prepare)
    n = len(ids)
    owner = np.repeat(np.arange(len(maps)), blocks.sizes)
    origins = max(int(blocks.end_ids.max()), int(blocks.start_ids.max())) + 1 + np.arange(pieces.count)
    start_ids = blocks.start_ids.copy()
    start_ids[pieces.first] = origins
    renamed = pieces.pose_piece[owner] * n + np.searchsorted(ids, blocks.feature_ids)
    problem = ExactProblem(dataclasses.replace(blocks, start_ids=start_ids, feature_ids=renamed), origins=origins)
    rows = np.argsort(np.searchsorted(problem.feature_ids, pieces.feature_piece * n + pieces.feature_ids))
    return problem, rows
