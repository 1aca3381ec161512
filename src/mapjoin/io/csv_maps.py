"""CSV local maps: one row per entity, any number of maps per file.

::

    map,start_id,end_id,kind,id,x,y,phi,var_xy,var_phi
    map-7,6,7,pose,7,1.5,-0.25,0.1,0.01,0.001
    map-7,6,7,feature,12,3.0,4.0,,0.02,

``map`` names the map (unique within a file, see "Map names" in mapjoin.io); its rows are
written together, in map order. Each map has exactly one ``pose`` row (its end pose,
``id`` = ``end_id``); ``feature`` rows carry the spherical variance in ``var_xy`` and leave
``phi`` and ``var_phi`` empty. CSV holds spherical variances only: writing maps with full
covariances drops them (the registry says so, and the writer warns once).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from ..errors import InputError, shown
from ..maps import LocalMap, StackedMaps, first_duplicate, first_invalid_map, size_groups, unstack
from . import csvtable
from .paths import map_name

__all__ = ["dump", "read"]

_HEADER = ("map", "start_id", "end_id", "kind", "id", "x", "y", "phi", "var_xy", "var_phi")


def read(text: str, source: str) -> list[LocalMap]:
    """The local maps of a CSV file, in the order their rows first appear; all checked at once."""
    table = csvtable.Table(text, source, [_HEADER])
    features, poses = table.kinds()
    names = table.text("map")
    _, first, group = np.unique(names, return_index=True, return_inverse=True)
    group = group.reshape(-1)
    ids = table.values(("start_id", "end_id"), None, "id")
    feature_ids = table.ids(features, group[features], " in this map")
    pose_ids = table.values(("id",), poses, "id")[:, 0]
    xy = table.values(("x", "y"), None, "number")
    var_xy = table.values(("var_xy",), None, "variance")[:, 0]
    orientation = table.values(("phi",), poses, "number")[:, 0]
    var_phi = table.values(("var_phi",), poses, "variance")[:, 0]
    table.empty(("phi", "var_phi"), features, "a feature has no orientation")

    changed = np.flatnonzero((ids != ids[first[group]]).any(axis=1))
    if changed.size:
        row = int(changed[0])
        raise table.error(row, "start_id", f"map {shown(names[row])} has start_id,end_id "
                          f"{ids[first[group[row]]].tolist()} on line {table.lines[first[group[row]]]}")
    pose_counts = np.bincount(group[poses], minlength=len(first))
    if (pose_counts == 0).any():
        row = int(first[np.flatnonzero(pose_counts == 0)[0]])
        raise table.error(row, "kind",
                          f"map {shown(names[row])} has no pose row; expected one (its end pose)")
    second = first_duplicate(group[poses])
    if second is not None:
        raise table.error(int(poses[second]), "kind",
                          f"map {shown(names[poses[second]])} has a second pose row; expected one")
    wrong = np.flatnonzero(pose_ids != ids[poses, 1])
    if wrong.size:
        raise table.error(int(poses[wrong[0]]), "id", f"expected the end_id {ids[poses[wrong[0]], 1]} on the pose "
                          f"row, got {pose_ids[wrong[0]]}")

    # the maps in file order, stacked by size and checked at once, as LocalMap(...) checks one
    in_order = np.argsort(first)                      # place -> the map's group
    pose = np.empty(len(first), dtype=np.int64)       # group -> its pose row among ``poses``
    pose[group[poses]] = np.arange(len(poses))
    pose = pose[in_order]
    pose_rows = poses[pose]
    sizes = np.bincount(group[features], minlength=len(first))
    by_map = np.argsort(group[features], kind="stable")  # the feature rows, map after map (groups' order)
    offsets = (np.cumsum(sizes) - sizes)[in_order]
    sizes = sizes[in_order]
    labels = [map_name(source, label, number if len(first) > 1 else None)
              for number, label in enumerate(names[pose_rows].tolist(), 1)]
    start_ids, end_ids = ids[pose_rows, 0].tolist(), ids[pose_rows, 1].tolist()
    stacks = []
    for places in size_groups(sizes):
        rows = by_map[offsets[places, np.newaxis] + np.arange(sizes[places[0]])]   # maps x features
        end_pose = np.column_stack([xy[pose_rows[places]], orientation[pose[places]]])
        pose_variances = np.column_stack([var_xy[pose_rows[places]], var_phi[pose[places]]])
        stacks.append((places, StackedMaps([labels[i] for i in places], end_pose, feature_ids[rows],
                                           xy[features[rows]], var_xy[features[rows]], pose_variances, None)))
    unmoved = np.flatnonzero(ids[pose_rows, 0] == ids[pose_rows, 1])   # LocalMap's first check
    invalid = first_invalid_map(stacks)
    if unmoved.size and (invalid is None or unmoved[0] <= invalid[0]):
        place = int(unmoved[0])
        invalid = place, InputError(f"end pose id equals start pose id ({end_ids[place]})", labels[place], "end_id")
    if invalid is not None:
        place, error = invalid
        field = f", field {error.where}" if error.where else ""
        raise InputError(error.detail, source, f"line {table.lines[first[in_order[place]]]}, map "
                                               f"{shown(names[pose_rows[place]])}{field}")
    return unstack(stacks, start_ids, end_ids)


def dump(maps: Sequence[LocalMap]) -> str:
    """Local maps as CSV, their spherical variances only."""
    rows: list[Sequence[Any]] = [_HEADER]
    for local_map in maps:
        head = [local_map.name, local_map.start_id, local_map.end_id]
        rows.append([*head, "pose", local_map.end_id, *local_map.end_pose.tolist(),
                     *local_map.pose_variances.tolist()])
        rows.extend([*head, *row] for row in csvtable.kind_rows("feature", local_map.size, [
            local_map.feature_ids.tolist(), *local_map.features.T.tolist(), None,
            local_map.feature_variances.tolist(), None]))
    return csvtable.to_text(rows)
