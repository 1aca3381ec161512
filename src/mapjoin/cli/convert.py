"""``mapjoin convert``: local maps from one format to another."""

from __future__ import annotations

import os

import click

from .. import io as mapio
from ..io.registry import LOCAL_MAPS
from . import common, main
from .common import format_option, input_format_option, inputs_argument


@main.command()
@inputs_argument
@click.option("-o", "--output", required=True, metavar="DIR|FILE",
              help="A directory (one localmap_<k> file per map), a file (one stream; a single map for mat and "
                   "linearslam), or - for stdout.")
@format_option(LOCAL_MAPS, f"Output format (default: from the -o name; {common.default_title(LOCAL_MAPS)} for a "
               "directory or stdout).", "--to", "to_format")
@input_format_option
@common.no_covariances_option
@common.json_option
@click.pass_context
def convert(ctx: click.Context, inputs: tuple[str, ...], output: str, to_format: str | None,
            input_format: str | None, no_covariances: bool) -> None:
    """Convert local maps: I-SLSJF .mat, Linear SLAM, YAML, CSV.

    YAML, .mat and Linear SLAM text keep each map's full covariance (Linear SLAM text
    stores its inverse, the information matrix: converting inverts it, exact up to
    rounding). CSV keeps them too (cov rows; README, "Formats"). A .mat file holds map
    k, from pose k-1 to pose k, and takes k from its name. A conversion that drops
    something says so in one warning.

    \b
    Examples:
      mapjoin convert ../shared/data/VicPark_200_local_maps -o vicpark/ --to yaml
      mapjoin convert ../shared/data/linearslam_txt/8240_data_50_local_maps -o sim/ --to mat
      mapjoin convert ../shared/data/8240_data_50_local_maps -o sim-txt/ --to linearslam
      mapjoin convert 'maps/*.yaml' -o maps.csv
    """
    is_directory = output.endswith(os.sep) or os.path.isdir(output)
    outputs = mapio.Outputs(**{"folders" if is_directory else "files": {"-o": output}})
    if to_format is None:
        with common.options_for(format="--to"):
            to_format = LOCAL_MAPS.default if is_directory else common.output_format(output, None, LOCAL_MAPS)
    common.check_output_formats((None if is_directory else output, to_format, LOCAL_MAPS, "--to"))
    maps = common.read_local_maps(inputs, input_format, outputs)
    with outputs:
        written = mapio.write_maps(maps, output, to_format, covariances=not no_covariances)
    common.summary(ctx, f"converted {common.counted(len(maps), 'map')} to {to_format}: {common.counted(len(written), 'file')} in {output}"
                   if output != "-" else f"converted {common.counted(len(maps), 'map')} to {to_format}",
                   {"maps": len(maps), "format": to_format, "files": written, "output": output},
                   data_on_stdout=output == "-")
