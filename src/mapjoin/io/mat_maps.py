"""I-SLSJF local maps (``localmap_<k>.mat``), the format distributed with the I-SLSJF code.

A MATLAB v5 file holding ``localmap_st``, a (3+2m)x2 array of ``[id, value]`` rows (three
end-pose rows x, y, phi with id 0, then an x row and a y row per feature, both with the
feature's id), and ``localmap_P``, the full (3+2m)x(3+2m) covariance. Map k runs from pose
k-1 to pose k, k taken from the file name. The spherical variances are the ``marginal``
summary of ``localmap_P``. As in the I-SLSJF code, when an end-pose variance is below
:data:`STAB_NOISE` (the robot did not move) it is added to the three pose diagonal entries,
with a warning. The file is parsed by :mod:`mapjoin.io.matfile`. Written uncompressed,
little-endian, one map per file named after its end id; only a map from pose k-1 to pose k
can be written (the format has nowhere else to keep its pose ids), and a map without a full
covariance is written with its diagonal one.
"""

from __future__ import annotations

import functools
import logging
import os
import re
from collections.abc import Callable, Mapping, Sequence

import numpy as np

from ..covariance import state_covariance
from ..errors import InputError
from ..maps import LocalMap, StackedMaps, first_flagged, first_invalid_map, marginal_variances, size_groups, unstack
from . import matfile
from .paths import read_file

__all__ = ["STAB_NOISE", "dump", "map_number", "read", "read_files"]

log = logging.getLogger("mapjoin")

#: I-SLSJF's ``StabNoise``: added to the end-pose variances of a map whose robot did not move.
STAB_NOISE = 1e-6
_VARIABLES = ("localmap_st", "localmap_P")
_NUMBER = re.compile(r"([0-9]+)(?:\.[^.]*)?$")  # k of localmap_<k>.mat


def read(data: bytes, source: str) -> list[LocalMap]:
    """One I-SLSJF local map; k from the file name (see the module docstring)."""
    return _local_maps([data], [source])


def read_files(paths: Sequence[str]) -> list[LocalMap]:
    """The I-SLSJF local maps of many .mat files, parsed and checked all at once: a bad file raises the
    error (after the warnings) that reading the files one by one with :func:`read` gives."""
    files: list[bytes] = []
    for path in paths:
        try:
            files.append(read_file(path, path, True))
        except InputError:
            _local_maps(files, paths[:len(files)])  # an error in an earlier file comes first
            raise
    return _local_maps(files, paths)


def _local_maps(files: Sequence[bytes], sources: Sequence[str]) -> list[LocalMap]:
    """The maps of I-SLSJF .mat files, map k from pose k-1 to pose k, as ``LocalMap.from_covariance`` makes
    them after I-SLSJF's stabilisation (see the module docstring).

    All files are parsed, checked and summarised at once, the maps of one size together; the
    first file that fails raises the error that reading the files one by one gives, after the
    warnings that reading logs before it.
    """
    table, errors = matfile.parse(files, sources)
    numbers: list[int] = []  # k of each file, up to the first that fails
    failure: tuple[int, Callable[[int], InputError] | InputError | None] = (len(files), None)
    for i, source in enumerate(sources):
        try:
            number = _checked_number(source)
            if i in errors:  # before its sizes are used: a corrupt file's may say 2^31 rows
                raise errors[i]
            numbers.append(number)
        except InputError as error:
            failure = (i, error)
            break
    count = len(numbers)
    state_row, covariance_row = (table.named(key, count) for key in _VARIABLES)
    (state_matrix, sizes, state_columns), (covariance_matrix, covariance_rows, covariance_columns) = (
        table.matrices(rows) for rows in (state_row, covariance_row))
    count = first_flagged(~state_matrix | ~covariance_matrix | (state_columns != 2) | (sizes < 3)
                          | ((sizes - 3) % 2 != 0), np.arange(count + 1))  # the files whose variables pass
    sizes = sizes[:count]
    starts = np.concatenate([[0], np.cumsum(sizes)])  # map i's localmap_st rows: starts[i] to starts[i + 1]
    first_row = np.repeat(starts[:-1], sizes)
    state = table.floats(state_row[:count])  # map i's ids, then its values, from 2 * starts[i]
    ids = state[np.arange(starts[-1]) + first_row]
    values = state[np.arange(starts[-1]) + first_row + np.repeat(sizes, sizes)]
    failed, error = min([  # (first file failing a check, its error), in the order one file is checked
        failure,
        (count, lambda i: _variables_error(table.variables(i), sources[i])),
        *((first_flagged(bad, starts), functools.partial(_id_error, fault, table, state_row, sources))
          for fault, bad in enumerate(_id_faults(ids, np.arange(starts[-1]) - first_row))),
        (first_flagged((covariance_rows[:count] != sizes) | (covariance_columns[:count] != sizes),
                       np.arange(count + 1)),
         lambda i: InputError("expected {0}x{0} (the size of localmap_st), got {1}".format(
             sizes[i], table.array(covariance_row[i]).shape), sources[i], "localmap_P")),
    ], key=lambda failure: failure[0])  # ties: the earlier check

    stacks = []  # (maps, StackedMaps) of each size, before the first failure
    stabilised: list[tuple[int, np.ndarray]] = []  # (map, its end-pose variances) where STAB_NOISE is added
    for group in size_groups(sizes[:failed]):
        n, m = int(sizes[group[0]]), int(sizes[group[0]] - 3) // 2
        rows = starts[group, np.newaxis] + np.arange(n)
        covariances = table.floats(covariance_row[group]).reshape(-1, n, n).transpose(0, 2, 1)  # column-major
        pose_variances = np.diagonal(covariances, axis1=1, axis2=2)[:, :3].copy()
        still = np.flatnonzero(pose_variances.min(axis=1) < STAB_NOISE)
        covariances[still[:, np.newaxis], np.arange(3), np.arange(3)] += STAB_NOISE
        stabilised += zip(group[still].tolist(), pose_variances[still])
        group_values = values[rows]
        stacks.append((group, StackedMaps(
            [sources[i] for i in group.tolist()], group_values[:, :3], ids[rows[:, 3::2]].astype(np.int64),
            group_values[:, 3:].reshape(len(group), m, 2), *marginal_variances(covariances), covariances)))
    invalid = first_invalid_map(stacks)
    last = invalid[0] if invalid else failed - 1  # the last map that one-by-one reading gets to
    for i, pose_variances in sorted(stabilised, key=lambda item: item[0]):
        if i <= last:
            log.warning("%s: end-pose variances %s include one below %g (the robot did not move); added %g to the "
                        "three pose diagonal entries, as I-SLSJF does", sources[i],
                        np.array2string(pose_variances, precision=3), STAB_NOISE, STAB_NOISE)
    if invalid:
        raise invalid[1]
    if error is not None:
        raise error if isinstance(error, InputError) else error(failed)
    return unstack(stacks, [k - 1 for k in numbers], numbers)


def map_number(name: str) -> int | None:
    """k of a file named ``localmap_<k>.mat`` (the number its name ends in), None if it ends in none."""
    match = _NUMBER.search(os.path.basename(name))
    return int(match[1]) if match else None


def _checked_number(source: str) -> int:
    """k of a file named ``localmap_<k>.mat`` (map k runs from pose k-1 to pose k)."""
    number = map_number(source)
    if number is None or number < 1:
        raise InputError("cannot tell the map number k from the file name; name it localmap_<k>.mat with k >= 1 "
                         "(map k runs from pose k-1 to pose k)", source)
    return number


def _variables_error(variables: Mapping[str, matfile.Array | str], source: str) -> InputError | None:
    """What is wrong with the variables of an I-SLSJF .mat file, if anything (their values aside): it must hold
    the real matrices ``localmap_st``, of (3+2m) x 2 [id, value] rows, and ``localmap_P``."""
    for key in _VARIABLES:
        if key not in variables:
            return InputError(f"missing; expected the I-SLSJF variables {' and '.join(_VARIABLES)}", source, key)
        value = variables[key]
        if isinstance(value, str) or len(value.shape) != 2:
            got = value if isinstance(value, str) else f"{len(value.shape)}-D array"
            return InputError(f"expected a real numeric matrix, got a {got}", source, key)
    shape = variables["localmap_st"].shape
    if shape[1] != 2 or shape[0] < 3 or (shape[0] - 3) % 2:
        return InputError(f"expected (3+2m)x2 [id, value] rows, got shape {shape}", source, "localmap_st")
    return None


def _id_faults(ids: np.ndarray, row: np.ndarray) -> list[np.ndarray]:
    """Masks over ``localmap_st`` rows (``row``: the row within its map) of each fault of their ids, in the
    order they are checked: a pose row without id 0, a feature id that is not an integer in [0, 2^53), an x
    row whose y row has another id."""
    pose, x = row < 3, (row >= 3) & (row % 2 == 1)
    mismatch = np.zeros(len(ids), dtype=bool)
    mismatch[x] = ids[x] != ids[np.flatnonzero(x) + 1]
    return [pose & (ids != 0), ~pose & ~((ids >= 0) & (ids < 2**53) & (ids == np.round(ids))), mismatch]


def _id_error(fault: int, table: matfile.Variables, state_row: np.ndarray, sources: Sequence[str], i: int) -> InputError:
    """The error of map i's first ``localmap_st`` row with ``fault`` (an index into :func:`_id_faults`)."""
    ids = table.array(state_row[i]).value()[:, 0]
    row = int(np.argmax(_id_faults(ids, np.arange(len(ids)))[fault]))
    if fault == 0:
        message = f"expected id 0 on the three end-pose rows, got {ids[row]:g}"
    elif fault == 1:
        message = f"expected a non-negative integer feature id, got {ids[row]:g}"
    else:
        message = (f"feature id {ids[row]:g} on the x row but {ids[row + 1]:g} on the y row (row {row + 2}); "
                   "expected the same id on both rows of a feature")
    return InputError(message, sources[i], f"localmap_st row {row + 1}")


def dump(maps: Sequence[LocalMap]) -> bytes:
    """One map as an I-SLSJF .mat file (MAT v5, little-endian, uncompressed): ``localmap_st``, ``localmap_P``."""
    [local_map] = maps
    if local_map.start_id != local_map.end_id - 1:
        raise InputError("cannot be written as an I-SLSJF .mat file, which holds map k from pose k-1 to pose k; "
                         f"this map runs from pose {local_map.start_id} to {local_map.end_id} (use yaml or "
                         "linearslam)", local_map.name)
    if local_map.size and local_map.feature_ids.max() >= 2**53:
        raise InputError(f"feature id {local_map.feature_ids.max()} is not exact as a double (2^53 or more), "
                         "so it cannot be written to a .mat file", local_map.name)
    covariance = state_covariance(local_map)
    if covariance.diagonal()[:3].min() < STAB_NOISE:
        log.warning("%s: an end-pose variance is below %g; reading the .mat file back adds %g to the pose "
                    "diagonal, as I-SLSJF does", local_map.name, STAB_NOISE, STAB_NOISE)
    ids = np.concatenate([np.zeros(3), np.repeat(local_map.feature_ids, 2)])
    state = np.column_stack([ids, np.concatenate([local_map.end_pose, local_map.features.ravel()])])
    return matfile.dump({"localmap_st": state, "localmap_P": covariance})
