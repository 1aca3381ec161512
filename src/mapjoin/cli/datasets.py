"""``mapjoin datasets``: list the public datasets and fetch them into a cache, verified by SHA-256."""

from __future__ import annotations

from pathlib import Path

import click

from . import common, main
from .common import progress_bar, say

_REMEDIES = {"into": "--into DIR", "source": "--source URL (e.g. --source file:///path/to/data)"}

into_option = click.option(
    "--into", type=click.Path(file_okay=False, path_type=Path), metavar="DIR",
    help="Cache directory (default: $XDG_CACHE_HOME/mapjoin, else ~/.cache/mapjoin).")


@main.group()
def datasets() -> None:
    """List and fetch the public local-map datasets, verified.

    The I-SLSJF and Linear SLAM distributions: Victoria Park, DLR, the simulations.

    \b
    Examples:
      mapjoin datasets list
      mapjoin datasets fetch vicpark-200
      mapjoin join "$(mapjoin datasets fetch sim-8240)" -o sim.csv
      mapjoin datasets fetch dlr-200 --source ../shared/data --into ./data
    """


@datasets.command("list")
@into_option
@click.pass_context
def list_datasets(ctx: click.Context, into: Path | None) -> None:
    """List the datasets, their checksums and whether they are cached.

    A set whose checksums are not known (it was not in the reference copy they were
    computed from) can be fetched but not verified; the CHECKSUMS column says so.

    \b
    Examples:
      mapjoin datasets list
      mapjoin datasets list --into ./data
    """
    from .. import datasets as catalogue  # urllib and http: imported only when used

    root = into or catalogue.default_cache()
    rows = [("NAME", "MAPS", "FORMAT", "FILES", "CHECKSUMS", "CACHED", "FROM", "WHAT")]
    for dataset in catalogue.DATASETS.values():
        known = catalogue.checksums(dataset)
        rows.append((dataset.name, str(dataset.maps), dataset.extension, str(len(dataset.files)),
                     "SHA-256 of every file" if known else "none known: cannot verify",
                     "yes" if catalogue.is_cached(dataset, root) else "no", dataset.distribution,
                     dataset.description))
    widths = [max(len(row[column]) for row in rows) for column in range(len(rows[0]) - 1)]
    for row in rows:
        click.echo("  ".join(cell.ljust(width) for cell, width in zip(row, widths)) + "  " + row[-1])
    say(ctx, f"cache: {root}; fetch with: mapjoin datasets fetch NAME [--into DIR] [--source URL]")


@datasets.command()
@click.argument("names", nargs=-1, required=True, metavar="NAME...")
@into_option
@click.option("--source", metavar="URL",
              help="Fetch from a mirror instead of GitHub: a URL or folder laid out like the cache, "
                   "<source>/<folder>/<file> (e.g. ../shared/data or https://mirror.example/data).")
@click.pass_context
def fetch(ctx: click.Context, names: tuple[str, ...], into: Path | None, source: str | None) -> None:
    """Download datasets into the cache and check each file's SHA-256.

    Prints each dataset's folder on stdout. Files go to a temporary folder first and
    are moved into place only when all have arrived and matched their recorded
    checksums. Sets without recorded checksums are fetched with a warning.

    \b
    Examples:
      mapjoin datasets fetch vicpark-200 dlr-200
      mapjoin datasets fetch sim-535 --source ../shared/data --into ./data
      mapjoin join "$(mapjoin datasets fetch sim-8240)" -o sim.csv
    """
    from .. import datasets as catalogue

    if source is not None and not source.strip():  # it would name the current folder
        raise click.BadParameter("is empty; expected a URL or a folder", ctx, param_hint="'--source'")
    for dataset in [catalogue.get(name) for name in names]:
        with progress_bar(ctx, len(dataset.files), f"fetching {dataset.name}") as progress:
            try:
                result = catalogue.fetch(dataset.name, into, source, progress)
            except catalogue.FetchError as error:
                if error.argument is None:
                    raise
                raise catalogue.FetchError(f"{error}: pass it with {_REMEDIES[error.argument]}") from None
        if result.already_cached:
            check = "checksums verified" if result.verified else "no checksums known"
            say(ctx, f"{dataset.name}: already in the cache ({common.counted(result.files, 'file')}, {check})")
        else:
            check = ("every SHA-256 verified" if result.verified
                     else "NOT verified: no checksums are known for this set")
            say(ctx, f"{dataset.name}: fetched {common.counted(result.files, 'file')}, {result.size / 1e6:.1f} MB, "
                     f"{check}")
        if result.skipped:
            say(ctx, f"{dataset.name}: the source does not hold {', '.join(result.skipped)} (optional; skipped)")
        click.echo(result.path)
