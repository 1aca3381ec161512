"""``mapjoin compare``: how far apart two global maps are (the paper's metric, RMS, max)."""

from __future__ import annotations

import dataclasses
import json
import math

import click

from .. import io as mapio
from ..errors import counted
from ..evaluation import compare as compare_maps
from . import main


@main.command()
@click.argument("map_a", metavar="A")
@click.argument("map_b", metavar="B")
@click.option("--json", "as_json", is_flag=True, help="Machine-readable JSON instead of the table.")
def compare(map_a: str, map_b: str, as_json: bool) -> None:
    """Compare two global maps (.csv, .yaml) entity by entity.

    Prints the paper's metric (Section 7: mean absolute x and y difference over the
    shared features and poses, mean absolute orientation difference over the shared
    poses) and the RMS and maximum of the position and orientation differences. Only
    ids in both maps count; the maps are not aligned (both are in the frame of the first
    local map's start pose). Either map may be - for stdin.

    \b
    Examples:
      mapjoin compare fast.csv exact.csv
      mapjoin join ../shared/data/VicPark_200_local_maps | mapjoin compare - exact.yaml --json
    """
    if map_a == "-" and map_b == "-":
        raise click.UsageError("A and B cannot both be - (stdin can be read only once)")
    a = mapio.read_global_map(map_a)
    b = mapio.read_global_map(map_b)
    difference = compare_maps(a, b)
    if as_json:
        document = {"a": a.name, "b": b.name, **dataclasses.asdict(difference)}
        click.echo(json.dumps(_finite(document), indent=2))
        return
    click.echo("\n".join([
        f"A: {a.name}",
        f"B: {b.name}",
        f"shared ids: {counted(difference.features, 'feature')}, {counted(difference.poses, 'pose')} "
        "(no alignment: both maps in the frame of pose 0)",
        "",
        f"{'':<12}{'mean |B-A|':>14}{'RMS':>14}{'max':>14}",
        f"{'x (m)':<12}{_number(difference.mean_abs_x):>14}",
        f"{'y (m)':<12}{_number(difference.mean_abs_y):>14}",
        f"{'xy (m)':<12}{'':>14}{_number(difference.rms_xy):>14}{_number(difference.max_xy):>14}",
        f"{'phi (rad)':<12}{_number(difference.mean_abs_phi):>14}{_number(difference.rms_phi):>14}"
        f"{_number(difference.max_phi):>14}",
        "",
        "mean |B-A| is the paper's metric: x and y over features and poses, phi over poses;",
        "xy is the Euclidean distance over features and poses; angles are wrapped.",
    ]))


def _number(value: float) -> str:
    return "-" if math.isnan(value) else f"{value:.6g}"


def _finite(values: dict) -> dict:
    """NaN and inf as JSON null."""
    return {k: None if isinstance(v, float) and not math.isfinite(v) else v for k, v in values.items()}
