"""Linear SLAM local maps (``localmap_<k>.txt``), text as distributed with Linear SLAM.

Line 1 the reference (start) pose id, line 2 the state dimension d = 3 + 2m, then d lines
``id value`` (the end pose's x, y, phi with id -k, k its pose id; then per feature an x and
a y line with its id), then d lines of d numbers: the information matrix, the inverse of the
covariance, row by row. It must be symmetric (up to ``maps.SYMMETRY_TOLERANCE``, then
symmetrised) and positive definite; the covariance is its inverse by Cholesky
factorisation, and writing inverts the covariance the same way, so a round trip is exact up
to rounding (about the condition number times 1e-16, relative). Rows may come in any order
as long as the pose's three are together and each feature's y follows its x. One map per
file; the end pose id must not be 0 (it would be -0). Feature id 0 is read and written, with
a warning on writing, as Linear SLAM's own code expects positive feature ids.
"""

from __future__ import annotations

import logging
import math
import re
from collections.abc import Sequence
from itertools import chain
from typing import NamedTuple

import numpy as np

from ..covariance import state_variances
from ..errors import InputError, shown
from ..maps import (
    COVARIANCE_ENTRY,
    LocalMap,
    StackedMaps,
    asymmetry,
    first_duplicate,
    first_invalid_map,
    marginal_variances,
    outside,
    size_groups,
    unstack,
)
from .numbers import first_unplain, symmetric_matrix
from .paths import read_file

__all__ = ["dump", "looks_like_linearslam", "read", "read_files"]

log = logging.getLogger("mapjoin")


def looks_like_linearslam(text: str) -> bool:
    """Whether a stream without a named format is Linear SLAM text: its first two lines are each one integer."""
    return re.match(r"[0-9]+[ \t]*\r?\n[ \t]*[0-9]+[ \t]*(?:\r?\n|$)", text.lstrip()) is not None


def read(text: str, source: str) -> list[LocalMap]:
    """One Linear SLAM local map (see the module docstring); its covariance is the inverse of the stored information."""
    return _local_maps([_parsed(text, source)])


def read_files(paths: Sequence[str]) -> list[LocalMap]:
    """The Linear SLAM local maps of many files, each parsed and checked on its own, then inverted and checked
    as maps all at once (the maps of one size together): a bad file raises the error that reading the
    files one by one with :func:`read` gives."""
    parsed: list[_Parsed] = []
    for path in paths:
        try:
            parsed.append(_parsed(read_file(path, path, False), path))
        except InputError:
            _local_maps(parsed)  # an error in an earlier file comes first
            raise
    return _local_maps(parsed)


class _Parsed(NamedTuple):
    """One file's map before its information matrix is inverted (the state in the file's row ``order``)."""

    source: str
    start_id: int
    end_id: int
    end_pose: np.ndarray
    feature_ids: np.ndarray
    features: np.ndarray
    order: np.ndarray  # the state's rows: the end pose's three, then x and y of each feature
    information: np.ndarray  # symmetric (symmetrised when it was so up to rounding)


def _parsed(text: str, source: str) -> _Parsed:
    """A file's map, checked up to the inversion of its information matrix (in range and symmetric)."""
    lines = text.splitlines()
    start_id = _text_integer(lines, 0, "the reference pose index (a non-negative integer)", source)
    size = _text_integer(lines, 1, "the state dimension d = 3 + 2m (m features)", source)
    if size < 3 or (size - 3) % 2:
        raise InputError(f"expected the state dimension d = 3 + 2m (m features), got {size}", source, "line 2")
    parsed = _plain_rows(lines, size)
    if parsed is None:  # read line by line, to name the line of the error
        state_rows = _text_rows(lines, 2, size, 2, f"`id value`, one of d = {size} state rows", source)
        ids = _text_ids(state_rows[:, 0], 2, source)
        state = _text_numbers(state_rows[:, 1:], 2, source, first_field=2)[:, 0]
        information = _text_numbers(
            _text_rows(lines, 2 + size, size, size, f"a row of the {size}x{size} information matrix", source),
            2 + size, source)
    else:
        ids, state, information = parsed
    trailing = next((i for i in range(2 + 2 * size, len(lines)) if lines[i].strip()), None)
    if trailing is not None:
        raise InputError(f"expected nothing after the {size} rows of the information matrix, got "
                         f"{shown(lines[trailing].strip())}", source, f"line {trailing + 1}")
    pose, features, end_id = _linearslam_layout(ids, start_id, source)
    return _Parsed(source, start_id, end_id, state[pose], ids[features[0::2]], state[features].reshape(-1, 2),
                   np.concatenate([pose, features]), _checked_information(information, 2 + size, source))


def _local_maps(parsed: Sequence[_Parsed]) -> list[LocalMap]:
    """The maps of parsed files, as ``LocalMap.from_covariance`` makes them from the inverses of their
    information matrices: inverted and checked a stack of one size at a time; the first map that fails
    raises the error reading the files one by one gives (a matrix that is not positive definite before
    the checks of the map)."""
    stacks = []  # (places, StackedMaps) of each size
    failures: list[tuple[int, InputError]] = []  # the first map of each size whose information is not definite
    for group in size_groups(np.array([len(item.information) for item in parsed], dtype=np.int64)):
        items = [parsed[i] for i in group.tolist()]
        inverses, failed = _spd_inverse(np.stack([item.information for item in items]))
        if failed.any():
            first = int(np.flatnonzero(failed)[0])
            failures.append((int(group[first]), InputError(
                f"expected a positive definite information matrix; its leading {failed[first]}x{failed[first]} "
                "block is not", items[first].source, f"line {2 + len(inverses[first]) + failed[first]}")))
        orders = np.stack([item.order for item in items])
        covariances = inverses[np.arange(len(items))[:, np.newaxis, np.newaxis], orders[:, :, np.newaxis],
                               orders[:, np.newaxis, :]]
        stacks.append((group, StackedMaps(
            [item.source for item in items], np.stack([item.end_pose for item in items]),
            np.stack([item.feature_ids for item in items]), np.stack([item.features for item in items]),
            *marginal_variances(covariances), covariances)))
    invalid = min(failures, key=lambda failure: failure[0], default=None)
    later = first_invalid_map(stacks)
    if later is not None and (invalid is None or later[0] < invalid[0]):  # ties: the inversion fails first
        invalid = later
    if invalid is not None:
        raise invalid[1]
    return unstack(stacks, [item.start_id for item in parsed], [item.end_id for item in parsed])


_PLAIN_IDS = re.compile(r"-?[0-9]+(?: -?[0-9]+)*")


def _plain_rows(lines: Sequence[str], size: int) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """The ids, state and information of a file whose rows are plain decimal numbers, as mapjoin and Linear
    SLAM write them, read in bulk (the values the line-by-line path gives); None when any row is otherwise
    (that path then reads them, naming the line of the error).

    Plain means: ``id value`` state rows with ids ``-?[0-9]+`` and ``size`` numbers per matrix
    row (split at blanks, as that path splits them); every number ASCII without ``_``
    (:func:`.numbers.first_unplain`) and one that ``float`` reads to a finite value, as that path
    requires. Each row is split once; a matrix whose text mirrors itself is checked and read by
    its lower triangle (:func:`.numbers.symmetric_matrix`)."""
    cells = list(map(str.split, lines[2:2 + 2 * size]))
    if list(map(len, cells)) != [2] * size + [size] * size:
        return None
    state_tokens = list(chain.from_iterable(cells[:size]))
    id_tokens, value_tokens = state_tokens[0::2], state_tokens[1::2]
    if not _PLAIN_IDS.fullmatch(" ".join(id_tokens)) or first_unplain(value_tokens) is not None:
        return None
    try:
        ids = np.array(id_tokens, dtype=np.int64)
        state = np.fromiter(map(float, value_tokens), dtype=float, count=size)
    except (OverflowError, ValueError):
        return None
    information = symmetric_matrix(list(chain.from_iterable(cells[size:])), size,
                                   lambda tokens: first_unplain(tokens) is None)
    if information is None or not (np.isfinite(state).all() and np.isfinite(information).all()):
        return None
    return ids, state, information


def _text_integer(lines: Sequence[str], index: int, expected: str, source: str) -> int:
    """Line ``index`` (0-based) as one non-negative integer."""
    text = lines[index].strip() if index < len(lines) else ""
    if not text.isdigit() or not text.isascii():
        raise InputError(f"expected {expected}, got {shown(text) if text else 'nothing'}", source,
                         f"line {index + 1}")
    return int(text)


def _text_rows(lines: Sequence[str], first: int, count: int, width: int, expected: str, source: str) -> np.ndarray:
    """Lines ``first .. first+count-1`` (0-based) as a (count x width) array of their whitespace-separated fields
    (str objects)."""
    cells = [line.split() for line in lines[first:first + count]]
    bad = next((i for i, row in enumerate(cells) if len(row) != width), None)
    if bad is None and len(cells) < count:
        bad = len(cells)
    if bad is not None:
        got = (f"{len(cells[bad])} fields: {shown(lines[first + bad].strip())}" if bad < len(cells)
               else "the end of the file")
        raise InputError(f"expected {expected} ({width} fields), got {got}", source, f"line {first + bad + 1}")
    # objects, not a fixed-width string array: that would give every cell the width of the longest one (one
    # 3 MB token in a 20x20 matrix: 4.8 GB)
    return np.array(list(chain.from_iterable(cells)), dtype=object).reshape(count, width)


def _text_numbers(cells: np.ndarray, first: int, source: str, first_field: int = 1) -> np.ndarray:
    """Text fields (rows from line ``first`` + 1, columns from field ``first_field``) as finite floats."""
    unplain = first_unplain(cells.ravel().tolist())
    try:
        values = None if unplain is not None else cells.astype(float)
    except ValueError:
        values = None
    if values is None or not np.isfinite(values).all():
        bad = np.array([not _is_finite_text(cell) for cell in cells.ravel()]).reshape(cells.shape)
        if unplain is not None:
            bad.ravel()[unplain] = True
        i, j = (int(index) for index in np.argwhere(bad)[0])
        raise InputError(f"expected a finite number in field {j + first_field}, got {shown(str(cells[i, j]))}",
                         source, f"line {first + i + 1}")
    return values


def _is_finite_text(text: str) -> bool:
    try:
        return math.isfinite(float(text))
    except ValueError:
        return False


def _text_ids(cells: np.ndarray, first: int, source: str) -> np.ndarray:
    """Text fields (one per row, from line ``first`` + 1) as 64-bit integers."""
    try:
        if first_unplain(cells.tolist()) is not None:
            raise ValueError("not ASCII")
        return cells.astype(np.int64)
    except (ValueError, OverflowError):
        bad = next(i for i, cell in enumerate(cells.tolist())
                   if not re.fullmatch(r"[-+]?[0-9]+", cell) or abs(int(cell)) >= 2**63)
        raise InputError(f"expected an integer id in field 1, got {shown(str(cells[bad]))}", source,
                         f"line {first + bad + 1}") from None


def _linearslam_layout(ids: np.ndarray, start_id: int, source: str) -> tuple[np.ndarray, np.ndarray, int]:
    """Rows of the end pose (three, consecutive, one id -k), rows of the features (x then y per id), and k."""
    pose = np.flatnonzero(ids < 0)
    if pose.size != 3 or pose[2] != pose[0] + 2 or (ids[pose] != ids[pose[0]]).any():
        got = ", ".join(f"{ids[row]} on line {row + 3}" for row in pose[:4]) or "none"
        raise InputError("expected one end pose: three consecutive rows with the same negative id -k; got "
                         f"negative ids {got}", source, f"line {(pose[0] if pose.size else 0) + 3}")
    end_id = -int(ids[pose[0]])
    if end_id == start_id:
        raise InputError(f"the end pose id {end_id} (rows with id {-end_id}) equals the reference pose index "
                         "on line 1", source, f"line {pose[0] + 3}")
    features = np.delete(np.arange(len(ids)), pose)
    x, y = features[0::2], features[1::2]
    split = np.flatnonzero(ids[x] != ids[y])
    if split.size:
        i = split[0]
        raise InputError(f"expected the y row of feature {ids[x[i]]} (x on line {x[i] + 3}), got id {ids[y[i]]}",
                         source, f"line {y[i] + 3}")
    duplicate = first_duplicate(ids[x])
    if duplicate is not None:
        earlier = x[np.flatnonzero(ids[x] == ids[x[duplicate]])[0]]
        raise InputError(f"duplicate feature id {ids[x[duplicate]]} (also on line {earlier + 3})", source,
                         f"line {x[duplicate] + 3}")
    return pose, features, end_id


def _checked_information(information: np.ndarray, first: int, source: str) -> np.ndarray:
    """An information matrix stored from line ``first`` + 1, checked within the accepted range (its sums would
    overflow beyond) and symmetric; symmetrised when it is so up to rounding only."""
    bad = outside(information, COVARIANCE_ENTRY)
    if bad.any():
        i, j = (int(index) for index in np.argwhere(bad)[0])
        raise InputError(f"expected {COVARIANCE_ENTRY.expected()} in the information matrix (field {j + 1}), got "
                         f"{shown(information[i, j])}", source, f"line {first + i + 1}")
    if (information == information.T).all():  # then (I + I^T) / 2 = I, exactly
        return information
    excess = asymmetry(information)
    if (excess > 0).any():
        i, j = (int(index) for index in np.unravel_index(np.argmax(excess), excess.shape))
        raise InputError(f"expected a symmetric information matrix, but entries ({i + 1}, {j + 1}) and "
                         f"({j + 1}, {i + 1}) differ: {float(information[i, j])!r} vs "
                         f"{float(information[j, i])!r}", source, f"line {first + i + 1}")
    return (information + information.T) / 2


def _spd_inverse(matrices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The inverses of a stack of symmetric positive definite matrices by Cholesky (exactly symmetric), and
    for each matrix 0, or the order of its first leading block that is not positive definite (its inverse
    is then not computed: the identity's stands in).

    numpy's LAPACK does the work, a stack at a time (each matrix's result as alone): importing
    scipy.linalg for it would cost more than reading a few hundred maps (benchmarks/reading.py)."""
    failed = np.zeros(len(matrices), dtype=np.int64)
    try:
        factors = np.linalg.cholesky(matrices)
    except np.linalg.LinAlgError:
        failed = np.array([_first_indefinite_block(matrix) for matrix in matrices], dtype=np.int64)
        factors = np.linalg.cholesky(np.where(failed[:, np.newaxis, np.newaxis] > 0, np.eye(matrices.shape[-1]),
                                              matrices))
    factor_inverses = np.linalg.inv(factors)
    inverses = np.swapaxes(factor_inverses, -1, -2) @ factor_inverses
    lower = np.tril(inverses)
    return lower + np.swapaxes(np.tril(lower, -1), -1, -2), failed


def _first_indefinite_block(matrix: np.ndarray) -> int:
    """The order of the smallest leading block of a matrix that is not positive definite, 0 if it is
    (bisection: a leading block of a positive definite block is positive definite)."""
    try:
        np.linalg.cholesky(matrix)
        return 0
    except np.linalg.LinAlgError:
        pass
    definite, indefinite = 0, len(matrix)
    while indefinite - definite > 1:
        middle = (definite + indefinite) // 2
        try:
            np.linalg.cholesky(matrix[:middle, :middle])
            definite = middle
        except np.linalg.LinAlgError:
            indefinite = middle
    return indefinite


def dump(maps: Sequence[LocalMap]) -> str:
    """One map as Linear SLAM text; the information matrix is the inverse of its covariance."""
    [local_map] = maps
    if local_map.end_id == 0:
        raise InputError("cannot be written as Linear SLAM text: its end pose id 0 would be the row id -0, "
                         "which reads as a feature", local_map.name)
    if local_map.size and local_map.feature_ids.min() == 0:
        log.warning("%s: feature id 0 written as Linear SLAM text (mapjoin reads it back; Linear SLAM's own code "
                    "expects positive feature ids)", local_map.name)
    if local_map.covariance is None:
        information = np.diag(1.0 / state_variances(local_map))
    else:
        inverses, failed = _spd_inverse(local_map.covariance[np.newaxis])
        information = None if failed[0] else inverses[0]
    if information is None or not np.isfinite(information).all():
        raise InputError("the covariance is numerically singular, so it has no finite information matrix",
                         local_map.name, "covariance")
    ids = np.concatenate([np.full(3, -local_map.end_id), np.repeat(local_map.feature_ids, 2)])
    values = np.concatenate([local_map.end_pose, local_map.features.ravel()])
    lines = [str(local_map.start_id), str(len(ids)),
             *(f"{i} {value!r}" for i, value in zip(ids.tolist(), values.tolist())),
             *(" ".join(map(repr, row)) for row in information.tolist())]
    return "\n".join(lines) + "\n"
