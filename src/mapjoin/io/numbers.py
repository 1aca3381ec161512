"""Which number tokens the text formats accept (ASCII only), and matrices read from them.

Python's ``float`` and ``int`` (and numpy's conversions of text, which call them) also read
digits of other scripts (fullwidth ``１２`` as 12) and ``_`` between digits (``1_000``);
a number in a mapjoin input is written with the ASCII digits, sign, point and exponent
only, so those are refused before converting. The check costs one join and two scans
in C, whatever the number of tokens.

Reading a decimal number correctly rounded (``float``, about 0.3 µs for the 17 digits
``repr`` writes; numpy's text conversions cost the same) is most of the time of reading a
text local map: :func:`symmetric_matrix` reads a covariance or information matrix whose
text mirrors itself by its lower triangle only, half the numbers.
"""

from __future__ import annotations

import functools
import operator
from collections.abc import Callable, Sequence

import numpy as np

__all__ = ["first_unplain", "symmetric_matrix"]


def first_unplain(tokens: Sequence[str]) -> int | None:
    """Index of the first token holding a non-ASCII character or ``_`` (which ``float`` would accept), or None."""
    joined = "".join(tokens)
    if joined.isascii() and "_" not in joined:
        return None
    return next(i for i, token in enumerate(tokens) if not token.isascii() or "_" in token)


def symmetric_matrix(tokens: Sequence[str], size: int, plain: Callable[[Sequence[str]], bool]
                     ) -> np.ndarray | None:
    """The ``size`` x ``size`` matrix (``size`` >= 2) of number tokens given row by row, each read with
    ``float``; None when there are not ``size`` squared tokens, or the ones read are not ``plain`` (the
    format's check of a sequence of tokens) or not numbers (``float`` raises).

    When the tokens mirror themselves across the diagonal (as strings: equal text reads as equal
    numbers) only the lower triangle is checked and read, and copied across: the matrix that
    checking and reading every token gives, in half the time.
    """
    if len(tokens) != size * size:
        return None
    lower, mirror, triangle = _triangle(size)
    lower_tokens = lower(tokens)
    read = lower_tokens if lower_tokens == mirror(tokens) else tokens
    if not plain(read):
        return None
    try:
        values = np.fromiter(map(float, read), dtype=float, count=len(read))
    except ValueError:
        return None
    if read is tokens:
        return values.reshape(size, size)
    matrix = np.empty((size, size))
    matrix[triangle] = values
    matrix.T[triangle] = values
    return matrix


@functools.lru_cache(maxsize=64)
def _triangle(size: int) -> tuple[operator.itemgetter, operator.itemgetter, tuple[np.ndarray, np.ndarray]]:
    """Getters of a row-major ``size`` x ``size`` matrix's lower triangle (row by row) and of the
    entries mirroring it across the diagonal, and the triangle's indices (``size`` >= 2, so that each getter
    returns a tuple: local maps have 3 + 2m rows)."""
    rows, columns = np.tril_indices(size)
    return (operator.itemgetter(*(rows * size + columns).tolist()),
            operator.itemgetter(*(columns * size + rows).tolist()), (rows, columns))
