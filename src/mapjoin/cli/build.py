"""``mapjoin build``: local maps from raw odometry and feature observations."""

from __future__ import annotations

import logging
import os
import time
from collections.abc import Sequence

import click
import numpy as np

from .. import io as mapio
from ..errors import InputError
from ..io.registry import GLOBAL_MAP, LOCAL_MAPS
from ..raw import RAW_FORMATS, read_raw
from . import common, main
from .common import format_option, say

log = logging.getLogger("mapjoin")

#: maps built when neither --maps nor --poses-per-map is given (the paper's Victoria Park experiment)
DEFAULT_MAPS = 200


@main.command()
@click.argument("raw_path", metavar="RAW")
@click.option("-o", "--output", required=True, metavar="DIR",
              help="Folder for the maps, one localmap_<k> file each (map k from pose k-1 to pose k); a file name "
                   "with an extension, or -, gets all maps in one stream.")
@click.option("--maps", "map_count", type=common.PlainInt(min=1),
              help=f"Cut the odometry into N maps of (nearly) equal length [default: {DEFAULT_MAPS}, or one per "
                   "step if there are fewer steps]. --maps 1 is the full batch SLAM solution.")
@click.option("--poses-per-map", type=common.PlainInt(min=1),
              help="Instead, a new map every K odometry steps (the last one takes what is left).")
@format_option(LOCAL_MAPS, f"Format of the maps [default: from the -o extension, else {LOCAL_MAPS.default}, which "
                           "keeps the full covariance].")
@click.option("--raw-format", type=click.Choice(RAW_FORMATS),
              help="Format of RAW when its name does not tell it (.mat: vicpark, .g2o: g2o; text is recognised by "
                   "its first tag).")
@click.option("--global-map", "global_path", metavar="FILE",
              help="Also write the full batch solution as a global map (.csv or .yaml): every feature and the "
                   "maps' end poses (pose k ends map k), with marginal covariances; compare it with `mapjoin join "
                   "DIR` (`mapjoin compare`). Every pose: --poses-per-map 1.")
@click.option("-j", "--jobs", type=common.PlainInt(min=1), default=1, show_default=True,
              help="Worker processes: the maps are cut into this many runs of consecutive maps, built in parallel "
                   "(the same maps, to rounding).")
@common.json_option
@click.pass_context
def build(ctx: click.Context, raw_path: str, output: str, map_count: int | None, poses_per_map: int | None,
          output_format: str | None, raw_format: str | None, global_path: str | None, jobs: int) -> None:
    """Build local maps from raw odometry and feature observations.

    The feature ids must be known (data association). RAW is I-SLSJF's preprocessed Victoria Park file (VicPark_clean_data.mat), iSAM text
    (ODOMETRY/LANDMARK lines, covariances) or g2o 2D (VERTEX_SE2, VERTEX_XY, EDGE_SE2,
    EDGE_SE2_XY, information matrices); docs/build.md, "Raw data formats", says how each format's noise
    numbers are read. The odometry is cut into consecutive maps; each map's full
    least-squares problem is solved (its start pose fixed as the origin) with refine's
    sparse Gauss-Newton, and written with its end pose, features and full covariance.
    The summary gives chi^2 and its degrees of freedom; a warning says when they disagree.

    \b
    Examples:
      mapjoin build ../shared/data/VicPark_200_local_maps/VicPark_clean_data.mat -o vicpark/ -j 2
      mapjoin join vicpark/ --refine -o vicpark.csv
      mapjoin build ../shared/data/victoria_park_raw/victoria_park_isam.txt -o isam/ --maps 1
      mapjoin build run.g2o -o maps.yaml --poses-per-map 50 --global-map batch.csv
    """
    from .. import build as builder  # scipy.sparse: imported only when building

    if map_count is not None and poses_per_map is not None:
        raise click.UsageError("give --maps or --poses-per-map, not both")
    stream = mapio.is_special(output) or os.path.splitext(output)[1] != ""
    outputs = mapio.Outputs(files={**({"-o": output} if stream else {}), "--global-map": global_path},
                            folders={} if stream else {"-o": output})
    outputs.guard([raw_path])
    common.check_output_formats((global_path, None, GLOBAL_MAP, None))
    with common.options_for(format="--format"):
        fmt = (common.output_format(output, output_format, LOCAL_MAPS) if stream
               else output_format or LOCAL_MAPS.default)
    start = time.perf_counter()
    with common.options_for(format="--raw-format"):
        raw = read_raw(raw_path, raw_format)
    reading = time.perf_counter() - start
    if map_count is None and poses_per_map is None:
        map_count = min(DEFAULT_MAPS, raw.steps)
    bounds = builder.cut(raw.steps, map_count, poses_per_map, raw.name)
    if not stream:
        _refuse_stale_maps(output, fmt, len(bounds) - 1)

    def report(iteration: int, cost: float) -> None:
        say(ctx, f"iteration {iteration}: chi^2 = {cost:.10g}")

    result = builder.build(raw, bounds, jobs=jobs, progress=report if ctx.obj["verbose"] else None,
                           with_batch=global_path is not None)
    _warn_if_doubtful(raw.name, result.costs, result.degrees_of_freedom)
    if result.batch is not None:
        _warn_if_doubtful(raw.name, [result.batch.cost], [result.batch.degrees_of_freedom])
    writing = time.perf_counter()
    with outputs:
        written = mapio.write_maps(result.maps, output if stream else os.path.join(output, ""), fmt)
        if global_path:
            mapio.write_global_map(result.batch.global_map, global_path,
                                   common.output_format(global_path, None, GLOBAL_MAP))
    writing = time.perf_counter() - writing
    dof = result.degrees_of_freedom
    pieces = f", from {result.pieces} pieces joined" if result.pieces else ""
    files = f" ({common.counted(len(written), 'file')})" if len(written) > 1 else ""
    message = (f"built {common.counted(len(result.maps), 'local map')} from {raw.name} ({raw.steps} steps, {len(raw.observations)} "
               f"observations): chi^2 {result.cost:.6f} for {int(dof.sum())} degrees of freedom (per map "
               f"{result.costs.min():.4g} to {result.costs.max():.4g}), {common.counted(result.iterations, 'iteration')}{pieces}; "
               f"{time.perf_counter() - start:.3f} s in all (reading {reading:.3f} s, solve {result.seconds:.3f} s, "
               f"covariances {result.covariance_seconds:.3f} s, writing {writing:.3f} s) -> "
               f"{output if output != '-' else 'stdout'}{files}")
    fields: dict[str, object] = {"maps": len(result.maps), "steps": raw.steps, "observations": len(raw.observations),
                                 "chi2": float(result.cost), "degrees_of_freedom": int(dof.sum()),
                                 "iterations": result.iterations, "seconds": time.perf_counter() - start,
                                 "output": output, "files": written}
    if global_path:
        solution = result.batch
        message += (f"\nbatch solution: chi^2 {solution.cost:.6f} (half: {solution.cost / 2:.6f}) for "
                    f"{solution.degrees_of_freedom} degrees of freedom, {common.counted(solution.iterations, 'iteration')} "
                    f"({solution.reason}), {solution.seconds + solution.covariance_seconds:.3f} s -> {global_path}")
        fields["batch"] = {"chi2": float(solution.cost), "degrees_of_freedom": solution.degrees_of_freedom,
                           "iterations": solution.iterations, "reason": solution.reason, "output": global_path}
    common.summary(ctx, message, fields, data_on_stdout="-" in (output, global_path))


def _refuse_stale_maps(folder: str, fmt: str, count: int) -> None:
    """Refuse a folder holding local maps that the ``count`` maps built would not replace (they would be joined
    with the new ones)."""
    if not os.path.isdir(folder):
        return
    planned = [os.path.join(folder, mapio.map_file_name(k, fmt)) for k in range(1, count + 1)]
    try:
        present = mapio.resolve_inputs([folder])
    except InputError:                           # no local maps in it
        present = []
    stale = sorted(set(map(os.path.normpath, present)) - set(map(os.path.normpath, planned)))
    if stale:
        raise InputError(f"holds local maps this build would not replace (e.g. {os.path.basename(stale[0])}), "
                         "which would be joined with the new ones; choose a new or empty folder", folder)


def _warn_if_doubtful(name: str, costs: Sequence[float], dofs: Sequence[int]) -> None:
    """Warn when chi^2, in all and map by map, is outside the 99.9% interval of a chi-square with
    its degrees of freedom (skipped under -q, which silences warnings)."""
    if not log.isEnabledFor(logging.WARNING):
        return
    from ..evaluation import chi2_verdict

    total, dof = float(np.sum(costs)), int(np.sum(dofs))
    verdict = chi2_verdict([total], [dof])
    if verdict.outside.size:
        look = "pessimistic (too large)" if verdict.too_small[0] else "optimistic (too small), or there are outliers"
        log.warning("%s: chi^2 = %.6g is outside the %g%% interval [%.6g, %.6g] of a chi-square with %d degrees "
                    "of freedom (chi^2/dof = %.3f): the noise numbers look %s", name, total, 100 * verdict.level,
                    verdict.low[0], verdict.high[0], dof, total / dof, look)
    if len(costs) > 1:
        each = chi2_verdict(costs, dofs)
        outside = each.outside
        if outside.size:
            j = int(outside[0])
            log.warning("%s: %d of %d local maps have chi^2 outside the %g%% interval for their degrees of freedom "
                        "(first: map %d, chi^2 %.4g for %d)", name, outside.size, len(costs), 100 * each.level,
                        j + 1, costs[j], dofs[j])
