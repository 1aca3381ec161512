"""CSV local maps: one row per entity, any number of maps per file, columns by header name.

::

    map,start_id,end_id,kind,id,x,y,phi,var_xy,var_phi
    map-7,6,7,pose,7,1.5,-0.25,0.1,0.01,0.001
    map-7,6,7,feature,12,3.0,4.0,,0.02,

Columns are found by their header name, in any order; spaces around a separator (and a
name) are ignored. ``kind``, ``id``, ``x``, ``y``, ``phi``, ``start_id`` and ``end_id`` are
required; the others are optional:

- ``map`` names the map (unique within a file, see "Map names" in mapjoin.io); without it,
  the rows of one map are those with its ``end_id``.
- ``var_xy`` (or ``var``, as YAML calls a feature's) is the spherical variance sigma^2 (m^2)
  of each of x and y; ``var_phi`` the heading's (rad^2), on the pose row. Both may be left
  out (column or cell) for a map that has ``cov`` rows: they are then the covariance's
  marginal ones (the ``marginal`` summary, docs/method.md#covariance-modes).
- ``i``, ``j``, ``cov``: the map's full covariance, one ``kind`` = ``cov`` row per entry
  (i, j) of its upper triangle (i <= j, every entry once), in the order of the state vector
  ``x y phi f1x f1y f2x f2y ...`` with the features in the order of their rows (0-based).
  A map has them all or none; with them, the covariance wins: the joins and the refinement
  use it, the variances only round-trip.

Each map has exactly one ``pose`` row (its end pose, ``id`` = ``end_id``); ``feature`` rows leave
``phi`` and ``var_phi`` empty, ``cov`` rows every column but ``map``, ``start_id``, ``end_id``,
``kind``, ``i``, ``j``, ``cov``. Other columns (a timestamp) are ignored, with one warning per file; a column
whose name is close to one of these (``var_pih``) is refused as a typo.
Example with a covariance (one feature: a 5x5 matrix, 15 entries)::

    map,start_id,end_id,kind,id,x,y,phi,var_xy,var_phi,i,j,cov
    m,0,1,pose,1,1.0,0.0,0.1,0.01,0.001,,,
    m,0,1,feature,12,3.0,4.0,,0.02,,,,
    m,0,1,cov,,,,,,,0,0,0.01
    m,0,1,cov,,,,,,,0,1,0.0
    ...
    m,0,1,cov,,,,,,,4,4,0.02

Written maps keep their names, variances and covariances, so CSV round-trips exactly.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from ..errors import InputError, shown
from ..maps import LocalMap, StackedMaps, first_duplicate, first_invalid_map, marginal_variances, size_groups, unstack
from . import csvtable
from .fields import filled_variances, ignored_fields, warn_ignored
from .paths import map_name

__all__ = ["dump", "read"]

_HEADER = ("map", "start_id", "end_id", "kind", "id", "x", "y", "phi", "var_xy", "var_phi")
_COVARIANCE_COLUMNS = ("i", "j", "cov")
_REQUIRED = ("start_id", "end_id", "kind", "id", "x", "y", "phi")
_KNOWN = (*_HEADER, *_COVARIANCE_COLUMNS)
_ALIASES = {"var": "var_xy"}  # the name YAML gives a feature's variance
_ENTITY_COLUMNS = ("id", "x", "y", "phi", "var_xy", "var_phi")  # empty on cov rows


def read(text: str, source: str, *, line_offset: int = 0, first_number: int = 1, several: bool | None = None,
         warn: bool = True) -> list[LocalMap]:
    """The local maps of a CSV file, in the order their rows first appear; all checked at once.

    A block of a longer stream (:mod:`.csv_blocks`) passes its place in it: ``line_offset`` (added to the
    line numbers), ``first_number`` (its first map's position), ``several`` (whether the stream holds more
    than one map, which decides the names; None: this text says) and ``warn`` (False: unknown columns were
    warned about already).
    """
    table = csvtable.Table(text, source, None, line_offset)
    _name_columns(table, warn)
    kinds = table.text("kind")
    features, poses, entries = (np.flatnonzero(kinds == kind) for kind in ("feature", "pose", "cov"))
    bad = np.flatnonzero((kinds != "feature") & (kinds != "pose") & (kinds != "cov"))
    if bad.size:
        raise table.error(int(bad[0]), "kind", f"expected feature, pose or cov, got {shown(kinds[bad[0]])}")
    entities = np.flatnonzero(kinds != "cov")
    ids = table.values(("start_id", "end_id"), None, "id")
    named = "map" in table.columns
    names = table.text("map") if named else ids[:, 1]
    _, first, group = np.unique(names, return_index=True, return_inverse=True)
    group = group.reshape(-1)
    if not named:  # how messages name a map: by its end id
        names = np.array([f"ending at {k}" for k in ids[first, 1].tolist()], dtype=object)[group]
    feature_ids = table.ids(features, group[features], " in this map")
    pose_ids = table.values(("id",), poses, "id")[:, 0]
    xy = np.empty((len(kinds), 2))
    xy[entities] = table.values(("x", "y"), entities, "number")
    orientation = np.empty(len(kinds))
    orientation[poses] = table.values(("phi",), poses, "number")[:, 0]
    table.empty([column for column in ("phi", "var_phi") if column in table.columns], features,
                "a feature has no orientation")
    table.empty([column for column in _ENTITY_COLUMNS if column in table.columns], entries,
                "a cov row holds one covariance entry: i, j, cov")
    table.empty([column for column in _COVARIANCE_COLUMNS if column in table.columns], entities,
                "only cov rows hold covariance entries")

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
    sizes = np.bincount(group[features], minlength=len(first))
    covariance = _Entries(table, entries, group[entries], sizes, first, names)
    var_xy = _variances(table, "var_xy", entities, covariance.given[group[entities]])
    var_phi = _variances(table, "var_phi", poses, covariance.given[group[poses]])

    # the maps in file order, stacked by size (and whether they have a covariance), checked at once, as
    # LocalMap(...) checks one
    in_order = np.argsort(first)                      # place -> the map's group
    pose = np.empty(len(first), dtype=np.int64)       # group -> its pose row
    pose[group[poses]] = poses
    pose_rows = pose[in_order]
    by_map = np.argsort(group[features], kind="stable")  # the feature rows, map after map (groups' order)
    offsets = (np.cumsum(sizes) - sizes)[in_order]
    sizes, given = sizes[in_order], covariance.given[in_order]
    several = len(first) > 1 if several is None else several
    labels = [map_name(source, label if named else None, number if several else None)
              for number, label in enumerate(names[pose_rows].tolist(), first_number)]
    start_ids, end_ids = ids[pose_rows, 0].tolist(), ids[pose_rows, 1].tolist()
    stacks = []
    for places in size_groups(2 * sizes + given):
        among = by_map[offsets[places, np.newaxis] + np.arange(sizes[places[0]])]   # maps x features, of features
        rows = features[among]
        feature_variances = var_xy[rows]
        pose_variances = np.column_stack([var_xy[pose_rows[places]], var_phi[pose_rows[places]]])
        matrices = covariance.stack(in_order[places], 3 + 2 * int(sizes[places[0]])) if given[places[0]] else None
        if matrices is not None:  # the variances left out: the covariance's marginal ones
            marginal_features, marginal_poses = marginal_variances(matrices)
            feature_variances = filled_variances(feature_variances, marginal_features)
            pose_variances = filled_variances(pose_variances, marginal_poses)
        stacks.append((places, StackedMaps([labels[i] for i in places], np.column_stack(
            [xy[pose_rows[places]], orientation[pose_rows[places]]]), feature_ids[among],
            xy[rows], feature_variances, pose_variances, matrices)))
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


def _name_columns(table: csvtable.Table, warn: bool = True) -> None:
    """Check the header names the required columns; ``var`` read as ``var_xy``; unknown columns ignored (one
    warning), a near miss of a known one refused."""
    where = f"line {table.header_line}"
    for alias, name in _ALIASES.items():
        if alias in table.columns:
            if name in table.columns:
                raise InputError(f"the columns {alias} and {name} are the same variance; give one", table.source,
                                 where)
            table.columns[name] = table.columns.pop(alias)
    missing = [name for name in _REQUIRED if name not in table.columns]
    if missing:
        got = shown(",".join(table.header)) if table.header else "nothing"
        raise InputError(f"expected the header to name the columns {', '.join(_REQUIRED)} (any order; optional: "
                         f"map, var_xy, var_phi, i, j, cov), missing {', '.join(missing)}; got {got}", table.source,
                         where)
    ignored = ignored_fields(table.columns, (*_KNOWN, *_ALIASES), table.source, where, "column")
    if warn:
        warn_ignored(table.source, "column", ignored)


def _variances(table: csvtable.Table, column: str, rows: np.ndarray, optional: np.ndarray) -> np.ndarray:
    """The variances of ``column`` at ``rows`` (a full-length array, NaN elsewhere and in the empty cells of the
    rows where they are ``optional``: maps with a covariance)."""
    values = np.full(len(table.cells), np.nan)
    if column not in table.columns:
        if not optional.all():
            raise table.error(int(rows[np.argmin(optional)]), column,
                              "missing; expected a positive finite number (or the map's cov rows)")
        return values
    given = rows[~optional | (table.text(column)[rows] != "")]
    values[given] = table.values((column,), given, "variance")[:, 0]
    return values


class _Entries:
    """The ``cov`` rows of a file: which maps have a covariance (``given``, by group), each checked complete."""

    def __init__(self, table: csvtable.Table, rows: np.ndarray, groups: np.ndarray, sizes: np.ndarray,
                 first: np.ndarray, names: np.ndarray):
        self.given = np.bincount(groups, minlength=len(sizes)) > 0
        self.groups = groups
        if not rows.size:
            self.i = self.j = self.values = np.zeros(0)
            return
        missing = next((column for column in _COVARIANCE_COLUMNS if column not in table.columns), None)
        if missing is not None:
            raise table.error(int(rows[0]), "kind", f"a cov row needs the columns i, j and cov; the header has no "
                              f"{missing}")
        i, j = table.values(("i", "j"), rows, "id").T
        self.values = table.values(("cov",), rows, "number")[:, 0]
        order = 3 + 2 * sizes[groups]
        lower = np.flatnonzero(i > j)
        if lower.size:
            raise table.error(int(rows[lower[0]]), "i", f"expected i <= j (the upper triangle of the symmetric "
                              f"covariance), got i={i[lower[0]]}, j={j[lower[0]]}")
        outside = np.flatnonzero(j >= order)
        if outside.size:
            k = int(outside[0])
            raise table.error(int(rows[k]), "j", f"expected i, j below {order[k]} (the map's covariance is "
                              f"{order[k]}x{order[k]}: 3 + 2 x {sizes[groups[k]]} features), got j={j[k]}")
        twice = first_duplicate(i * int(order.max()) + j, groups)
        if twice is not None:
            raise table.error(int(rows[twice]), "i", f"entry ({i[twice]}, {j[twice]}) given twice for map "
                              f"{shown(names[rows[twice]])}")
        counts = np.bincount(groups, minlength=len(sizes))
        full = (3 + 2 * sizes) * (4 + 2 * sizes) // 2
        short = np.flatnonzero(self.given & (counts != full))
        if short.size:
            g = int(short[np.argmin(first[short])])
            n = 3 + 2 * int(sizes[g])
            present = set(zip(i[groups == g].tolist(), j[groups == g].tolist()))
            absent = next((a, b) for a in range(n) for b in range(a, n) if (a, b) not in present)
            raise table.error(int(first[g]), "kind", f"map {shown(names[first[g]])} has {counts[g]} cov rows; "
                              f"expected {full[g]} (every entry i <= j of its {n}x{n} covariance), missing "
                              f"({absent[0]}, {absent[1]})")
        self.i, self.j = i, j

    def stack(self, groups: np.ndarray, order: int) -> np.ndarray:
        """The covariances of the maps ``groups`` (each has one, of size ``order``), stacked."""
        place = np.full(len(self.given), -1)
        place[groups] = np.arange(len(groups))
        mine = np.flatnonzero(place[self.groups] >= 0)
        matrices = np.empty((len(groups), order, order))
        at = place[self.groups[mine]]
        matrices[at, self.i[mine], self.j[mine]] = self.values[mine]
        matrices[at, self.j[mine], self.i[mine]] = self.values[mine]
        return matrices


def dump(maps: Sequence[LocalMap]) -> str:
    """Local maps as CSV: their names, variances and (``cov`` rows) full covariances."""
    covariances = any(local_map.covariance is not None for local_map in maps)
    extra: list[None] = [None] * len(_COVARIANCE_COLUMNS) if covariances else []
    rows: list[Sequence[Any]] = [(*_HEADER, *_COVARIANCE_COLUMNS) if covariances else _HEADER]
    for local_map in maps:
        if local_map.name != local_map.name.strip(" \t"):
            raise InputError(f"cannot be written as CSV: its name {shown(local_map.name)} has blanks around it, "
                             "which CSV reading ignores (rename the map)", local_map.name)
        head = [local_map.name, local_map.start_id, local_map.end_id]
        rows.append([*head, "pose", local_map.end_id, *local_map.end_pose.tolist(),
                     *local_map.pose_variances.tolist(), *extra])
        rows.extend([*head, *row] for row in csvtable.kind_rows("feature", local_map.size, [
            local_map.feature_ids.tolist(), *local_map.features.T.tolist(), None,
            local_map.feature_variances.tolist(), None, *extra]))
        if local_map.covariance is not None:
            i, j = np.triu_indices(len(local_map.covariance))
            rows.extend([*head, *row] for row in csvtable.kind_rows("cov", len(i), [
                *[None] * len(_ENTITY_COLUMNS), i.tolist(), j.tolist(), local_map.covariance[i, j].tolist()]))
    return csvtable.to_text(rows)
