"""A join with data association: :func:`join_associated` and its result (docs/method.md#data-association).

:func:`join_associated` joins maps whose feature ids are local to each map as :func:`mapjoin.joining.join` does, the
hooks of :mod:`mapjoin.association.associator` deciding before each join which features are common; the global ids
are numbered from 0 in order of first sighting, by map, then by local id. Its :class:`AssociatedJoin` holds each input
feature's global id and the report's rows with the association's counts (:class:`AssociatedJoinRecord`);
:class:`FeatureAssociation` is a row of ``join --associations``.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

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

__all__ = ["AssociatedJoin", "AssociatedJoinRecord", "FeatureAssociation", "join_associated"]

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
    associator = _Associator([feature_covariances(m) for m in maps], points,
                             np.array([m.end_pose for m in maps]).reshape(-1, 3), gate, margin,
                             [m.covariance for m in maps], orders,
                             np.array([m.pose_variances for m in maps]).reshape(-1, 2), [end_relative(m) for m in maps])
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
    return AssociatedJoin(global_map, report, tuple(per_map))
