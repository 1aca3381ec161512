"""``mapjoin merge``: global maps of several robots or sessions, each in its own frame, into one."""

from __future__ import annotations

import time

import click

from .. import io as mapio
from ..io.registry import GLOBAL_MAP, TABLE
from ..maps import Range
from . import common, main
from .common import TABLE_EXTENSIONS, global_map_format_option, global_map_output_option, say

PROBABILITY_RANGE = Range("gate probability", 0.5, 1.0 - 1e-12)


@main.command()
@click.argument("inputs", nargs=-1, required=True, metavar="A B [C ...]")
@global_map_output_option
@global_map_format_option
@click.option("--report", "report_path", metavar="FILE",
              help=f"Per-merge report ({TABLE_EXTENSIONS}): phi, x, y of each map's frame, common features, "
                   "residual cost, ids given anew.")
@click.option("--associate", is_flag=True,
              help="The maps share no feature ids: find the common features by a global search (refused "
                   "when the overlap is too small to be sure).")
@click.option("--min-common", type=common.PlainInt(min=2), default=lambda: _defaults()[0], show_default="5",
              help="--associate: fewest features the transform found must match (and twice as many as any "
                   "other transform).")
@click.option("--gate-association", "probability", type=common.FiniteFloat(PROBABILITY_RANGE),
              default=lambda: _defaults()[1], show_default="0.999",
              help="--associate: chi-square level of the distance gates.")
@common.json_option
@click.pass_context
def merge(ctx: click.Context, inputs: tuple[str, ...], output: str, output_format: str | None,
          report_path: str | None, associate: bool, min_common: int, probability: float) -> None:
    """Merge global maps, each in its own frame, into one.

    A, B, ... are global maps (e.g. `mapjoin join` outputs of several robots or sessions)
    that share features but no pose. B is brought into A's frame by the one-step solution
    without orientation link over the common features (closed form, point-set
    registration), common features are fused (A's ids), B's other features and its poses
    are moved (B's ids; an id already taken gets a new one, with a warning); then C, etc.
    Without --associate the common features are those with the same id (at least two).

    \b
    Examples:
      mapjoin merge robot1.csv robot2.csv -o merged.csv --report merges.csv
      mapjoin merge session1.yaml session2.yaml --associate -o merged.yaml
    """
    from ..merging import merge as merge_maps

    if list(inputs).count("-") > 1:
        raise click.UsageError("- can be given once (stdin can be read only once)")
    if len(inputs) < 2:
        raise click.UsageError("merge needs at least two global maps (A B)")
    outputs = mapio.Outputs(files={"-o": output, "--report": report_path})
    common.check_output_formats((output, output_format, GLOBAL_MAP, "--format"), (report_path, None, TABLE, None))
    paths = outputs.guard(list(inputs))
    start = time.perf_counter()
    maps = [mapio.read_global_map(path) for path in paths]
    result = merge_maps(maps, associate, min_common=min_common, probability=probability)
    elapsed = time.perf_counter() - start
    with outputs, common.options_for(format="--format"):
        mapio.write_global_map(result.global_map, output, common.output_format(output, output_format, GLOBAL_MAP))
        if report_path:
            mapio.write_table(result.report, report_path, common.output_format(report_path, None, TABLE))
    if ctx.obj["verbose"]:
        for r in result.report:
            say(ctx, f"merge {r.merge}: {r.map}: phi={r.phi:+.6f} rad, t=({r.x:.6g}, {r.y:.6g}), {r.common} common, "
                     f"{r.new} new, cost {r.cost:.6g}")
    g = result.global_map
    fused = sum(r.common for r in result.report)
    common.summary(ctx, f"merged {common.counted(len(maps), 'map')}: {common.counted(len(g.feature_ids), 'feature')}, "
                        f"{common.counted(len(g.pose_ids), 'pose')}, {common.counted(fused, 'feature')} fused, "
                        f"{common.counted(len(result.renamed), 'id')} given anew, {elapsed:.3f} s -> "
                        f"{'stdout' if output == '-' else output}",
                   {"maps": len(maps), "features": len(g.feature_ids), "poses": len(g.pose_ids), "fused": fused,
                    "renamed": len(result.renamed), "seconds": elapsed, "output": output,
                    "merges": [{"map": r.map, "phi": r.phi, "x": r.x, "y": r.y, "common": r.common, "cost": r.cost}
                               for r in result.report]},
                   data_on_stdout=output == "-")


def _defaults() -> tuple[int, float]:
    """The search's defaults (asked for only when the command runs)."""
    from ..registration import GATE_PROBABILITY, MIN_COMMON

    return MIN_COMMON, GATE_PROBABILITY
