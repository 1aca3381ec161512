"""Local and global maps: immutable dataclasses of numpy arrays, validated on creation.

A local map holds, in the frame of its start pose, the estimate of its end pose
``(x, y, phi)`` and of the point features it saw, with spherical variances (one
``sigma^2`` per feature, ``(sigma_xy^2, p_phi)`` for the end pose) and optionally the
full covariance of its state vector ``[x, y, phi, f1x, f1y, f2x, ...]``.

The joiner needs spherical covariances (docs/method.md#definition-2); :mod:`mapjoin.covariance`
derives them from a map.

The values of local maps are checked on stacks of maps of one size (:class:`StackedMaps`):
the constructor checks a stack of one, and readers of thousands of files check theirs with
a few numpy calls per size.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable, Sequence
from dataclasses import InitVar, dataclass, field
from typing import NamedTuple

import numpy as np

from .errors import InputError, JoinError, shown

__all__ = [
    "LocalMap",
    "GlobalMap",
    "GroundTruth",
    "Correspondence",
    "Provenance",
    "StackedMaps",
    "asymmetry",
    "outside",
]

SYMMETRY_TOLERANCE = 1e-6  # |P_ij - P_ji| allowed, relative to sqrt(P_ii P_jj); rounding in stored files
#: the least share of its variance a covariance's state entry keeps given the entries before it (the squared
#: diagonal of the Cholesky factor over the matrix's diagonal; independent of the entries' units). Below it the
#: matrix is singular to rounding (an entry a combination of others up to 1e-16 of its variance passes the
#: factorisation) and its inverse, which the information mode and the exact join take, fails or is noise. The
#: real datasets' least share is 1.6e-4 (the 8240 simulation's maps).
CONDITIONAL_SHARE = 1e-12


def _coerced(value, name: str, source: str, shape: tuple[int | None, ...], dtype=float) -> np.ndarray:
    """A copy of ``value`` as an array of ``dtype`` and ``shape`` (None = any length)."""
    try:
        array = np.array(value, dtype=dtype)
    except (TypeError, ValueError) as error:
        raise InputError(f"expected numbers, got {shown(value)}", source, name) from error
    if array.ndim != len(shape) or any(s is not None and s != n for s, n in zip(shape, array.shape)):
        expected = "x".join("n" if s is None else str(s) for s in shape) or "a scalar"
        raise InputError(f"expected shape {expected}, got {array.shape}", source, name)
    return array


class Range(NamedTuple):
    """The values an input field accepts: ``low <= value <= high`` (NaN is outside every range)."""

    what: str
    low: float
    high: float

    def outside(self, array: np.ndarray) -> np.ndarray:
        """Where ``array`` (or a number) is outside the range."""
        return np.logical_not((array >= self.low) & (array <= self.high))

    def expected(self) -> str:
        """How errors name the range, e.g. ``finite coordinates (m) in [-1e+09, 1e+09]``."""
        return f"finite {self.what} in [{self.low:g}, {self.high:g}]"


# The accepted ranges (docs/formats.md, "Accepted values"). Local maps and raw data: the one-step constants square
# coordinate differences (< 4e18 m^2) and divide them by sums of variances (>= 2e-30), then sum over up to
# 10^7 features: < 1e56, far from overflow, and a = a0 * p_phi stays below 1e86. Global maps and ground truth
# chain up to 10^7 maps of such size, so they allow coordinates to 1e16 m and variances in [1e-40, 1e40]:
# their squares, ratios and sums over 10^7 features (compare, evaluate) stay below 1e90. An angle beyond
# 1e6 rad has an ulp above 1e-10 rad, and is reduced exactly (se2.wrap) within it.
MAX_ANGLE = 1e6
COORDINATE = Range("coordinates (m)", -1e9, 1e9)
ANGLE = Range("angles (rad)", -MAX_ANGLE, MAX_ANGLE)
VARIANCE = Range("variances", 1e-30, 1e30)
COVARIANCE_ENTRY = Range("covariance entries", -1e30, 1e30)
GLOBAL_COORDINATE = Range("coordinates (m)", -1e16, 1e16)
GLOBAL_VARIANCE = Range("variances", 1e-40, 1e40)
GLOBAL_COVARIANCE_ENTRY = Range("covariance entries", -1e40, 1e40)
#: Theorem 2's a = a0 * p_phi (check-minima, minima tables): within the ranges above a stays below 1e86
MINIMA_A = Range("a", 0.0, 1e100)
#: per column of a pose (x, y, phi)
POSE = (COORDINATE, COORDINATE, ANGLE)
GLOBAL_POSE = (GLOBAL_COORDINATE, GLOBAL_COORDINATE, ANGLE)

Ranges = Range | tuple[Range, ...]  # one range, or one per entry of the last axis


def outside(array: np.ndarray, ranges: Ranges) -> np.ndarray:
    """Where ``array`` is outside ``ranges`` (NaN always is)."""
    if isinstance(ranges, Range):
        return ranges.outside(array)
    low, high = (np.array([getattr(r, bound) for r in ranges]) for bound in ("low", "high"))
    return ~((array >= low) & (array <= high))


def _value_error(array: np.ndarray, name: str, source: str, ranges: Ranges) -> InputError:
    """The error for the first entry of ``array`` that :func:`_outside` flags."""
    index = tuple(int(i) for i in np.argwhere(outside(array, ranges))[0])
    limits = ranges if isinstance(ranges, Range) else ranges[index[-1]]
    if not np.isfinite(array).all():  # NaN and inf first, as what they are
        index = tuple(int(i) for i in np.argwhere(~np.isfinite(array))[0])
        expected = "finite numbers"
    elif limits.low > 0 >= array[index]:
        expected = f"positive {limits.what}"
    else:
        expected = limits.expected()
    return InputError(f"expected {expected}, got {shown(array[index])} at index {index}", source, name)


def _diagonal_error(diagonal: np.ndarray, source: str) -> InputError:
    """The error for a covariance whose diagonal holds a variance outside :data:`VARIANCE`, at its (i, i)."""
    i = int(np.argwhere(outside(diagonal, VARIANCE))[0][0])
    return InputError(f"expected {VARIANCE.expected()} on the diagonal, got {shown(diagonal[i])} at index {(i, i)}",
                      source, "covariance")


def _checked(value, name: str, source: str, shape: tuple[int | None, ...], *,
             dtype=float, ranges: Ranges | None = None) -> np.ndarray:
    """A read-only :func:`_coerced` copy; floats must also be within ``ranges``."""
    array = _coerced(value, name, source, shape, dtype)
    if ranges is not None and outside(array, ranges).any():
        raise _value_error(array, name, source, ranges)
    array.flags.writeable = False
    return array


def _duplicate_id(ids: np.ndarray) -> int | None:
    """The smallest id that occurs more than once, if any."""
    if len(ids) < 2 or (ids[1:] > ids[:-1]).all():  # sorted ids (the common case) need no sort
        return None
    unique, counts = np.unique(ids, return_counts=True)
    return int(unique[counts > 1][0]) if (counts > 1).any() else None


def _unique_ids(ids: np.ndarray, name: str, source: str) -> None:
    duplicate = _duplicate_id(ids)
    if duplicate is not None:
        raise InputError(f"duplicate id {duplicate}", source, name)


def first_duplicate(values: np.ndarray, groups: np.ndarray | None = None) -> int | None:
    """Index of the first entry that repeats an earlier (group, value) pair, or None."""
    keys = (values,) if groups is None else (values, groups)
    order = np.lexsort(keys)  # stable: within equal keys, earlier entries first
    same = values[order[1:]] == values[order[:-1]]
    if groups is not None:
        same &= groups[order[1:]] == groups[order[:-1]]
    repeats = order[1:][same]
    return int(repeats.min()) if repeats.size else None


def locate(keys: np.ndarray, wanted: np.ndarray, sorter: np.ndarray | None = None
           ) -> tuple[np.ndarray, np.ndarray]:
    """Where each of ``wanted`` is in ``keys`` (ascending, or in the order ``sorter`` gives) and
    whether it is there: ``(index, found)`` with ``keys[index] == wanted`` where ``found``, and
    ``index`` some valid index of ``keys`` elsewhere (0 when ``keys`` is empty)."""
    if not len(keys):
        return np.zeros(len(wanted), dtype=np.intp), np.zeros(len(wanted), dtype=bool)
    index = np.minimum(np.searchsorted(keys, wanted, sorter=sorter), len(keys) - 1)
    if sorter is not None:
        index = sorter[index]
    return index, keys[index] == wanted


def size_groups(sizes: np.ndarray) -> list[np.ndarray]:
    """Indices of ``sizes`` grouped by value, each group ascending: the maps of one size can be stacked."""
    if not len(sizes):
        return []
    order = np.argsort(sizes, kind="stable")
    return np.split(order, np.flatnonzero(np.diff(sizes[order])) + 1)


def spherical_diagonal(diagonal: np.ndarray, power: float) -> tuple[np.ndarray, np.ndarray]:
    """Spherical variances from the diagonal of full covariances (or, with ``power`` -1, of information matrices):
    the mean of each x/y pair of ``diagonal`` (the last axis: pose x, y, phi, then features), the phi entry as is; ``**power``."""
    features = (diagonal[..., 3::2] + diagonal[..., 4::2]) / 2
    poses = diagonal[..., 1:3].copy()
    poses[..., 0] = (diagonal[..., 0] + diagonal[..., 1]) / 2
    return features**power, poses**power


def marginal_variances(covariances: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The ``marginal`` spherical variances of a stack of full covariances of one size (k x n x n): the
    feature variances (k x m) and pose variances (k x 2) that ``LocalMap.from_covariance`` gives each."""
    return spherical_diagonal(np.diagonal(covariances, axis1=-2, axis2=-1), 1.0)


def first_flagged(bad: np.ndarray, offsets: np.ndarray) -> int:
    """The item holding the first flagged row of ``bad``, a mask over the rows of items' arrays concatenated
    (item i's rows from ``offsets[i]`` to ``offsets[i + 1]``); the number of items if none is flagged."""
    if bad.ndim > 1:
        bad = bad.any(axis=tuple(range(1, bad.ndim)))
    if not bad.any():
        return len(offsets) - 1
    return int(np.searchsorted(offsets, bad.argmax(), side="right")) - 1


@dataclass(frozen=True)
class LocalMap:
    """One local map, everything in the frame of its start pose.

    ``covariance`` (optional) is the full covariance of ``[end_pose, features.ravel()]``;
    when present it must be symmetric positive definite (rounding-level asymmetry, within
    ``SYMMETRY_TOLERANCE``, is averaged away, in a copy).

    Every value must lie in its accepted range (docs/formats.md, "Accepted values"): coordinates in
    :data:`COORDINATE` (|x| <= 1e9 m), the heading in :data:`ANGLE` (|phi| <= 1e6 rad),
    variances in :data:`VARIANCE` ([1e-30, 1e30]), covariance entries in :data:`COVARIANCE_ENTRY`;
    then no arithmetic of a join overflows or divides by a subnormal.

    ``checked`` is for :meth:`StackedMaps.local_maps` only: its values were checked for the
    whole stack at once and are stored as they are (read-only arrays of the right dtypes and
    shapes); otherwise the constructor copies and checks them.
    """

    name: str
    start_id: int
    end_id: int
    end_pose: np.ndarray
    feature_ids: np.ndarray
    features: np.ndarray
    feature_variances: np.ndarray
    pose_variances: np.ndarray
    covariance: np.ndarray | None = None
    checked: InitVar[bool] = False

    def __post_init__(self, checked: bool) -> None:
        """Each field as an array of its dtype and shape, then the values checked as a stack of one map."""
        if checked:
            return
        source = self.name
        for key in ("start_id", "end_id"):
            value = getattr(self, key)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 0:
                raise InputError(f"expected a non-negative integer, got {shown(value)}", source, key)
            object.__setattr__(self, key, int(value))
        if self.end_id == self.start_id:
            raise InputError(f"end pose id equals start pose id ({self.end_id})", source, "end_id")
        end_pose = _coerced(self.end_pose, "end_pose", source, (3,))
        features = _coerced(self.features, "features", source, (None, 2))
        m = len(features)
        ids = np.asarray(self.feature_ids)
        if ids.shape != (m,) or (m and not np.issubdtype(ids.dtype, np.integer)
                                 and not np.array_equal(ids, np.round(ids))):
            raise InputError(f"expected {m} integer ids, got {shown(ids)}", source, "feature_ids")
        stack = StackedMaps(
            [source], end_pose[np.newaxis], _coerced(ids, "feature_ids", source, (m,), np.int64)[np.newaxis],
            features[np.newaxis], _coerced(self.feature_variances, "feature_variances", source, (m,))[np.newaxis],
            _coerced(self.pose_variances, "pose_variances", source, (2,))[np.newaxis],
            None if self.covariance is None else
            _coerced(self.covariance, "covariance", source, (3 + 2 * m, 3 + 2 * m))[np.newaxis])
        invalid = stack.first_invalid()
        if invalid is not None:
            raise invalid[1]
        [valid] = stack.local_maps([self.start_id], [self.end_id])
        for key in StackedMaps._fields[1:]:
            object.__setattr__(self, key, getattr(valid, key))

    @classmethod
    def from_covariance(cls, name: str, start_id: int, end_id: int, end_pose, feature_ids,
                        features, covariance) -> "LocalMap":
        """A map whose spherical variances are the ``marginal`` summary of its full covariance."""
        covariance = np.asarray(covariance, dtype=float)
        feature_variances, pose_variances = marginal_variances(covariance[np.newaxis])
        return cls(name, start_id, end_id, end_pose, feature_ids, features,
                   feature_variances[0], pose_variances[0], covariance)

    @property
    def size(self) -> int:
        """Number of features."""
        return len(self.feature_ids)


class StackedMaps(NamedTuple):
    """Local maps of one size m, stacked: row r of each array belongs to the map named ``name[r]``.

    How readers of many maps hold them before they become :class:`LocalMap` objects:
    :meth:`first_invalid` checks all rows at once, exactly as the constructor checks one map
    (which it does as a stack of one), and :meth:`local_maps` makes the maps without checking
    them again.
    """

    name: Sequence[str]
    end_pose: np.ndarray  # k x 3
    feature_ids: np.ndarray  # k x m, int64
    features: np.ndarray  # k x m x 2
    feature_variances: np.ndarray  # k x m
    pose_variances: np.ndarray  # k x 2
    covariance: np.ndarray | None  # k x (3+2m) x (3+2m)

    def first_invalid(self) -> tuple[int, InputError] | None:
        """The first map whose values are invalid and the error ``LocalMap(...)`` raises for it, or None.

        Each check runs on the whole stack (one Cholesky factorisation for all covariances); the
        first row any check flags is the first invalid map, and the first check (in the order
        below) that flags it gives its error. The arrays are not changed.
        """
        count = len(self.name)
        if not count:
            return None

        def first(bad: np.ndarray) -> int:
            flagged = bad.reshape(count, -1).any(axis=1)
            return int(flagged.argmax()) if flagged.any() else count

        def values(key: str, ranges: Ranges) -> tuple[int, Callable[[int], InputError]]:
            array = getattr(self, key)
            return first(outside(array, ranges)), lambda r: _value_error(array[r], key, self.name[r], ranges)

        ids = self.feature_ids
        increasing = (ids[:, 1:] > ids[:, :-1]).all(axis=1)  # sorted ids (the common case) need no sort
        repeats = np.zeros(count, dtype=bool)
        repeats[~increasing] = (np.diff(np.sort(ids[~increasing], axis=1), axis=1) == 0).any(axis=1)
        failures = [  # (first map failing a check, its error), in the order LocalMap(...) checks one
            values("end_pose", POSE),
            values("features", COORDINATE),
            (first(ids < 0), lambda r: InputError(f"expected non-negative ids, got {int(ids[r].min())}",
                                                  self.name[r], "feature_ids")),
            (first(repeats), lambda r: InputError(f"duplicate id {_duplicate_id(ids[r])}", self.name[r],
                                                  "feature_ids")),
            values("feature_variances", VARIANCE),
            values("pose_variances", VARIANCE),
        ]
        if self.covariance is not None:
            failures += self._covariance_failures(first)
        index, error = min(failures, key=lambda failure: failure[0])  # ties: the earlier check
        return None if index == count else (index, error(index))

    def _covariance_failures(self, first: Callable[[np.ndarray], int]
                             ) -> list[tuple[int, Callable[[int], InputError]]]:
        """The checks of the covariances: finite, symmetric up to rounding, positive definite (of the symmetrised
        matrices, as the maps will hold them), variances (the diagonal) in :data:`VARIANCE` as the spherical ones."""
        covariance, name = self.covariance, self.name
        finite = ~outside(covariance, COVARIANCE_ENTRY).any(axis=(1, 2))
        diagonal = np.diagonal(covariance, axis1=1, axis2=2)
        variances = finite & ~outside(diagonal, VARIANCE).any(axis=1)  # 1e-300: a join's weights would overflow
        rounded = finite & ~_exactly_symmetric(covariance)  # the rest pass, or fail first
        asymmetric = np.zeros(len(covariance), dtype=bool)
        if rounded.any():
            asymmetric[rounded] = (asymmetry(covariance[rounded]) > 0).any(axis=(1, 2))
        return [(first(~finite), lambda r: _value_error(covariance[r], "covariance", name[r], COVARIANCE_ENTRY)),
                (first(asymmetric), lambda r: _asymmetry_error(covariance[r], name[r])),
                (first(_indefinite(_symmetrised(covariance, rounded & ~asymmetric))),
                 lambda r: _indefinite_error(_symmetrised(covariance[r:r + 1], rounded[r:r + 1])[0], name[r])),
                (first(finite & ~variances), lambda r: _diagonal_error(diagonal[r], name[r]))]

    def local_maps(self, start_ids: Sequence[int], end_ids: Sequence[int]) -> list[LocalMap]:
        """The maps of the rows, NOT checked again: only once :meth:`first_invalid` found none invalid;
        the ids must be non-negative ints, start != end. The maps hold read-only views of the arrays,
        the covariances symmetric up to rounding symmetrised (in a copy)."""
        if self.covariance is None:
            covariances = itertools.repeat(None)
        else:
            covariances = _read_only(_symmetrised(self.covariance, ~_exactly_symmetric(self.covariance)))
        return [LocalMap(*fields, checked=True) for fields in zip(
            self.name, start_ids, end_ids, *map(_read_only, self[1:-1]), covariances)]


def _read_only(array: np.ndarray) -> np.ndarray:
    """A read-only view of ``array`` (the array itself stays as it is)."""
    view = array.view()
    view.flags.writeable = False
    return view


def _exactly_symmetric(covariance: np.ndarray) -> np.ndarray:
    """Which matrices of a stack equal their transpose."""
    return (covariance == covariance.transpose(0, 2, 1)).all(axis=(1, 2))


def _symmetrised(covariance: np.ndarray, which: np.ndarray) -> np.ndarray:
    """The stack with the matrices ``which`` replaced by their symmetric part ``(P + P^T) / 2``: a new
    array if ``which`` flags any, else ``covariance`` itself (never changed)."""
    if not which.any():
        return covariance
    symmetric = covariance.copy()
    part = covariance[which]
    symmetric[which] = (part + part.transpose(0, 2, 1)) / 2
    return symmetric


Stacks = Sequence[tuple[Sequence[int], StackedMaps]]  # (the places of a stack's maps in a list of maps, the stack)


def first_invalid_map(stacks: Stacks) -> tuple[int, InputError] | None:
    """The place of the first invalid map of ``stacks`` and the error ``LocalMap(...)`` raises for it
    (the error constructing the maps in turn raises first), or None."""
    return min([(int(places[found[0]]), found[1]) for places, stack in stacks if (found := stack.first_invalid())],
               key=lambda failure: failure[0], default=None)


def unstack(stacks: Stacks, start_ids: Sequence[int], end_ids: Sequence[int]) -> list[LocalMap]:
    """The maps of ``stacks``, checked (:func:`first_invalid_map` found none), each at its place;
    the map at place i runs from pose ``start_ids[i]`` to ``end_ids[i]``."""
    maps: list[LocalMap] = [None] * sum(len(places) for places, _ in stacks)  # type: ignore[list-item]
    for places, stack in stacks:
        places = list(map(int, places))
        for i, local_map in zip(places, stack.local_maps([start_ids[i] for i in places],
                                                         [end_ids[i] for i in places])):
            maps[i] = local_map
    return maps


def asymmetry(covariance: np.ndarray) -> np.ndarray:
    """``|P_ij - P_ji|`` less what rounding allows, ``SYMMETRY_TOLERANCE * sqrt(|P_ii P_jj|)``, for a matrix or
    each of a stack; positive where it is asymmetric."""
    deviation = np.sqrt(np.abs(np.diagonal(covariance, axis1=-2, axis2=-1)))
    return (np.abs(covariance - np.swapaxes(covariance, -2, -1))
            - SYMMETRY_TOLERANCE * (deviation[..., :, None] * deviation[..., None, :]))


def _asymmetry_error(covariance: np.ndarray, source: str) -> InputError:
    excess = asymmetry(covariance)
    i, j = (int(v) for v in np.unravel_index(np.argmax(excess), excess.shape))
    return InputError(f"expected a symmetric matrix, but entries ({i}, {j}) and ({j}, {i}) differ: "
                      f"{shown(covariance[i, j])} vs {shown(covariance[j, i])}", source, "covariance")


def _conditional_shares(matrices: np.ndarray) -> np.ndarray | None:
    """Each state entry's variance given the entries before it, as a share of its own variance (the squared
    diagonal of the Cholesky factor over the matrix's diagonal), for a matrix or each of a stack; None when
    the factorisation fails (not positive definite)."""
    try:
        factor = np.linalg.cholesky(matrices)
    except np.linalg.LinAlgError:
        return None
    with np.errstate(divide="ignore", invalid="ignore"):  # a stack holding inf or NaN fails the finite check first
        return np.diagonal(factor, axis1=-2, axis2=-1) ** 2 / np.diagonal(matrices, axis1=-2, axis2=-1)


def _indefinite(stack: np.ndarray) -> np.ndarray:
    """Which matrices of a stack are not positive definite, to rounding (:data:`CONDITIONAL_SHARE`): one
    factorisation of the stack, then one per matrix only if that fails."""
    shares = _conditional_shares(stack)
    if shares is not None:
        return shares.min(axis=-1, initial=1.0) < CONDITIONAL_SHARE
    return np.array([(found := _conditional_shares(matrix)) is None or found.min() < CONDITIONAL_SHARE
                     for matrix in stack], dtype=bool)


def _indefinite_error(covariance: np.ndarray, source: str) -> InputError:
    """The error for a covariance that :func:`_indefinite` flags: not positive definite, or singular to rounding
    (naming the entry that the ones before it determine, and its share)."""
    shares = _conditional_shares(covariance)
    if shares is None:
        return InputError("expected a positive definite matrix", source, "covariance")
    i = int(np.argmin(shares))
    return InputError(f"expected a positive definite matrix, but it is singular to rounding: entry {i}'s variance "
                      f"given the entries before it is {shares[i]:.3g} of its own (at least "
                      f"{CONDITIONAL_SHARE:g})", source, "covariance")


@dataclass(frozen=True)
class Provenance:
    """Where a global map came from: the input maps in join order and the settings used."""

    maps: tuple[str, ...] = ()
    covariance: str = ""
    solver: str = ""
    strategy: str = ""


@dataclass(frozen=True)
class GlobalMap:
    """Features and end poses in the global frame (the start pose of the first map).

    Values are checked against the wider global ranges (:data:`GLOBAL_COORDINATE`, |x| <= 1e16 m;
    :data:`GLOBAL_VARIANCE`, [1e-40, 1e40]; :data:`ANGLE`), within which compare and evaluate cannot
    overflow. Joining maps within the local ranges stays inside them unless their values are extreme together
    (:func:`joined_map` then names the maps joined).

    Pose ``k`` is the end pose of the k-th joined local map. Variances are spherical
    (``sigma^2`` per feature; ``(sigma_xy^2, p_phi)`` per pose). ``feature_covariances``
    (n x 2 x 2) and ``pose_covariances`` (p x 3 x 3) are full marginal blocks when a
    method computed them (exact refinement), else None. Without them the spherical
    numbers are the fast join's weights, not covariances (:attr:`has_covariances`).
    """

    feature_ids: np.ndarray
    features: np.ndarray
    feature_variances: np.ndarray
    pose_ids: np.ndarray
    poses: np.ndarray
    pose_variances: np.ndarray
    provenance: Provenance = field(default_factory=Provenance)
    feature_covariances: np.ndarray | None = None
    pose_covariances: np.ndarray | None = None
    name: str = "global map"

    def __post_init__(self) -> None:
        source = self.name
        set_ = lambda key, array: object.__setattr__(self, key, array)  # noqa: E731
        set_("features", _checked(self.features, "features", source, (None, 2), ranges=GLOBAL_COORDINATE))
        n = len(self.features)
        set_("feature_ids", _checked(self.feature_ids, "feature_ids", source, (n,), dtype=np.int64))
        _unique_ids(self.feature_ids, "feature_ids", source)
        set_("feature_variances",
             _checked(self.feature_variances, "feature_variances", source, (n,), ranges=GLOBAL_VARIANCE))
        set_("poses", _checked(self.poses, "poses", source, (None, 3), ranges=GLOBAL_POSE))
        p = len(self.poses)
        set_("pose_ids", _checked(self.pose_ids, "pose_ids", source, (p,), dtype=np.int64))
        _unique_ids(self.pose_ids, "pose_ids", source)
        set_("pose_variances", _checked(self.pose_variances, "pose_variances", source, (p, 2), ranges=GLOBAL_VARIANCE))
        if self.feature_covariances is not None:
            set_("feature_covariances",
                 _checked(self.feature_covariances, "feature_covariances", source, (n, 2, 2),
                          ranges=GLOBAL_COVARIANCE_ENTRY))
        if self.pose_covariances is not None:
            set_("pose_covariances", _checked(self.pose_covariances, "pose_covariances", source, (p, 3, 3),
                                          ranges=GLOBAL_COVARIANCE_ENTRY))

    @property
    def has_covariances(self) -> bool:
        """Whether the map carries marginal covariance blocks, so that its spherical numbers are
        their summaries (written ``var*``) rather than the one-step method's propagated weights,
        which are not covariances (written ``weight*``; docs/method.md#uncertainty-columns)."""
        return self.feature_covariances is not None or self.pose_covariances is not None


def span(names: Sequence[str]) -> str:
    """How an error names a run of maps: the one, or the first and the last with their count."""
    return names[0] if len(names) == 1 else f"{names[0]} ... {names[-1]} ({len(names)} maps)"


def joined_map(**fields) -> GlobalMap:
    """The :class:`GlobalMap` of ``fields`` that a join of the local maps its provenance names made. A value
    outside the global ranges is not the inputs' fault one by one (each was in range) but their join's: a
    heading variance of 1e30 rad^2 carried 1e9 m gives a variance of 1e48 m^2, and variances 60 orders
    apart leave a marginal variance to rounding, even negative. So it is a JoinError naming those maps."""
    try:
        return GlobalMap(**fields)
    except InputError as error:
        names = fields["provenance"].maps
        raise JoinError(f"{span(names) if names else 'the maps'}: their join gives {error.where} outside the "
                        f"accepted values: {error.detail}") from None


@dataclass(frozen=True)
class GroundTruth:
    """True feature positions and poses in the global frame (simulations); pose 0 is the origin. Checked
    against the global ranges, as :class:`GlobalMap`."""

    feature_ids: np.ndarray
    features: np.ndarray
    pose_ids: np.ndarray
    poses: np.ndarray
    name: str = "ground truth"

    def __post_init__(self) -> None:
        source = self.name
        set_ = lambda key, array: object.__setattr__(self, key, array)  # noqa: E731
        set_("features", _checked(self.features, "features", source, (None, 2), ranges=GLOBAL_COORDINATE))
        set_("feature_ids", _checked(self.feature_ids, "feature_ids", source, (len(self.features),),
                                     dtype=np.int64))
        _unique_ids(self.feature_ids, "feature_ids", source)
        set_("poses", _checked(self.poses, "poses", source, (None, 3), ranges=GLOBAL_POSE))
        set_("pose_ids", _checked(self.pose_ids, "pose_ids", source, (len(self.poses),), dtype=np.int64))
        _unique_ids(self.pose_ids, "pose_ids", source)


@dataclass(frozen=True)
class Correspondence:
    """Which global feature each input feature is: feature ``local_ids[i]`` of input map ``maps[i]`` (1-based, in the
    input order) is ``global_ids[i]``. The table ``join --associations`` writes (an association's answer) and the
    one ``simulate --local-ids`` writes (the truth). Each (map, local id) once. Errors name ``name`` and the row, or
    the file's line when the reader gives ``lines`` (the line of each row)."""

    maps: np.ndarray
    local_ids: np.ndarray
    global_ids: np.ndarray
    name: str = "correspondence"
    lines: InitVar[np.ndarray | None] = None

    def __post_init__(self, lines: np.ndarray | None) -> None:
        source = self.name

        def where(row: int, column: str = "") -> str:
            return (f"line {lines[row]}" if lines is not None else f"row {row + 1}") + (f", column {column}" if column else "")

        for key, column, least in (("maps", "map", 1), ("local_ids", "local_id", 0), ("global_ids", "global_id", 0)):
            array = _checked(getattr(self, key), key, source, (None,) if key == "maps" else (len(self.maps),),
                             dtype=np.int64)
            low = np.flatnonzero(array < least)
            if low.size:
                raise InputError(f"expected an integer >= {least}, got {array[low[0]]}", source, where(low[0], column))
            object.__setattr__(self, key, array)
        repeated = first_duplicate(self.local_ids, self.maps)
        if repeated is not None:
            raise InputError(f"map {self.maps[repeated]}, local id {self.local_ids[repeated]} has a row already; each "
                             "input feature has one", source, where(repeated))
