"""Fields a local-map file holds that mapjoin does not read: a typo is refused, anything else ignored with a warning.

A person writing maps by hand keeps their own data beside mapjoin's (a timestamp, a sensor
name): such a field or column is ignored, and one warning per file names it. A name close
to one of mapjoin's (``covarience``, ``var_pih``) is almost surely a typo of an optional
field, which ignoring would silently turn into a different problem: that is an error.
"""

from __future__ import annotations

import difflib
import logging
from collections.abc import Iterable, Sequence

from ..errors import InputError, shown

__all__ = ["ignored_fields", "warn_ignored"]

log = logging.getLogger("mapjoin")

_TYPO_CUTOFF = 0.8  # difflib's similarity ratio from which an unknown name is taken for a typo of a known one


def ignored_fields(names: Iterable[str], known: Sequence[str], source: str, where: str | None, what: str) -> list[str]:
    """The ``names`` that are not ``known``, in order; InputError at ``where`` if one looks like a typo of a known
    name (``what``: ``field`` or ``column``)."""
    unknown = [name for name in names if name not in known]
    for name in unknown:
        close = difflib.get_close_matches(str(name), known, n=1, cutoff=_TYPO_CUTOFF)
        if close:
            raise InputError(f"unknown {what} {shown(name)} (did you mean {shown(close[0])}?); expected only "
                             f"{', '.join(known)}, or names not close to them, which are ignored", source, where)
    return unknown


def warn_ignored(source: str, what: str, names: Sequence[str]) -> None:
    """One warning naming the ignored fields (or columns) of ``source``."""
    if names:
        log.warning("%s: ignored the %s%s %s (not read by mapjoin)", source, what, "s" if len(names) > 1 else "",
                    ", ".join(shown(name) for name in names))
