"""``mapjoin refine``: the exact least-squares join (the problem I-SLSJF solves)."""

from __future__ import annotations

import time

import click

from .. import io as mapio
from ..io.registry import GLOBAL_MAP
from ..joining import STRATEGIES
from ..maps import Range
from . import common, main
from .common import (global_map_format_option, global_map_output_option, input_format_option, inputs_argument,
                     json_option, progress_bar, say, trajectory_option)


def _default_tolerance() -> float:
    """refine's default stopping tolerance (asked for only when the command runs: refine imports scipy)."""
    from ..refine import TOLERANCE

    return TOLERANCE


TOLERANCE_RANGE = Range("tolerance", 0.0, 1.0)  # relative: beyond 1, every step would stop the solve


@main.command()
@inputs_argument
@global_map_output_option
@global_map_format_option
@click.option("--max-iterations", type=click.IntRange(min=0), default=100, show_default=True,
              help="At most this many (accepted) Gauss-Newton/Newton steps.")
@click.option("--tolerance", type=common.FiniteFloat(TOLERANCE_RANGE), default=lambda: _default_tolerance(), show_default="1e-12",
              help="Stop when a step changes chi^2 by at most this (relative) or moves no unknown by more "
                   "than this times (1 + largest |unknown|); 0 runs to chi^2's rounding.")
@click.option("--start", "strategy", type=click.Choice(STRATEGIES), default="sequential", show_default=True,
              help="The fast join to start from. On long runs with loop closures the sequential join drifts "
                   "(hundreds of metres over two laps of 3000 simulated maps) and the solve can end in a worse "
                   "local minimum, where the tree's start reaches the optimum (benchmarks/README.md, 'Synthetic "
                   "scale series').")
@click.option("--no-covariances", is_flag=True,
              help="Skip the marginal covariances (faster): no cov columns, the fast join's variances.")
@input_format_option
@trajectory_option
@json_option
@click.pass_context
def refine(ctx: click.Context, inputs: tuple[str, ...], output: str, output_format: str | None,
           max_iterations: int, tolerance: float, strategy: str, no_covariances: bool,
           input_format: str | None, trajectory_path: str | None) -> None:
    """Join local maps exactly: the least-squares optimum.

    Solves the problem I-SLSJF solves: all end poses and features at once, each local
    map weighted by its full covariance, by sparse Gauss-Newton with Levenberg-Marquardt
    safeguards (Newton steps near the optimum) from the fast join (--start). The global
    map holds the marginal covariance of every feature and pose (cov_* columns in CSV,
    cov in YAML) unless --no-covariances. With -v, chi^2 is printed after every step; a
    warning says when the final chi^2 is implausible for its degrees of freedom. A
    summary (maps, features, poses, the fast join's minima, iterations, chi^2, time) ends
    on stderr; on a terminal a progress bar shows the fast join.

    \b
    Examples:
      mapjoin refine ../shared/data/VicPark_200_local_maps -o vicpark_exact.csv
      mapjoin -v refine 'maps/localmap_*.yaml' --format yaml -o exact.yaml
      mapjoin simulate -o - | mapjoin refine - --no-covariances > exact.csv
      mapjoin refine ../shared/data/VicPark_6898_local_maps --start tree -o vp_exact.csv
    """
    from ..refine import join_and_refine  # scipy.sparse: imported only when refining

    outputs = mapio.Outputs(files={"-o": output, "--trajectory": trajectory_path})
    paths = outputs.guard(mapio.resolve_inputs(inputs))
    start = time.perf_counter()
    with common.options_for(format="--input-format"):
        maps = mapio.read_map_paths(paths, format=input_format)

    read = time.perf_counter() - start
    def report(iteration: int, cost: float) -> None:
        say(ctx, f"iteration {iteration}: chi^2 = {cost:.10g}")

    with progress_bar(ctx, len(maps), "fast join") as progress:
        result = join_and_refine(maps, start=strategy, join_progress=progress, max_iterations=max_iterations,
                                 tolerance=tolerance, covariances=not no_covariances,
                                 progress=report if ctx.obj["verbose"] else None)
    elapsed = time.perf_counter() - start
    with outputs, common.options_for(format="--format"):
        mapio.write_global_map(result.global_map, output, common.output_format(output, output_format, GLOBAL_MAP))
        common.write_trajectory(result.global_map, maps[0].start_id, trajectory_path)
    common.warn_if_doubtful(result)
    g, joins = result.global_map, result.fast_join.report
    two = sum(r.minima == 2 for r in joins)
    common.summary(ctx, f"refined {len(maps)} maps: {len(g.feature_ids)} features, {len(g.pose_ids)} poses, "
             f"{len(joins)} joins ({two} with two minima), {result.iterations} iterations, chi^2 "
             f"{result.costs[0]:.6f} -> {result.cost:.6f} ({result.reason}), {elapsed:.3f} s (read {read:.3f} s, fast join "
             f"{result.initial_seconds:.3f} s, solve {result.seconds:.3f} s, covariances "
             f"{result.covariance_seconds:.3f} s) -> {'stdout' if output == '-' else output}",
                   {"maps": len(maps), "features": len(g.feature_ids), "poses": len(g.pose_ids), "joins": len(joins),
                    "two_minima": two, "iterations": result.iterations, "chi2_initial": result.costs[0],
                    "chi2": result.cost, "reason": result.reason, "converged": result.converged,
                    "degrees_of_freedom": result.degrees_of_freedom, "seconds": elapsed, "read_seconds": read,
                    "output": output}, data_on_stdout=output == "-" or trajectory_path == "-")
    common.exit_if_not_converged(ctx, result, output)
