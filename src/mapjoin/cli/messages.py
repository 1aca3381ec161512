"""The library's log records as lines on stderr, a repeated warning summarised with a count."""

from __future__ import annotations

import logging
import re
import sys

import click

from ..errors import counted, shown

#: how much of a held-back kind's message its summary line repeats
_QUOTED = 70
_FIELD = re.compile(r"%[-#0 +]*\d*(?:\.\d+)?[a-zA-Z]")  # a %-field of a message template


class StderrHandler(logging.Handler):
    """Log records as ``mapjoin: warning: ...`` lines on stderr.

    A warning of a kind already shown (the same message template, e.g. "%s shares no feature with the
    maps it is joined onto") is counted instead of printed, unless ``every_warning`` (-v), and
    :meth:`summarise` prints one line per kind with the count held back: a tree join of 6898 maps says
    what happened once, not 41 times.
    """

    def __init__(self, every_warning: bool = False):
        super().__init__()
        self.every_warning = every_warning
        self.held: dict[str, int] = {}  # template -> how many more of its kind came

    def emit(self, record: logging.LogRecord) -> None:
        message = record.getMessage()
        if record.levelno == logging.WARNING and not self.every_warning:
            kind = str(record.msg)
            if kind in self.held:
                self.held[kind] += 1
                return
            self.held[kind] = 0
        _echo(record.levelno, message)

    def summarise(self) -> None:
        """One line for each kind of warning some of which were held back, then forget them."""
        for template, more in self.held.items():
            if more:
                kind = _FIELD.sub("...", template.replace("%%", "%"))
                _echo(logging.WARNING, f"{counted(more, 'more warning')} like "
                                       f"{shown(kind, _QUOTED)} (-v lists them all)")
        self.held.clear()


def _echo(level: int, message: str) -> None:
    prefix = "mapjoin: " if level < logging.WARNING else f"mapjoin: {logging.getLevelName(level).lower()}: "
    clear = "\r\x1b[K" if sys.stderr.isatty() else ""  # start a clean line under a progress bar
    click.echo(clear + prefix + message, err=True)
