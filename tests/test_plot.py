"""Figures (mapjoin.plot and the plot commands) and the polish of the command line.

What a figure shows is read back from its artists (their ``gid``) and checked against
independent references: the two-minima region against ``analyse_minima`` and the
brute-force counter of ``theorem_oracles``; the plotted f1 against Theorem 1's dense
formulas, and its marked minima against the discrete minima of the plotted samples.
"""

from __future__ import annotations

import functools
import io
import math
import os
import pty
import struct
import subprocess
import sys
from pathlib import Path
from xml.etree import ElementTree

import click
import numpy as np
import pytest
from cli_runner import run
from hypothesis import given, settings
from hypothesis import strategies as st
from matplotlib.path import Path as Polygon
from theorem_oracles import Dense, brute_count

from mapjoin import io as mapio
from mapjoin import plot as figures
from mapjoin.cli import main
from mapjoin.errors import InputError
from mapjoin.joining import join_sequential
from mapjoin.onestep import analyse_minima
from mapjoin.se2 import wrap

REPO = Path(__file__).resolve().parents[1]
TWO_MINIMA = [str(REPO / "examples" / "two-minima" / f"localmap_{k}.yaml") for k in (1, 2)]


def artists(figure, gid: str) -> list:
    """Every artist of ``figure`` tagged ``gid``."""
    return list(figure.findobj(lambda artist: artist.get_gid() == gid))


def check_image(path: Path) -> None:
    """``path`` holds a complete, parseable figure of the format its extension names."""
    data = path.read_bytes()
    kind = path.suffix
    if kind == ".png":
        assert data[:8] == b"\x89PNG\r\n\x1a\n" and data[12:16] == b"IHDR" and data.endswith(b"IEND\xaeB`\x82")
        width, height = struct.unpack(">II", data[16:24])
        assert 400 < width < 3000 and 300 < height < 3000
    elif kind == ".svg":
        root = ElementTree.fromstring(data)
        assert root.tag == "{http://www.w3.org/2000/svg}svg" and len(root) > 0
    else:
        assert kind == ".pdf" and data.startswith(b"%PDF-") and data.rstrip().endswith(b"%%EOF")
        assert b"/Type /Page" in data


# --------------------------------------------------------------------------- the commands


@pytest.fixture(scope="module")
def joined(simulated_folder, tmp_path_factory) -> dict[str, Path]:
    """The simulated folder joined (fast, with a report) and refined (with covariances)."""
    folder = tmp_path_factory.mktemp("joined")
    paths = {"fast": folder / "fast.csv", "exact": folder / "exact.yaml", "report": folder / "joins.json"}
    assert run("join", simulated_folder, "-o", str(paths["fast"]), "--report", str(paths["report"])).exit_code == 0
    assert run("refine", simulated_folder, "-o", str(paths["exact"])).exit_code == 0
    return paths


@pytest.mark.parametrize("extension", [".png", ".svg", ".pdf"])
def test_every_command_writes_a_valid_figure_of_each_format(extension, joined, simulated_folder, tmp_path):
    truth = os.path.join(simulated_folder, "truth.yaml")
    commands = {
        "plot": ["plot", str(joined["fast"]), str(joined["exact"]), "--truth", truth, "--ellipses"],
        "plot-minima": ["plot-minima", str(joined["report"])],
        "plot-join": ["plot-join", simulated_folder, "--join", "4"],
    }
    for name, args in commands.items():
        target = tmp_path / f"{name}{extension}"
        result = run(*args, "-o", str(target))
        assert result.exit_code == 0, result.output
        assert f"-> {target}" in result.stderr
        check_image(target)
    assert sorted(os.listdir(tmp_path)) == sorted(f"{name}{extension}" for name in commands)  # no temporary files


def test_map_figure_draws_every_map_truth_and_the_covariances_it_has(joined, simulated_folder):
    fast, exact = (mapio.read_global_map(joined[k]) for k in ("fast", "exact"))
    truth = mapio.read_truth(os.path.join(simulated_folder, "truth.yaml"))
    figure = figures.map_figure([fast, exact], ["fast", "exact"], truth, ellipses=True)
    drawn = artists(figure, "features")
    assert [len(d.get_offsets()) for d in drawn] == [len(fast.feature_ids), len(exact.feature_ids)]
    np.testing.assert_array_equal(drawn[1].get_offsets(), exact.features)
    trajectory = artists(figure, "poses")[1].get_xydata()
    np.testing.assert_array_equal(trajectory[0], [0, 0])      # starts at the first map's start pose
    np.testing.assert_array_equal(trajectory[1:], exact.poses[:, :2])
    # truth: only the features some map holds, every pose
    assert len(artists(figure, "truth-features")[0].get_offsets()) == len(np.intersect1d(truth.feature_ids,
                                                                                           fast.feature_ids))
    assert len(artists(figure, "truth-poses")[0].get_xydata()) == len(truth.pose_ids)
    legend = " ".join(t.get_text() for t in figure.legends[0].get_texts())
    assert "circles at the 95% scale of the spherical weights (not uncertainty regions)" in legend
    assert "95% ellipses from full covariances" in legend
    # the exact map's ellipses: the axes and direction of each 2x2 block in closed form (not
    # eigh), scaled to the 95% chi-square quantile for 2 degrees of freedom
    ellipses = artists(figure, "ellipses-features")[1]
    blocks = exact.feature_covariances
    xx, xy, yy = blocks[:, 0, 0], blocks[:, 0, 1], blocks[:, 1, 1]
    spread = np.hypot((xx - yy) / 2, xy)
    np.testing.assert_allclose(ellipses.get_widths(), 2 * np.sqrt(5.991464547107979 * ((xx + yy) / 2 + spread)))
    np.testing.assert_allclose(ellipses.get_heights(), 2 * np.sqrt(5.991464547107979 * ((xx + yy) / 2 - spread)))
    major_axis = 0.5 * np.arctan2(2 * xy, xx - yy)
    np.testing.assert_allclose(wrap(2 * (np.radians(ellipses.get_angles()) - major_axis)), 0, atol=1e-9)  # mod pi
    circles = artists(figure, "ellipses-poses")[0]
    np.testing.assert_allclose(circles.get_widths(), 2 * np.sqrt(5.991464547107979 * fast.pose_variances[:, 0]))
    np.testing.assert_allclose(circles.get_heights(), circles.get_widths())
    # nothing clipped: every ellipse's bounding box inside the axes' data limits
    ax = figure.axes[0]
    figure.canvas.draw()
    (x0, x1), (y0, y1) = ax.get_xlim(), ax.get_ylim()
    reach = np.sqrt(5.991464547107979 * blocks[:, [0, 1], [0, 1]])
    assert (exact.features - reach >= (x0, y0)).all() and (exact.features + reach <= (x1, y1)).all()


def test_shell_pipelines_into_the_plot_commands(tmp_path):
    """`simulate | join | plot` and a report on stdout piped into plot-minima, in a real shell."""
    mapjoin = f"{sys.executable} -m mapjoin"
    command = (f"{mapjoin} simulate -o - --maps 8 --seed 4 | {mapjoin} join - --report - -o g.csv "
               f"| {mapjoin} plot-minima - -o minima.svg && {mapjoin} plot g.csv -o map.png")
    subprocess.run(command, shell=True, cwd=tmp_path, check=True, capture_output=True)
    check_image(tmp_path / "minima.svg")
    check_image(tmp_path / "map.png")


# --------------------------------------------------------------------------- Theorem 2's region


@functools.cache
def drawn_region() -> list[Polygon]:
    """The two-minima polygons as drawn by plot-minima's figure (a up to 1e3)."""
    points = mapio.MinimaTable("test", np.array([0.5, 400.0]), np.array([0.0, 3.0]))
    figure = figures.minima_figure(points)
    polygons = artists(figure, "two-minima")
    assert len(polygons) == 2 and figure.axes[0].get_ylim()[1] == 1000
    return [Polygon(p.get_xy()) for p in polygons]


def inside(c_phi: np.ndarray, a: np.ndarray) -> np.ndarray:
    """Whether (C_phi, a) is shaded; C_phi = +-pi, where the polygons end at the plot's edges, a hair inside."""
    points = np.column_stack([np.clip(c_phi, -math.pi + 1e-9, math.pi - 1e-9), a])
    return np.logical_or.reduce([polygon.contains_points(points) for polygon in drawn_region()])


def clear_count(a: float, c_phi: float) -> int | None:
    """analyse_minima's count at (a, C_phi) when it is the same a little way off in a and C_phi, else None."""
    counts = {analyse_minima(a * fa, c_phi + dc).count for fa in (0.99, 1.0, 1.01) for dc in (-5e-3, 0.0, 5e-3)}
    return counts.pop() if len(counts) == 1 else None


def test_shaded_region_is_where_analyse_minima_and_brute_force_find_two_minima():
    rng = np.random.default_rng(5)
    c_phi = rng.uniform(-math.pi, math.pi, 6000)
    a = 10.0 ** rng.uniform(-1, 3, 6000)
    shaded = inside(c_phi, a)
    brute, resolved = brute_count(a, c_phi)
    clear = np.array([clear_count(ai, ci) for ai, ci in zip(a.tolist(), c_phi.tolist())], dtype=object)
    usable = np.array([count is not None for count in clear]) & resolved
    assert usable.sum() > 5800
    assert shaded[usable].sum() > 300 and (~shaded[usable]).sum() > 3000        # both sides sampled
    np.testing.assert_array_equal(shaded[usable], clear[usable] == 2)
    np.testing.assert_array_equal(shaded[usable], brute[usable] == 2)


@settings(max_examples=300, deadline=None)
@given(st.floats(-math.pi, math.pi), st.floats(-1.0, 3.0))
def test_shaded_region_agrees_with_analyse_minima_at_any_clear_point(c_phi, log_a):
    a = 10.0**log_a
    count = clear_count(a, c_phi)
    if count is not None:
        assert bool(inside(np.array([c_phi]), np.array([a]))[0]) == (count == 2)


def test_region_boundary_vertices_are_where_the_count_changes():
    positive, negative = figures.two_minima_region(1e3)
    tip = (math.atan(math.pi), math.hypot(1, math.pi))
    for polygon in (positive, negative):
        for c_phi, a in polygon:
            if abs(abs(c_phi) - math.pi) < 1e-9 or a >= 1e3 or math.hypot(abs(c_phi) - tip[0], a - tip[1]) < 1e-2:
                continue                                     # the C = +-pi and a = a_max edges, the tip
            below, above = analyse_minima(a * (1 - 1e-7), c_phi).count, analyse_minima(a * (1 + 1e-7), c_phi).count
            assert {below, above} == {1, 2}, (c_phi, a)


def test_report_points_are_every_join_and_two_minima_are_highlighted(tmp_path):
    joins = tmp_path / "joins.yaml"
    joins.write_text("- {join: 7, a: 5.0, c_phi: 2.5}\n- {join: 9, a: 203570, c_phi: -0.0028}\n"
                     "- {join: 12, a: 0.0, c_phi: 1.0}\n")
    points = mapio.read_minima_table(str(joins))
    figure = figures.minima_figure(points)
    two, one = artists(figure, "minima-2")[0].get_offsets(), artists(figure, "minima-1")[0].get_offsets()
    np.testing.assert_array_equal(two, [[2.5, 5.0]])                 # 5 sin 2.5 = 2.99 < pi: two minima
    assert len(one) == 2 and one[0][1] == 203570
    assert one[1][1] == figure.axes[0].get_ylim()[0] > 0             # a = 0 on the bottom edge of the log axis
    assert [t.get_text() for t in figure.axes[0].texts if t.get_text() == "7"] == ["7"]


def test_a_batch_without_join_column_has_its_problems_numbered_by_row():
    figure = figures.minima_figure(mapio.MinimaTable("batch.csv", np.array([0.5, 5.0]), np.array([1.0, 2.5])))
    assert [t.get_text() for t in figure.axes[0].texts if t.get_text().isdigit()] == ["2"]   # row 2: two minima
    assert figure.axes[0].get_title() == "batch.csv: 2 problems, 1 with two minima"


def test_a_report_reads_the_same_in_every_format_and_from_stdin(simulated_folder, tmp_path, monkeypatch):
    report = join_sequential(mapio.read_maps([simulated_folder])).report
    for extension in ("csv", "yaml", "json"):
        target = tmp_path / f"joins.{extension}"
        mapio.write_table(report, target)
        for source in (str(target), "-"):
            monkeypatch.setattr(sys, "stdin", io.StringIO(target.read_text()))
            points = mapio.read_minima_table(source)
            assert points.source == ("<stdin>" if source == "-" else str(target))
            np.testing.assert_array_equal(points.join, [r.join for r in report])
            np.testing.assert_array_equal(points.a, [r.a for r in report])
            np.testing.assert_array_equal(points.c_phi, [r.c_phi for r in report])


# --------------------------------------------------------------------------- one join's curve


def curve_minima(figure) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The plotted f1 samples (phi, f) and the marked minima (phi) of a join figure."""
    line = artists(figure, "f1")[0]
    marked = artists(figure, "minima")[0].get_xdata()
    return np.asarray(line.get_xdata()), np.asarray(line.get_ydata()), np.asarray(marked)


@pytest.mark.parametrize("case", ["two-minima", "vicpark-42", "sim535-3"])
def test_marked_minima_are_the_minima_of_the_plotted_curve(case, data_dir):
    if case == "two-minima":
        maps, join = mapio.read_maps(TWO_MINIMA), 1
    elif case == "vicpark-42":
        maps, join = mapio.read_maps([str(data_dir / "VicPark_200_local_maps")])[:44], 42
    else:
        maps, join = mapio.read_maps([str(data_dir / "535_data_5_local_maps")]), 3
    problem = figures.join_problem(maps, join, "information")
    curve = figures.join_curve(problem)
    figure = figures.join_figure(curve, case)
    phi, f, marked = curve_minima(figure)
    # the plotted curve is Theorem 1's f1, by the paper's dense matrix formulas
    dense = Dense(problem)
    sample = np.linspace(0, len(phi) - 1, 300).astype(int)
    np.testing.assert_allclose(f[sample], dense.f(phi[sample]), rtol=1e-9, atol=1e-9 * np.ptp(f))
    # brute force: the discrete local minima of the samples (the interval's ends are not minima)
    interior = np.flatnonzero((f[1:-1] < f[:-2]) & (f[1:-1] <= f[2:])) + 1
    assert len(interior) == len(marked) == (2 if case == "two-minima" else 1)
    spacing = np.diff(phi).max()
    for m in marked:
        nearest = interior[np.argmin(np.abs(phi[interior] - m))]
        assert abs(phi[nearest] - m) <= spacing
    # phi* is the lowest, and inside [z_phi - pi, z_phi + pi)
    assert f[interior].min() == pytest.approx(curve.minima[0][1], rel=1e-9, abs=1e-9)
    assert all(curve.z_phi - math.pi <= m < curve.z_phi + math.pi for m in marked)
    assert (figure.axes[1] if len(figure.axes) > 1 else figure.axes[0]).get_xlim()[0] <= curve.minima[0][0]


def test_join_problem_is_the_problem_join_sequential_solved(simulated_folder):
    maps = mapio.read_maps([simulated_folder])
    report = join_sequential(maps).report
    for record in report:
        curve = figures.join_curve(figures.join_problem(maps, record.join, "information"))
        assert len(curve.minima) == record.minima
        assert curve.a == pytest.approx(record.a, rel=1e-12)
        assert abs(wrap(curve.minima[0][0] - record.phi)) < 1e-9
        assert curve.minima[0][1] == pytest.approx(record.cost, rel=1e-9)


def test_join_problem_names_its_argument_not_a_command_line_option(simulated_folder):
    maps = mapio.read_maps([simulated_folder])
    with pytest.raises(InputError) as error:
        figures.join_problem(maps, len(maps), "information")
    assert error.value.where == "join=" and "--join" not in str(error.value)


# --------------------------------------------------------------------------- errors


@pytest.mark.parametrize("args, code, message", [
    (["plot", "missing.csv", "-o", "{tmp}/m.png"], 1, "missing.csv: cannot read"),
    (["plot", "{fast}", "-o", "{tmp}/m.jpg"], 1,
     "m.jpg: cannot tell the figure format from the extension '.jpg'; expected .png, .svg, .pdf"),
    (["plot", "{fast}", "-o", "{tmp}/m"], 1, "from no extension"),
    (["plot", "{fast}", "{fast}", "--label", "one", "-o", "{tmp}/m.png"], 2, "give one --label per map"),
    (["plot-minima", "{tmp}/bad_header.csv", "-o", "{tmp}/m.png"], 1,
     "bad_header.csv, line 1: expected a header with the columns a and c_phi"),
    (["plot-minima", "{tmp}/bad_value.csv", "-o", "{tmp}/m.png"], 1,
     "bad_value.csv, line 3, column c_phi: expected a finite number, got 'abc'"),
    (["plot-minima", "{tmp}/negative.csv", "-o", "{tmp}/m.png"], 1,
     "line 2, column a: expected a non-negative finite number"),
    (["plot-minima", "{tmp}/no_c.yaml", "-o", "{tmp}/m.png"], 1, "no_c.yaml, line 2, field [1].c_phi: missing"),
    (["plot-minima", "{tmp}/empty.json", "-o", "{tmp}/m.png"], 1, "empty.json: expected at least one row"),
    (["plot", "{tmp}/old.png", "-o", "{tmp}/old.png"], 1, "old.png: is an input file"),
    (["plot-join", "{sim}", "-o", "{tmp}/m.png"], 2, "12 maps: choose a join with --join K (1 to 11"),
    (["plot-join", "{sim}", "--join", "12", "-o", "{tmp}/m.png"], 1, "--join: expected a join number from 1 to 11"),
    (["plot-join", "{map1}", "{map3}", "-o", "{tmp}/m.png"], 1, "does not connect"),
], ids=["missing-map", "bad-extension", "no-extension", "labels", "report-header", "report-value",
        "report-negative-a", "report-yaml-field", "report-empty", "overwrite-input", "join-needed",
        "join-out-of-range", "broken-chain"])
def test_errors_are_one_line_naming_the_file_and_nothing_is_written(args, code, message, joined, simulated_folder,
                                                                      tmp_path):
    (tmp_path / "bad_header.csv").write_text("join,x,y\n1,2,3\n")
    (tmp_path / "bad_value.csv").write_text("a,c_phi\n1,0.5\n2,abc\n")
    (tmp_path / "negative.csv").write_text("c_phi,a\n0.5,-1\n")
    (tmp_path / "no_c.yaml").write_text("- {a: 1, c_phi: 0}\n- {a: 2}\n")
    (tmp_path / "empty.json").write_text("[]\n")
    (tmp_path / "old.png").write_bytes(b"\x89PNG\r\n\x1a\n")
    before = sorted(os.listdir(tmp_path))
    values = {"tmp": str(tmp_path), "fast": str(joined["fast"]), "sim": simulated_folder,
              "map1": os.path.join(simulated_folder, "localmap_1.yaml"),
              "map3": os.path.join(simulated_folder, "localmap_3.yaml")}
    result = run(*[arg.format(**values) for arg in args])
    assert result.exit_code == code
    lines = result.stderr.strip().splitlines()
    if code == 2:   # click's usage error: the usage, a hint, then the one error line
        lines = [line for line in lines if not line.startswith(("Usage: ", "Try ")) and line]
    assert lines == [lines[0]] and lines[0].startswith("Error: ") and message in lines[0]
    assert sorted(os.listdir(tmp_path)) == before


def test_without_matplotlib_the_figures_say_how_to_install_it_and_the_rest_works(joined, tmp_path):
    script = ("import sys; sys.modules['matplotlib'] = None\n"    # makes `import matplotlib` fail
              "from mapjoin.cli import main\n"
              "main(sys.argv[1:])")
    target = tmp_path / "m.png"
    result = subprocess.run([sys.executable, "-c", script, "plot", str(joined["fast"]), "-o", str(target)],
                            capture_output=True, text=True, check=False)
    assert result.returncode == 1 and not target.exists()
    assert result.stderr == "Error: figures need matplotlib, an optional extra: pip install 'mapjoin-slam[plot]'\n"
    result = subprocess.run([sys.executable, "-c", script, "compare", str(joined["fast"]), str(joined["fast"])],
                            capture_output=True, text=True, check=False)
    assert result.returncode == 0 and "x (m)" in result.stdout


def test_matplotlib_is_imported_only_to_draw():
    code = ("import sys, mapjoin.cli, mapjoin.plot\n"
            "from mapjoin.cli import main\n"
            "assert not [m for m in sys.modules if m.startswith('matplotlib')], 'imported'\n")
    subprocess.run([sys.executable, "-c", code], check=True)


# --------------------------------------------------------------------------- the command line's polish


def every_command(group: click.Group, path: tuple[str, ...] = ()):
    """``(words, command, listing)`` for every command under ``group``, subcommands of groups too;
    ``listing`` is the parent's --help, which lists the command with its summary."""
    listing = run(*path, "--help").output
    for name, command in group.commands.items():
        yield (*path, name), command, listing
        if isinstance(command, click.Group):
            yield from every_command(command, (*path, name))


def test_every_command_has_examples_and_a_whole_summary_line():
    for words, command, listing in every_command(main):
        assert "Examples:" in run(*words, "--help").output, words
        summary = command.get_short_help_str(limit=1000)
        assert f"  {words[-1]}  " in listing and summary in listing, (words, summary)   # not cut to "..."
    assert run("--version").output.startswith("mapjoin, version ")


@pytest.mark.parametrize("shell, marker", [
    ("bash", "complete -o nosort -F _mapjoin_completion mapjoin"),
    ("zsh", "#compdef mapjoin"),
    ("fish", "complete --no-files --command mapjoin"),
])
def test_shell_completion_scripts_and_completions(shell, marker):
    """The installed `mapjoin` script (click names the variable after it) prints each shell's script."""
    mapjoin = str(Path(sys.executable).parent / "mapjoin")
    environment = {**os.environ, "_MAPJOIN_COMPLETE": f"{shell}_source"}
    script = subprocess.run([mapjoin], env=environment, capture_output=True, text=True, check=True).stdout
    assert marker in script
    if shell == "bash":   # the script's protocol: complete "mapjoin plot" to the three plot commands
        environment = {**os.environ, "_MAPJOIN_COMPLETE": "bash_complete", "COMP_WORDS": "mapjoin plot",
                       "COMP_CWORD": "1"}
        answer = subprocess.run([mapjoin], env=environment, capture_output=True, text=True, check=True).stdout
        assert answer.split() == ["plain,plot", "plain,plot-join", "plain,plot-minima"]


def run_on_a_terminal(*args: str) -> tuple[int, str]:
    """``mapjoin ARGS`` with stderr on a pseudo-terminal: exit code and what the terminal showed."""
    leader, follower = pty.openpty()
    process = subprocess.Popen([sys.executable, "-m", "mapjoin", *args], stdout=subprocess.DEVNULL,
                               stderr=follower, stdin=subprocess.DEVNULL)
    os.close(follower)
    shown = b""
    while True:
        try:
            chunk = os.read(leader, 4096)
        except OSError:   # the terminal closed
            break
        if not chunk:
            break
        shown += chunk
    os.close(leader)
    return process.wait(), shown.decode()


@pytest.mark.parametrize("command", ["join", "refine"])
def test_progress_on_a_terminal_only_and_not_with_quiet_and_a_summary_at_the_end(command, simulated_folder, tmp_path):
    code, shown = run_on_a_terminal(command, simulated_folder, "-o", str(tmp_path / "g.csv"))
    if command == "join":  # read as joined: the count so far (a stream's length is known at its end only)
        assert code == 0 and "maps joined: 1" in shown
    else:
        assert code == 0 and "fast join" in shown and "100%" in shown
    summary = shown.replace("\r\x1b[K", "\n").strip().splitlines()[-1]
    assert f"{command.rstrip('e')}ed 12 maps: " in summary and "12 poses, 11 joins (0 with two minima, " in summary
    assert summary.endswith(f"-> {tmp_path / 'g.csv'}") and " features, " in summary and " s " in summary
    code, shown = run_on_a_terminal("-q", command, simulated_folder, "-o", str(tmp_path / "q.csv"))
    assert code == 0 and shown == ""
    result = run(command, simulated_folder, "-o", str(tmp_path / "n.csv"), "--gate", "0")  # not a terminal
    assert "%" not in result.stderr and "\r" not in result.stderr and result.stderr.count("\n") == 1


def test_verbose_join_prints_one_line_per_join(simulated_folder):
    result = run("-v", "join", simulated_folder)
    lines = [line for line in result.stderr.splitlines() if line.startswith("join ")]
    assert [line.split(":")[0] for line in lines] == [f"join {k}" for k in range(1, 12)]
    assert all("minima=1" in line and "phi*=" in line for line in lines)
