"""One set of options per concept (issue 15, part 5): the commands agree on options, inputs, hints, counts
and wording. Each test failed before: join --refine refused the refine options, refine had no --report or
--jobs, hints named options a command does not have, plot refused local maps, check-minima refused a folder,
--batch dropped the join and map columns and wrote nan, 41 warnings of one kind came as 41 lines, "1 maps"."""

from __future__ import annotations

import csv
import io
import logging
import math
import os
import re
import shutil

import numpy as np
import pytest
import yaml
from click.testing import CliRunner

from cli_runner import run
from mapjoin import io as mapio
from mapjoin.cli import main
from mapjoin.cli.messages import StderrHandler
from mapjoin.errors import counted
from mapjoin.se2 import compose, transform


def options_of(command: str) -> set[str]:
    """Every option name the command ``mapjoin COMMAND`` takes (e.g. ``--start``, ``-o``)."""
    ctx = main.make_context("mapjoin", [command, "--help"], resilient_parsing=True)
    sub = main.get_command(ctx, command)
    return {name for parameter in sub.params for name in (*parameter.opts, *parameter.secondary_opts)}


def test_join_takes_every_option_of_refine():
    """One concept, one option: what refine takes (start, tolerance, iterations, covariances, report, jobs),
    join takes too (the solve's options with --refine), and the other way round for the fast join's."""
    join, refine = options_of("join"), options_of("refine")
    assert refine - join == set()
    assert join - refine == {"--refine", "--associate", "--gate-association", "--associations"}  # the fast join's own
    assert {"--start", "--tolerance", "--max-iterations", "--no-covariances", "--report", "--jobs"} <= join


def test_join_refine_with_the_solve_options_writes_what_refine_writes(simulated_folder, tmp_path):
    options = ["--start", "tree", "--tolerance", "1e-6", "--max-iterations", "50", "--no-covariances",
               "--covariance", "identity"]
    joined = run("join", simulated_folder, "--refine", *options, "-o", str(tmp_path / "j.csv"),
                 "--report", str(tmp_path / "j_report.csv"))
    refined = run("refine", simulated_folder, *options, "-o", str(tmp_path / "r.csv"),
                  "--report", str(tmp_path / "r_report.csv"))
    assert joined.exit_code == 0 and refined.exit_code == 0, joined.stderr + refined.stderr
    assert (tmp_path / "j.csv").read_text() == (tmp_path / "r.csv").read_text()
    assert "cov_" not in (tmp_path / "r.csv").read_text()         # --no-covariances reached the solve
    # refine --report is the fast join's report: that of `mapjoin join` with the same start
    fast = run("join", simulated_folder, "--strategy", "tree", "--covariance", "identity",
               "-o", str(tmp_path / "fast.csv"), "--report", str(tmp_path / "fast_report.csv"))
    assert fast.exit_code == 0
    report = (tmp_path / "fast_report.csv").read_text()
    assert (tmp_path / "r_report.csv").read_text() == report == (tmp_path / "j_report.csv").read_text()
    assert report.count("\n") == 12                                # header + 11 joins of 12 maps


def test_a_solve_option_without_refine_is_a_usage_error(simulated_folder, tmp_path):
    result = run("join", simulated_folder, "--tolerance", "1e-3", "-o", str(tmp_path / "g.csv"))
    assert result.exit_code == 2 and "--tolerance is an option of the exact solve; add --refine" in result.stderr
    assert not (tmp_path / "g.csv").exists()


def test_verbose_prints_the_solve_iterations_on_both_commands(simulated_folder, tmp_path):
    for command in (["join", "--refine"], ["refine"]):
        result = run("-v", *command, simulated_folder, "-o", str(tmp_path / "g.csv"))
        assert result.exit_code == 0 and "iteration 0: chi^2 = " in result.stderr, result.stderr


def test_join_max_iterations_reaches_the_solve(simulated_folder, tmp_path):
    """--max-iterations 0 on join --refine: the start itself, not converged (exit 3), as refine says."""
    for command in (["join", "--refine"], ["refine"]):
        result = run(*command, simulated_folder, "--max-iterations", "0", "-o", str(tmp_path / "g.csv"))
        assert result.exit_code == 3 and "did not converge" in result.stderr, result.stderr


def test_refine_jobs_runs_the_tree_start_in_parallel(simulated_folder, tmp_path):
    one = run("refine", simulated_folder, "--start", "tree", "-o", str(tmp_path / "one.csv"))
    two = run("refine", simulated_folder, "--start", "tree", "--jobs", "2", "-o", str(tmp_path / "two.csv"))
    assert one.exit_code == 0 and two.exit_code == 0
    assert (tmp_path / "one.csv").read_text() == (tmp_path / "two.csv").read_text()
    default = run("refine", simulated_folder, "--jobs", "2", "-o", str(tmp_path / "default.csv"))  # tree start
    assert default.exit_code == 0 and (tmp_path / "default.csv").read_text() == (tmp_path / "one.csv").read_text()
    refused = run("refine", simulated_folder, "--start", "sequential", "--jobs", "2", "-o", str(tmp_path / "three.csv"))
    assert refused.exit_code == 2 and "--strategy tree" in refused.stderr


@pytest.mark.parametrize("command", ["join", "refine", "convert", "plot", "plot-join", "compare", "evaluate",
                                     "check-minima", "build"])
def test_hints_name_only_options_the_command_has(command, simulated_folder, tmp_path):
    """A file (and stdin) whose format cannot be told: every option the error names is one of the command's,
    and the library's neutral remedy ("give its format") never reaches a command line."""
    unknown = tmp_path / "map.dat"
    shutil.copy(os.path.join(simulated_folder, "localmap_1.yaml"), unknown)
    second = os.path.join(simulated_folder, "localmap_2.yaml")
    out = str(tmp_path / ("out.png" if command.startswith("plot") else "out.csv"))
    arguments = {"join": [str(unknown), "-o", out], "refine": [str(unknown), "-o", out],
                 "convert": [str(unknown), "-o", str(tmp_path / "maps/")], "plot": [str(unknown), "-o", out],
                 "plot-join": [str(unknown), second, "-o", out], "compare": [str(unknown), second],
                 "evaluate": [str(unknown), "--truth", os.path.join(simulated_folder, "truth.yaml")],
                 "check-minima": [str(unknown), second], "build": [str(unknown), "-o", str(tmp_path / "b/")]}
    for args, stdin in ((arguments[command], None), (["-" if a == str(unknown) else a for a in arguments[command]],
                                                     "hello\n")):
        result = run(command, *args, input=stdin)
        assert result.exit_code == 1, result.stderr
        named = set(re.findall(r"(?<![\w-])--[a-z][a-z-]*", result.stderr))
        assert named <= options_of(command), (command, named, result.stderr)
        assert "give its" not in result.stderr


def test_plot_draws_local_maps_chained_by_their_start_poses(simulated_folder, tmp_path):
    result = run("plot", simulated_folder, os.path.join(simulated_folder, "localmap_1.yaml"),
                 "-o", str(tmp_path / "maps.svg"))
    assert result.exit_code == 0, result.stderr
    assert "plotted 2 maps" in result.stderr and (tmp_path / "maps.svg").stat().st_size > 0
    with open(os.path.join(simulated_folder, "localmap_1.yaml")) as stream:
        piped = run("plot", "-", "-o", str(tmp_path / "piped.svg"), input=stream.read())
    assert piped.exit_code == 0 and "plotted 1 map " in piped.stderr, piped.stderr
    refused = run("plot", simulated_folder, "--ellipses", "-o", str(tmp_path / "e.svg"))
    assert refused.exit_code == 2 and "join them first" in refused.stderr
    assert not (tmp_path / "e.svg").exists()


def test_chained_local_maps_compose_the_end_poses(simulated_folder):
    """Against se2.compose applied map after map (the chain's definition, docs/method.md): the poses are the
    composed end poses, each feature where the first map holding it puts it."""
    pytest.importorskip("matplotlib")
    from mapjoin.plot import chained_local_maps

    maps = mapio.read_maps(simulated_folder)
    chained = chained_local_maps(maps, "chain")
    start = np.zeros(3)
    expected_features: dict[int, np.ndarray] = {}
    for k, local_map in enumerate(maps):
        for feature_id, position in zip(local_map.feature_ids.tolist(), transform(start, local_map.features)):
            expected_features.setdefault(feature_id, position)
        start = compose(start, local_map.end_pose)
        np.testing.assert_allclose(chained.poses[k, :2], start[:2], atol=1e-9)
        assert math.isclose(math.remainder(chained.poses[k, 2] - start[2], 2 * math.pi), 0.0, abs_tol=1e-12)
    assert chained.feature_ids.tolist() == sorted(expected_features)
    np.testing.assert_allclose(chained.features, [expected_features[i] for i in sorted(expected_features)],
                               atol=1e-9)
    assert chained.pose_ids.tolist() == [m.end_id for m in maps]


def test_check_minima_takes_a_folder_as_plot_join_does(simulated_folder, tmp_path):
    two = tmp_path / "two"
    two.mkdir()
    for name in ("localmap_1.yaml", "localmap_2.yaml"):
        shutil.copy(os.path.join(simulated_folder, name), two / name)
    folder = run("check-minima", str(two))
    files = run("check-minima", str(two / "localmap_1.yaml"), str(two / "localmap_2.yaml"))
    assert folder.exit_code == files.exit_code == 0, folder.stderr
    assert folder.stdout == files.stdout and "common features" in folder.stdout
    assert run("plot-join", str(two), "-o", str(tmp_path / "j.svg")).exit_code == 0
    many = run("check-minima", simulated_folder)
    assert many.exit_code == 2 and "got 12" in many.stderr


def test_batch_keeps_the_identifying_columns_and_writes_absent_values_empty(simulated_folder, tmp_path):
    report = tmp_path / "report.csv"
    assert run("join", simulated_folder, "-o", str(tmp_path / "g.csv"), "--report", str(report)).exit_code == 0
    for suffix in ("csv", "yaml"):
        out = tmp_path / f"batch.{suffix}"
        assert run("check-minima", "--batch", str(report), "-o", str(out)).exit_code == 0
        with open(report) as stream:
            joins = list(csv.DictReader(stream))
        rows = (list(csv.DictReader(out.open())) if suffix == "csv" else yaml.safe_load(out.read_text()))
        assert [(str(r["join"]), r["map"]) for r in rows] == [(j["join"], j["map"]) for j in joins]
        assert list(rows[0])[:4] == ["join", "map", "a", "c_phi"]
        table = mapio.read_minima_table(str(out))                 # read back: the identifying columns too
        assert table.map_names == tuple(j["map"] for j in joins)
        assert table.join.tolist() == [int(j["join"]) for j in joins]
    # a < 1: no phi1, phi2 (Theorem 2's zeros of fbar'' do not exist), one minimum: no second
    plain = run("check-minima", "--batch", "-", input="a,c_phi\n0.5,1\n")
    assert plain.exit_code == 0
    [row] = list(csv.DictReader(io.StringIO(plain.stdout)))
    assert list(row)[:2] == ["a", "c_phi"] and "nan" not in plain.stdout.lower()
    assert row["phi1"] == row["phi2"] == row["varphi_2"] == row["fbar_2"] == ""
    assert float(row["varphi_1"]) < 0          # the minimum of -0.5 cos(v + 1) + v^2/2 lies left of 0


def test_a_repeated_warning_is_shown_once_with_a_count(data_dir, tmp_path):
    """The tree join of VicPark 6898: the maps that share no feature (counted from the report, independently)
    are one line and a count; -v lists them all."""
    folder = str(data_dir / "VicPark_6898_local_maps")
    report = tmp_path / "report.csv"
    quiet = run("join", folder, "--strategy", "tree", "-o", str(tmp_path / "g.csv"), "--report", str(report))
    assert quiet.exit_code == 0
    with open(report) as stream:
        unlinked = sum(row["common"] == "0" for row in csv.DictReader(stream))
    assert unlinked > 2
    lines = quiet.stderr.splitlines()
    assert sum("shares no feature" in line and "more warnings" not in line for line in lines) == 1
    assert any(f"{unlinked - 1} more warnings like '... shares no feature" in line for line in lines), lines
    verbose = run("-v", "join", folder, "--strategy", "tree", "--jobs", "2", "-o", str(tmp_path / "v.csv"))
    assert sum("shares no feature" in line for line in verbose.stderr.splitlines()) == unlinked
    assert "more warning" not in verbose.stderr


def test_stderr_handler_counts_each_kind(capsys):
    handler = StderrHandler()
    logger = logging.getLogger("mapjoin.test_counts")
    logger.addHandler(handler)
    logger.propagate = False
    logger.setLevel(logging.INFO)
    try:
        for name in ("a", "b", "c"):
            logger.warning("%s shares nothing", name)
        logger.warning("one of a kind: %d", 5)
        logger.info("not a warning: %s", "x")
        logger.info("not a warning: %s", "y")
        handler.summarise()
    finally:
        logger.removeHandler(handler)
    lines = capsys.readouterr().err.splitlines()
    assert lines == ["mapjoin: warning: a shares nothing", "mapjoin: warning: one of a kind: 5",
                     "mapjoin: not a warning: x", "mapjoin: not a warning: y",
                     "mapjoin: warning: 2 more warnings like '... shares nothing' (-v lists them all)"]


@pytest.mark.parametrize("count, singular, plural, expected", [
    (0, "map", None, "0 maps"), (1, "map", None, "1 map"), (2, "file", None, "2 files"),
    (1, "minimum", "minima", "1 minimum"), (2, "minimum", "minima", "2 minima")])
def test_counted(count, singular, plural, expected):
    assert counted(count, singular, plural) == expected


def test_one_map_is_one_map(simulated_folder, tmp_path):
    first = os.path.join(simulated_folder, "localmap_1.yaml")
    joined = run("join", first, "-o", str(tmp_path / "g.csv"))
    assert joined.exit_code == 0 and "joined 1 map:" in joined.stderr and "0 joins" in joined.stderr
    converted = run("convert", first, "-o", str(tmp_path / "out/"), "--to", "csv")
    assert converted.exit_code == 0 and "converted 1 map to csv: 1 file in" in converted.stderr
    assert "(s)" not in joined.stderr + converted.stderr


def test_help_and_readme_show_no_path_of_one_machine():
    """Examples use the project's relative ../shared/data, never an absolute file:// URL of one machine."""
    runner = CliRunner()
    texts = [runner.invoke(main, ["--help"]).output]
    for name, command in main.commands.items():
        texts.append(runner.invoke(main, [name, "--help"]).output)
        for sub in getattr(command, "commands", {}):
            texts.append(runner.invoke(main, [name, sub, "--help"]).output)
    readme = os.path.join(os.path.dirname(__file__), os.pardir, "README.md")
    with open(readme, encoding="utf-8") as stream:
        texts.append(stream.read())
    for text in texts:
        assert not re.search(r"file:///(?!path/to)", text), re.search(r"file:///\S*", text).group()
        assert "/work/" not in text
