"""Start-up (issue 17, item 6): the dense backend of the exact solve against the sparse one, the chi^2
certificate that spares scipy.special against scipy's interval, and what each command imports."""

from __future__ import annotations

import importlib
import json
import math
import os
import subprocess
import sys

import click
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mapjoin import io as mapio
from mapjoin.__main__ import BLAS_THREAD_VARIABLES, one_blas_thread
from mapjoin.cli import COMMAND_MODULES, COMMAND_SUMMARIES, main
from mapjoin.evaluation import CHI2_LEVEL, chi2_interval, chi2_surely_inside
from mapjoin.joining import join
from mapjoin.refine.dense import DENSE_UNKNOWNS, DENSE_WORK, backend_for
from mapjoin.refine.problem import ExactProblem
from mapjoin.refine.solver import minimise
from mapjoin.simulation import simulate

KNOWN_OPTIMA = {"VicPark_200_local_maps": 3643.435, "DLR_200_local_maps": 11163.64}


def solve_both(maps, start, offset: float = 0.0, seed: int = 0):
    """The exact solve from ``start`` (a global map; its unknowns moved by normal noise of deviation
    ``offset``) with each backend: {backend: (problem, minimum, (pose, feature) marginal covariances)}."""
    solved = {}
    for backend in ("dense", "sparse"):
        problem = ExactProblem(maps, backend=backend)
        assert problem.backend == backend
        x = problem.pack(start)
        found = minimise(problem, x + np.random.default_rng(seed).normal(0, offset, x.size))
        solved[backend] = problem, found, problem.marginals(found.final_factor(problem))
    return solved


def assert_same_solve(solved, rtol):
    """Same number of steps, the same chi^2 after each (down to rounding: a single map's optimum is 0), the
    same optimum and marginal covariances."""
    (_, a, (pa, fa)), (_, b, (pb, fb)) = solved["dense"], solved["sparse"]
    assert a.iterations == b.iterations and a.converged and b.converged
    np.testing.assert_allclose(a.costs, b.costs, rtol=1e-9, atol=1e-14 * b.costs[0])
    scale = 1.0 + np.max(np.abs(b.x))
    np.testing.assert_allclose(a.x, b.x, rtol=0, atol=1e-9 * scale)
    for dense_blocks, sparse_blocks in ((pa, pb), (fa, fb)):
        np.testing.assert_allclose(dense_blocks, sparse_blocks, rtol=rtol, atol=rtol * np.abs(sparse_blocks).max())
        assert np.array_equal(dense_blocks, dense_blocks.transpose(0, 2, 1))   # written as a triangle in CSV


@pytest.mark.parametrize("name", ["VicPark_200_local_maps", "DLR_200_local_maps", "8240_data_50_local_maps"])
def test_dense_and_sparse_backends_solve_the_real_datasets_alike(name, data_dir):
    """Every chi^2 on the way (1e-9 relative), the optimum and the marginal covariances agree, and the dense
    backend reaches the known optima (1e-6 relative)."""
    maps = mapio.read_maps([str(data_dir / name)])
    solved = solve_both(maps, join(maps, strategy="tree").global_map)
    assert_same_solve(solved, rtol=1e-9)
    if name in KNOWN_OPTIMA:
        assert solved["dense"][1].cost == pytest.approx(KNOWN_OPTIMA[name], rel=1e-6)


@settings(max_examples=25, deadline=None)
@given(count=st.integers(1, 8), seed=st.integers(0, 10_000), full=st.booleans(), noise=st.floats(0.0, 0.3))
def test_dense_and_sparse_backends_solve_small_simulations_alike(count, seed, full, noise):
    """Small simulated chains (full or spherical covariances), started off the fast join by noise."""
    maps = list(simulate(count, seed=seed, full_covariance=full).maps)
    assert_same_solve(solve_both(maps, join(maps).global_map, noise, seed), rtol=1e-9)


def test_dense_backend_equals_the_sparse_one_on_a_singular_problem():
    """A feature seen by no map's information cannot be: both backends call exact singularity RuntimeError."""
    maps = list(simulate(3, seed=1).maps)
    for backend in ("dense", "sparse"):
        problem = ExactProblem(maps, backend=backend)
        data = problem.linearise(problem.pack(join(maps).global_map))[0] * 0.0
        with pytest.raises(RuntimeError):
            problem.solve(problem.factorise(data), np.ones(problem.n_unknowns))


@pytest.mark.parametrize("name, count", [("VicPark_200_local_maps", 120), ("DLR_200_local_maps", 80)])
def test_auto_takes_the_dense_backend_for_real_prefixes_below_the_crossover_and_it_solves_them_as_sparse(
        name, count, data_dir):
    """The first maps of the real datasets (732 and 762 unknowns), well below DENSE_WORK: ``auto`` is dense, and
    the dense solve equals the sparse one (every chi^2 to 1e-9, the optimum, the marginal covariances)."""
    maps = mapio.read_maps([str(data_dir / name)])[:count]
    assert ExactProblem(maps).backend == "dense"
    assert_same_solve(solve_both(maps, join(maps, strategy="tree").global_map), rtol=1e-9)


class _Partition:
    """A stand-in for refine.dense.Partition of a given work."""

    def __init__(self, work: float):
        self.work = work


def test_auto_backend_is_dense_up_to_the_measured_work():
    """``auto``: dense while the partition's work is at most DENSE_WORK; beyond DENSE_UNKNOWNS not even
    partitioned; a forced backend is taken as it is."""
    assert backend_for("auto", 10, lambda: _Partition(DENSE_WORK))[0] == "dense"
    assert backend_for("auto", 10, lambda: _Partition(DENSE_WORK * 1.01)) == ("sparse", None)
    assert backend_for("auto", DENSE_UNKNOWNS + 1, lambda: pytest.fail("partitioned")) == ("sparse", None)
    assert backend_for("sparse", 3, lambda: pytest.fail("partitioned")) == ("sparse", None)
    assert backend_for("dense", 10**6, lambda: _Partition(1e30))[0] == "dense"
    with pytest.raises(ValueError, match="backend"):
        backend_for("cholmod", 10, lambda: _Partition(0.0))
    small = list(simulate(2, seed=0).maps)
    assert ExactProblem(small).backend == "dense"


# ---- the chi^2 certificate ------------------------------------------------------------------------


@settings(max_examples=400, deadline=None)
@given(dof=st.one_of(st.integers(1, 30), st.integers(1, 10**7)), z=st.floats(-6.0, 6.0))
def test_a_chi2_surely_inside_is_inside_scipys_interval(dof, z):
    """Sound: whatever it certifies lies in scipy's central interval (chdtri), around dof +- 6 sigma."""
    cost = dof + z * math.sqrt(2 * dof)
    if cost <= 0:
        cost = dof * 1e-3
    if chi2_surely_inside(cost, dof):
        low, high = chi2_interval(dof, CHI2_LEVEL)
        assert low <= cost <= high


@pytest.mark.parametrize("dof", [10, 100, 2800, 7180, 10**6])
def test_the_chi2_certificate_covers_two_sigma(dof):
    """Useful: the values a well-weighted problem gives (within two standard deviations) need no scipy; far
    out it certifies nothing (and the verdict, with scipy, decides)."""
    sigma = math.sqrt(2 * dof)
    assert all(chi2_surely_inside(dof + z * sigma, dof) for z in np.linspace(-1.7, 2.0, 9))
    low, high = chi2_interval(dof, CHI2_LEVEL)
    assert not chi2_surely_inside(low * 0.999, dof) and not chi2_surely_inside(high * 1.001, dof)
    assert not chi2_surely_inside(0.0, dof) and not chi2_surely_inside(math.inf, dof)
    assert not chi2_surely_inside(dof, 0)


# ---- what the commands import -------------------------------------------------------------------------

_IMPORTS = """
import json, runpy, sys
sys.argv = ["mapjoin", *sys.argv[1:]]
try:
    runpy.run_module("mapjoin", run_name="__main__", alter_sys=True)
except SystemExit as exit:
    code = exit.code
print(json.dumps([code, sorted(sys.modules)]), file=sys.stderr)
"""


def imported(*args: str) -> set[str]:
    """The modules a fresh interpreter holds after ``mapjoin ARGS`` (which must succeed)."""
    process = subprocess.run([sys.executable, "-c", _IMPORTS, *args], capture_output=True, text=True, check=False)
    code, modules = json.loads(process.stderr.splitlines()[-1])
    assert code in (0, None), process.stderr
    return set(modules)


def test_join_imports_neither_scipy_nor_the_other_commands(data_dir, tmp_path):
    modules = imported("join", str(data_dir / "8240_data_50_local_maps"), "-o", str(tmp_path / "g.csv"))
    assert "mapjoin.cli.join" in modules
    heavy = {m for m in modules if m.split(".")[0] in ("scipy", "yaml", "matplotlib")
             or m in ("numpy.ma", "numpy.random", "mapjoin.refine", "mapjoin.cli.refine", "mapjoin.cli.build",
                      "mapjoin.build", "mapjoin.evaluation", "mapjoin.simulation", "mapjoin.cli.plot",
                      "mapjoin.association")}
    assert not heavy


def test_joins_default_association_gate_is_the_librarys():
    """cli/join.py writes the association gate's default out (not to import the association module)."""
    from mapjoin.association import DEFAULT_GATE
    from mapjoin.cli.join import DEFAULT_ASSOCIATION_GATE

    assert DEFAULT_ASSOCIATION_GATE == DEFAULT_GATE


def test_dense_refines_and_confirmations_import_no_scipy(data_dir, tmp_path):
    """Problems within DENSE_WORK import no scipy: a small refine, 8240's (its chi^2, 458.15, certified inside
    its interval, needs no scipy.special either), VicPark 200's and DLR 200's quiet refines (the issue's
    target command) and DLR 200's join, whose confirmation solves its first ~182 maps."""
    def scipy_modules(*args: str) -> set[str]:
        return {m for m in imported(*args, "-o", str(tmp_path / "out.csv")) if m.split(".")[0] == "scipy"}

    assert not scipy_modules("refine", str(data_dir / "535_data_5_local_maps"))
    assert not scipy_modules("refine", str(data_dir / "8240_data_50_local_maps"))
    assert not scipy_modules("-q", "refine", str(data_dir / "VicPark_200_local_maps"))
    assert not scipy_modules("-q", "refine", str(data_dir / "DLR_200_local_maps"))
    assert not scipy_modules("-q", "join", str(data_dir / "DLR_200_local_maps"))
    # VicPark 200's chi^2/dof of 0.51 is outside its interval: the warning's bounds need no scipy either
    assert not scipy_modules("refine", str(data_dir / "VicPark_200_local_maps"))


def test_the_issues_commands_import_no_numpy_ma(data_dir, tmp_path):
    """numpy.ma (7 ms of start-up) is loaded by np.unique and np.isin without indices: neither DLR 200's join,
    whose confirmation puts two pieces' optima together, nor VicPark 200's refine call them."""
    for args, solved in ((("join", "DLR_200_local_maps"), "mapjoin.confirmation"),
                         (("refine", "VicPark_200_local_maps"), "mapjoin.refine.solver")):
        modules = imported("-q", args[0], str(data_dir / args[1]), "-o", str(tmp_path / "out.csv"))
        assert solved in modules and "numpy.ma" not in modules, args


#: every format module of mapjoin.io (io/registry.FORMATS names their functions, imported on use)
_FORMAT_MODULES = {f"mapjoin.io.{name}" for name in ("yaml_maps", "csv_maps", "csv_blocks", "mat_maps", "matfile",
                                                     "linearslam", "global_maps", "g2o", "tables", "trajectory",
                                                     "truth", "csvtable", "yamldoc")}


@pytest.mark.parametrize("source, used", [
    ("8240_data_50_local_maps", {"mat_maps", "matfile"}),
    ("8240.csv", {"csv_blocks", "csv_maps"}),
    ("8240.yaml", {"yaml_maps"}),
])
def test_a_join_imports_the_formats_it_reads_and_writes_only_and_no_confirmation(source, used, data_dir, tmp_path):
    """A join of .mat, CSV or YAML maps to a CSV global map: its reader's modules and the CSV writer's, no other
    format's, and, with no join flagged, neither the confirmation nor the exact solve nor
    statistics (chi2_quantile's NormalDist, asked by no join)."""
    if source.startswith("8240."):
        maps = mapio.read_maps([str(data_dir / "8240_data_50_local_maps")])
        mapio.write_maps(maps, str(tmp_path / source), source.split(".")[1])
        source = tmp_path / source
    else:
        source = data_dir / source
    modules = imported("join", str(source), "-o", str(tmp_path / "g.csv"))
    expected = {f"mapjoin.io.{name}" for name in used | {"global_maps", "csvtable", "yamldoc"}}  # the CSV writer's
    assert modules & _FORMAT_MODULES == expected
    assert not modules & {"mapjoin.confirmation", "mapjoin.refine", "mapjoin.evaluation", "statistics"}


def test_a_join_imports_a_table_or_trajectory_writer_when_asked_for_one(data_dir, tmp_path):
    """The reverse of the test above: --report and --trajectory do import their writers."""
    modules = imported("join", str(data_dir / "535_data_5_local_maps"), "-o", str(tmp_path / "g.yaml"),
                       "--report", str(tmp_path / "r.json"), "--trajectory", str(tmp_path / "t.tum"))
    assert {"mapjoin.io.tables", "mapjoin.io.trajectory", "mapjoin.io.global_maps", "mapjoin.io.yamldoc"} <= modules
    assert "mapjoin.io.csv_maps" not in modules and "mapjoin.io.linearslam" not in modules


def test_quiet_refine_without_a_flagged_join_imports_no_confirmation(data_dir, tmp_path):
    """refine VicPark 200 -q (the issue's target; its fast join flags nothing): the exact solve, no confirmation,
    no chi^2 verdict (-q), no format it does not read or write."""
    modules = imported("-q", "refine", str(data_dir / "VicPark_200_local_maps"), "-o", str(tmp_path / "x.csv"))
    assert "mapjoin.refine.solver" in modules
    assert not modules & {"mapjoin.confirmation", "mapjoin.evaluation", "statistics", "mapjoin.io.tables",
                          "mapjoin.io.trajectory", "mapjoin.io.yaml_maps", "mapjoin.io.linearslam"}


def test_convert_imports_no_join(data_dir, tmp_path):
    """``convert`` reads and writes maps: the shared options' constants come from below the join strategies
    (cli/common takes STRATEGIES from joins), so it imports no join module, and only its two formats."""
    modules = imported("convert", str(data_dir / "535_data_5_local_maps"), "-o", str(tmp_path / "maps.yaml"))
    assert "mapjoin.cli.convert" in modules and "mapjoin.io.yaml_maps" in modules
    assert not modules & {"mapjoin.joining", "mapjoin.drift", "mapjoin.streaming", "mapjoin.confirmation",
                          "mapjoin.refine", "mapjoin.io.csv_maps", "mapjoin.io.linearslam", "mapjoin.io.tables"}


def test_importing_io_imports_no_format_module_and_each_of_its_names_resolves():
    """``import mapjoin.io``: its own layers only (paths, registry, inputs, lines, outputs); the names it takes from
    format modules (``Trajectory``, ``STAB_NOISE``, ...) are the modules' own, imported when asked for."""
    code = "import json, sys, mapjoin.io; print(json.dumps(sorted(m for m in sys.modules if m.startswith('mapjoin.io.'))))"
    loaded = json.loads(subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                                       check=True).stdout)
    assert loaded == [f"mapjoin.io.{name}" for name in ("inputs", "lines", "outputs", "paths", "registry")]
    for name in mapio.__all__:
        assert getattr(mapio, name) is not None, name
    from mapjoin.io import mat_maps, tables, trajectory, truth

    assert (mapio.STAB_NOISE, mapio.MinimaTable, mapio.Trajectory, mapio.read_truth_folder) == (
        mat_maps.STAB_NOISE, tables.MinimaTable, trajectory.Trajectory, truth.read_truth_folder)
    with pytest.raises(AttributeError):
        mapio.no_such_name  # noqa: B018


def test_every_function_the_format_registry_names_exists():
    """io/registry.FORMATS names its codecs' functions by ``module.function`` (imported on use): each resolves,
    so that a misspelt name fails here, not in a user's command."""
    from mapjoin.io import registry

    named = [fmt.sniff for fmt in registry.FORMATS] + [fmt.map_number for fmt in registry.FORMATS]
    named += [function for fmt in registry.FORMATS for kind in (registry.LOCAL_MAPS, registry.GLOBAL_MAP, registry.TRUTH,
                                                                registry.TABLE, registry.TRAJECTORY)
              if (codec := fmt.codec(kind)) for function in codec]
    references = [function.reference for function in named if function is not None]
    assert len(references) >= 30
    for reference in references:
        module, name = reference.rsplit(".", 1)
        assert callable(getattr(importlib.import_module(f"mapjoin.io.{module}"), name)), reference


# ---- the lazily loaded commands ---------------------------------------------------------------------


def test_every_command_lives_in_the_module_it_is_listed_under():
    """COMMAND_MODULES names each command's module, and no module registers a command it does not list."""
    commands = dict(main.commands.items())       # imports every command's module
    assert set(commands) == set(COMMAND_MODULES)
    for name, command in commands.items():
        assert command.callback.__module__ == f"mapjoin.cli.{COMMAND_MODULES[name]}", name
        assert command.name == name


def test_help_lists_every_command_with_its_short_help():
    from click.testing import CliRunner

    output = CliRunner().invoke(main, ["--help"]).output
    listed = output.split("Commands:\n", 1)[1].splitlines()
    assert [line.split()[0] for line in listed if line.strip()] == sorted(COMMAND_MODULES)
    for name in COMMAND_MODULES:
        short = main.commands[name].get_short_help_str(limit=200)
        assert any(line.split(None, 1) == [name, short] for line in listed), name


def test_command_summaries_are_the_first_paragraphs_of_the_commands_help():
    """COMMAND_SUMMARIES, which ``mapjoin --help`` lists, holds every command's and only theirs, each the first
    paragraph of the command's help (click shortens that paragraph to the listed line)."""
    assert set(COMMAND_SUMMARIES) == set(COMMAND_MODULES)
    for name, summary in COMMAND_SUMMARIES.items():
        assert " ".join(main.commands[name].help.split("\n\n")[0].split()) == summary, name


@pytest.mark.parametrize("width", [30, 45, 52, 60, 80, 120, 200])
def test_help_lists_the_commands_as_click_lists_their_modules_commands(width):
    """At any width (narrow ones shorten the summaries with "..."), the list made from COMMAND_SUMMARIES equals
    click's own list made from the commands themselves (every command's module imported)."""
    ctx = click.Context(main, info_name="mapjoin")
    from_summaries, from_commands = click.HelpFormatter(width=width), click.HelpFormatter(width=width)
    main.format_commands(ctx, from_summaries)
    click.Group.format_commands(main, ctx, from_commands)
    assert "Commands:" in from_commands.getvalue()
    assert from_summaries.getvalue() == from_commands.getvalue()


@pytest.mark.parametrize("option", ["--help", "--version"])
def test_help_and_version_import_no_command_module_no_numpy_and_no_logging(option):
    """``mapjoin --help`` lists the commands by their summaries: no command's module, no numpy; it and
    ``--version`` end before the group's callback, which sets up logging."""
    modules = imported(option)
    assert "mapjoin.cli" in modules
    assert not {m for m in modules if m.startswith("mapjoin.cli.")}
    assert not {m for m in modules if m.split(".")[0] in ("numpy", "scipy", "yaml", "logging")}


def test_dense_module_needs_no_scipy():
    """refine/dense.py is numpy's: imported alone it loads no scipy."""
    code = "import sys, mapjoin.refine.problem; print(any(m.startswith('scipy') for m in sys.modules))"
    assert subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip() \
        == "False"


# ---- OpenBLAS's threads in the command ---------------------------------------------------------------

_THREADS = """
import json, os, runpy, sys
sys.argv = ["mapjoin", *sys.argv[1:]]
try:
    runpy.run_module("mapjoin", run_name="__main__", alter_sys=True)
except SystemExit:
    pass
print(json.dumps([os.environ.get("OPENBLAS_NUM_THREADS"), len(os.listdir("/proc/self/task"))]), file=sys.stderr)
"""


def blas_threads(data_dir, tmp_path, **environment: str) -> tuple[str | None, int]:
    """``(OPENBLAS_NUM_THREADS, threads of the process)`` after ``mapjoin refine`` of a small dataset in a fresh
    interpreter whose environment has no BLAS thread variable but ``environment``."""
    env = {k: v for k, v in os.environ.items() if k not in BLAS_THREAD_VARIABLES} | environment
    process = subprocess.run([sys.executable, "-c", _THREADS, "refine", str(data_dir / "535_data_5_local_maps"),
                              "-o", str(tmp_path / "exact.csv")], capture_output=True, text=True, env=env, check=False)
    variable, threads = json.loads(process.stderr.splitlines()[-1])
    return variable, threads


@pytest.mark.skipif(not os.path.isdir("/proc/self/task"), reason="counts the process's threads in /proc")
def test_the_command_runs_openblas_on_one_thread_unless_told(data_dir, tmp_path):
    """OpenBLAS starts its worker threads when numpy loads it: the command's process has none of them, unless
    the environment asked for a count (then OpenBLAS's own threads are there: the count is what OpenBLAS read)."""
    assert blas_threads(data_dir, tmp_path) == ("1", 1)
    variable, threads = blas_threads(data_dir, tmp_path, OPENBLAS_NUM_THREADS="2")
    assert variable == "2" and threads >= 2
    variable, threads = blas_threads(data_dir, tmp_path, OMP_NUM_THREADS="2")
    assert variable is None and threads >= 2


def test_a_program_running_the_command_keeps_its_blas_threads(monkeypatch):
    """numpy loaded already (this test process): the environment is left alone, as it would change nothing here
    but only what this process starts."""
    for name in BLAS_THREAD_VARIABLES:
        monkeypatch.delenv(name, raising=False)
    one_blas_thread()
    assert not any(name in os.environ for name in BLAS_THREAD_VARIABLES)
