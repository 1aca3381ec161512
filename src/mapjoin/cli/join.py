"""``mapjoin join``: join local maps into a global map."""

from __future__ import annotations

import time

import click

from .. import io as mapio
from ..io.registry import GLOBAL_MAP, TABLE
from ..association import DEFAULT_GATE
from ..joining import STRATEGIES, join as join_maps
from ..maps import Range
from . import common, main

ASSOCIATION_GATE = Range("chi-square levels", 0.5, 0.999999)
from .common import (TABLE_EXTENSIONS, covariance_option, global_map_format_option, global_map_output_option,
                     input_format_option, inputs_argument, progress_bar, say, solver_option)


@main.command()
@inputs_argument
@global_map_output_option
@global_map_format_option
@click.option("--report", "report_path", metavar="FILE",
              help=f"Per-join report ({TABLE_EXTENSIONS}): common/new features, a, C_phi, minima, phi*.")
@covariance_option
@solver_option
@click.option("--strategy", type=click.Choice(STRATEGIES), default="sequential", show_default=True,
              help="Order of the joins: each map onto the global map so far, or neighbours pairwise, "
                   "level by level (faster, less accurate: README, 'Strategies').")
@click.option("-j", "--jobs", type=click.IntRange(min=1), default=1, show_default=True,
              help="Processes for the independent joins of the tree's lower levels (--strategy tree).")
@click.option("--refine", "exact", is_flag=True,
              help="Then refine to the exact least-squares join (as `mapjoin refine`), with covariances.")
@click.option("--associate", is_flag=True,
              help="Feature ids are local to each map: match each map's features with the map so far "
                   "(Mahalanobis gate, joint compatibility; README, 'Data association').")
@click.option("--gate-association", "gate", type=common.FiniteFloat(ASSOCIATION_GATE), default=DEFAULT_GATE,
              show_default=True, help="Chi-square level of the association's gate and joint test (--associate).")
@click.option("--associations", "associations_path", metavar="FILE",
              help=f"With --associate: each input feature's global id ({TABLE_EXTENSIONS}): map,local_id,global_id.")
@input_format_option
@click.pass_context
def join(ctx: click.Context, inputs: tuple[str, ...], output: str, output_format: str | None,
         report_path: str | None, covariance: str, solver: str, strategy: str, jobs: int, exact: bool,
         associate: bool, gate: float, associations_path: str | None, input_format: str | None) -> None:
    """Join a chain of local maps into one global map.

    Map k must start at the end pose of map k-1; the global frame is the start pose of
    the first map. Each join is certified: the report says how many local minima
    (1 or 2, Theorem 2) its 1-D problem had and which one was taken.

    \b
    Examples:
      mapjoin join ../shared/data/VicPark_200_local_maps -o vicpark.csv --report joins.csv
      mapjoin join 'maps/localmap_*.yaml' --covariance identity --format yaml
      mapjoin simulate -o - | mapjoin join - > global.csv
      mapjoin join ../shared/data/VicPark_6898_local_maps --strategy tree --jobs 2 -o vp.csv
      mapjoin join ../shared/data/DLR_200_local_maps --refine -o dlr_exact.yaml
      mapjoin join maps/ --associate --associations ids.csv -o global.csv
    """
    if jobs > 1 and strategy != "tree":
        raise click.UsageError("--jobs runs the tree's independent joins in parallel; add --strategy tree")
    if not associate and (associations_path or ctx.get_parameter_source("gate").name != "DEFAULT"):
        raise click.UsageError("--associations and --gate-association need --associate")
    if associate and (jobs > 1 or exact):
        raise click.UsageError("--associate runs the join in one process and without --refine; "
                               "drop --jobs/--refine (refine the written map's inputs with their ids instead)")
    outputs = mapio.Outputs(files={"-o": output, "--report": report_path, "--associations": associations_path})
    paths = outputs.guard(mapio.resolve_inputs(inputs))
    start = time.perf_counter()
    with common.options_for(format="--input-format"):
        maps = mapio.read_map_paths(paths, format=input_format)
    read = time.perf_counter() - start
    with progress_bar(ctx, len(maps), "joining") as progress:
        if exact:
            from ..refine import join_and_refine  # scipy.sparse: imported only when refining

            refined = join_and_refine(maps, start=strategy, covariance=covariance, solver=solver, jobs=jobs,
                                      join_progress=progress)
            result, global_map = refined.fast_join, refined.global_map
        elif associate:
            from ..association import join_associated

            result = join_associated(maps, covariance, solver, strategy, gate=gate, progress=progress)
            global_map = result.global_map
        else:
            result = join_maps(maps, covariance, solver, strategy, jobs, progress)
            global_map = result.global_map
    if exact:
        common.warn_if_doubtful(refined)
        say(ctx, f"refined to the exact join: chi^2 {refined.costs[0]:.6f} -> {refined.cost:.6f} in "
                 f"{refined.iterations} iterations ({refined.reason})")
    elapsed = time.perf_counter() - start
    with outputs, common.options_for(format="--format"):
        mapio.write_global_map(global_map, output, common.output_format(output, output_format, GLOBAL_MAP))
        if report_path:
            mapio.write_table(result.report, report_path, common.output_format(report_path, None, TABLE))
        if associations_path:
            mapio.write_table(result.rows(maps), associations_path,
                              common.output_format(associations_path, None, TABLE))
    if ctx.obj["verbose"]:
        for r in result.report:
            second = f", other minimum at {r.phi2:+.4f} rad" if r.minima == 2 else ""
            say(ctx, f"join {r.join}: {r.map}: {r.common} common, {r.new} new, a={r.a:.6g}, "
                     f"C_phi={r.c_phi:+.4f}, minima={r.minima}, phi*={r.phi:+.6f}{second}")
    two = sum(r.minima == 2 for r in result.report)
    g = global_map
    say(ctx, f"joined {len(maps)} maps: {len(g.feature_ids)} features, {len(g.pose_ids)} poses, "
             f"{len(result.report)} joins ({two} with two minima), covariance {covariance}, {strategy}, "
             f"read {read:.3f} s, joined {elapsed - read:.3f} s -> {'stdout' if output == '-' else output}")
    if exact:
        common.exit_if_not_converged(ctx, refined, output)
