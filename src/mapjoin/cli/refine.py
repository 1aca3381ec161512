"""``mapjoin refine``: the exact least-squares join (the problem I-SLSJF solves)."""

from __future__ import annotations

import time

import click

from .. import io as mapio
from ..io.registry import GLOBAL_MAP, TABLE, TRAJECTORY
from . import common, main
from .common import (covariance_option, gate_option, global_map_format_option, global_map_output_option,
                     input_format_option, inputs_argument, json_option, on_inconsistent_option, progress_bar, solver_option, trajectory_option)


@main.command()
@inputs_argument
@global_map_output_option
@global_map_format_option
@common.report_option
@covariance_option
@solver_option
@common.strategy_option
@common.jobs_option
@common.refine_options
@gate_option
@on_inconsistent_option
@input_format_option
@trajectory_option
@json_option
@click.pass_context
def refine(ctx: click.Context, inputs: tuple[str, ...], output: str, output_format: str | None,
           report_path: str | None, covariance: str, solver: str, strategy: str, jobs: int, max_iterations: int,
           tolerance: float | None, no_covariances: bool, gate: float, on_inconsistent: str,
           input_format: str | None, trajectory_path: str | None) -> None:
    """Join local maps exactly: the least-squares optimum.

    Solves the problem I-SLSJF solves: all end poses and features at once, each local
    map weighted by its full covariance, by sparse Gauss-Newton with Levenberg-Marquardt
    safeguards (Newton steps near the optimum) from the fast join (--start, by default the
    tree join, which leads the solve to the optimum where the sequential one may not; made with
    --covariance, --solver and --jobs as `mapjoin join` makes it; --report writes that
    fast join's per-join report, the table `join --report` writes). The global
    map holds the marginal covariance of every feature and pose (cov_* columns in CSV,
    cov in YAML) unless --no-covariances. With -v, chi^2 and its change are printed after
    every step; a warning says when the final chi^2 is implausible for its degrees of freedom. A
    summary (maps, features, poses, the fast join's minima, iterations, chi^2, time) ends
    on stderr; on a terminal a progress bar shows the fast join.

    \b
    Examples:
      mapjoin refine ../shared/data/VicPark_200_local_maps -o vicpark_exact.csv
      mapjoin -v refine 'maps/localmap_*.yaml' --format yaml -o exact.yaml
      mapjoin simulate -o - | mapjoin refine - --no-covariances > exact.csv
      mapjoin refine ../shared/data/VicPark_6898_local_maps --jobs 2 -o vp_exact.csv
      mapjoin refine ../shared/data/VicPark_200_local_maps --report joins.csv -o exact.csv
    """
    from ..refine import join_and_refine  # scipy.sparse: imported only when refining

    given, strategy = strategy, common.start_of(strategy, True, on_inconsistent)
    common.check_jobs(jobs, strategy)
    outputs = mapio.Outputs(files={"-o": output, "--report": report_path, "--trajectory": trajectory_path})
    common.check_output_formats((output, output_format, GLOBAL_MAP, "--format"), (report_path, None, TABLE, None),
                                (trajectory_path, None, TRAJECTORY, "--trajectory"))
    if on_inconsistent == "skip" and strategy != "sequential":
        raise click.UsageError("--on-inconsistent skip re-joins the chain map by map; use --start sequential")
    start = time.perf_counter()
    maps = common.read_local_maps(inputs, input_format, outputs)
    read = time.perf_counter() - start
    with progress_bar(ctx, len(maps), "fast join") as progress:
        result = join_and_refine(maps, start=given and strategy, covariance=covariance, solver=solver,
                                 jobs=jobs, join_progress=progress, progress=common.iteration_printer(ctx),
                                 gate=gate, on_inconsistent=on_inconsistent, confirm=common.confirm,
                                 **common.solve_arguments(max_iterations, tolerance, no_covariances))
    elapsed = time.perf_counter() - start
    with outputs, common.options_for(format="--format"):
        mapio.write_global_map(result.global_map, output, common.output_format(output, output_format, GLOBAL_MAP))
        if report_path:
            mapio.write_table(result.fast_join.report, report_path, common.output_format(report_path, None, TABLE))
        common.write_trajectory(result.global_map, maps[0].start_id, trajectory_path)
    common.warn_if_doubtful(result)
    g, joins = result.global_map, result.fast_join.report
    abandoned = f" (the {result.abandoned} join's solve did not converge)" if result.abandoned else ""
    counts = common.join_counts(joins)
    two = counts["two_minima"]
    common.summary(ctx, f"refined {common.counted(len(maps), 'map')}: {common.counted(len(g.feature_ids), 'feature')}, "
             f"{common.counted(len(g.pose_ids), 'pose')}, {common.counted(len(joins), 'join')} ({two} with two "
             f"minima, {common.inconsistency(counts)}), from the {result.start} join{abandoned}, "
             f"{common.counted(result.iterations, 'iteration')}, chi^2 "
             f"{result.costs[0]:.6f} -> {result.cost:.6f} ({result.reason}), {elapsed:.3f} s (read {read:.3f} s, fast join "
             f"{result.initial_seconds:.3f} s, solve {result.seconds:.3f} s, covariances "
             f"{result.covariance_seconds:.3f} s) -> {'stdout' if output == '-' else output}",
                   {"maps": len(maps), "features": len(g.feature_ids), "poses": len(g.pose_ids), "joins": len(joins),
                    "start": result.start, "abandoned_start": result.abandoned, "two_minima": two,
                    "inconsistent": counts["inconsistent"],
                    "iterations": result.iterations, "chi2_initial": result.costs[0],
                    "chi2": result.cost, "reason": result.reason, "converged": result.converged,
                    "degrees_of_freedom": result.degrees_of_freedom, "seconds": elapsed, "read_seconds": read,
                    "output": output}, data_on_stdout=output == "-" or trajectory_path == "-")
    common.exit_if_not_converged(ctx, result, output)
