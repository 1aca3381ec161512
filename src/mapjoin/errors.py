"""The exceptions mapjoin raises, and the command line's exit codes: the CLI turns each exception into one line on
stderr and exit code 1. This module imports nothing, so that ``python -m mapjoin``'s outermost guard can take
its exit code from here before anything else is loaded."""

from __future__ import annotations

__all__ = ["ECHO_LIMIT", "EXIT_INTERRUPTED", "EXIT_NOT_CONVERGED", "EXIT_TWO_MINIMA", "NAME_LIMIT", "MapjoinError", "InputError", "JoinError", "counted", "one_line", "shown",
           "shown_name"]

#: exit code of a command stopped by Ctrl-C (128 + SIGINT, as a shell reports a process the signal ended)
EXIT_INTERRUPTED = 130
#: exit code of ``check-minima`` finding a join with two minima: a result written, but one to look at
EXIT_TWO_MINIMA = 3
#: exit code of ``refine`` / ``join --refine`` stopping without converging: the same code, for the same reason
EXIT_NOT_CONVERGED = 3

#: the most characters of an input value an error message shows (:func:`shown`)
ECHO_LIMIT = 40


def shown(value: object, limit: int = ECHO_LIMIT, *, quoted: bool = True) -> str:
    """How an error message shows a value taken from the input: text as its ``repr`` (``quoted``; else as
    it is), anything else as ``str``, control characters escaped so that the message stays one line; cut
    to ``limit`` characters with ``...`` so that a 3 MB token does not become a 3 MB message."""
    try:
        text = repr(value) if isinstance(value, str) and quoted else str(value)
    except RecursionError:  # a container nested deeper than Python's repr goes (YAML's [[[[...]]]])
        text = f"a {type(value).__name__} nested too deep to show"
    text = text if text.isprintable() else repr(text)[1:-1]
    return text if len(text) <= limit else text[:limit - 3] + "..."


#: the most characters of a file name an error message shows (:func:`shown_name`)
NAME_LIMIT = 160


def one_line(text: str) -> str:
    """``text`` with its control characters (line ends included) escaped as Python writes them, so that a
    message about a file named ``a<newline>b`` stays one line."""
    return text if text.isprintable() else "".join(c if c.isprintable() else repr(c)[1:-1] for c in text)


def shown_name(name: str, limit: int = NAME_LIMIT) -> str:
    """How an error message names a file: on one line (:func:`one_line`) and, when longer than ``limit``, cut in
    the middle, keeping its start and its last part, the file's own name; an empty name as ``''``."""
    name = one_line(name) or "''"
    if len(name) <= limit:
        return name
    keep = (limit - 3) // 2
    return f"{name[:keep]}...{name[len(name) - (limit - 3 - keep):]}"


def counted(count: int, singular: str, plural: str | None = None) -> str:
    """How a message shows a count of things, the noun in the number it needs: ``1 map``, ``2 maps``,
    ``0 maps``, ``1 minimum`` / ``2 minima`` (``plural`` when not ``singular + "s"``)."""
    return f"{count} {singular if count == 1 else plural or singular + 's'}"


class MapjoinError(Exception):
    """Base class of every error mapjoin raises on purpose."""


class InputError(MapjoinError):
    """A file, stream or value that does not hold what mapjoin expects.

    The message names the source (file or ``<stdin>``), the line or field when known,
    and what was expected, e.g. ``maps/a.yaml, field features[3].var: expected a
    positive number, got -1``.

    ``argument`` names the argument of the call that would settle the error (e.g. ``format``):
    ``message`` then stops where the remedy goes, and the error ends ``give its <argument>``.
    A command line names its own option instead (:meth:`naming`).
    """

    def __init__(self, message: str, source: str | None = None, where: str | None = None, *,
                 argument: str | None = None):
        self.source = source
        self.where = where
        self.argument = argument
        self._before_remedy = message
        self.detail = f"{message}give its {argument}" if argument else message
        prefix = ", ".join(part for part in (None if source is None else shown_name(source), where) if part)
        super().__init__(f"{prefix}: {self.detail}" if prefix else self.detail)

    def naming(self, option: str) -> InputError:
        """This error with the remedy ``pass <option>`` (a command's option for :attr:`argument`)."""
        return self.with_remedy(f"pass {option}")

    def with_remedy(self, remedy: str) -> InputError:
        """This error ending with ``remedy`` instead of ``give its <argument>``."""
        return InputError(f"{self._before_remedy}{remedy}", self.source, self.where)


class JoinError(MapjoinError):
    """Maps that are valid one by one but cannot be joined (e.g. an unconnected pose chain)."""
