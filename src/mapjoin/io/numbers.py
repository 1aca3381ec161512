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

__all__ = ["first_unplain", "lower_matrix", "mirrored_lower", "symmetric_matrix"]


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
    lower, mirror, _, _ = _triangle(size)
    lower_tokens = lower(tokens)
    if lower_tokens == mirror(tokens):
        return lower_matrix(lower_tokens, size) if plain(lower_tokens) else None
    if not plain(tokens):
        return None
    try:
        return np.fromiter(map(float, tokens), dtype=float, count=size * size).reshape(size, size)
    except ValueError:
        return None


def mirrored_lower(rows: Sequence[str], separator: str, size: int) -> list[str] | None:
    """The lower triangle's tokens, row by row, of a ``size`` x ``size`` matrix whose rows are texts of tokens
    joined by ``separator``, when each row is exactly that: the lower triangle's tokens of its row, then
    those of its column below the diagonal (the text mirrors itself); else None.

    Only the lower triangle is split into tokens (the rest of each row is compared as text, in
    C): for text a writer laid out so, as :func:`symmetric_matrix` without splitting it all.
    """
    lower: list[str] = []
    for i, row in enumerate(rows):
        lower += row.split(separator, i + 1)[:i + 1]
    if len(rows) != size or len(lower) != size * (size + 1) // 2:
        return None
    full = _triangle(size)[3](lower)
    if any(separator.join(full[i * size:(i + 1) * size]) != row for i, row in enumerate(rows)):
        return None
    return lower


def lower_matrix(lower: Sequence[str], size: int) -> np.ndarray | None:
    """The symmetric ``size`` x ``size`` matrix of its lower triangle's number tokens, row by row, each read
    with ``float`` (checked beforehand to be numbers in the format's grammar); None if ``float`` raises."""
    try:
        values = np.fromiter(map(float, lower), dtype=float, count=len(lower))
    except ValueError:
        return None
    triangle = _triangle(size)[2]
    matrix = np.empty((size, size))
    matrix[triangle] = values
    matrix.T[triangle] = values
    return matrix


@functools.lru_cache(maxsize=64)
def _triangle(size: int) -> tuple[operator.itemgetter, operator.itemgetter, tuple[np.ndarray, np.ndarray],
                                  operator.itemgetter]:
    """For a row-major ``size`` x ``size`` matrix (``size`` >= 2, so that each getter returns a tuple: local
    maps have 3 + 2m rows): getters of its lower triangle (row by row) and of the entries mirroring it
    across the diagonal, the triangle's indices, and a getter of the whole matrix, row-major, from the
    lower triangle's entries."""
    rows, columns = np.tril_indices(size)
    row, column = np.divmod(np.arange(size * size), size)
    high, low = np.maximum(row, column), np.minimum(row, column)
    return (operator.itemgetter(*(rows * size + columns).tolist()),
            operator.itemgetter(*(columns * size + rows).tolist()), (rows, columns),
            operator.itemgetter(*(high * (high + 1) // 2 + low).tolist()))
