"""Synthetic scale series: time and peak memory of join (both strategies) and exact refine
for 10^3, 10^4, 10^5 simulated local maps, written between the ``scale`` markers of
benchmarks/README.md.

    python benchmarks/scale.py                    # the full series (about 20 minutes; run it alone)
    python benchmarks/scale.py --quick            # 300 and 1000 maps in a minute, printed only
    python benchmarks/scale.py --sizes 1000,10000 --refine 1000:100 --no-readme
    python benchmarks/scale.py --commit HEAD      # measure the committed src/, not work in progress

The maps are ``simulate(N, seed=1)``: a figure-eight driven twice (loop closures), 10 steps
and about 20 features per map, full covariances. They are simulated once per size and
pickled; every measurement runs in a fresh child process (Linux: it reads ``/proc``) that
loads them, so its memory is its own:

- time: ``time.perf_counter`` around the call alone (``join`` or ``refine``), median of the runs;
- peak: the child's resident-set high-water mark during the call (``VmHWM``, reset through
  ``/proc/self/clear_refs`` just before it) minus its resident set just before it, with the
  allocator's free memory returned first (``malloc_trim``): what the call added on top of the
  loaded maps (Python objects, numpy, BLAS, SuperLU alike);
- maps: the child's resident set after loading the maps minus before;
- workers (``--jobs 2``): the largest worker's peak resident set, which includes the pages it
  shares copy-on-write with the parent it was forked from.

Whole commands (sizes up to ``--command-max``): the maps are written once as one CSV
stream (``mapjoin simulate -o - --format csv --no-covariances``, spherical variances only: YAML with the full
covariances is about 45 MB per 1000 maps), and ``mapjoin -q join FILE -o OUT`` is timed as a
subprocess, with its parts timed beside it in fresh interpreters: start-up (``mapjoin join
--help``), reading the file, joining the read maps, writing the global map.
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # before numpy: one BLAS thread per process

import argparse
import cProfile
import ctypes
import gc
import io
import json
import math
import pickle
import pstats
import re
import resource
import shutil
import statistics
import subprocess
import sys
import tarfile
import tempfile
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from functools import partial
from itertools import pairwise
from pathlib import Path

import numpy as np
from common import ROOT, compile_mapjoin, median_seconds, write_section

from mapjoin import io as mapio
from mapjoin.joining import join
from mapjoin.maps import LocalMap
from mapjoin.refine import refine
from mapjoin.simulation import simulate

SEED = 1
LARGE = 100_000           # sizes from here on are run --repeat-large times
REFINE_ONCE = 10_000      # refine sizes from here on are run once
TARGET_SECONDS = 60.0     # issue 4: join of 10^5 synthetic maps in under a minute
CASES: dict[str, tuple[str, int]] = {"sequential": ("sequential", 1), "tree": ("tree", 1),
                                     "tree --jobs 2": ("tree", 2)}
PROFILED = ("sequential", "tree")
REFINE_FROM = ("sequential", "tree")
SNAPSHOT = "MAPJOIN_SCALE_COMMIT"      # set in a run on a --commit snapshot of src/   # the joins refine starts from (tree: its default)
PROFILE_LINES = 15


# --- child: one case on the pickled maps ---------------------------------------------------

def _status_mb(key: str) -> float:
    """``VmRSS`` or ``VmHWM`` of this process, in MB."""
    text = Path("/proc/self/status").read_text()
    return int(re.search(rf"^{key}:\s+(\d+) kB", text, re.MULTILINE).group(1)) / 1024


def _settled_rss_mb() -> float:
    """Resident set once garbage is collected and the allocator's free memory returned to the
    system (glibc ``malloc_trim``), in MB: the live data, so that peaks are measured from it."""
    gc.collect()
    ctypes.CDLL(None).malloc_trim(0)
    return _status_mb("VmRSS")


def _reset_peak() -> None:
    """Reset this process's resident-set high-water mark (Linux >= 4.0)."""
    Path("/proc/self/clear_refs").write_text("5")


def _case_call(maps: list[LocalMap], case: str, max_iterations: int) -> Callable[[], dict]:
    """The call a child measures; it returns the facts to report about its result."""
    if case.startswith("refine from "):
        initial = join(maps, strategy=case.removeprefix("refine from ")).global_map

        def run_refine() -> dict:
            r = refine(maps, initial, max_iterations=max_iterations)
            return {"iterations": r.iterations, "initial_cost": r.costs[0], "cost": r.cost,
                    "dof": r.degrees_of_freedom, "reason": r.reason, "unknowns": r.unknowns,
                    "residuals": r.residuals, "solve": r.seconds, "cov": r.covariance_seconds}
        return run_refine
    strategy, jobs = CASES[case]

    def run_join() -> dict:
        result = join(maps, strategy=strategy, jobs=jobs)
        return {"features": len(result.global_map.feature_ids),
                "two_minima": sum(r.minima == 2 for r in result.report)}
    return run_join


def child(path: str, case: str, runs: int, max_iterations: int, profile: bool) -> dict:
    """Load the pickled maps and run ``case`` ``runs`` times (or once under cProfile), measuring each run."""
    before = _settled_rss_mb()
    with open(path, "rb") as stream:
        maps = pickle.load(stream)
    out: dict = {"maps_mb": _settled_rss_mb() - before, "runs": []}
    call = _case_call(maps, case, max_iterations)
    if profile:
        profiler = cProfile.Profile()
        start = time.perf_counter()
        profiler.runcall(call)
        out["seconds"] = time.perf_counter() - start
        text = io.StringIO()
        pstats.Stats(profiler, stream=text).strip_dirs().sort_stats("tottime").print_stats(PROFILE_LINES)
        out["profile"] = text.getvalue()
        return out
    for _ in range(runs):
        start_rss = _settled_rss_mb()
        _reset_peak()
        start = time.perf_counter()
        facts = call()
        seconds = time.perf_counter() - start
        peak = _status_mb("VmHWM")
        workers = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024
        out["runs"].append({"seconds": seconds, "peak_mb": peak - start_rss, "process_mb": peak,
                            "workers_mb": workers or None, **facts})
    return out


# --- parent: simulate, run the children, time the commands -----------------------------------

@dataclass(frozen=True)
class Series:
    """One simulated size: what was simulated, and where its pickled maps are."""

    maps: int
    features: int
    observations: int
    array_mb: float
    simulate_seconds: float
    path: Path


def make_series(size: int, folder: Path) -> Series:
    """Simulate ``size`` maps and pickle them into ``folder``, keeping only their description."""
    start = time.perf_counter()
    simulation = simulate(size, seed=SEED)
    seconds = time.perf_counter() - start
    maps = list(simulation.maps)
    arrays = sum(value.nbytes for m in maps for value in vars(m).values() if isinstance(value, np.ndarray))
    path = folder / f"maps-{size}.pickle"
    with open(path, "wb") as stream:
        pickle.dump(maps, stream, protocol=pickle.HIGHEST_PROTOCOL)
    return Series(size, len(simulation.truth.feature_ids), sum(m.size for m in maps), arrays / 2**20,
                  seconds, path)


def run_child(path: Path, case: str, runs: int = 1, max_iterations: int = 100, profile: bool = False) -> dict:
    """Run one case on the maps in ``path`` in a fresh interpreter and return its measurements."""
    command = [sys.executable, __file__, "--child", str(path), "--case", case, "--runs", str(runs),
               "--max-iterations", str(max_iterations), *(["--profile"] if profile else [])]
    done = subprocess.run(command, capture_output=True, text=True, check=False)
    if done.returncode:
        sys.exit(f"{case} on {path.name} failed:\n{done.stderr}")
    return json.loads(done.stdout)


def mapjoin_command() -> list[str]:
    """The installed ``mapjoin`` command (else ``python -m mapjoin``)."""
    found = shutil.which("mapjoin")
    return [found] if found else [sys.executable, "-m", "mapjoin"]


def command_parts(stream: str) -> dict[str, float]:
    """Seconds of the command's parts in this (fresh) interpreter: read the CSV stream, join it
    with each strategy, write the global map."""
    start = time.perf_counter()
    maps = mapio.read_maps([stream])
    seconds = {"read": time.perf_counter() - start}
    for case, (strategy, jobs) in CASES.items():
        start = time.perf_counter()
        global_map = join(maps, strategy=strategy, jobs=jobs).global_map
        seconds[case] = time.perf_counter() - start
    start = time.perf_counter()
    mapio.write_global_map(global_map, str(Path(stream).with_suffix(".out.csv")), "csv")
    seconds["write"] = time.perf_counter() - start
    return seconds


def command_rows(size: int, runs: int, folder: Path) -> list[str]:
    """Wall times of ``mapjoin join`` on a CSV stream of ``size`` maps per strategy, and of their parts."""
    mapjoin = mapjoin_command()
    compile_mapjoin()  # fresh interpreters below: leave compiling mapjoin out of their times
    stream, target = folder / f"maps-{size}.csv", folder / "global.csv"
    with open(stream, "w") as out:
        subprocess.run([*mapjoin, "-q", "simulate", "-o", "-", "--maps", str(size), "--seed", str(SEED),
                        "--format", "csv", "--no-covariances"], stdout=out, check=True)
    startup, _ = median_seconds(
        partial(subprocess.run, [*mapjoin, "join", "--help"], capture_output=True, check=True), runs)
    measured = [run_child(stream, "parts") for _ in range(runs)]
    part = {key: statistics.median(m[key] for m in measured) for key in measured[0]}
    rows = []
    for case, (strategy, jobs) in CASES.items():
        whole, _ = median_seconds(partial(subprocess.run, [*mapjoin, "-q", "join", str(stream), "-o", str(target),
                                                           "--strategy", strategy, "--jobs", str(jobs)],
                                          check=True), runs)
        rest = whole - startup - part["read"] - part[case] - part["write"]
        rows.append(f"| {size} | {stream.stat().st_size / 2**20:.1f} | {case} | {runs} | {whole:.2f} | "
                    f"{startup:.2f} | {part['read']:.2f} | {part[case]:.2f} | {part['write']:.2f} | {rest:+.2f} |")
        print(rows[-1], flush=True)
    return rows


@dataclass
class Results:
    """Everything measured, as table rows and the numbers the findings quote."""

    sizes: list[int]
    runs: dict[int, int]
    loads: list[float]
    size_rows: list[str]
    join_rows: list[str]
    refine_rows: list[str]
    command_rows: list[str]
    joins: dict[str, list[tuple[int, float, float]]]     # case -> (maps, seconds, peak / maps memory)
    refines: list[dict]
    profiles: dict[str, tuple[float, str]]               # case -> (seconds under the profiler, pstats text)


def measure(sizes: list[int], runs: dict[int, int], refine_at: dict[int, int], command_max: int,
            profile: bool) -> Results:
    """Run the whole series."""
    results = Results(sizes, runs, [os.getloadavg()[0]], [], [], [], [], {case: [] for case in CASES}, [], {})
    print(f"load average at start: {results.loads[0]:.2f}", flush=True)
    with tempfile.TemporaryDirectory(prefix="mapjoin-scale-") as temporary:
        folder = Path(temporary)
        for size in sizes:
            series = make_series(size, folder)
            for case in CASES:
                results.loads.append(os.getloadavg()[0])
                measured = run_child(series.path, case, runs[size])
                maps_mb, rows = measured["maps_mb"], measured["runs"]
                seconds = statistics.median(r["seconds"] for r in rows)
                peak = statistics.median(r["peak_mb"] for r in rows)
                workers = max((r["workers_mb"] for r in rows if r["workers_mb"]), default=None)
                results.joins[case].append((size, seconds, peak / maps_mb))
                results.join_rows.append(
                    f"| {size} | {case} | {runs[size]} | {seconds:.3f} | {1e6 * seconds / size:.0f} | {peak:.0f} | "
                    f"{peak / maps_mb:.2f} | {max(r['process_mb'] for r in rows):.0f} | "
                    f"{'–' if workers is None else f'{workers:.0f}'} | {rows[-1]['features']} | "
                    f"{rows[-1]['two_minima']} |")
                print(results.join_rows[-1], flush=True)
            results.size_rows.append(
                f"| {size} | {series.features} | {series.observations} | {series.observations / size:.1f} | "
                f"{series.array_mb:.0f} | {maps_mb:.0f} | {series.simulate_seconds:.1f} |")
            print(results.size_rows[-1], flush=True)
            for start in REFINE_FROM if size in refine_at else ():
                refine_runs = runs[size] if size < REFINE_ONCE else 1
                results.loads.append(os.getloadavg()[0])
                rows = run_child(series.path, f"refine from {start}", refine_runs, refine_at[size])["runs"]
                r = {**rows[-1], "maps": size, "start": start,
                     **{key: statistics.median(run[key] for run in rows) for key in ("seconds", "solve", "cov", "peak_mb")}}
                results.refines.append(r)
                results.refine_rows.append(
                    f"| {size} | {start} | {r['unknowns']} | {r['residuals']} | {refine_runs} | {r['seconds']:.2f} | "
                    f"{r['solve']:.2f} | {r['cov']:.2f} | {r['iterations']} / {refine_at[size]} | "
                    f"{r['initial_cost']:.4g} | {r['cost']:.1f} | {r['dof']} | {r['reason']} | {r['peak_mb']:.0f} |")
                print(results.refine_rows[-1], flush=True)
            if profile and size == sizes[-1]:
                for case in PROFILED:
                    results.loads.append(os.getloadavg()[0])
                    measured = run_child(series.path, case, profile=True)
                    results.profiles[case] = (measured["seconds"], measured["profile"])
                    print(profile_text(measured["profile"]), flush=True)
            series.path.unlink()
        for size in sizes:
            if size <= command_max:
                results.loads.append(os.getloadavg()[0])
                results.command_rows += command_rows(size, runs[size], folder)
    return results


# --- the README section ----------------------------------------------------------------

def _profile_table(profile: str) -> tuple[list[str], list[str]]:
    """A pstats listing split into its total line and its table (header first), blank lines dropped."""
    lines = [line.rstrip() for line in profile.splitlines() if line.strip()]
    header = next(i for i, line in enumerate(lines) if line.lstrip().startswith("ncalls"))
    return [line for line in lines[:header] if "function calls" in line], lines[header:]


def profile_text(profile: str) -> str:
    """The total line and the table of a pstats listing."""
    summary, table = _profile_table(profile)
    return "\n".join(summary + table)


def top_functions(profile: str, count: int = 4) -> str:
    """The ``count`` functions with the most own time, with their share of the profiled total."""
    summary, table = _profile_table(profile)
    total = float(re.search(r"in ([\d.]+) seconds", summary[0]).group(1))
    rows = [line.split(None, 5) for line in table[1:count + 1]]
    return ", ".join(f"`{row[5]}` {float(row[1]):.2f} s ({100 * float(row[1]) / total:.0f} %)" for row in rows)


def exponent(n0: int, v0: float, n1: int, v1: float) -> float:
    """The empirical growth exponent from (n0, v0) to (n1, v1): v grows as n^exponent (1 = linear)."""
    return math.log(v1 / v0) / math.log(n1 / n0)


def exponents(points: Sequence[tuple[int, float]]) -> str:
    """Growth exponents between consecutive (size, value) points."""
    return ", ".join(f"{exponent(n0, v0, n1, v1):.2f}" for (n0, v0), (n1, v1) in pairwise(points))


def table(header: str, align: str, rows: list[str]) -> list[str]:
    """A markdown table: ``header`` cells and ``align`` cells separated by ``|``."""
    return [f"| {header} |", f"|{align}", *rows]


def findings(results: Results) -> str:
    """The paragraph of findings, from the measured numbers."""
    sizes = results.sizes
    growth = "; ".join(f"{case} " + " / ".join(f"{1e6 * s / n:.0f}" for n, s, _ in points)
                       + f" µs (exponents {exponents([(n, s) for n, s, _ in points])})" for case, points in results.joins.items())
    memory = "; ".join(f"{case} " + " / ".join(f"{ratio:.2f}" for _, _, ratio in points)
                       for case, points in results.joins.items())
    text = (f"**Growth.** Join time per map at {' / '.join(map(str, sizes))} maps: {growth} "
            f"(exponent 1 = linear). The join's peak memory over the loaded maps' memory: {memory} "
            "(a ratio that stays flat = memory proportional to the data).")
    if sizes[-1] >= LARGE:
        verdicts = ", ".join(
            f"{case} {points[-1][1]:.1f} s ("
            + ("met" if points[-1][1] < TARGET_SECONDS else f"missed by {points[-1][1] - TARGET_SECONDS:.1f} s") + ")"
            for case, points in results.joins.items())
        text += f" **Target** (join of {sizes[-1]} maps in under {TARGET_SECONDS:.0f} s): {verdicts}."
    for r in results.refines:
        text += (f" **Refine** of {r['maps']} maps from the {r['start']} join: {r['iterations']} iterations ({r['reason']}) in "
                 f"{r['seconds']:.1f} s, {r['solve'] / max(r['iterations'], 1):.2f} s of solve per iteration "
                 f"(set-up included), chi^2 {r['initial_cost']:.3g} → {r['cost']:.1f} (dof {r['dof']}), "
                 f"peak {r['peak_mb']:.0f} MB.")
    memory = [(r["maps"], r["peak_mb"]) for r in results.refines if r["start"] == REFINE_FROM[0]]
    if len(memory) > 1 and sizes[-1] > memory[-1][0]:
        (n0, m0), (n1, m1) = memory[-2:]
        guess = m1 * (sizes[-1] / n1) ** exponent(n0, m0, n1, m1)
        text += (f" Refine's peak memory grows with exponent {exponents(memory)}: at {sizes[-1]} maps that "
                 f"extrapolates to about {guess / 1024:.1f} GB, so it is not run there.")
    for case, (_, profile) in results.profiles.items():
        text += f" **Where the {case} join's time goes** ({sizes[-1]} maps, own time): {top_functions(profile)}."
    return text


def report(results: Results) -> str:
    """The README section: set-up, tables, profiles and findings."""
    runs = ", ".join(f"{n} maps: {results.runs[n]}" for n in results.sizes)
    lines = [
        "## Synthetic scale series (`python benchmarks/scale.py`)",
        "",
        (f"Measured {time.strftime('%Y-%m-%d')} at {source_version()} on this shared 2-core machine (load average "
         f"{min(results.loads):.1f}–{max(results.loads):.1f} while measuring), `OPENBLAS_NUM_THREADS=1`, maps "
         f"from `simulate(N, seed={SEED})` (a figure-eight driven twice, 10 steps per map, full covariances). "
         f"Runs per case (median): {runs}; refine from {REFINE_ONCE} maps on: 1. Each case runs in its own "
         "child process on the loaded maps: *time* is the call alone (`time.perf_counter`); *peak* the "
         "resident memory the call added on top of the loaded maps (resident-set high-water mark, reset "
         "just before the call, minus the resident set then, free heap returned to the system first); "
         "*maps* the resident memory of the loaded "
         "maps; *process* the child's whole peak; *workers* the largest `--jobs` worker's whole peak "
         "(forked: it includes pages shared with the parent, so it is not all additional)."),
        "",
        *table("maps | features (world) | map features (observations) | per map | arrays (MB) "
               "| maps resident (MB) | simulate (s)", "---:|" * 7, results.size_rows),
        "",
        "### Join (in-process, information covariances)",
        "",
        *table("maps | strategy | runs | time (s) | per map (µs) | peak (MB) | peak / maps | process (MB) "
               "| workers (MB) | global features | two-minima joins",
               "---:|---|" + "---:|" * 9, results.join_rows)]
    if results.refine_rows:
        lines += [
            "", "### Exact refine (in-process)", "",
            ("Started from the sequential join and from the tree join (refine's default since 2026-11-26; the "
             "sequential join was before). Time = set-up, iterations and marginal covariances (solve + cov); "
             "initial chi^2 is the start's; dof = residuals − unknowns (chi^2's expected value at the optimum)."),
            "",
            *table("maps | from | unknowns | residuals | runs | time (s) | solve (s) | cov (s) | iterations / max "
                   "| initial chi^2 | chi^2 | dof | stop | peak (MB)", "---:|---|" + "---:|" * 10 + "---|---:|",
                   results.refine_rows)]
    if results.command_rows:
        lines += [
            "", "### Whole command: `mapjoin -q join maps.csv -o global.csv --strategy S --jobs J`", "",
            ("The maps as one CSV stream from `mapjoin simulate -o - --format csv --no-covariances` (spherical variances "
             "only; YAML with the full covariances is about 45 MB per 1000 maps), the "
             "command timed as a subprocess (mapjoin's bytecode compiled beforehand, as an installed "
             "package's is); its parts timed beside it in fresh interpreters (one per run, "
             "each reading the file, joining it with every strategy and writing the result once), medians "
             "of the same number of runs: start-up = `mapjoin join --help` (interpreter, imports), read = "
             "`mapjoin.io.read_maps`, join = the read maps joined, write = `mapjoin.io.write_global_map`, rest = "
             "what the parts leave (noise included)."),
            "",
            *table("maps | file (MB) | strategy | runs | command (s) | start-up (s) | read (s) | join (s) "
                   "| write (s) | rest (s)", "---:|---:|---|" + "---:|" * 7, results.command_rows)]
    for case, (seconds, profile) in results.profiles.items():
        lines += ["", (f"### cProfile: {case} join of {results.sizes[-1]} maps ({seconds:.1f} s under the "
                       f"profiler), top {PROFILE_LINES} by own time"), "", "```", profile_text(profile), "```"]
    lines += ["", "### Findings", "", findings(results)]
    return "\n".join(lines)


def git(*arguments: str) -> str:
    """Output of a read-only git command in the repository."""
    return subprocess.run(["git", *arguments], cwd=ROOT, capture_output=True, text=True, check=False).stdout.strip()


def source_version() -> str:
    """The source measured: a ``--commit`` snapshot, or the working tree's commit and whether src/ differs."""
    if SNAPSHOT in os.environ:
        return f"commit {os.environ[SNAPSHOT]}"
    commit = git("rev-parse", "--short", "HEAD") or "an unknown commit"
    return commit + (" with uncommitted changes in src/" if git("status", "--porcelain", "src") else "")


def run_at_commit(commit: str) -> int:
    """Run this script again on ``git archive COMMIT src`` (first on PYTHONPATH, so children and
    commands import it too): the measured code cannot change under a long run."""
    with tempfile.TemporaryDirectory(prefix="mapjoin-scale-src-") as snapshot:
        archive = subprocess.run(["git", "archive", commit, "src"], cwd=ROOT, capture_output=True, check=True).stdout
        with tarfile.open(fileobj=io.BytesIO(archive)) as tar:
            tar.extractall(snapshot, filter="data")
        env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(Path(snapshot) / "src"), os.environ.get("PYTHONPATH", "")]),
               SNAPSHOT: git("rev-parse", "--short", commit)}
        return subprocess.run([sys.executable, __file__, *sys.argv[1:]], env=env, check=False).returncode


def parse_refine(text: str) -> dict[int, int]:
    """``"1000:100,10000:100"`` -> {maps: max_iterations}."""
    pairs = [item.split(":") for item in text.split(",") if item]
    return {int(size): int(iterations) for size, iterations in pairs}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", default="1000,10000,100000", help="map counts, comma-separated")
    parser.add_argument("--repeat", type=int, default=5, help=f"runs per case below {LARGE} maps (median)")
    parser.add_argument("--repeat-large", type=int, default=1, help=f"runs per case from {LARGE} maps on")
    parser.add_argument("--refine", default="1000:100,10000:100",
                        help="sizes to refine, each with its max iterations: SIZE:ITER,... ('' for none)")
    parser.add_argument("--command-max", type=int, default=10_000, help="largest size timed as a whole command")
    parser.add_argument("--no-profile", action="store_true", help="skip the cProfile of the largest size")
    parser.add_argument("--quick", action="store_true", help="300 and 1000 maps, 3 runs, README untouched")
    parser.add_argument("--no-readme", action="store_true", help="print only; leave benchmarks/README.md")
    parser.add_argument("--commit", help="measure this commit's src/ (a git archive snapshot), not the working tree")
    parser.add_argument("--child", help=argparse.SUPPRESS)
    parser.add_argument("--case", help=argparse.SUPPRESS)
    parser.add_argument("--runs", type=int, default=1, help=argparse.SUPPRESS)
    parser.add_argument("--max-iterations", type=int, default=100, help=argparse.SUPPRESS)
    parser.add_argument("--profile", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        print(json.dumps(command_parts(args.child) if args.case == "parts"
                         else child(args.child, args.case, args.runs, args.max_iterations, args.profile)))
        return
    if args.commit and SNAPSHOT not in os.environ:
        sys.exit(run_at_commit(args.commit))
    if args.quick:
        args.sizes, args.repeat, args.refine, args.command_max, args.no_readme = "300,1000", 3, "1000:100", 300, True
    sizes = sorted(int(s) for s in args.sizes.split(","))
    runs = {n: args.repeat if n < LARGE else args.repeat_large for n in sizes}
    results = measure(sizes, runs, parse_refine(args.refine), args.command_max, not args.no_profile)
    text = report(results)
    print(text)
    if not args.no_readme:
        write_section("scale", text)


if __name__ == "__main__":
    main()
