"""Ids local to each map made from a map set with global ids, the true correspondence, and an association's errors
against it (docs/method.md#data-association).

:func:`local_ids` turns a map set with global ids into one with ids local to each map and returns the true
correspondence (tests, benchmarks, ``simulate --local-ids``); :func:`correspondence_rows` gives it as the rows
``join --associations`` writes; :func:`link_errors` counts an association's missed and false links against it.
"""

from __future__ import annotations

import collections
import dataclasses
from collections.abc import Sequence

import numpy as np

from ..maps import LocalMap
from .associated_join import AssociatedJoin, FeatureAssociation

__all__ = ["correspondence_rows", "link_errors", "local_ids"]

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


def link_errors(local: Sequence[LocalMap], truth: Sequence[np.ndarray], found: AssociatedJoin) -> tuple[int, int, int]:
    """How an association compares with the true one: (true links, links missed, false links).

    A link is a feature seen again by a later map. ``truth[k]`` are map k's true global ids in the
    order of its sorted local ids (as :func:`local_ids` returns them); ``found`` the association's
    global ids. Both partition the input features: a true feature split over several found ones
    counts the extra parts as missed links, a found feature joining several true ones counts the
    extra ones as false links."""
    true = np.concatenate(truth)
    mine = np.concatenate([found.global_ids[k][np.argsort(m.feature_ids)] for k, m in enumerate(local)])
    pairs = set(zip(mine.tolist(), true.tolist()))
    per_found = collections.Counter(f for f, _ in pairs)
    per_true = collections.Counter(t for _, t in pairs)
    return (len(true) - len(set(true.tolist())), sum(c - 1 for c in per_true.values()),
            sum(c - 1 for c in per_found.values()))
