"""Tables: rows of dataclass instances written as CSV, YAML or JSON; minima tables read back.

Written tables (e.g. a per-join report): CSV with the field names as header (``None`` ->
empty cell), YAML as a list of mappings or JSON as a list of objects (``None`` -> null).
Numpy scalars and arrays become plain numbers/lists.

Minima tables (``check-minima --batch``, and any table holding the columns): CSV with a
header naming ``a`` and ``c_phi`` (and optionally ``join`` and ``map``, which identify a row), one row per problem of
Theorem 2 (``a`` in [0, 1e100], ``|c_phi|`` <= 1e6), or a YAML/JSON list of mappings with them.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator, Sequence
from typing import Any

import numpy as np

from ..errors import InputError, shown
from ..maps import ANGLE, MINIMA_A, Correspondence
from . import csvtable, yamldoc
from .outputs import Parts

__all__ = ["MinimaTable", "dump_csv", "dump_json", "dump_yaml", "read_correspondence_csv", "read_correspondence_records",
           "read_minima_csv", "read_minima_records"]


@dataclasses.dataclass(frozen=True)
class MinimaTable:
    """Theorem 2's ``a`` and ``C_phi`` of each row of a table; ``join`` the join numbers when it has a join column,
    ``map_names`` the map column's names when it has one (a report of ``mapjoin join``): what identifies a row."""

    source: str
    a: np.ndarray
    c_phi: np.ndarray
    join: np.ndarray | None = None
    map_names: tuple[str, ...] | None = None

    def __post_init__(self) -> None:
        """Refuse a row outside the accepted ranges (docs/formats.md, "Accepted values"): ``a`` in [0, 1e100],
        ``|c_phi|`` <= 1e6 rad (beyond, its reduction modulo 2 pi loses the digits the minima depend on)."""
        for column, values in (("c_phi", self.c_phi), ("join", self.join), ("map", self.map_names)):
            if values is not None and len(values) != len(self.a):
                raise ValueError(f"{len(values)} {column} values for {len(self.a)} rows")
        for column, limits in (("a", MINIMA_A), ("c_phi", ANGLE)):
            values = getattr(self, column)
            bad = np.flatnonzero(limits.outside(values))
            if bad.size:
                raise InputError(f"expected {limits.expected()}, got {shown(values[bad[0]])}", self.source,
                                 f"row {bad[0] + 1}, column {column}")


_MINIMA_COLUMNS = {"a": "nonnegative", "c_phi": "number"}  # column -> kind of its values; "join" ("id") optional


def read_minima_csv(text: str, source: str) -> MinimaTable:
    """A CSV table whose header names a and c_phi (in any order, among any other columns)."""
    table = csvtable.Table(text, source, None)
    if not set(_MINIMA_COLUMNS) <= set(table.header):
        raise InputError(f"expected a header with the columns a and c_phi (as `mapjoin join --report` writes "
                         f"them), got {shown(','.join(table.header)) if table.header else 'nothing'}", source,
                         f"line {table.header_line}")
    a, c_phi = (table.values((column,), None, kind)[:, 0] for column, kind in _MINIMA_COLUMNS.items())
    join = table.values(("join",), None, "id")[:, 0] if "join" in table.header else None
    map_names = tuple(table.text("map").tolist()) if "map" in table.header else None
    return MinimaTable(source, a, c_phi, join, map_names)


def read_minima_records(text: str, source: str) -> MinimaTable:
    """A YAML or JSON list of mappings with a and c_phi, and join in every one or none (JSON is read as
    YAML, so that errors name lines)."""
    document = yamldoc.document(text, source)
    records = document.get((), "list")
    for row in range(len(records)):
        document.get((row,), "mapping")
    kinds = {**_MINIMA_COLUMNS, **{key: kind for key, kind in (("join", "id"), ("map", "text"))
                                   if any(key in record for record in records)}}
    columns = {key: [document.get((row, key), kind) for row in range(len(records))] for key, kind in kinds.items()}
    join = np.array(columns["join"], dtype=np.int64) if "join" in columns else None
    map_names = tuple(columns["map"]) if "map" in columns else None
    return MinimaTable(source, np.array(columns["a"], dtype=float), np.array(columns["c_phi"], dtype=float), join,
                       map_names)


_CORRESPONDENCE_COLUMNS = ("map", "local_id", "global_id")


def read_correspondence_csv(text: str, source: str) -> Correspondence:
    """The CSV ``join --associations`` writes: the header map,local_id,global_id, one row per input feature."""
    table = csvtable.Table(text, source, [_CORRESPONDENCE_COLUMNS])
    values = table.values(_CORRESPONDENCE_COLUMNS, None, "id")
    return Correspondence(*values.T, name=source, lines=table.lines)


def read_correspondence_records(text: str, source: str) -> Correspondence:
    """The YAML or JSON ``join --associations`` writes: a list of mappings with map, local_id and global_id."""
    document = yamldoc.document(text, source)
    records = document.get((), "list")
    for row in range(len(records)):
        document.get((row,), "mapping")
        document.only((row,), _CORRESPONDENCE_COLUMNS)
    columns = [[document.get((row, key), "id") for row in range(len(records))] for key in _CORRESPONDENCE_COLUMNS]
    return Correspondence(*(np.array(column, dtype=np.int64) for column in columns), name=source)


def _table(rows: Sequence[Any]) -> tuple[list[str], list[list[Any]]]:
    """Field names and plain-Python values of dataclass instances of one type, or of mappings with the same
    keys (a table whose columns depend on its input, e.g. ``check-minima --batch``)."""
    if not rows:
        return [], []
    if isinstance(rows[0], dict):
        names = list(rows[0])
        if any(list(row) != names for row in rows):
            raise TypeError("table rows must all have the same keys, in the same order")
        return names, [[_plain(row[name]) for name in names] for row in rows]
    kind = type(rows[0])
    if any(type(row) is not kind for row in rows):
        raise TypeError(f"table rows must all be {kind.__name__} instances")
    names = [field.name for field in dataclasses.fields(kind)]
    return names, [[_plain(getattr(row, name)) for name in names] for row in rows]


def _plain(value: Any) -> Any:
    """Numpy scalars and arrays as Python numbers and lists, tuples as lists."""
    if isinstance(value, (np.ndarray, np.generic)):
        return value.tolist()
    if isinstance(value, (list, tuple)):
        return [_plain(item) for item in value]
    return value


def dump_csv(rows: Sequence[Any]) -> Parts:
    """Dataclass instances as a CSV table, their field names as header; made a block of rows at a time as it is
    written (:class:`.outputs.Parts`: the report of a stream of 10^6 joins is never held as text at once)."""
    return Parts(_csv_parts(rows))


_ROWS_PER_PART = 1 << 14  # rows made into text at a time


def _csv_parts(rows: Sequence[Any]) -> Iterator[str]:
    """:func:`dump_csv`'s text, a block of rows at a time (every block's rows of the first block's kind)."""
    header: list[str] | None = None
    for start in range(0, len(rows), _ROWS_PER_PART):
        names, values = _table(rows[start:start + _ROWS_PER_PART])
        if header is not None and names != header:
            raise TypeError("table rows must all be of one kind, with the same fields")
        yield csvtable.to_text(values if header is not None else [names, *values])
        header = names


def dump_yaml(rows: Sequence[Any]) -> str:
    """Dataclass instances as a YAML list of mappings."""
    names, values = _table(rows)
    return yamldoc.dump([[dict(zip(names, row)) for row in values]])


def dump_json(rows: Sequence[Any]) -> str:
    """Dataclass instances as a JSON list of objects."""
    import json

    names, values = _table(rows)
    return json.dumps([dict(zip(names, row)) for row in values], indent=2) + "\n"
