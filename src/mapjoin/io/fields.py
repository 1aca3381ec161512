"""What a person writing local maps may add or leave out (YAML and CSV alike).

Added: a person keeps their own data beside mapjoin's (a timestamp, a sensor name): such a
field or column is ignored, and one warning per file names it. A name close to one of
mapjoin's (``covarience``, ``var_pih``) is almost surely a typo of an optional field, which
ignoring would silently turn into a different problem: that is an error.

Left out: the spherical variances of a map that has its full covariance; they are then the
covariance's marginal ones (:func:`filled_variances`). When both are given the covariance
wins: every covariance mode and the refinement use it, the variances are kept as written.
"""

from __future__ import annotations

import logging
from collections.abc import Iterable, Sequence

import numpy as np

from ..errors import InputError, shown

__all__ = ["filled_variances", "ignored_fields", "typo_message", "typo_of", "warn_ignored"]

log = logging.getLogger("mapjoin")

_TYPO_CUTOFF = 0.8  # difflib's similarity ratio from which an unknown name is taken for a typo of a known one


def ignored_fields(names: Iterable[str], known: Sequence[str], source: str, where: str | None, what: str) -> list[str]:
    """The ``names`` that are not ``known``, in order; InputError at ``where`` if one looks like a typo of a known
    name (``what``: ``field`` or ``column``)."""
    unknown = [name for name in names if name not in known]
    for name in unknown:
        close = typo_of(name, known)
        if close:
            raise InputError(typo_message(what, name, close, known), source, where)
    return unknown


def typo_of(name: object, known: Sequence[str]) -> str | None:
    """The known name that ``name`` looks like a typo of, if any (difflib is imported only for unknown names)."""
    import difflib

    close = difflib.get_close_matches(str(name), known, n=1, cutoff=_TYPO_CUTOFF)
    return close[0] if close else None


def typo_message(what: str, name: object, close: str, known: Sequence[str]) -> str:
    """The error for an unknown ``name`` close to the known ``close``."""
    return (f"unknown {what} {shown(name)} (did you mean {shown(close)}?); expected {', '.join(known)}, or names not "
            "close to them, which are ignored")


def filled_variances(given: np.ndarray, marginal: np.ndarray) -> np.ndarray:
    """The variances ``given`` (NaN: left out) with the left-out ones the covariance's ``marginal`` ones; a
    non-positive marginal (of a covariance that is not positive definite, which the map's check refuses next)
    fills 1, so that the error is about the covariance."""
    return np.where(np.isnan(given), np.where(marginal > 0, marginal, 1.0), given)


def warn_ignored(source: str, what: str, names: Sequence[str]) -> None:
    """One warning naming the ignored fields (or columns) of ``source``."""
    if names:
        log.warning("%s: ignored the %s%s %s (not read by mapjoin)", source, what, "s" if len(names) > 1 else "",
                    ", ".join(shown(name) for name in names))
