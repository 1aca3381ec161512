"""The arithmetic backends of the one-step algorithms: one problem on Python numbers, or a batch as arrays.

:mod:`mapjoin.onestep` writes each algorithm (Theorem 1's sums, Theorem 2's brackets, bisection,
golden section, Algorithm 1; docs/method.md#algorithm-1) once, without branches on the data, over
the few operations listed below. ``FLOATS`` runs them on Python numbers and ``math`` (one problem:
a join of the sequential strategy, with no numpy call per search step, which a numpy batch of one
would make 2-4 times slower), ``ARRAYS`` on numpy arrays, one entry per problem (the joins of a tree
level, a fixed number of numpy calls per step whatever their number). Every operation gives the same
number for a problem on both: +, -, *, / and sqrt are correctly rounded either way, numpy's sin, cos
and floor call the C library's as math does (the tests check it), and atan, atan2 and hypot call
math's for each entry of an array (numpy's own may differ in the last bit). So a problem gets the
same numbers, bit for bit, alone or in any batch.

The operations (``ops`` below is FLOATS or ARRAYS; arithmetic and comparisons are Python's operators):

    where(condition, x, y): x where condition holds, else y (x, y: values or tuples of values)
    not_: logical not; any, all: whether any, every problem's condition holds
    full(like, value): value for each problem of ``like``; size: the number of problems
    largest, smallest: over the problems; first(mask, x): x of the first problem where mask holds
    apply_where(mask, function, arguments, fill): function's results where mask holds, else fill
    total(group, values, count): each problem's sum of ``values``, added left to right from 0 by
      np.bincount (``group``: each value's problem; one problem is group 0 of 1, its sum a Python float)
    pairs(group): the group of each x and y of complex values seen as floats (x/y of problem i: 2i, 2i + 1)
    total_xy(pairs, values, count): each problem's sums of the x and of the y entries of such ``values``
    at(values, group): each problem's value at the entries of ``group``
    complex(x, y): x + iy; rows(columns): per problem, a tuple of its values in ``columns``
"""

from __future__ import annotations

import math
import operator
from types import SimpleNamespace

import numpy as np

__all__ = ["ARRAYS", "FLOATS", "backend"]


def _each(function):
    """``function`` of Python numbers applied entry by entry to arrays."""
    return lambda *arrays: np.array(list(map(function, *(x.tolist() for x in arrays))), dtype=float)


def _alternating(count: int) -> np.ndarray:
    """0, 1, 0, 1, ... (``2 count`` entries): the x/y groups of one problem's complex values seen as floats;
    a slice of one read-only array, made longer when a problem needs it (the sequential join asks once a join)."""
    global _ALTERNATING
    if 2 * count > len(_ALTERNATING):
        _ALTERNATING = np.arange(4 * count, dtype=np.intp) & 1
        _ALTERNATING.flags.writeable = False
    return _ALTERNATING[:2 * count]


_ALTERNATING = np.zeros(0, dtype=np.intp)
_XY = np.array([0, 1], dtype=np.intp)


def _batch_sums_xy(pairs: np.ndarray, values: np.ndarray, count: int) -> tuple[np.ndarray, np.ndarray]:
    """Each problem's sums of the x and of the y entries of ``values`` (x/y pairs, ``pairs``: ARRAYS.pairs)."""
    sums = np.bincount(pairs, values, 2 * count)
    return sums[0::2], sums[1::2]


def _apply_where(mask: np.ndarray, function, arguments: tuple, fill: tuple) -> tuple:
    """``function(*arguments)`` on the problems where ``mask`` holds (array arguments taken at those rows),
    the results spread out with ``fill`` elsewhere."""
    rows = np.flatnonzero(mask)
    results = function(*(x[rows] if isinstance(x, np.ndarray) else x for x in arguments))
    spread = []
    for value, result in zip(fill, results):
        full = np.full(len(mask), value, dtype=np.asarray(result).dtype)
        full[rows] = result
        spread.append(full)
    return tuple(spread)


FLOATS = SimpleNamespace(
    sin=math.sin, cos=math.cos, sqrt=math.sqrt, floor=math.floor, atan=math.atan, atan2=math.atan2,
    hypot=math.hypot, minimum=min, maximum=max, isfinite=math.isfinite, not_=operator.not_, any=bool, all=bool,
    where=lambda condition, x, y: x if condition else y, full=lambda like, value: value, size=lambda x: 1,
    largest=float, smallest=float, first=lambda mask, x: x, complex=complex,
    apply_where=lambda mask, function, arguments, fill: function(*arguments) if mask else fill,
    total=lambda group, values, count: np.bincount(group, values, 1).item(), at=lambda values, group: values,
    pairs=lambda group: _alternating(len(group)),
    total_xy=lambda pairs, values, count: np.bincount(pairs, values, 2).tolist(),
    rows=lambda columns: (columns,))
ARRAYS = SimpleNamespace(
    sin=np.sin, cos=np.cos, sqrt=np.sqrt, floor=np.floor, atan=_each(math.atan), atan2=_each(math.atan2),
    hypot=_each(math.hypot), minimum=np.minimum, maximum=np.maximum, isfinite=np.isfinite,
    not_=np.logical_not, any=np.any, all=np.all, where=np.where, full=lambda like, value: np.full(np.shape(like), value),
    size=len, largest=np.max, smallest=np.min, first=lambda mask, x: x[np.argmax(mask)],
    complex=lambda x, y: x + 1j * y, apply_where=_apply_where, total=np.bincount,
    pairs=lambda group: (2 * group[:, None] + _XY).ravel(), total_xy=_batch_sums_xy,
    at=lambda values, group: values[group],
    rows=lambda columns: zip(*(column.tolist() for column in columns)))


def backend(value) -> SimpleNamespace:
    """``ARRAYS`` for an array of problems, ``FLOATS`` for one problem given as numbers."""
    return ARRAYS if isinstance(value, np.ndarray) else FLOATS
