"""``mapjoin simulate``: a ground-truth world cut into local maps."""

from __future__ import annotations

import os

import click

from .. import io as mapio
from ..io.registry import LOCAL_MAPS, TRUTH, by_name, names
from ..simulation import simulate as run_simulation
from . import common, main
from .common import say

#: formats that write both the maps and the truth beside them
_FORMATS = tuple(name for name in names(LOCAL_MAPS, writing=True) if name in names(TRUTH, writing=True))
_STREAM_EXTENSIONS = tuple(extension for name in _FORMATS for extension in by_name[name].extensions)


@main.command()
@click.option("-o", "--output", required=True, metavar="DIR|FILE|-",
              help="Directory for localmap_<k> files and truth; a .csv/.yaml file, or - for stdout, gets "
                   "one stream of maps (no truth unless --truth).")
@click.option("--maps", "count", type=click.IntRange(min=1), default=20, show_default=True,
              help="Number of local maps.")
@click.option("--seed", type=int, default=0, show_default=True, help="Random seed (same seed, same output).")
@click.option("--steps-per-map", type=click.IntRange(min=1), default=10, show_default=True,
              help="Robot steps in each local map.")
@click.option("--format", "output_format", type=click.Choice(_FORMATS),
              help=f"Format of the local maps (default: a stream file's extension, else {LOCAL_MAPS.default}).")
@click.option("--truth", "truth_path", metavar="FILE",
              help="Where to write the ground truth (default: truth.<format> in the directory).")
@click.option("--local-ids", is_flag=True,
              help="Number each map's features from 0 (ids local to the map, for `join --associate`); a folder "
                   "output also gets the true correspondence, associations.csv (map,local_id,global_id).")
@click.pass_context
def simulate(ctx: click.Context, output: str, count: int, seed: int, steps_per_map: int,
             output_format: str, truth_path: str | None, local_ids: bool) -> None:
    """Simulate a robot run, with ground truth, as local maps.

    The maps' estimates are drawn from their declared full covariances, so joins can be
    checked against the truth.

    \b
    Examples:
      mapjoin simulate -o sim/ --maps 50 --seed 7
      mapjoin simulate -o - --maps 20 | mapjoin join - > global.csv
      mapjoin simulate -o maps.csv --maps 1000 --truth truth.csv
    """
    stream = mapio.is_special(output) or (os.path.splitext(output)[1].lower() in _STREAM_EXTENSIONS
                                          and not os.path.isdir(output))
    output_format = output_format or (common.output_format(output, None, LOCAL_MAPS) if stream
                                      else LOCAL_MAPS.default)
    if not stream:
        truth_path = truth_path or os.path.join(output, f"truth.{output_format}")
    outputs = mapio.Outputs(files={**({"-o": output} if stream else {}), "--truth": truth_path},
                            folders={} if stream else {"-o": output})
    simulation = run_simulation(count, seed=seed, steps_per_map=steps_per_map)
    maps = simulation.maps
    if local_ids:
        from ..association import correspondence_rows, local_ids as localise

        maps, correspondence = localise(maps)
    with outputs:
        mapio.write_maps(maps, output if stream else os.path.join(output, ""), output_format)
        if truth_path:
            mapio.write_truth(simulation.truth, truth_path)
        if local_ids and not stream:
            mapio.write_table(correspondence_rows(correspondence), os.path.join(output, "associations.csv"), "csv")
    say(ctx, f"simulated {count} local map{'s' * (count != 1)} (seed {seed})"
             + (f" -> {output}" if output != "-" else "") + (f", truth -> {truth_path}" if truth_path else ""))
