"""Options and helpers that several commands share."""

from __future__ import annotations

import contextlib
import logging
import math
import sys
import time
from collections.abc import Callable, Iterable, Iterator
from typing import TYPE_CHECKING

import click

from .. import io as mapio
from ..consistency import DEFAULT_GATE, POLICIES
from ..covariance import COVARIANCE_MODES, DEFAULT_COVARIANCE
from ..errors import InputError, counted, shown  # noqa: F401  (counted: the commands' common.counted)
from ..io.numbers import first_unplain
from ..io.registry import GLOBAL_MAP, LOCAL_MAPS, TABLE, TRAJECTORY, Kind, by_name, extensions_text, names
from ..joins import STRATEGIES  # not ..joining: convert, datasets and the like need no join strategy
from ..maps import LocalMap, Range
from ..onestep import SOLVERS

if TYPE_CHECKING:
    from ..joining import JoinRecord, JoinResult, Strategy
    from ..maps import GlobalMap
    from ..refine import RefineResult

log = logging.getLogger("mapjoin")

class FiniteFloat(click.FloatRange):
    """A float option's type: a finite number (click's ``float`` takes ``nan`` and ``inf``, which no
    command can use) in ASCII digits, within ``limits`` when given (shown in the help as a range);
    else a usage error naming the option."""

    def __init__(self, limits: Range | None = None):
        super().__init__(*((limits.low, limits.high) if limits else (None, None)))
        self.limits = limits

    def convert(self, value: object, param: click.Parameter | None, ctx: click.Context | None) -> float:
        try:
            number = float(value)  # type: ignore[arg-type]
        except (TypeError, ValueError):
            number = math.nan
        if isinstance(value, str) and first_unplain([value]) is not None:
            number = math.nan
        if not math.isfinite(number) or (self.limits is not None and self.limits.outside(number)):
            expected = self.limits.expected() if self.limits else "a finite number"
            self.fail(f"expected {expected}, got {shown(value)}", param, ctx)
        return number


class PlainInt(click.IntRange):
    """An integer option's type: ASCII digits (click's ``int`` takes fullwidth ``１２`` and ``1_000``, which the
    float options and the text formats refuse), within ``min``/``max``; else a usage error naming the option."""

    def convert(self, value: object, param: click.Parameter | None, ctx: click.Context | None) -> int:
        if isinstance(value, str) and first_unplain([value]) is not None:
            self.fail(f"expected an integer in ASCII digits, got {shown(value)}", param, ctx)
        return super().convert(value, param, ctx)


inputs_argument = click.argument("inputs", nargs=-1, required=True, metavar="INPUTS...")
input_format_option = click.option(
    "--input-format", type=click.Choice(names(LOCAL_MAPS)),
    help="Format of the inputs when their names do not tell it (e.g. stdin). In YAML and CSV local maps, fields and "
         "columns mapjoin does not know are ignored with one warning per file; a near miss of a known one "
         "(covarience) is an error.")
covariance_option = click.option(
    "--covariance", type=click.Choice(COVARIANCE_MODES), default=DEFAULT_COVARIANCE, show_default=True,
    help="How each local map's covariance is made spherical (see docs/joining.md, 'Covariance modes').")
gate_option = click.option(
    "--gate", type=FiniteFloat(Range("gate", 0.0, 1.0)), default=DEFAULT_GATE, show_default=True, metavar="LEVEL",
    help="Flag a join whose chi-square p-value is below LEVEL (and every join with two minima); the statistic "
         "allows for the chain's drift and the run's variance factor, and the default comes from the clean real "
         "datasets (docs/joining.md, 'Consistency'). A join that fails is confirmed on the exact least-squares "
         "problem (docs/method.md#confirmation).")
on_inconsistent_option = click.option(
    "--on-inconsistent", type=click.Choice(POLICIES), default="warn", show_default=True,
    help="What a flagged join does: warn (one warning per map), stop (exit 1 naming the map, nothing written) "
         "or skip (sequential: join the map by its features alone, or leave its features out).")
solver_option = click.option(
    "--solver", type=click.Choice(SOLVERS), default="bisection", show_default=True,
    help="1-D global solver of Algorithm 1.")


def output_option(help_text: str) -> Callable:
    return click.option("-o", "--output", default="-", show_default=True, metavar="FILE", help=help_text)


def format_option(kind: Kind, help_text: str, *names_: str) -> Callable:
    """An option choosing among the formats that write ``kind`` (default ``--format``, as ``output_format``)."""
    return click.option(*(names_ or ("--format", "output_format")), type=click.Choice(names(kind, writing=True)),
                        help=help_text)


def default_title(kind: Kind) -> str:
    """How help texts name the format ``kind`` is written in when nothing names one, e.g. ``CSV``."""
    return by_name[kind.default].title


#: -o and --format of a command writing a global map (join, refine)
global_map_output_option = output_option(
    f"Global map ({extensions_text(GLOBAL_MAP)}); - for stdout ({default_title(GLOBAL_MAP)} unless --format).")
global_map_format_option = format_option(
    GLOBAL_MAP, f"Format of the global map (default: from the -o extension, else {default_title(GLOBAL_MAP)})"
    + "".join(f"; {name}: {by_name[name].note}" for name in names(GLOBAL_MAP, writing=True) if by_name[name].note)
    + ".")
#: what a table the commands write (a report, a batch result) can be
TABLE_EXTENSIONS = extensions_text(TABLE)
#: --trajectory of a command writing a global map (join, refine): the origin and every end pose
trajectory_option = click.option(
    "--trajectory", "trajectory_path", metavar="FILE",
    help=f"Also write the trajectory ({extensions_text(TRAJECTORY)}; - for stdout, {default_title(TRAJECTORY)}): the "
         "origin (the first map's start pose, at 0 0 0) and every map's end pose. TUM lines are 'timestamp tx ty tz "
         "qx qy qz qw' with the pose id as the timestamp, as evo reads them.")


#: --no-covariances of a command writing local maps (convert, simulate)
no_covariances_option = click.option(
    "--no-covariances", is_flag=True,
    help="Write the spherical variances only, not the maps' full covariances (smaller files; a warning says how "
         "many were dropped).")


def write_trajectory(global_map: GlobalMap, origin_id: int, path: str | None) -> None:
    """Write ``--trajectory`` when given (inside the command's ``with outputs`` block)."""
    if path:
        with options_for(format="--trajectory"):
            mapio.write_trajectory(global_map, origin_id, path, output_format(path, None, TRAJECTORY))


def _remember_json(ctx: click.Context, _parameter: click.Parameter, value: bool) -> None:
    ctx.meta["mapjoin.json"] = value


#: --json of a command that prints a summary: :func:`summary` prints it as one JSON object instead
json_option = click.option(
    "--json", is_flag=True, expose_value=False, callback=_remember_json,
    help="Print the summary as one JSON object on one line (even under -q): on stdout, or on stderr (its last "
         "line) when stdout holds the data (-o -).")


def summary(ctx: click.Context, message: str, fields: dict[str, object], *, data_on_stdout: bool = False) -> None:
    """The command's summary: ``message`` on stderr (unless -q), or with ``--json`` the ``fields`` (plain numbers,
    strings, lists) as one JSON object, on stdout unless ``data_on_stdout``. The counts of repeated warnings
    held back come first, so that the summary is the last line."""
    warnings = (ctx.obj or {}).get("warnings")
    if warnings is not None:
        warnings.summarise()
    if not ctx.meta.get("mapjoin.json"):
        say(ctx, message)
        return
    import json

    plain = {key: None if isinstance(value, float) and not math.isfinite(value) else value
             for key, value in fields.items()}  # JSON has no NaN
    click.echo(json.dumps({"command": ctx.info_name, **plain}, default=lambda value: value.tolist()),  # numpy values
               err=data_on_stdout)


#: the starts of the exact join, :data:`mapjoin.refine.STARTS` (not imported here: it imports scipy.sparse; a test
#: checks that they agree): the fast joins' strategies, and the tree with its top pieces solved exactly
STARTS = (*STRATEGIES, "hierarchical")
#: the order of the fast joins, which is also the start of the exact join: one option, two names
strategy_option = click.option(
    "--strategy", "--start", "strategy", type=click.Choice(STARTS), default=None,
    show_default="join: sequential; refine, --refine: tree, sequential with --on-inconsistent skip",
    help="Order of the fast joins (and so the start of the exact join, --refine / refine): each map onto the "
         "global map so far, or neighbours pairwise, level by level (faster, less accurate: README, "
         "'Strategies'). On long runs with loop closures the sequential start drifts and the exact solve can "
         "creep or end in a worse local minimum, where the tree's start reaches the optimum. hierarchical "
         "(exact solve only): the tree with the root's two pieces solved exactly before their join, for very "
         "long runs where the tree's start does not converge (slower: docs, 'Hierarchical start').")
#: refine's default start, :data:`mapjoin.refine.DEFAULT_START` (not imported here: it imports scipy.sparse;
#: a test checks that they agree)
REFINE_START = "tree"


def start_of(strategy: str | None, refining: bool, on_inconsistent: str) -> str:
    """The fast join's strategy: the one given, else for a join that starts the exact solve refine's
    default start (sequential under --on-inconsistent skip, which re-joins the chain map by map, as
    :func:`mapjoin.refine.default_start`), else sequential."""
    if strategy == "hierarchical" and not refining:
        raise click.UsageError("--start hierarchical solves the tree's top pieces exactly: it starts the exact "
                               "join only; add --refine")
    if strategy is not None:
        return strategy
    return REFINE_START if refining and on_inconsistent != "skip" else "sequential"


jobs_option = click.option(
    "-j", "--jobs", type=PlainInt(min=1), default=1, show_default=True,
    help="Processes for the independent joins of the tree's lower levels (--strategy tree).")
report_option = click.option(
    "--report", "report_path", metavar="FILE",
    help=f"Per-join report of the fast join ({TABLE_EXTENSIONS}): common/new features, a, C_phi, minima, phi*, "
         "the consistency check (chi2, dof, variance_factor, p, flag, action).")


def check_jobs(jobs: int, strategy: str) -> None:
    """--jobs runs only the tree's independent joins: with another strategy it would do nothing."""
    if jobs > 1 and strategy != "tree":
        raise click.UsageError("--jobs runs the tree's independent joins in parallel; add --strategy tree")


TOLERANCE_RANGE = Range("tolerance", 0.0, 1.0)  # relative: beyond 1, every step would stop the solve
#: the exact solve's own options, by parameter name (join takes them with --refine, refine always)
REFINE_OPTIONS = {"max_iterations": "--max-iterations", "tolerance": "--tolerance",
                  "no_covariances": "--no-covariances"}


def refine_options(command: Callable) -> Callable:
    """The options of the exact solve (:func:`mapjoin.refine.refine`), declared once for ``refine`` and
    ``join --refine``."""
    for option in reversed((
            click.option("--max-iterations", type=PlainInt(min=0), default=100, show_default=True,
                         help="At most this many (accepted) Gauss-Newton/Newton steps of the exact solve."),
            click.option("--tolerance", type=FiniteFloat(TOLERANCE_RANGE), show_default="1e-12",
                         help="Stop the exact solve when a full undamped step (not shortened after a rejected "
                              "one) changes chi^2 by at most this (relative) or moves no unknown by more than this "
                              "times (1 + largest |unknown|); 0 runs to chi^2's rounding."),
            click.option("--no-covariances", is_flag=True,
                         help="Skip the exact join's marginal covariances (faster): no cov columns, the fast "
                              "join's variances."))):
        command = option(command)
    return command


def solve_arguments(max_iterations: int, tolerance: float | None, no_covariances: bool) -> dict:
    """The keyword arguments of :func:`mapjoin.refine.join_and_refine` that :func:`refine_options` give
    (no --tolerance: the solver's own default, looked up there, so that a command that does not refine never
    imports scipy.sparse to show or fill it)."""
    return {"max_iterations": max_iterations, "covariances": not no_covariances,
            **({"tolerance": tolerance} if tolerance is not None else {})}


def given(ctx: click.Context, parameters: dict[str, str]) -> list[str]:
    """The options among ``parameters`` (parameter name -> option) given on the command line."""
    return [option for name, option in parameters.items()
            if ctx.get_parameter_source(name) not in (None, click.core.ParameterSource.DEFAULT)]


def iteration_printer(ctx: click.Context) -> Callable[[int, float], None] | None:
    """With -v, the exact solve's chi^2 after every step on stderr, and its change: on a long chain the last
    steps change it by 1e-11 relative, below the ten digits shown, while they move the estimate by metres
    (docs/method.md#solver); else None."""
    if not ctx.obj["verbose"]:
        return None
    previous: list[float] = []

    def show(iteration: int, cost: float) -> None:
        change = f" (change {cost - previous[0]:+.3g})" if previous else ""
        previous[:] = [cost]
        say(ctx, f"iteration {iteration}: chi^2 = {cost:.10g}{change}")

    return show


def read_local_maps(inputs: tuple[str, ...], input_format: str | None, outputs: mapio.Outputs) -> list[LocalMap]:
    """The local maps of ``inputs`` (files, globs, folders, -), checked against the command's ``outputs``
    first: the one input resolver of every command that reads local maps, so that they all take the same
    inputs (a folder of two maps for check-minima as for plot-join)."""
    paths = outputs.guard(mapio.resolve_inputs(inputs))
    with options_for(format="--input-format"):
        return mapio.read_map_paths(paths, format=input_format)


@contextlib.contextmanager
def local_map_stream(inputs: tuple[str, ...], input_format: str | None, outputs: mapio.Outputs
                     ) -> Iterator[Iterator[LocalMap]]:
    """:func:`read_local_maps` one map at a time (``join`` reads them as it joins them): the maps are read
    inside the ``with`` block, so their errors name the command's options as :func:`read_local_maps`' do."""
    paths = outputs.guard(mapio.resolve_inputs(inputs))
    with options_for(format="--input-format"):
        yield mapio.iter_map_paths(paths, format=input_format)


def confirm(maps: list[LocalMap], result: JoinResult, strategy: Strategy, gate: float) -> JoinResult:
    """:func:`mapjoin.confirmation.confirm`, the ``confirm`` hook ``join`` and ``refine`` pass on: its module is
    imported when a join calls it, i.e. when a join is flagged (most joins of the real datasets pass, and need
    neither it nor the exact solve)."""
    from ..confirmation import confirm as confirm_flagged

    return confirm_flagged(maps, result, strategy, gate)


def say(ctx: click.Context, message: str) -> None:
    """A human message on stderr, unless -q."""
    if not ctx.obj["quiet"]:
        click.echo(message, err=True)


@contextlib.contextmanager
def progress_bar(ctx: click.Context, length: int | None, label: str) -> Iterator[Callable[[int], None] | None]:
    """A progress callback drawing a bar on stderr when it is a terminal (and not -q), else None.
    The bar's line ends when the count reaches ``length``, so that what the command does and
    says next (e.g. a refinement after the fast join) comes below it. ``length`` None (a stream, whose
    length is known only at its end): a count of what is done, redrawn at most ten times a second."""
    if ctx.obj["quiet"] or not sys.stderr.isatty() or (length is not None and length < 2):
        yield None
        return
    if length is None:
        shown = [0.0, 0]

        def count(done: int) -> None:
            now = time.monotonic()
            if now - shown[0] >= 0.1:
                shown[0], shown[1] = now, done
                click.echo(f"\r\x1b[K{label}: {done}", err=True, nl=False)

        yield count
        if shown[1]:
            click.echo("\r\x1b[K", err=True, nl=False)
        return
    with click.progressbar(length=length, label=label, file=sys.stderr) as bar:
        done = 0

        def update(count: int) -> None:
            nonlocal done
            bar.update(count - done)
            done = count
            if done >= length and not bar.hidden:
                bar.render_finish()
                bar.hidden = True          # finished: nothing more to draw, not even on leaving

        yield update


def check_output_formats(*targets: tuple[str | None, str | None, Kind, str | None]) -> None:
    """Refuse, before any input is read, an output whose format (explicit, else its extension's) cannot hold its
    data, e.g. a table as .mat, a global map as .tum, a .mat file on stdout: the writers would find it only after
    the work, below its warnings. ``targets``: (path or None, explicit format, kind, the option that would settle
    it or None)."""
    from ..io import registry

    for path, explicit, kind, option in targets:
        if path:
            with options_for(**({"format": option} if option else {})):
                name = mapio.source_name(path, "<stdout>")
                fmt, _ = registry.codec(output_format(path, explicit, kind), kind, name, writing=True)
                if fmt.binary and mapio.is_special(path):
                    raise InputError(f"a {fmt.extensions[0]} file cannot be written to stdout or a special file; "
                                     "give a file path", name)


def output_format(path: str, explicit: str | None, kind: Kind) -> str:
    """The format to write ``path`` in: ``explicit``, else ``kind``'s default for stdout or a special file (a
    device, a FIFO: written through), else its extension's."""
    if explicit:
        return explicit
    return kind.default if mapio.is_special(path) else mapio.detect_format(path)


@contextlib.contextmanager
def options_for(**options: str) -> Iterator[None]:
    """Library errors about an argument of the calls inside name the command's option for it instead
    (``options``: argument -> option): an error that the argument would settle (:attr:`InputError.argument`,
    e.g. ``format``) and an error in the argument's value (``where="join="``)."""
    try:
        yield
    except InputError as error:
        if error.argument in options:
            raise error.naming(options[error.argument]) from None
        argument = (error.where or "").removesuffix("=")
        if error.source is None and error.where != argument and argument in options:
            raise InputError(error.detail, None, options[argument]) from None
        raise


def exit_if_not_converged(ctx: click.Context, result: RefineResult, output: str) -> None:
    """A refine that stopped without converging must not look like success: one line on stderr (under -q
    too) and exit code 3; the output written holds the last iterate."""
    if result.converged:
        return
    from ..errors import EXIT_NOT_CONVERGED

    where = "stdout" if output == "-" else output
    # the tree's pieces keep their drift until the top join, where Gauss-Newton can creep (docs/method.md#solver)
    hint = "; try --start hierarchical" if result.start == "tree" else ""
    click.echo(f"mapjoin: error: the exact join did not converge ({result.reason} after {result.iterations} "
               f"iterations, chi^2 = {result.cost:.10g}): {where} holds the last iterate, not the optimum{hint}",
               err=True)
    ctx.exit(EXIT_NOT_CONVERGED)


def warn_if_doubtful(result: RefineResult) -> None:
    """Warn when the exact join's chi^2 is outside the 99.9% interval
    of its chi-square distribution (skipped under -q, which silences warnings: the interval's quantiles cost
    O(dof) a step, 0.1-0.4 s in all at 10^6 degrees of freedom, so a chi^2 certainly inside it is not asked for
    them either)."""
    dof = result.degrees_of_freedom
    if dof <= 0 or not log.isEnabledFor(logging.WARNING):
        return
    from ..evaluation import chi2_surely_inside, chi2_verdict

    if chi2_surely_inside(result.cost, dof):
        return

    verdict = chi2_verdict([result.cost], [dof])
    if not verdict.outside.size:
        return
    which = ("pessimistic (too large)" if verdict.too_small[0]
             else "optimistic (too small), or the maps disagree (outliers, wrong data association)")
    log.warning("final chi^2 = %.6g is outside the %g%% interval [%.6g, %.6g] of a chi-square with %d degrees "
                "of freedom (%d residuals - %d unknowns; chi^2/dof = %.3f): the local maps' covariances look %s",
                result.cost, 100 * verdict.level, verdict.low[0], verdict.high[0], dof, result.residuals,
                result.unknowns, result.cost / dof, which)


def join_counts(report: Iterable[JoinRecord]) -> dict[str, int]:
    """The report's counts the summaries give, in one pass over its records (a streamed join's report makes
    each record as it is taken): ``two_minima``, ``inconsistent`` (flagged), and the skip policy's
    ``features only`` and ``left out`` joins."""
    counts = dict.fromkeys(("two_minima", "inconsistent", "features only", "left out"), 0)
    for r in report:
        counts["two_minima"] += r.minima == 2
        counts["inconsistent"] += bool(r.flag)
        if r.action in counts:
            counts[r.action] += 1
    return counts


def inconsistency(counts: dict[str, int]) -> str:
    """The summary's count of flagged joins, and what the skip policy did with them (``counts``:
    :func:`join_counts`)."""
    text = f"{counts['inconsistent']} inconsistent"
    unlinked, left_out = counts["features only"], counts["left out"]
    if unlinked or left_out:
        text += f": {unlinked} joined by features alone, {left_out} left out"
    return text
