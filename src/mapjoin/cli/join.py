"""``mapjoin join``: join local maps into a global map."""

from __future__ import annotations

import time

import click

from .. import io as mapio
from ..io.registry import GLOBAL_MAP, TABLE, TRAJECTORY
from ..joining import JoinResult, join as join_maps
from ..streaming import KEEP_VALUES, KeptMaps, join_stream
from ..maps import Range
from . import common, main
from .common import (TABLE_EXTENSIONS, covariance_option, gate_option, global_map_format_option,
                     global_map_output_option, input_format_option, inputs_argument, json_option,
                     on_inconsistent_option, progress_bar, say, solver_option, trajectory_option)

ASSOCIATION_GATE = Range("chi-square levels", 0.5, 0.999999)
#: association.DEFAULT_GATE, written out so that a join without --associate does not import the association
#: module (~10 ms of every join's start-up); tests/test_startup.py checks that the two agree
DEFAULT_ASSOCIATION_GATE = 0.999


@main.command()
@inputs_argument
@global_map_output_option
@global_map_format_option
@common.report_option
@covariance_option
@solver_option
@common.strategy_option
@common.jobs_option
@click.option("--refine", "exact", is_flag=True,
              help="Then refine to the exact least-squares join (as `mapjoin refine`), with marginal "
                   "covariances unless --no-covariances; the exact solve's options below need it.")
@common.refine_options
@gate_option
@on_inconsistent_option
@click.option("--associate", is_flag=True,
              help="Feature ids are local to each map: match each map's features with the map so far "
                   "(Mahalanobis gate, joint compatibility; docs/joining.md, 'Data association').")
@click.option("--gate-association", "association_gate", type=common.FiniteFloat(ASSOCIATION_GATE),
              default=DEFAULT_ASSOCIATION_GATE, show_default=True,
              help="Chi-square level of the association's gate and joint test (--associate).")
@click.option("--associations", "associations_path", metavar="FILE",
              help=f"With --associate: each input feature's global id ({TABLE_EXTENSIONS}): map,local_id,global_id.")
@input_format_option
@trajectory_option
@json_option
@click.pass_context
def join(ctx: click.Context, inputs: tuple[str, ...], output: str, output_format: str | None,
         report_path: str | None, covariance: str, solver: str, strategy: str, jobs: int, exact: bool,
         max_iterations: int, tolerance: float | None, no_covariances: bool, gate: float, on_inconsistent: str,
         associate: bool, association_gate: float, associations_path: str | None, input_format: str | None,
         trajectory_path: str | None) -> None:
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
    given, strategy = strategy, common.start_of(strategy, exact, on_inconsistent)
    common.check_jobs(jobs, strategy)
    if not exact and (solve_options := common.given(ctx, common.REFINE_OPTIONS)):
        raise click.UsageError(f"{solve_options[0]} is an option of the exact solve; add --refine")
    if on_inconsistent == "skip" and strategy != "sequential":
        raise click.UsageError("--on-inconsistent skip re-joins the chain map by map; use --strategy sequential")
    if not associate and (associations_path or ctx.get_parameter_source("association_gate").name != "DEFAULT"):
        raise click.UsageError("--associations and --gate-association need --associate")
    if associate and (jobs > 1 or exact or on_inconsistent == "skip"):
        raise click.UsageError("--associate runs the join in one process, without --refine and without "
                               "--on-inconsistent skip; drop those (refine the written map's inputs with their ids)")
    outputs = mapio.Outputs(files={"-o": output, "--report": report_path, "--trajectory": trajectory_path,
                                   "--associations": associations_path})
    common.check_output_formats((output, output_format, GLOBAL_MAP, "--format"), (report_path, None, TABLE, None),
                                (trajectory_path, None, TRAJECTORY, "--trajectory"),
                                (associations_path, None, TABLE, None))
    start = time.perf_counter()
    if strategy == "sequential" and not (exact or associate or on_inconsistent == "skip"):
        with common.local_map_stream(inputs, input_format, outputs) as stream, \
                progress_bar(ctx, None, "maps joined") as progress:  # read as they are joined: a count, not a bar
            # stdin, a FIFO or a pipe give their data once: its joins are not confirmed, its maps not kept
            once = next((path for path in mapio.resolve_inputs(inputs) if mapio.read_once(path)), None)
            kept = KeptMaps(stream, 0 if once else KEEP_VALUES)   # for the confirmation: not read again if few
            streamed = join_stream(kept, covariance, solver, progress, gate=gate, on_inconsistent=on_inconsistent,
                                   confirm=lambda joined: confirm_stream(ctx, joined, inputs, input_format, outputs,
                                                                         gate, once, kept))
        result, global_map, read = streamed.result, streamed.result.global_map, streamed.read_seconds
        origin_id, count = streamed.origin_id, len(global_map.pose_ids)
    else:
        maps = common.read_local_maps(inputs, input_format, outputs)
        read = time.perf_counter() - start
        origin_id, count = maps[0].start_id, len(maps)
        with progress_bar(ctx, len(maps), "joining") as progress:
            if exact:
                from ..refine import join_and_refine  # scipy.sparse: imported only when refining

                refined = join_and_refine(maps, start=given and strategy, covariance=covariance, solver=solver,
                                          jobs=jobs, join_progress=progress, progress=common.iteration_printer(ctx),
                                          gate=gate, on_inconsistent=on_inconsistent, confirm=common.confirm,
                                          **common.solve_arguments(max_iterations, tolerance, no_covariances))
                result, global_map, strategy = refined.fast_join, refined.global_map, refined.start
            elif associate:
                from ..association import join_associated

                result = join_associated(maps, covariance, solver, strategy, gate=association_gate, progress=progress)
                global_map = result.global_map
            else:
                result = join_maps(maps, covariance, solver, strategy, jobs, progress, gate=gate,
                                   on_inconsistent=on_inconsistent, confirm=common.confirm)
                global_map = result.global_map
    if exact:
        common.warn_if_doubtful(refined)
        say(ctx, f"refined to the exact join: chi^2 {refined.costs[0]:.6f} -> {refined.cost:.6f} in "
                 f"{common.counted(refined.iterations, 'iteration')} ({refined.reason})")
    elapsed = time.perf_counter() - start
    with outputs, common.options_for(format="--format"):
        mapio.write_global_map(global_map, output, common.output_format(output, output_format, GLOBAL_MAP))
        if report_path:
            mapio.write_table(result.report, report_path, common.output_format(report_path, None, TABLE))
        common.write_trajectory(global_map, origin_id, trajectory_path)
        if associations_path:
            mapio.write_table(result.rows(maps), associations_path,
                              common.output_format(associations_path, None, TABLE))
    if ctx.obj["verbose"]:
        for r in result.report:
            second = f", other minimum at {r.phi2:+.4f} rad" if r.minima == 2 else ""
            say(ctx, f"join {r.join}: {r.map}: {r.common} common, {r.new} new, a={r.a:.6g}, "
                     f"C_phi={r.c_phi:+.4f}, minima={r.minima}, phi*={r.phi:+.6f}{second}")
    counts = common.join_counts(result.report)
    two = counts["two_minima"]
    g = global_map
    abandoned = f" (the {refined.abandoned} join's solve did not converge)" if exact and refined.abandoned else ""
    associated = result.counts._asdict() if associate else {}
    matched = (f", {associated['matched']} features matched ({associated['ambiguous']} left ambiguous, "
               f"{associated['rejected']} rejected)" if associate else "")
    common.summary(ctx, f"joined {common.counted(count, 'map')}: {common.counted(len(g.feature_ids), 'feature')}, "
                        f"{common.counted(len(g.pose_ids), 'pose')}, {common.counted(len(result.report), 'join')} "
                        f"({two} with two minima, {common.inconsistency(counts)}), covariance {covariance}, "
                        f"{strategy}{abandoned}{matched}, read {read:.3f} s, joined {elapsed - read:.3f} s -> "
                        f"{'stdout' if output == '-' else output}",
                   {"maps": count, "features": len(g.feature_ids), "poses": len(g.pose_ids),
                    "joins": len(result.report), "two_minima": two,
                    "inconsistent": counts["inconsistent"], "covariance": covariance,
                    "strategy": strategy, **({"abandoned_start": refined.abandoned} if exact else {}),
                    **({f"associated_{column}": count for column, count in associated.items()}),
                    **({"chi2_initial": refined.costs[0], "chi2": refined.cost, "iterations": refined.iterations,
                        "converged": refined.converged} if exact else {}),
                    "read_seconds": read, "join_seconds": elapsed - read, "output": output},
                   data_on_stdout=output == "-" or trajectory_path == "-")
    if exact:
        common.exit_if_not_converged(ctx, refined, output)


def confirm_stream(ctx: click.Context, result: JoinResult, inputs: tuple[str, ...], input_format: str | None,
                   outputs: mapio.Outputs, gate: float, once: str | None, kept: KeptMaps) -> JoinResult:
    """The streamed join's flags confirmed on the exact problem, on its maps as ``kept`` or read again from files
    (not from ``once``, stdin, a FIFO or a pipe, which give their data once: read again, they would block or give
    none)."""
    from ..confirmation import confirm_streamed  # join_stream calls this only when a join is flagged

    maps = kept.maps
    read = (None if once else (lambda: maps) if maps is not None else
            (lambda: common.read_local_maps(inputs, input_format, outputs)))
    confirmed, unconfirmed = confirm_streamed(result, read, gate,
                                              "stdin" if once == mapio.STDIN else f"{once}, read once")
    if unconfirmed:
        say(ctx, unconfirmed)
    return confirmed
