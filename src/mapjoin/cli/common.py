"""Options and helpers that several commands share."""

from __future__ import annotations

import contextlib
import sys
from collections.abc import Callable, Iterator

import click

from .. import formats
from ..maps import COVARIANCE_MODES
from ..joining import DEFAULT_COVARIANCE
from ..onestep import SOLVERS

inputs_argument = click.argument("inputs", nargs=-1, required=True, metavar="INPUTS...")
input_format_option = click.option(
    "--input-format", type=click.Choice(formats.MAP_FORMATS),
    help="Format of the inputs when their names do not tell it (e.g. stdin).")
covariance_option = click.option(
    "--covariance", type=click.Choice(COVARIANCE_MODES), default=DEFAULT_COVARIANCE, show_default=True,
    help="How each local map's covariance is made spherical (see README, 'Covariance modes').")
solver_option = click.option(
    "--solver", type=click.Choice(SOLVERS), default="bisection", show_default=True,
    help="1-D global solver of Algorithm 1.")


def output_option(help_text: str) -> Callable:
    return click.option("-o", "--output", default="-", show_default=True, metavar="FILE", help=help_text)


def format_option(choices: tuple[str, ...], help_text: str) -> Callable:
    return click.option("--format", "output_format", type=click.Choice(choices), help=help_text)


def say(ctx: click.Context, message: str) -> None:
    """A human message on stderr, unless -q."""
    if not ctx.obj["quiet"]:
        click.echo(message, err=True)


@contextlib.contextmanager
def progress_bar(ctx: click.Context, length: int, label: str) -> Iterator[Callable[[int], None] | None]:
    """A progress callback drawing a bar on stderr when it is a terminal (and not -q), else None."""
    if ctx.obj["quiet"] or not sys.stderr.isatty() or length < 2:
        yield None
        return
    with click.progressbar(length=length, label=label, file=sys.stderr) as bar:
        done = 0

        def update(count: int) -> None:
            nonlocal done
            bar.update(count - done)
            done = count

        yield update


def output_format(path: str, explicit: str | None, default: str) -> str:
    """The format to write ``path`` in: ``explicit``, else its extension, else ``default`` for stdout."""
    if explicit:
        return explicit
    return default if path == "-" else formats.detect_format(path)
