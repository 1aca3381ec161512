"""CSV local maps read from a stream a block of lines at a time, so that its length costs no memory.

The lines are gathered until a block holds :data:`BLOCK_LINES` lines and the next line starts
another map (its ``map`` cell, else its ``end_id``, differs from the line before, outside a
quoted cell); the block, under the stream's header, is then read as a file is
(:func:`.csv_maps.read`, with the block's line numbers and map positions), and its maps are
yielded. A stream of one block reads exactly as the whole text does. A map's rows must
therefore be consecutive across blocks: a map whose rows come back after other maps' rows in a
later block is an error naming the line (within a block, rows may be in any order, as in a file).
"""

from __future__ import annotations

import csv
import itertools
from collections.abc import Callable, Iterable, Iterator

from ..errors import InputError, shown
from ..maps import LocalMap
from . import csv_maps

__all__ = ["BLOCK_LINES", "read_lines"]

BLOCK_LINES = 1 << 16  # lines read before a block may end: a few MB of text


def read_lines(lines: Iterable[str], source: str) -> Iterator[LocalMap]:
    """The local maps of a CSV stream given line by line, a block at a time (module docstring)."""
    lines = iter(lines)
    block: list[str] = []
    for line in lines:  # the header: the first line with a cell (blank lines before it are skipped, as in a file)
        block.append(line)
        if line.strip("\r\n"):
            break
    key_column, named = _key_column(block[-1] if block else "")
    header, first_line, number, quoted = block[-1:], 1, 1, False
    seen: set = set()  # the maps of earlier blocks (:func:`_read_block`)
    while True:
        batch = list(itertools.islice(lines, max(BLOCK_LINES - len(block), 0)))   # the block's lines at once
        block.extend(batch)
        quoted ^= "".join(batch).count('"') % 2 == 1  # inside a quoted cell that spans lines
        if len(block) < BLOCK_LINES:
            break                                       # the stream ended
        for line in lines:                              # then line by line, to the end of a map
            if quoted or key_column is None or _key(block[-1], key_column) is None \
                    or _key(line, key_column) in (None, _key(block[-1], key_column)):
                block.append(line)
                quoted ^= line.count('"') % 2 == 1
                continue
            maps = _read_block(block, source, first_line, number, True, key_column, named, seen)
            yield from maps
            first_line += len(block) - (first_line > 1)  # a later block's text starts with the header
            number += len(maps)
            block = [*header, line]
            quoted = line.count('"') % 2 == 1
            break
        else:
            break
    yield from _read_block(block, source, first_line, number, None if number == 1 else True, key_column, named,
                           seen)


def _read_block(block: list[str], source: str, first_line: int, number: int, several: bool | None,
                key_column: int | None, named: bool, seen: set) -> list[LocalMap]:
    """The maps of one block (the header first); a map of an earlier block again is an error. ``seen`` holds
    the earlier maps' names (``named``: by a ``map`` column) or end ids (else)."""
    offset = 0 if first_line == 1 else first_line - 2  # the block's line 2 is the stream's first_line
    try:
        maps = csv_maps.read("".join(block), source, line_offset=offset, first_number=number, several=several,
                             warn=first_line == 1)
    except InputError:  # a map's rows cut by the block: say so rather than what its part lacks
        if key_column is not None and seen:
            _check_consecutive(block, source, offset, key_column, lambda cell: _map_key(cell, source, named), seen)
        raise
    if key_column is None:
        return maps
    keys = [local_map.name if named else local_map.end_id for local_map in maps]
    if not seen.isdisjoint(keys):
        _check_consecutive(block, source, offset, key_column, lambda cell: _map_key(cell, source, named), seen)
    seen.update(keys)
    return maps


def _check_consecutive(block: list[str], source: str, offset: int, key_column: int, key: Callable, seen: set) -> None:
    """InputError at the first line of ``block`` whose map is one of an earlier block (``seen``), if any."""
    for row, line in enumerate(block[1:], 2):
        cell = _key(line, key_column)
        if cell is not None and key(cell) in seen:
            label = shown(cell) if isinstance(key(cell), str) else f"ending at {cell}"
            raise InputError(f"the rows of the map {label} continue here after other maps' rows; a CSV stream "
                             "is read a block of lines at a time, so each map's rows must be consecutive", source,
                             f"line {row + offset}")


def _map_key(cell: str, source: str, named: bool) -> str | int | None:
    """What ``seen`` holds for a map with this key cell: its name, else its end id."""
    if named:
        return f"{source}#{cell}"
    try:
        return int(cell)
    except ValueError:
        return None


def _key_column(header: str) -> tuple[int | None, bool]:
    """The column telling one map's rows from the next: ``map`` (True), else ``end_id`` (None: neither, the
    stream is read at once, and its reading says what is missing)."""
    names = [name.strip(" \t") for name in next(csv.reader([header]), [])]
    column = next((names.index(name) for name in ("map", "end_id") if name in names), None)
    return column, "map" in names


def _key(line: str, column: int) -> str | None:
    """The cell of ``column`` on ``line`` (None for a blank or short line, which never ends a block)."""
    cells = next(csv.reader([line]), [])
    return cells[column].strip(" \t") if len(cells) > column else None
