"""The ``mapjoin`` command line: a thin layer that parses, calls the library, writes.

Exit codes: 0 success; 1 bad input or a join that cannot be done (one line on stderr,
naming the file and field); 2 a usage error; 3 the result needs attention: ``check-minima``
found two minima, or ``refine`` / ``join --refine`` stopped without converging (the last
iterate is written, and one line on stderr says so); 130 interrupted (Ctrl-C).
Data goes to stdout (or ``-o``); messages, warnings and progress go to stderr. Each
command declares its outputs to :class:`mapjoin.io.Outputs`, which checks them before any
input is read and writes them all or none.
"""

from __future__ import annotations

import importlib
import os
from collections.abc import Iterator, MutableMapping

import click

from ..errors import EXIT_INTERRUPTED, InputError, MapjoinError, one_line, shown, shown_name

#: what a command without an option for a library argument (InputError.argument) tells instead
_REMEDIES = {"format": "save it under a name with its format's extension"}


class MapjoinGroup(click.Group):
    """A group that turns mapjoin's own errors into one line and exit code 1."""

    def parse_args(self, ctx: click.Context, args: list[str]) -> list[str]:
        """Refuse a NUL character in any argument first: no file name can hold one (``os`` raises ValueError on
        it), and only a caller in the same process can pass one (a process's arguments cannot)."""
        bad = next((arg for arg in args if "\0" in arg), None)
        if bad is not None:
            raise click.UsageError(f"the argument {shown(bad)} holds a NUL character, which no file name or value "
                                   "can", ctx)
        return super().parse_args(ctx, args)

    def invoke(self, ctx: click.Context):
        try:
            return super().invoke(ctx)
        except MapjoinError as error:
            if isinstance(error, InputError) and error.argument in _REMEDIES:  # no option of the command named it
                error = error.with_remedy(_REMEDIES[error.argument])
            raise click.ClickException(one_line(str(error))) from error  # a name with a line end stays one line
        except KeyboardInterrupt:
            click.echo("mapjoin: interrupted", err=True)
            raise click.exceptions.Exit(EXIT_INTERRUPTED) from None
        except OSError as error:
            if isinstance(error, BrokenPipeError):  # e.g. `mapjoin join ... | head`: the reader wants no more
                raise click.exceptions.Exit(0) from None
            name = f"{shown_name(os.fsdecode(error.filename))}: " if error.filename else ""
            raise click.ClickException(one_line(f"{name}{error.strerror or error}")) from error

    def format_commands(self, ctx: click.Context, formatter: click.HelpFormatter) -> None:
        """The list of commands in ``mapjoin --help``: each command's summary (:data:`COMMAND_SUMMARIES`) shortened
        by click as it shortens the command's own help, so that listing the commands imports none of their modules
        (nor numpy and the library with them: most of ``--help``'s time)."""
        listed = [click.Command(name, help=COMMAND_SUMMARIES[name]) if name in COMMAND_SUMMARIES
                  else self.commands[name] for name in self.list_commands(ctx)]
        click.Group(commands=listed).format_commands(ctx, formatter)


def _show_version(ctx: click.Context, _parameter: click.Parameter, value: bool) -> None:
    """``--version``: the version is looked up only when asked for (see mapjoin.__version__)."""
    if value and not ctx.resilient_parsing:
        from .. import __version__

        click.echo(f"mapjoin, version {__version__}")
        ctx.exit()


@click.group(cls=MapjoinGroup, context_settings={"help_option_names": ["-h", "--help"]})
@click.option("--version", is_flag=True, expose_value=False, is_eager=True, callback=_show_version,
              help="Show the version and exit.")
@click.option("-q", "--quiet", is_flag=True, help="Only errors on stderr: no warnings, summary or progress.")
@click.option("-v", "--verbose", count=True, help="More detail on stderr (-v: one line per join).")
@click.pass_context
def main(ctx: click.Context, quiet: bool, verbose: int) -> None:
    """Join 2D point-feature local maps into one global map, fast and certified.

    Each join is the spherical-covariance one-step problem of Wang, Huang, Frese and
    Dissanayake (Automatica 2013): a 1-D problem whose minima Theorem 2 counts.
    Inputs are files, globs, folders (e.g. an I-SLSJF folder of localmap_k.mat) or - for
    stdin; data goes to stdout unless -o is given. Outputs are checked before any input
    is read, never overwrite an input or each other (links and letter case included),
    and are written all or none; a symbolic link is written through (the file it points
    to is replaced), a device or FIFO is written into (docs/formats.md).

    \b
    Examples:
      mapjoin join examples/sim20 -o global.csv --report report.csv
      mapjoin simulate -o - --maps 50 | mapjoin join - > global.csv
      mapjoin join ../shared/data/VicPark_6898_local_maps --strategy tree --jobs 2 -o vp.csv
      mapjoin join ../shared/data/VicPark_200_local_maps --refine -o exact.yaml
      mapjoin check-minima --a 203570 --c-phi -0.0028
      mapjoin evaluate global.csv --truth ../shared/data/535_data_5_local_maps
      mapjoin merge robot1.csv robot2.csv -o merged.csv --associate
      mapjoin plot global.csv exact.yaml -o maps.png
      mapjoin build raw.g2o -o maps/ --maps 100
      mapjoin datasets fetch vicpark-200
    """
    import logging  # here, not at the top: ``mapjoin --help`` and ``--version`` end before this runs

    from .messages import StderrHandler

    logger = logging.getLogger("mapjoin")
    saved = logger.handlers[:], logger.propagate, logger.level
    handler = StderrHandler(every_warning=verbose > 0)
    logger.handlers[:] = [handler]
    logger.propagate = False
    logger.setLevel(logging.ERROR if quiet else logging.DEBUG if verbose else logging.INFO)

    def restore() -> None:  # leave the logger as found (the CLI is also called in-process)
        handler.summarise()
        logger.handlers[:], logger.propagate, logger.level = saved

    ctx.call_on_close(restore)
    ctx.obj = {"quiet": quiet, "verbose": verbose, "warnings": handler}


#: each command's module in this package: imported when the command is first looked up (to run it or show its
#: help; ``mapjoin --help`` lists it by its summary), so that a command pays for its own imports only
COMMAND_MODULES = {"build": "build", "check-minima": "check_minima", "compare": "compare", "convert": "convert",
                   "datasets": "datasets", "evaluate": "evaluate", "join": "join", "merge": "merge", "plot": "plot",
                   "plot-join": "plot", "plot-minima": "plot", "refine": "refine", "simulate": "simulate"}
#: each command's summary, the first paragraph of its help (its docstring's), for the list of ``mapjoin --help``
#: (:meth:`MapjoinGroup.format_commands`); tests/test_startup.py checks them against the commands
COMMAND_SUMMARIES = {
    "build": "Build local maps from raw odometry and feature observations.",
    "check-minima": "Count and locate a join's local minima (Theorem 2).",
    "compare": "Compare two global maps (.csv, .yaml) entity by entity.",
    "convert": "Convert local maps: I-SLSJF .mat, Linear SLAM, YAML, CSV.",
    "datasets": "List and fetch the public local-map datasets, verified.",
    "evaluate": "Evaluate a global map (.csv or .yaml) against ground truth.",
    "join": "Join a chain of local maps into one global map.",
    "merge": "Merge global maps, each in its own frame, into one.",
    "plot": "Draw maps: features, trajectories, uncertainty.",
    "plot-join": "Draw one join's cost curve f1(phi) and its minima.",
    "plot-minima": "Draw a report's joins on Theorem 2's minima diagram.",
    "refine": "Join local maps exactly: the least-squares optimum.",
    "simulate": "Simulate a robot run, with ground truth, as local maps."}


class LazyCommands(MutableMapping):
    """A group's commands by name (``click.Group.commands``), each one's module imported on first lookup:
    the module registers its commands (``@main.command()``), as they were when all were imported up front."""

    def __init__(self, modules: dict[str, str]):
        self._modules = dict(modules)
        self._loaded: dict[str, click.Command] = {}

    def __getitem__(self, name: str) -> click.Command:
        if name not in self._loaded and name in self._modules:
            importlib.import_module(f"{__name__}.{self._modules[name]}")
        return self._loaded[name]

    def __setitem__(self, name: str, command: click.Command) -> None:
        self._loaded[name] = command

    def __delitem__(self, name: str) -> None:
        self._modules.pop(name, None)
        del self._loaded[name]

    def __iter__(self) -> Iterator[str]:
        return iter(sorted(self._modules.keys() | self._loaded.keys()))

    def __len__(self) -> int:
        return len(self._modules.keys() | self._loaded.keys())


main.commands = LazyCommands(COMMAND_MODULES)
