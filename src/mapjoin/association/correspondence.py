"""Ids local to each map made from a map set with global ids, the true correspondence, and an association's errors
against it (docs/method.md#data-association).

:func:`local_ids` turns a map set with global ids into one with ids local to each map and returns the true
correspondence (tests, benchmarks, ``simulate --local-ids``); :func:`correspondence_rows` gives it as the rows
``join --associations`` writes; :func:`link_errors` counts an association's missed and false links against it, and
:func:`scored` the same between two tables (:class:`~mapjoin.maps.Correspondence`, ``evaluate --associations``),
whose :func:`truth_of_found` says which true feature each found one stands for.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from typing import NamedTuple

import numpy as np

from ..errors import InputError
from ..maps import Correspondence, LocalMap
from .associated_join import AssociatedJoin, FeatureAssociation

__all__ = ["LinkErrors", "correspondence_rows", "link_errors", "local_ids", "scored", "truth_of_found"]


class LinkErrors(NamedTuple):
    """An association against the true one. A *link* is an input feature seen again by a later map (``links``: how
    many the truth has); both partition the input features, so a true feature split over several found ones counts
    its extra parts as ``missed`` links, a found feature joining several true ones its extra ones as ``false``."""

    links: int
    missed: int
    false: int

    @property
    def recall(self) -> float:
        """The share of the true links recovered (NaN without links)."""
        return 1.0 - self.missed / self.links if self.links else math.nan


def _counted(found: np.ndarray, true: np.ndarray) -> LinkErrors:
    """:class:`LinkErrors` of the found and true global ids of the same input features (aligned arrays): over the
    distinct (found, true) pairs, each true id's pairs beyond its first are missed links, each found id's false."""
    pairs = np.unique(np.stack([found, true]), axis=1)
    return LinkErrors(len(true) - len(np.unique(true)), pairs.shape[1] - len(np.unique(pairs[1])),
                      pairs.shape[1] - len(np.unique(pairs[0])))

def local_ids(maps: Sequence[LocalMap]) -> tuple[tuple[LocalMap, ...], tuple[np.ndarray, ...]]:
    """``maps`` with each map's feature ids replaced by ids local to it (0 .. m-1, in the order of the global
    ids), and the truth: ``truth[k][local_id]`` is the global id of map k's feature ``local_id``."""
    relabelled, truth = [], []
    for local_map in maps:
        order = np.argsort(local_map.feature_ids, kind="stable")
        ranks = np.empty(local_map.size, dtype=np.int64)
        ranks[order] = np.arange(local_map.size)
        relabelled.append(dataclasses.replace(local_map, feature_ids=ranks))
        truth.append(local_map.feature_ids[order].copy())
    return tuple(relabelled), tuple(truth)


def correspondence_rows(truth: Sequence[np.ndarray]) -> list[FeatureAssociation]:
    """:func:`local_ids`' truth as the rows ``join --associations`` writes (map 1-based, by local id)."""
    return [FeatureAssociation(k + 1, local, int(found)) for k, ids in enumerate(truth)
            for local, found in enumerate(ids.tolist())]


def link_errors(local: Sequence[LocalMap], truth: Sequence[np.ndarray], found: AssociatedJoin) -> LinkErrors:
    """How an association compares with the true one (:class:`LinkErrors`, a tuple: links, missed, false).

    ``truth[k]`` are map k's true global ids in the order of its sorted local ids (as :func:`local_ids` returns
    them); ``found`` the association's global ids."""
    true = np.concatenate(truth)
    mine = np.concatenate([found.global_ids[k][np.argsort(m.feature_ids)] for k, m in enumerate(local)])
    return _counted(mine, true)


def _aligned(found: Correspondence, true: Correspondence) -> tuple[np.ndarray, np.ndarray]:
    """The two tables' global ids row by row of the same input feature (map, local id); an input feature in one
    table and not the other is an error naming the found table."""
    order_found, order_true = (np.lexsort((table.local_ids, table.maps)) for table in (found, true))
    keys_found = np.stack([found.maps[order_found], found.local_ids[order_found]])
    keys_true = np.stack([true.maps[order_true], true.local_ids[order_true]])
    if keys_found.shape != keys_true.shape or not np.array_equal(keys_found, keys_true):
        one, other, which = (keys_found, keys_true, "has") if keys_found.shape[1] >= keys_true.shape[1] else (
            keys_true, keys_found, "lacks")
        first = _first_unmatched(one, other)
        raise InputError(f"{which} a row for map {one[0, first]}, local id {one[1, first]}, which {true.name} "
                         f"{'does not have' if which == 'has' else 'has'}: the tables are of different maps "
                         f"({found.maps.size} and {true.maps.size} rows)", found.name)
    return found.global_ids[order_found], true.global_ids[order_true]


def _first_unmatched(one: np.ndarray, other: np.ndarray) -> int:
    """The first column of ``one`` (2 x n keys, each once) that ``other`` (each once) does not hold."""
    _, inverse = np.unique(np.concatenate([one, other], axis=1), axis=1, return_inverse=True)
    held = np.zeros(inverse.max(initial=-1) + 1, dtype=bool)
    held[inverse[one.shape[1]:]] = True
    return int(np.flatnonzero(~held[inverse[:one.shape[1]]])[0])


def scored(found: Correspondence, true: Correspondence) -> LinkErrors:
    """:class:`LinkErrors` of the table ``found`` (``join --associations``) against ``true`` (``simulate
    --local-ids``): both must have one row for every input feature."""
    return _counted(*_aligned(found, true))


def truth_of_found(found: Correspondence, true: Correspondence) -> tuple[np.ndarray, np.ndarray]:
    """Each found global id and the true id most of its input features have (ties: the smallest): the feature of
    the truth a found feature stands for, when it is evaluated against the truth's positions."""
    mine, real = _aligned(found, true)
    pairs, counts = np.unique(np.stack([mine, real]), axis=1, return_counts=True)
    order = np.lexsort((pairs[1], -counts, pairs[0]))  # by found id, then most rows first, then smallest true id
    first = np.ones(len(order), dtype=bool)
    first[1:] = pairs[0, order[1:]] != pairs[0, order[:-1]]
    return pairs[0, order[first]], pairs[1, order[first]]
