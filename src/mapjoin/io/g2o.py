"""g2o export of a global map (write-only; for g2o's viewer and GTSAM's ``readG2o``).

::

    # mapjoin global map: VERTEX_SE2 <pose id> x y phi per end pose, VERTEX_XY <feature id + 1000> x y ...
    VERTEX_SE2 1 1.5 -0.25 0.1
    VERTEX_XY 1012 3.0 4.0

g2o has one id space, so feature ids are offset by :func:`g2o_feature_offset` (the smallest
power of ten above every pose id, at least 10); the first line says which. Vertices only:
the variances are not exported, and no edges: a local map's estimates are correlated (one
covariance over its end pose and all its features) while g2o's 2D edges are independent,
so edges from the maps' marginal blocks would pose another problem than the exact join.
"""

from __future__ import annotations

import numpy as np

from ..errors import InputError
from ..maps import GlobalMap

__all__ = ["dump", "g2o_feature_offset"]

_G2O_MAX_ID = 2**31 - 1  # g2o vertex ids are C ints


def g2o_feature_offset(pose_ids: np.ndarray) -> int:
    """What the g2o export adds to feature ids so they cannot clash with pose ids (g2o has one id space):
    the smallest power of ten above every pose id, at least 10 (poses 1..200: feature 7 is vertex 1007)."""
    return 10 ** len(str(int(np.max(pose_ids, initial=0))))


def dump(global_map: GlobalMap) -> str:
    """``VERTEX_SE2 id x y phi`` per end pose (its id), ``VERTEX_XY id x y`` per feature (its id plus
    :func:`g2o_feature_offset`), after a comment stating the mapping."""
    offset = g2o_feature_offset(global_map.pose_ids)
    largest = max(int(np.max(global_map.pose_ids, initial=0)), int(np.max(global_map.feature_ids, initial=-1)) + offset)
    if largest > _G2O_MAX_ID:
        raise InputError(f"vertex id {largest} does not fit g2o's 32-bit ids (feature ids are offset by {offset})",
                         global_map.name)
    return "\n".join([
        (f"# mapjoin global map: VERTEX_SE2 <pose id> x y phi per end pose, VERTEX_XY <feature id + {offset}> x y "
         "per feature"),
        *(f"VERTEX_SE2 {i} {x!r} {y!r} {phi!r}" for i, (x, y, phi) in zip(global_map.pose_ids.tolist(),
                                                                           global_map.poses.tolist())),
        *(f"VERTEX_XY {i + offset} {x!r} {y!r}" for i, (x, y) in zip(global_map.feature_ids.tolist(),
                                                                      global_map.features.tolist())),
    ]) + "\n"
