"""Faults a front end makes, injected into a chain of local maps: what the consistency check must find.

The consistency check (docs/method.md#chi-square-check) and its exact confirmation
(docs/method.md#confirmation) are measured and tested on real chains with one map corrupted in
one of three ways, each a fault seen in practice:

- ``heading``: the map's end heading off by 0.6 rad (a bad odometry integration); the
  value enters the problem of the *next* join, whose link it is;
- ``feature``: a feature the earlier maps saw moved by 5 m in x (a bad measurement or a
  wrong association inside the front end);
- ``swap``: the ids of that feature and the next one exchanged (a wrong association).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Literal

import numpy as np

from .maps import LocalMap

__all__ = ["FAULTS", "Fault", "corrupted"]

Fault = Literal["heading", "feature", "swap"]
FAULTS: tuple[str, ...] = ("heading", "feature", "swap")
HEADING_ERROR = 0.6   # rad, added to the end heading
FEATURE_ERROR = 5.0   # m, added to the feature's x


def corrupted(maps: Sequence[LocalMap], k: int, fault: Fault) -> tuple[list[LocalMap], int]:
    """``maps`` with map ``k`` (0-based, k >= 1) corrupted by ``fault``, and the number (1-based) of the
    sequential join whose problem holds the corrupted value: join k for a feature or an id (map k joins
    the maps before it there), join k + 1 for the heading (the odometry link to the next map). The
    feature corrupted is map k's first one that the maps before it saw, so that the fault is in a common
    feature; ValueError if there is none, or ``fault`` or ``k`` is out of range."""
    if fault not in FAULTS:
        raise ValueError(f"fault must be one of {', '.join(FAULTS)}, got {fault!r}")
    if not 1 <= k < len(maps):
        raise ValueError(f"k must be a map after the first (1 to {len(maps) - 1}), got {k}")
    local_map = maps[k]
    seen = np.flatnonzero(np.isin(local_map.feature_ids, np.concatenate([m.feature_ids for m in maps[:k]])))
    if not len(seen):
        raise ValueError(f"map {k} shares no feature with the maps before it")
    j = int(seen[0])
    if fault == "heading":
        changed = dataclasses.replace(local_map, end_pose=local_map.end_pose + [0.0, 0.0, HEADING_ERROR])
        return [*maps[:k], changed, *maps[k + 1:]], k + 1
    if fault == "feature":
        features = local_map.features.copy()
        features[j, 0] += FEATURE_ERROR
        changed = dataclasses.replace(local_map, features=features)
    else:
        ids = local_map.feature_ids.copy()
        other = (j + 1) % len(ids)
        ids[[j, other]] = ids[[other, j]]
        changed = dataclasses.replace(local_map, feature_ids=ids)
    return [*maps[:k], changed, *maps[k + 1:]], k
