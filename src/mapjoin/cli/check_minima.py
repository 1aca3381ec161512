"""``mapjoin check-minima``: Theorem 2's certificate for one (a, C_phi), two maps, or a batch."""

from __future__ import annotations

import dataclasses
import json
import math

import click

from .. import io as mapio
from ..errors import EXIT_TWO_MINIMA
from ..io.registry import TABLE
from ..joining import certify_pair
from ..maps import ANGLE, MINIMA_A
from ..onestep import analyse_minima, summarise_minima
from . import common, main
from .common import TABLE_EXTENSIONS, covariance_option, input_format_option, output_option, solver_option


@main.command("check-minima")
@click.argument("maps", nargs=-1, metavar="[MAP_A MAP_B]")
@click.option("--a", "a", type=common.FiniteFloat(MINIMA_A), help=f"a = a0 * p_phi of Theorem 2 (in [0, {MINIMA_A.high:g}]).")
@click.option("--c-phi", "c_phi", type=common.FiniteFloat(ANGLE),
              help=f"C_phi = wrap(z_phi - phi0), radians (|C_phi| <= {ANGLE.high:g}).")
@click.option("--batch", metavar="FILE", help=f"A table ({TABLE_EXTENSIONS}) with columns a and c_phi, e.g. "
                                             "a report of `mapjoin join --report`; - for stdin.")
@output_option(f"Batch result ({TABLE_EXTENSIONS}); - for stdout.")
@click.option("--json", "as_json", is_flag=True, help="Machine-readable JSON instead of the human report.")
@covariance_option
@solver_option
@input_format_option
@click.pass_context
def check_minima(ctx: click.Context, maps: tuple[str, ...], a: float | None, c_phi: float | None,
                 batch: str | None, output: str, as_json: bool, covariance: str, solver: str,
                 input_format: str | None) -> None:
    """Count and locate a join's local minima (Theorem 2).

    The 1-D problem of a join has one or two local minima; Theorem 2's conditions
    (16)-(21) say which, and Algorithm 1 locates them.

    Give --a and --c-phi; or two local maps MAP_A MAP_B (MAP_B starting at MAP_A's end
    pose), whose join is analysed; or --batch FILE, any table with columns a and c_phi
    (a report of `mapjoin join --report` too).

    Exit code: 0 when every problem has one minimum, 3 when any has two, 1 on bad input.

    \b
    Examples:
      mapjoin check-minima --a 203570 --c-phi -0.0028
      mapjoin check-minima --a 5 --c-phi 2.5 --json
      mapjoin check-minima maps/localmap_1.yaml maps/localmap_2.yaml
      printf 'a,c_phi\\n5,2.5\\n0.5,1\\n' | mapjoin check-minima --batch -
      mapjoin join examples/sim20 --report - -o g.csv | mapjoin check-minima --batch - -o minima.yaml
    """
    modes = [bool(maps), a is not None or c_phi is not None, batch is not None]
    if sum(modes) != 1:
        raise click.UsageError("give exactly one of: --a A --c-phi C; two local maps (MAP_A MAP_B, or a folder "
                               "of two); --batch FILE")
    if batch is not None:
        outputs = mapio.Outputs(files={"-o": output})
        outputs.guard([batch])
        common.check_output_formats((output, None, TABLE, None))
        fmt = common.output_format(output, None, TABLE)
        table = mapio.read_minima_table(batch)
        rows = _batch_rows(table, solver)
        with outputs:
            mapio.write_table(rows, output, fmt)
        ctx.exit(EXIT_TWO_MINIMA if any(r["minima"] == 2 for r in rows) else 0)
    preamble: list[str] = []
    record = None
    if maps:
        local_maps = common.read_local_maps(maps, input_format, mapio.Outputs(files={}))
        if len(local_maps) != 2:
            raise click.UsageError(f"expected two local maps (MAP_A MAP_B, or a folder of two), got "
                                   f"{len(local_maps)}")
        first, second = local_maps
        record = certify_pair(first, second, covariance, solver)
        a, c_phi = record.a, record.c_phi
        preamble = [f"joining {second.name} onto {first.name} ({covariance} covariances): "
                    f"{record.common} common features",
                    f"phi* = {record.phi:+.9f} rad, f1(phi*) = {record.cost:.9g}"]
    if a is None or c_phi is None:
        raise click.UsageError("--a and --c-phi go together")
    analysis = analyse_minima(a, c_phi)
    summary = summarise_minima(a, c_phi, solver)
    if as_json:
        document = {**_finite(dataclasses.asdict(summary)),
                    "conditions": [{**_finite(dataclasses.asdict(c)), "holds": c.holds}
                                   for c in analysis.conditions]}
        if record is not None:
            document["join"] = _finite(dataclasses.asdict(record))
        click.echo(json.dumps(document, indent=2))
    else:
        click.echo("\n".join(preamble + _human(analysis, summary)))
    ctx.exit(EXIT_TWO_MINIMA if summary.minima == 2 else 0)


def _batch_rows(table: mapio.MinimaTable, solver: str) -> list[dict]:
    """The batch result: each input row's identifying columns (join, map: those the input has), then its
    minima; a value that does not exist (the second minimum of a one-minimum problem, phi1 and phi2 when
    a < 1) is absent, an empty cell, not ``nan``."""
    ids = {column: values for column, values in (("join", table.join), ("map", table.map_names))
           if values is not None}
    return [{**{column: values[row] for column, values in ids.items()},
             **_finite(dataclasses.asdict(summarise_minima(a, c_phi, solver)))}
            for row, (a, c_phi) in enumerate(zip(table.a.tolist(), table.c_phi.tolist()))]


def _finite(values: dict) -> dict:
    """NaN and inf as absent values (None: JSON null, an empty CSV cell)."""
    return {k: None if isinstance(v, float) and not math.isfinite(v) else v for k, v in values.items()}


def _human(analysis, summary) -> list[str]:
    lines = [f"a = {analysis.a:.9g}, C_phi = {analysis.c_phi:+.9g} rad "
             "(reduced cost fbar(varphi) = -a cos(varphi + C_phi) + varphi^2/2, varphi in [-pi, pi))",
             "Theorem 2: two minima iff (16)-(21) all hold (strictly):"]
    for c in analysis.conditions:
        value = "undefined (a < 1)" if math.isnan(c.value) else f"{c.value:.6g}"
        lines.append(f"  ({c.number}) {c.expression + ' ' + c.relation + ' ' + format(c.bound, 'g'):<28}"
                     f"  value {value:<20} {'holds' if c.holds else 'fails'}")
    if not math.isnan(analysis.phi1):
        lines.append(f"zeros of fbar'': phi1 = {analysis.phi1:+.6f}, phi2 = {analysis.phi2:+.6f}")
    lines.append("2 minima:" if summary.minima == 2 else "1 minimum (the join is certified unique):")
    lines.append(f"  global: varphi = {summary.varphi_1:+.9f} rad, fbar = {summary.fbar_1:.9g}")
    if summary.minima == 2:
        lines.append(f"  other:  varphi = {summary.varphi_2:+.9f} rad, fbar = {summary.fbar_2:.9g}")
    return lines
