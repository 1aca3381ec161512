"""A join with data association: :func:`join_associated` and its result (docs/method.md#data-association).

:func:`join_associated` joins maps whose feature ids are local to each map as :func:`mapjoin.joining.join` does, the
hooks of :mod:`mapjoin.association.associator` deciding before each join which features are common; the global ids
are numbered from 0 in order of first sighting, by map, then by local id. Its :class:`AssociatedJoin` holds each input
feature's global id and the report's rows with the association's counts (:class:`AssociatedJoinRecord`);
:class:`FeatureAssociation` is a row of ``join --associations``.
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, NamedTuple

import numpy as np

from ..covariance import DEFAULT_COVARIANCE, CovarianceMode
from ..joining import join
from ..joins import JoinRecord, Strategy
from ..maps import GlobalMap, LocalMap
from ..onestep import as_complex
from .associator import _Associator
from .covariance_blocks import end_relative, feature_covariances
from .gate import DEFAULT_GATE, DEFAULT_MARGIN, _check_gate

if TYPE_CHECKING:
    from ..onestep import Solver

__all__ = ["AssociatedJoin", "AssociatedJoinRecord", "AssociationCounts", "FeatureAssociation", "join_associated"]

log = logging.getLogger("mapjoin")


@dataclass(frozen=True)
class AssociatedJoinRecord(JoinRecord):
    """A join's report row when associating: ``common`` features were matched, ``new`` were not, of which
    ``ambiguous`` had two candidates in the gate and ``rejected`` failed the joint compatibility test; ``guarded``
    pairs of the first association were left out by the association again under a wider drift, the join being
    inconsistent with an outlying pair (step 9, :mod:`mapjoin.association.guard`; they may be counted ambiguous or
    rejected there as well)."""

    ambiguous: int = 0
    rejected: int = 0
    guarded: int = 0


class AssociationCounts(NamedTuple):
    """The report's association columns summed over every join: incoming features ``matched`` (the joins'
    ``common``) and ``new``, and of the new ones those left ``ambiguous`` or ``rejected``; ``guarded`` pairs."""

    matched: int
    new: int
    ambiguous: int
    rejected: int
    guarded: int

    @property
    def doubtful(self) -> bool:
        """Whether the features left ambiguous are at least half as many as those matched: the incoming maps'
        features then lie closer together than their uncertainty, and many true pairs were left new (features
        mapped twice). Measured (docs/joining.md, limits; seeds 0-1 of 30 maps): on VicPark 200, DLR 200 and the 8240
        simulation with local ids and on the default simulations, ambiguous features are 0.4-40 % of the matched ones
        (recall 66-99 %); sequentially with 15-20 steps per local map 25-48 % (recall 62-73 %); by the tree with 15-20
        steps 67-96 % (recall 41-50 %), and with 30 steps either way 170-550 % (recall 27 % down to 17 %)."""
        return self.ambiguous > 0 and 2 * self.ambiguous >= self.matched


@dataclass(frozen=True)
class FeatureAssociation:
    """One row of ``join --associations``: feature ``local_id`` of input map ``map`` (1-based) is ``global_id``."""

    map: int
    local_id: int
    global_id: int


@dataclass(frozen=True)
class AssociatedJoin:
    """A join with data association: the result (global ids numbered by first sighting, report rows
    :class:`AssociatedJoinRecord`), each input feature's global id (``maps[k]``'s ``feature_ids[j]`` is
    ``global_ids[k][j]``)."""

    global_map: GlobalMap
    report: tuple[AssociatedJoinRecord, ...]
    global_ids: tuple[np.ndarray, ...]

    @property
    def counts(self) -> AssociationCounts:
        """The association's counts summed over every join of the report."""
        return AssociationCounts(*(sum(getattr(r, column) for r in self.report)
                                   for column in ("common", "new", "ambiguous", "rejected", "guarded")))

    def relabel(self, maps: Sequence[LocalMap]) -> tuple[LocalMap, ...]:
        """The input ``maps`` with their features' global ids: a known-id join of them is the same join."""
        return tuple(dataclasses.replace(m, feature_ids=ids) for m, ids in zip(maps, self.global_ids))

    def rows(self, maps: Sequence[LocalMap]) -> list[FeatureAssociation]:
        """The ``--associations`` table of the input ``maps``: one row per feature, by map then local id."""
        return [FeatureAssociation(k + 1, int(local), int(found)) for k, m in enumerate(maps)
                for local, found in sorted(zip(m.feature_ids.tolist(), self.global_ids[k].tolist()))]


def join_associated(maps: Sequence[LocalMap], covariance: CovarianceMode = DEFAULT_COVARIANCE,
                    solver: Solver = "bisection", strategy: Strategy = "sequential", *,
                    gate: float = DEFAULT_GATE, progress: Callable[[int], None] | None = None,
                    margin: float = DEFAULT_MARGIN) -> AssociatedJoin:
    """Join ``maps`` whose feature ids are local to each map, associating their features before each join
    (see :mod:`mapjoin.association`; ``gate`` is the chi-square level of the gate and of the joint test, ``margin``
    how much farther a rival candidate must be). The tree runs in one process."""
    _check_gate(gate)
    if not margin >= 0.0:
        raise ValueError(f"margin must be a squared distance >= 0, got {margin!r}")
    orders = [np.argsort(m.feature_ids, kind="stable") for m in maps]
    points = [as_complex(m.features[order]) for m, order in zip(maps, orders)]
    # the link rule reads the link maps': every map's sequentially, the tree's the first level's left maps (the even
    # ones; all would cost a tree's association on the datasets 5-17 ms)
    ends = [end_relative(m) if strategy == "sequential" or k % 2 == 0 else None for k, m in enumerate(maps)]
    associator = _Associator([feature_covariances(m) for m in maps], points,
                             np.array([m.end_pose for m in maps]).reshape(-1, 3), gate, margin,
                             [m.covariance for m in maps], orders,
                             np.array([m.pose_variances for m in maps]).reshape(-1, 2),
                             ends)
    # one map is no join: numbered as the sequential strategy's first map (the tree's hook runs per level)
    result = join(maps, covariance, solver, strategy if len(maps) > 1 else "sequential", 1, progress,
                  associate=associator)
    numbering, row_global = associator.global_ids()
    global_map = result.global_map
    if global_map.provenance.strategy != strategy:
        global_map = dataclasses.replace(global_map, provenance=dataclasses.replace(global_map.provenance,
                                                                                    strategy=strategy))
    relabelled = numbering[global_map.feature_ids]
    order = np.argsort(relabelled, kind="stable")
    global_map = dataclasses.replace(global_map, feature_ids=relabelled[order], features=global_map.features[order],
                                     feature_variances=global_map.feature_variances[order])
    report = tuple(AssociatedJoinRecord(**vars(record), ambiguous=ambiguous, rejected=rejected, guarded=guarded)
                   for record, (ambiguous, rejected, guarded) in zip(result.report, associator.counts))
    offsets = associator.offsets.tolist()
    per_map = []
    for k, local_map in enumerate(maps):  # rows in _prepare's order: each map's ids sorted
        order_ids = np.argsort(local_map.feature_ids, kind="stable")
        ids = np.empty(local_map.size, dtype=np.int64)
        ids[order_ids] = row_global[offsets[k]:offsets[k + 1]]
        per_map.append(ids)
    joined = AssociatedJoin(global_map, report, tuple(per_map))
    if (counts := joined.counts).doubtful:
        log.warning("the association left %d incoming features ambiguous (two candidates in its gate) against %d "
                    "matched: the maps' features lie closer than their uncertainty, and the global map likely holds "
                    "features twice (docs/joining.md, limits of data association)", counts.ambiguous, counts.matched)
    return joined
