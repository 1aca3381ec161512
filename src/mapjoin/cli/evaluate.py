"""``mapjoin evaluate``: a global map's errors and NEES against ground truth."""

from __future__ import annotations

import dataclasses
import json
import math
import os
from typing import TYPE_CHECKING

import click

from .. import io as mapio
from ..errors import counted
from ..evaluation import ALIGNMENTS, Evaluation
from ..evaluation import evaluate as evaluate_map
from ..maps import GlobalMap, GroundTruth
from . import main

if TYPE_CHECKING:
    from ..association import LinkErrors


@main.command()
@click.argument("map_path", metavar="MAP")
@click.option("--truth", "truth_path", required=True, metavar="TRUTH",
              help="A truth file from `mapjoin simulate` (.yaml/.csv), its folder, or a simulation folder "
                   "with store_robotTrue.mat and store_beaconsTrue.mat.")
@click.option("--align", type=click.Choice(ALIGNMENTS), default="none", show_default=True,
              help="none: map and truth share the frame of pose 0; rigid: first fit the map onto the truth.")
@click.option("--associations", "found_path", metavar="FILE",
              help="MAP came from `join --associate`: its --associations table (map,local_id,global_id). The "
                   "links it recovered, missed and made falsely are counted against the true table, and features "
                   "are compared through it (each found feature as the true one most of its sightings are).")
@click.option("--true-associations", "true_path", metavar="FILE",
              help="The true map,local_id,global_id table (default: associations.csv beside --truth, as "
                   "`simulate --local-ids` writes it).")
@click.option("--json", "as_json", is_flag=True, help="Machine-readable JSON instead of the table.")
def evaluate(map_path: str, truth_path: str, align: str, found_path: str | None, true_path: str | None,
             as_json: bool) -> None:
    """Evaluate a global map (.csv or .yaml) against ground truth.

    Features and poses are matched by id (pose k = end pose of local map k). Prints the
    RMS and maximum position and orientation errors, and the average NEES of features
    and poses against the map's own covariances (the full blocks of an exact join) with
    two-sided 95% chi-square bounds and a verdict. A fast join carries spherical weights,
    not covariances: its NEES is printed against them, labelled so, and is no consistency
    test (join --refine gives covariances).
    For an I-SLSJF simulation folder, pose k is step round(k * steps / maps) of
    store_robotTrue.mat. MAP may be - for stdin.

    \b
    Examples:
      mapjoin join ../shared/data/535_data_5_local_maps -o g.csv
      mapjoin evaluate g.csv --truth ../shared/data/535_data_5_local_maps
      mapjoin simulate -o sim/ --maps 50 && mapjoin join sim/ | mapjoin evaluate - --truth sim/truth.yaml --json
      mapjoin simulate -o own/ --maps 50 --local-ids
      mapjoin join own/ --associate --associations ids.csv -o g.csv
      mapjoin evaluate g.csv --truth own/ --associations ids.csv
    """
    paths = [path for path in (map_path, truth_path, found_path, true_path) if path is not None]
    if paths.count("-") > 1:
        raise click.UsageError("only one of MAP, --truth, --associations and --true-associations can be - "
                               "(stdin can be read only once)")
    if true_path is not None and found_path is None:
        raise click.UsageError("--true-associations needs --associations (the table MAP's join wrote)")
    global_map = mapio.read_global_map(map_path)
    truth = mapio.read_truth(truth_path)
    links = feature_truth = None
    if found_path is not None:
        from ..association import scored, truth_of_found

        found = mapio.read_correspondence(found_path)
        true = mapio.read_correspondence(true_path or _beside(truth_path))
        links, feature_truth = scored(found, true), truth_of_found(found, true)
    result = evaluate_map(global_map, truth, align, feature_truth=feature_truth)
    covariances = _covariance_source(global_map)
    if as_json:
        association = None if links is None else {**links._asdict(), "recall": links.recall}
        document = {"map": global_map.name, "truth": truth.name, **dataclasses.asdict(result),
                    "nees_covariances": covariances, "associations": association}
        click.echo(json.dumps({k: None if isinstance(v, float) and not math.isfinite(v) else v
                               for k, v in document.items()}, indent=2))
        return
    click.echo("\n".join(_human(global_map, truth, result, covariances, links)))


def _beside(truth_path: str) -> str:
    """The true correspondence ``simulate --local-ids`` writes: associations.csv in --truth's folder, or beside it."""
    folder = truth_path if os.path.isdir(truth_path) else os.path.dirname(truth_path)
    path = os.path.join(folder, "associations.csv")
    if truth_path == "-" or not os.path.isfile(path):
        raise click.UsageError(f"--associations needs the true correspondence: no {path} beside --truth; give "
                               "--true-associations (`simulate --local-ids` writes associations.csv)")
    return path


#: what a map without covariance blocks is evaluated against: the fast join's weights
WEIGHTS_SOURCE = "spherical weights (not covariances; join --refine gives covariances)"


def _covariance_source(global_map: GlobalMap) -> str:
    full = [kind for kind, blocks in (("features", global_map.feature_covariances),
                                      ("poses", global_map.pose_covariances)) if blocks is not None]
    if len(full) == 2:
        return "full marginal blocks"
    if full:
        return f"full marginal blocks for {full[0]}, spherical weights for the rest"
    return WEIGHTS_SOURCE


def _number(value: float | None) -> str:
    return "-" if value is None or math.isnan(value) else f"{value:.6g}"


def _verdict(value: float | None, bounds: tuple[float, float] | None) -> str:
    if value is None or bounds is None:
        return "not available"
    if value > bounds[1]:
        return "too large: errors exceed the covariances (overconfident)"
    if value < bounds[0]:
        return "too small: covariances exceed the errors (conservative)"
    return "within bounds"


def _human(global_map: GlobalMap, truth: GroundTruth, result: Evaluation, covariances: str,
           links: LinkErrors | None) -> list[str]:
    lines = [
        f"map:       {global_map.name}",
        f"truth:     {truth.name}",
        f"alignment: {result.alignment}",
    ]
    if links is None:
        lines.append(f"compared:  {counted(result.features, 'feature')}, {counted(result.poses, 'pose')} (ids in both)")
    else:
        recall = "-" if math.isnan(links.recall) else f"{100 * links.recall:.2f} %"
        lines += [f"links:     {links.links} true (features seen again), {links.links - links.missed} recovered "
                  f"({recall}), {links.missed} missed, {links.false} false",
                  f"compared:  {counted(result.features, 'feature')} (through the associations), "
                  f"{counted(result.poses, 'pose')} (ids in both)"]
    lines += [
        "",
        f"{'error':<18}{'RMS':>14}{'max':>14}",
        f"{'features xy (m)':<18}{_number(result.feature_rms):>14}{_number(result.feature_max):>14}",
        f"{'poses xy (m)':<18}{_number(result.pose_rms_xy):>14}{_number(result.pose_max_xy):>14}",
        f"{'poses phi (rad)':<18}{_number(result.pose_rms_phi):>14}{_number(result.pose_max_phi):>14}",
        "",
        f"average NEES against the map's {covariances} (two-sided 95% chi-square bounds):",
    ]
    for label, value, bounds, dof in (("features", result.nees_features, result.nees_bounds_features, 2),
                                      ("poses", result.nees_poses, result.nees_bounds_poses, 3)):
        interval = f"[{bounds[0]:.4g}, {bounds[1]:.4g}]" if bounds else "-"
        lines.append(f"  {label:<10}{_number(value):>12}  expected {dof}, bounds {interval:<20}"
                     f"{_verdict(value, bounds)}")
    verdict = {None: "not available", True: "consistent", False: "inconsistent"}[result.consistent]
    if covariances == WEIGHTS_SOURCE:
        verdict = f"none: weights are not covariances ({verdict} if they were)"
    lines.append(f"verdict: {verdict}")
    return lines
