"""The command line: outputs, exit codes, pipelines, and one-line errors for bad input."""

from __future__ import annotations

import csv
import io
import json
import math
import os
import subprocess
import sys

import numpy as np
import pytest
from cli_runner import run
from click.testing import CliRunner

from mapjoin import io as mapio
from mapjoin.cli import main
from mapjoin.errors import InputError


def rows(text: str) -> list[dict[str, str]]:
    return list(csv.DictReader(io.StringIO(text)))


def test_version_and_every_help_has_examples():
    assert run("--version").output.startswith("mapjoin, version ")
    for command in ("join", "check-minima", "convert", "simulate", "compare", "evaluate", "refine"):
        result = run(command, "--help")
        assert result.exit_code == 0 and "Examples:" in result.output, command


def test_join_writes_the_documented_csv_contract(simulated_folder, tmp_path):
    report = tmp_path / "report.csv"
    result = run("join", simulated_folder, "--report", str(report))
    assert result.exit_code == 0, result.output
    table = rows(result.stdout)
    assert {"kind", "id", "x", "y", "phi"} <= set(table[0])
    poses = [r for r in table if r["kind"] == "pose"]
    features = [r for r in table if r["kind"] == "feature"]
    assert [int(r["id"]) for r in poses] == list(range(1, 13))
    assert all(r["phi"] == "" for r in features) and features
    joins = rows(report.read_text())
    assert len(joins) == 11 and {"a", "c_phi", "minima"} <= set(joins[0])
    assert "joined 12 maps" in result.stderr


def test_join_yaml_output_by_extension_equals_csv(simulated_folder, tmp_path):
    from mapjoin import io as mapio

    run("join", simulated_folder, "-o", str(tmp_path / "g.yaml"))
    run("join", simulated_folder, "-o", str(tmp_path / "g.csv"))
    a = mapio.read_global_map(tmp_path / "g.yaml")
    b = mapio.read_global_map(tmp_path / "g.csv")
    np.testing.assert_array_equal(a.features, b.features)
    np.testing.assert_array_equal(a.poses, b.poses)
    assert a.provenance.covariance == "information"


def test_convert_round_trip_gives_the_same_join(data_dir, tmp_path):
    folder = data_dir / "VicPark_200_local_maps"
    out = tmp_path / "yaml"
    assert run("convert", str(folder), "-o", f"{out}/", "--to", "yaml").exit_code == 0
    assert len(list(out.glob("localmap_*.yaml"))) == 200
    direct, converted = run("-q", "join", str(folder)), run("-q", "join", str(out))
    assert direct.exit_code == converted.exit_code == 0
    assert direct.stdout.startswith("kind,id,x,y,phi") and direct.stdout == converted.stdout


def test_vicpark_200_has_299_features_200_poses_and_199_single_minimum_joins(data_dir, tmp_path):
    report = tmp_path / "r.csv"
    result = run("-q", "join", str(data_dir / "VicPark_200_local_maps"), "--report", str(report))
    assert result.exit_code == 0, result.output
    table = rows(result.stdout)
    assert sum(r["kind"] == "feature" for r in table) == 299
    assert sum(r["kind"] == "pose" for r in table) == 200
    joins = rows(report.read_text())
    assert len(joins) == 199 and all(r["minima"] == "1" for r in joins)
    assert result.stderr == ""


@pytest.mark.parametrize("strategy", ["sequential", "tree"])
@pytest.mark.parametrize("name", ["DLR_200_local_maps", "535_data_5_local_maps", "8240_data_50_local_maps",
                                  "VicPark_6898_local_maps"])
def test_every_real_dataset_joins(data_dir, name, strategy, tmp_path):
    out = tmp_path / "g.csv"
    result = run("join", str(data_dir / name), "-o", str(out), "--strategy", strategy)
    assert result.exit_code == 0, result.output
    assert f"{strategy}, " in result.stderr
    assert out.exists()


def test_tree_join_with_jobs_prints_the_same_map(simulated_folder):
    one = run("-q", "join", simulated_folder, "--strategy", "tree")
    two = run("-q", "join", simulated_folder, "--strategy", "tree", "--jobs", "2")
    assert one.exit_code == two.exit_code == 0
    assert one.stdout == two.stdout and one.stdout.startswith("kind,id,x,y,phi")
    refused = run("join", simulated_folder, "--jobs", "2")
    assert refused.exit_code == 2 and "add --strategy tree" in refused.output


def test_check_minima_paper_case_is_unique():
    result = run("check-minima", "--a", "203570", "--c-phi", "-0.0028")
    assert result.exit_code == 0
    assert "1 minimum" in result.stdout and "(16)" in result.stdout and "(21)" in result.stdout


def test_check_minima_two_minima_exit_code_and_json():
    result = run("check-minima", "--a", "5", "--c-phi", "2.5", "--json")
    assert result.exit_code == 3
    document = json.loads(result.stdout)
    assert document["minima"] == 2 and len(document["conditions"]) == 6
    assert all(c["holds"] for c in document["conditions"])
    # both reported minima are stationary points of fbar (an independent check)
    for varphi in (document["varphi_1"], document["varphi_2"]):
        assert abs(5 * math.sin(varphi + 2.5) + varphi) < 1e-9


def test_check_minima_of_two_map_files(data_dir):
    folder = data_dir / "VicPark_200_local_maps"
    result = run("check-minima", str(folder / "localmap_1.mat"), str(folder / "localmap_2.mat"), "--json")
    assert result.exit_code == 0, result.output
    document = json.loads(result.stdout)
    assert document["join"]["common"] > 0 and document["minima"] == 1


@pytest.mark.parametrize("args, message", [
    (["join", "missing.yaml"], "missing.yaml"),
    (["check-minima"], "exactly one of"),
    (["check-minima", "--a", "1"], "go together"),
    (["check-minima", "--a", "nan", "--c-phi", "0"], "finite"),
], ids=["missing-file", "no-mode", "a-without-c", "nan-a"])
def test_errors_are_one_line_without_traceback(args, message):
    result = CliRunner().invoke(main, args)
    assert result.exit_code in (1, 2)
    assert message in result.output
    assert "Traceback" not in result.output


@pytest.mark.parametrize("args, option", [
    (["join", "-", "-o", "-"], "--input-format"),
    (["join", "{maps}", "-o", "{out}/global.txt"], "--format"),
    (["convert", "{maps}", "-o", "{out}/maps.txt"], "--to"),
    (["build", "-", "-o", "{out}/maps/"], "--raw-format"),
], ids=["join-stdin", "join-output", "convert-output", "build-raw"])
def test_a_format_the_library_cannot_tell_is_asked_for_by_the_commands_option(simulated_folder, tmp_path, args,
                                                                                  option):
    """The library says "give its format" (its argument); each command names its own option instead."""
    args = [arg.format(maps=simulated_folder, out=tmp_path) for arg in args]
    result = run(*args, input="hello\n")
    assert result.exit_code == 1
    assert result.stderr.rstrip().endswith(f"pass {option}"), result.stderr
    with pytest.raises(InputError, match="give its format$"):
        mapio.read_maps(["-"], stdin=io.StringIO("hello\n"))


def test_output_that_is_an_input_is_refused_and_nothing_written(simulated_folder):
    target = os.path.join(simulated_folder, "localmap_1.yaml")
    before = open(target).read()
    result = CliRunner().invoke(main, ["join", simulated_folder, "-o", target])
    assert result.exit_code == 1 and "input" in result.output
    assert open(target).read() == before


def test_broken_chain_names_both_maps(simulated_folder):
    result = CliRunner().invoke(main, ["join", os.path.join(simulated_folder, "localmap_1.yaml"),
                                       os.path.join(simulated_folder, "localmap_3.yaml")])
    assert result.exit_code == 1
    assert "does not connect" in result.output and "localmap_3.yaml" in result.output


def test_shell_pipeline_simulate_join():
    """The README's pipeline, run by a real shell."""
    command = (f"{sys.executable} -m mapjoin simulate -o - --maps 15 --seed 2 "
               f"| {sys.executable} -m mapjoin join - | head -n 3")
    result = subprocess.run(command, shell=True, capture_output=True, text=True, check=True)
    lines = result.stdout.splitlines()
    assert lines[0].startswith("kind,id,x,y,phi") and len(lines) == 3
    assert "Traceback" not in result.stderr


def test_check_minima_batch_reads_a_join_report_and_its_own_output(tmp_path):
    """A report of `join --report` is a batch, and so is check-minima's output (.csv, .yaml, .json): the
    same a and c_phi come back, with the minima count the join certified."""
    examples = os.path.join(os.path.dirname(__file__), os.pardir, "examples", "sim20")
    report = tmp_path / "joins.csv"
    assert run("-q", "join", examples, "-o", str(tmp_path / "g.csv"), "--report", str(report)).exit_code == 0
    joins = rows(report.read_text())
    for source in ("joins.csv", "joins.yaml", "joins.json"):
        if source != "joins.csv":
            assert run("check-minima", "--batch", str(report), "-o", str(tmp_path / source)).exit_code == 0
        result = run("check-minima", "--batch", str(tmp_path / source))
        assert result.exit_code == 0, result.stderr
        table = rows(result.stdout)
        assert [(r["a"], r["c_phi"], r["minima"]) for r in table] == \
            [(r["a"], r["c_phi"], r["minima"]) for r in joins]
    assert len(joins) == 19


def test_check_minima_batch_agrees_with_brute_force_on_a_large_random_grid(tmp_path):
    from theorem_oracles import brute_count

    rng = np.random.default_rng(7)
    a = np.concatenate([10 ** rng.uniform(-2, 4, 2000), rng.uniform(1, 12, 2000)])
    c = np.concatenate([rng.uniform(-np.pi, np.pi, 2000), rng.uniform(1.2, np.pi, 2000) * rng.choice([-1, 1], 2000)])
    queries = tmp_path / "queries.csv"
    queries.write_text("a,c_phi\n" + "".join(f"{float(x)!r},{float(y)!r}\n" for x, y in zip(a, c)))
    result = run("check-minima", "--batch", str(queries))
    table = rows(result.stdout)
    counted = np.array([int(r["minima"]) for r in table])
    expected, resolved = brute_count(a, c)
    assert resolved.all()
    assert 200 < (expected == 2).sum() < len(a) - 200  # the grid covers both answers
    np.testing.assert_array_equal(counted, expected)
    assert result.exit_code == 3  # some rows have two minima
    np.testing.assert_array_equal([float(r["a"]) for r in table], a)


def test_simulate_writes_one_stream_to_a_map_file_and_a_folder_otherwise(tmp_path):
    """``-o maps.csv`` (or .yaml) is one stream file in that format, as ``-o -`` is on stdout; any
    other name is a folder of localmap_<k> files with the truth beside them."""
    stream = tmp_path / "maps.csv"
    result = run("simulate", "-o", str(stream), "--maps", "4", "--seed", "1")
    assert result.exit_code == 0 and stream.is_file()
    assert stream.read_text().startswith("map,start_id,end_id,kind")
    piped = run("simulate", "-o", "-", "--maps", "4", "--seed", "1", "--format", "csv")
    assert stream.read_text() == piped.stdout
    result = run("-q", "simulate", "-o", str(tmp_path / "maps.yaml"), "--maps", "3", "--truth", str(tmp_path / "t.csv"))
    assert result.exit_code == 0 and result.stderr == ""
    assert [m.end_id for m in mapio.read_maps([str(tmp_path / "maps.yaml")])] == [1, 2, 3]
    assert mapio.read_truth(str(tmp_path / "t.csv")).pose_ids.tolist() == [0, 1, 2, 3]
    folder = tmp_path / "run"
    assert run("-q", "simulate", "-o", str(folder), "--maps", "2").exit_code == 0
    assert sorted(p.name for p in folder.iterdir()) == ["localmap_1.yaml", "localmap_2.yaml", "truth.yaml"]
