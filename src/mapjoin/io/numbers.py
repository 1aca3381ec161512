"""Which number tokens the text formats accept: ASCII only.

Python's ``float`` and ``int`` (and numpy's conversions of text, which call them) also read
digits of other scripts (fullwidth ``１２`` as 12) and ``_`` between digits (``1_000``);
a number in a mapjoin input is written with the ASCII digits, sign, point and exponent
only, so those are refused before converting. The check costs one join and two scans
in C, whatever the number of tokens.
"""

from __future__ import annotations

from collections.abc import Sequence

__all__ = ["first_unplain"]


def first_unplain(tokens: Sequence[str]) -> int | None:
    """Index of the first token holding a non-ASCII character or ``_`` (which ``float`` would accept), or None."""
    joined = "".join(tokens)
    if joined.isascii() and "_" not in joined:
        return None
    return next(i for i, token in enumerate(tokens) if not token.isascii() or "_" in token)
