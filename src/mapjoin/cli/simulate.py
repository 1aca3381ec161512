"""``mapjoin simulate``: a ground-truth world cut into local maps."""

from __future__ import annotations

import os

import click

from .. import io as mapio
from ..io.registry import LOCAL_MAPS, TRUTH, by_name, names
from ..simulation import MAX_STEPS, simulate as run_simulation, simulate_robots, simulate_stream
from . import common, main

#: formats that write both the maps and the truth beside them
_FORMATS = tuple(name for name in names(LOCAL_MAPS, writing=True) if name in names(TRUTH, writing=True))
_STREAM_EXTENSIONS = tuple(extension for name in _FORMATS for extension in by_name[name].extensions)


@main.command()
@click.option("-o", "--output", required=True, metavar="DIR|FILE|-",
              help="Directory for localmap_<k> files and truth; a .csv/.yaml file, or - for stdout, gets "
                   "one stream of maps (no truth unless --truth).")
@click.option("--maps", "count", type=common.PlainInt(min=1), default=20, show_default=True,
              help="Number of local maps.")
@click.option("--seed", type=common.PlainInt(min=0), default=0, show_default=True, help="Random seed (same seed, same output).")
@click.option("--steps-per-map", type=common.PlainInt(min=1), default=10, show_default=True,
              help="Robot steps in each local map.")
@click.option("--format", "output_format", type=click.Choice(_FORMATS),
              help=f"Format of the local maps (default: a stream file's extension, else {LOCAL_MAPS.default}).")
@click.option("--truth", "truth_path", metavar="FILE",
              help="Where to write the ground truth (default: truth.<format> in the directory).")
@click.option("--robots", type=common.PlainInt(min=1), default=1, show_default=True,
              help="Robots in one world, --maps maps each, their areas overlapping: the directory gets one "
                   "folder robot<r> per robot (its maps and truth, in its own frame) and the world's truth in "
                   "the first robot's frame (README, 'Merging maps').")
@click.option("--local-ids", is_flag=True,
              help="Number each map's features from 0 (ids local to the map, for `join --associate`); a folder "
                   "output also gets the true correspondence, associations.csv (map,local_id,global_id; with "
                   "--robots one per robot's folder, global_id the world's id, as in the truths).")
@common.no_covariances_option
@common.json_option
@click.pass_context
def simulate(ctx: click.Context, output: str, count: int, seed: int, steps_per_map: int,
             output_format: str, truth_path: str | None, robots: int, local_ids: bool,
             no_covariances: bool) -> None:
    """Simulate a robot run, with ground truth, as local maps.

    The maps' estimates are drawn from their declared full covariances, so joins can be
    checked against the truth.

    \b
    Examples:
      mapjoin simulate -o sim/ --maps 50 --seed 7
      mapjoin simulate -o - --maps 20 | mapjoin join - > global.csv
      mapjoin simulate -o maps.csv --maps 1000 --truth truth.csv
      mapjoin simulate -o world/ --robots 3 --maps 30
    """
    if count * steps_per_map * robots > MAX_STEPS:
        raise click.UsageError(f"--maps x --steps-per-map x --robots = {count * steps_per_map * robots} robot steps; "
                               f"at most {MAX_STEPS} are simulated")
    stream = mapio.is_special(output) or (os.path.splitext(output)[1].lower() in _STREAM_EXTENSIONS
                                          and not os.path.isdir(output))
    output_format = output_format or (common.output_format(output, None, LOCAL_MAPS) if stream
                                      else LOCAL_MAPS.default)
    if robots > 1:
        if stream:
            raise click.UsageError("--robots writes one folder per robot: give -o a directory")
        _simulate_robots(ctx, output, robots, count, seed, steps_per_map, output_format, truth_path, local_ids,
                         no_covariances)
        return
    if not stream:
        truth_path = truth_path or os.path.join(output, f"truth.{output_format}")
    outputs = mapio.Outputs(files={**({"-o": output} if stream else {}), "--truth": truth_path},
                            folders={} if stream else {"-o": output})
    common.check_output_formats((output if stream else None, output_format, LOCAL_MAPS, "--format"),
                                (truth_path, None, TRUTH, None))
    if stream and not local_ids:  # made and written a chunk at a time: a run of any length fits in memory
        run = simulate_stream(count, seed=seed, steps_per_map=steps_per_map)
        with outputs:
            mapio.write_map_stream(run.chunks, output, output_format, covariances=not no_covariances)
            if truth_path:
                mapio.write_truth(run.truth, truth_path)
        _summary(ctx, count, seed, output, truth_path)
        return
    simulation = run_simulation(count, seed=seed, steps_per_map=steps_per_map)
    maps = simulation.maps
    if local_ids:
        from ..association import correspondence_rows, local_ids as localise

        maps, correspondence = localise(maps)
    with outputs:
        mapio.write_maps(maps, output if stream else os.path.join(output, ""), output_format,
                         covariances=not no_covariances)
        if truth_path:
            mapio.write_truth(simulation.truth, truth_path)
        if local_ids and not stream:
            mapio.write_table(correspondence_rows(correspondence), os.path.join(output, "associations.csv"), "csv")
    _summary(ctx, count, seed, output, truth_path)


def _summary(ctx: click.Context, count: int, seed: int, output: str, truth_path: str | None) -> None:
    common.summary(ctx, f"simulated {common.counted(count, 'local map')} (seed {seed})"
                   + (f" -> {output}" if output != "-" else "") + (f", truth -> {truth_path}" if truth_path else ""),
                   {"maps": count, "seed": seed, "output": output, "truth": truth_path},
                   data_on_stdout="-" in (output, truth_path))


def _simulate_robots(ctx: click.Context, output: str, robots: int, count: int, seed: int, steps_per_map: int,
                     output_format: str, truth_path: str | None, local_ids: bool, no_covariances: bool) -> None:
    """``--robots``: ``output/robot<r>/`` (localmap files, truth.<format>, with ``--local-ids`` associations.csv) per
    robot, the world's truth beside. A robot's local ids are its own; the truths and associations.csv keep the
    world's ids, so that ``join --associate`` per robot and ``merge --associate`` can be scored against them."""
    truth_path = truth_path or os.path.join(output, f"truth.{output_format}")
    folders = [os.path.join(output, f"robot{r}") for r in range(1, robots + 1)]
    truths = [os.path.join(folder, f"truth.{output_format}") for folder in folders]
    correspondences = [os.path.join(folder, "associations.csv") for folder in folders] if local_ids else []
    # every folder and file declared up front: --truth may go into a robot's folder, never onto its truth
    outputs = mapio.Outputs(files={**{f"robot {r} truth": path for r, path in enumerate(truths, 1)},
                                   **{f"robot {r} associations": path for r, path in enumerate(correspondences, 1)},
                                   "--truth": truth_path},
                            folders={"-o": output, **{f"robot {r} folder": path for r, path in enumerate(folders, 1)}})
    common.check_output_formats((truth_path, None, TRUTH, None))
    world = simulate_robots(robots, count, seed=seed, steps_per_map=steps_per_map)
    with outputs:
        for folder, truth, run in zip(folders, truths, world.robots):
            maps = run.maps
            if local_ids:
                from ..association import correspondence_rows, local_ids as localise

                maps, correspondence = localise(maps)
                mapio.write_table(correspondence_rows(correspondence), os.path.join(folder, "associations.csv"), "csv")
            mapio.write_maps(maps, os.path.join(folder, ""), output_format, covariances=not no_covariances)
            mapio.write_truth(run.truth, truth)
        mapio.write_truth(world.truth, truth_path)
    common.summary(ctx, f"simulated {common.counted(robots, 'robot')}, {common.counted(count, 'local map')} each (seed {seed}) -> "
                   f"{os.path.join(output, 'robot<r>')}, world truth -> {truth_path}",
                   {"robots": robots, "maps": count, "seed": seed, "output": output, "truth": truth_path})
