"""``mapjoin plot``, ``plot-minima``, ``plot-join``: figures of maps, of Theorem 2, of one join.

matplotlib is needed only here (``pip install 'mapjoin-slam[plot]'``) and is imported when a
figure is drawn, so the other commands start without it.
"""

from __future__ import annotations

import io
import os

import click

from .. import io as mapio
from .. import plot as figures
from ..errors import MapjoinError
from ..maps import GlobalMap
from . import common, main
from .common import covariance_option, input_format_option, inputs_argument, solver_option

figure_option = click.option("-o", "--output", required=True, metavar="FILE",
                              help="Figure file; its extension chooses the format: .png, .svg or .pdf.")


@main.command("plot")
@click.argument("maps", nargs=-1, required=True, metavar="MAP [MAP2 ...]")
@figure_option
@click.option("--truth", "truth_path", metavar="TRUTH",
              help="Also draw the ground truth: a truth file from `mapjoin simulate`, its folder, or an "
                   "I-SLSJF simulation folder (store_robotTrue.mat, store_beaconsTrue.mat).")
@click.option("--ellipses", is_flag=True,
              help="Draw the 95% uncertainty region of every feature and pose: ellipses from full "
                   "covariances (refine, join --refine); a fast join has weights, not covariances: circles of "
                   "that scale from its spherical weights, labelled so.")
@click.option("--label", "labels", multiple=True, metavar="TEXT",
              help="Legend label of each MAP, in order (repeat; default: the file names).")
@common.json_option
@click.pass_context
def plot(ctx: click.Context, maps: tuple[str, ...], output: str, truth_path: str | None, ellipses: bool,
         labels: tuple[str, ...]) -> None:
    """Draw maps: features, trajectories, uncertainty.

    Several maps are overlaid in distinct styles with a legend, e.g. the fast join against
    the exact one (the paper's Fig. 5). Axes are in metres with equal scales; the
    trajectories start at the origin, the start pose of the first local map. MAP is a
    global map (.csv or .yaml), - for stdin, or a chain of local maps (a folder, a glob,
    a file), drawn chained by their start poses, without a join: the drift a join
    corrects (--ellipses needs a global map: join them first).

    \b
    Examples:
      mapjoin join ../shared/data/VicPark_200_local_maps -o fast.csv
      mapjoin refine ../shared/data/VicPark_200_local_maps -o exact.csv
      mapjoin plot fast.csv exact.csv --label "fast join" --label exact -o vicpark.png
      mapjoin plot ../shared/data/VicPark_200_local_maps fast.csv -o drift.png
      mapjoin join ../shared/data/535_data_5_local_maps | mapjoin plot - --ellipses \\
          --truth ../shared/data/535_data_5_local_maps -o sim535.pdf
    """
    figures.figure_format(output)
    if labels and len(labels) != len(maps):
        raise click.UsageError(f"give one --label per map: {len(maps)} maps, {len(labels)} labels")
    if list(maps).count("-") + (truth_path == "-") > 1:
        raise click.UsageError("stdin (-) can be read only once")
    outputs = mapio.Outputs(files={"-o": output})
    outputs.guard([*maps, *([truth_path] if truth_path else [])])
    global_maps = [_drawable(path, ellipses) for path in maps]
    truth = mapio.read_truth(truth_path) if truth_path else None
    names = labels or [global_map.name for global_map in global_maps]
    with outputs:
        _say_missing(ctx, figures.save(figures.map_figure(global_maps, names, truth, ellipses), output))
    common.summary(ctx, f"plotted {common.counted(len(global_maps), 'map')}"
                        f"{' and the ground truth' if truth else ''} -> {output}",
                   {"maps": len(global_maps), "truth": truth is not None, "output": output}, data_on_stdout=output == "-")


@main.command("plot-minima")
@click.argument("report", metavar="REPORT")
@figure_option
@common.json_option
@click.pass_context
def plot_minima(ctx: click.Context, report: str, output: str) -> None:
    """Draw a report's joins on Theorem 2's minima diagram.

    The region where a join's 1-D problem has two local minima is shaded (the paper's
    Fig. 3), a on a log scale; each join is a point, those with two minima highlighted and
    numbered, so the figure shows how far each join was from ambiguity. REPORT is the
    table of `mapjoin join --report` (.csv, .yaml or .json), or any CSV/YAML/JSON table
    with columns a and c_phi (e.g. the output of `mapjoin check-minima --batch`); - for stdin.

    \b
    Examples:
      mapjoin join ../shared/data/VicPark_200_local_maps -o vicpark.csv --report joins.csv
      mapjoin plot-minima joins.csv -o minima.png
      mapjoin join examples/sim20 --report - -o global.csv | mapjoin plot-minima - -o minima.svg
    """
    figures.figure_format(output)
    outputs = mapio.Outputs(files={"-o": output})
    outputs.guard([report])
    table = mapio.read_minima_table(report)
    with outputs:
        _say_missing(ctx, figures.save(figures.minima_figure(table), output))
    what = "join" if table.join is not None else "problem"
    common.summary(ctx, f"plotted {common.counted(len(table.a), what)} -> {output}",
                   {what + "s": len(table.a), "output": output},
                   data_on_stdout=output == "-")


@main.command("plot-join")
@inputs_argument
@figure_option
@click.option("--join", "join_number", type=common.PlainInt(min=1), metavar="K",
              help="Which join of the chain INPUTS: join K places map K+1 (the `join` column of a report of "
                   "`mapjoin join`, sequential strategy). Default: 1 when INPUTS are two maps.")
@covariance_option
@solver_option
@input_format_option
@common.json_option
@click.pass_context
def plot_join(ctx: click.Context, inputs: tuple[str, ...], output: str, join_number: int | None, covariance: str,
              solver: str, input_format: str | None) -> None:
    """Draw one join's cost curve f1(phi) and its minima.

    f1 is drawn over [z_phi - pi, z_phi + pi): the paper's shifted cosine (the
    features' term) plus a parabola (the orientation link to the odometry z_phi). Both
    terms are drawn, with every local minimum, phi*, z_phi and the features' own
    optimum phi0, and a zoom on phi* when its basin is narrow. INPUTS are two local maps (MAP_A, then MAP_B starting at its end
    pose), or a chain of local maps with --join K: the global map of maps 1..K joined
    sequentially, then map K+1, as `mapjoin join` (--strategy sequential, the default)
    does with the same --covariance and --solver.

    \b
    Examples:
      mapjoin plot-join examples/two-minima -o two-minima.png
      mapjoin plot-join ../shared/data/VicPark_200_local_maps --join 42 -o join42.pdf
      mapjoin plot-join examples/sim20 --join 3 --covariance identity -o join3.svg
    """
    figures.figure_format(output)
    outputs = mapio.Outputs(files={"-o": output})
    maps = common.read_local_maps(inputs, input_format, outputs)
    if join_number is None:
        if len(maps) != 2:
            raise click.UsageError(f"{len(maps)} maps: choose a join with --join K (1 to {len(maps) - 1}; "
                                   "K is the join column of `mapjoin join --report`)")
        join_number = 1
    with common.options_for(join="--join"):
        problem = figures.join_problem(maps, join_number, covariance)
    curve = figures.join_curve(problem, solver)
    incoming = maps[join_number]
    title = (f"join {join_number}: {_short(incoming.name)} onto "
             f"{_short(maps[0].name) if join_number == 1 else f'maps 1..{join_number}'} "
             f"({len(problem.z0)} common features, covariance {covariance})")
    with outputs:
        _say_missing(ctx, figures.save(figures.join_figure(curve, title), output))
    common.summary(ctx, f"plotted join {join_number} ({common.counted(len(curve.minima), 'minimum', 'minima')}, "
                        f"phi* = {curve.minima[0][0]:+.6f} rad) -> {output}",
                   {"join": join_number, "minima": len(curve.minima), "phi": curve.minima[0][0], "output": output},
                   data_on_stdout=output == "-")


def _drawable(argument: str, ellipses: bool) -> GlobalMap:
    """MAP as a global map: read as one, else read as local maps (a folder, a glob, a local-map file, stdin)
    chained by their start poses; the global map's error when it is neither."""
    source: str | io.StringIO = argument
    if argument == "-":  # read once, tried as both
        source = io.StringIO(mapio.read_text("-", "<stdin>"))
        source.name = "<stdin>"
    single = not (os.path.isdir(argument) or any(character in argument for character in "*?["))
    if single:  # a file, -, or nothing there (the global map's error says so)
        try:
            return mapio.read_global_map(source)
        except MapjoinError as error:
            not_global = error
            if isinstance(source, io.StringIO):
                source.seek(0)
    try:
        local_maps = (mapio.read_map_file(source, name="<stdin>") if isinstance(source, io.StringIO)
                      else mapio.read_map_paths(mapio.resolve_inputs([argument])))
    except MapjoinError:
        if single:
            raise not_global from None
        raise
    if ellipses:
        raise click.UsageError(f"{argument} holds local maps: --ellipses draws a global map's uncertainty; "
                               "join them first (mapjoin join MAPS -o global.csv)")
    return figures.chained_local_maps(local_maps, f"{argument} (local maps chained, not joined)")


def _short(name: str) -> str:
    """A map's name without its folders, for a title."""
    return os.path.basename(name) or name


def _say_missing(ctx: click.Context, missing: str) -> None:
    """One warning line for the characters the figure's font could not draw (drawn as boxes)."""
    if missing:
        common.say(ctx, "warning: the font has no glyph for " + ", ".join(f"U+{ord(c):04X}" for c in missing)
                   + " (drawn as a box)")
