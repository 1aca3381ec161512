"""Where refine's memory goes: resident memory and time by phase of one exact refine.

    python benchmarks/refine_memory.py MAPS [--no-covariances] [--json OUT]

MAPS: anything ``mapjoin refine`` reads (a .mat folder, a CSV stream of ``mapjoin simulate``).
The phases are those of the command, in one process: reading, the fast join (refine's default
start), the problem's set-up (groups and whitening), the normal equations' pattern (ordering,
CSC pattern, where each block goes), the iterations (linearisations, factorisations, solves,
costs), the marginal covariances (selected inversion) and writing the global map (to
/dev/null). A thread samples the resident set (``/proc/self/statm``) every 10 ms; each phase
gets its resident set at the start and its peak (largest sample, or the end), its wall time and
its CPU time (user + system of the process, the sampler's share included: the figure to compare
on a loaded machine). The phases of the iterations interleave: their peaks are over all their
calls. Prints a Markdown table.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import resource
import threading
import time

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

from mapjoin import io as mapio  # noqa: E402
from mapjoin.joining import join  # noqa: E402
from mapjoin.refine import DEFAULT_START, problem as problem_module, refine  # noqa: E402

_PAGE = os.sysconf("SC_PAGE_SIZE")


def cpu() -> float:
    """User + system CPU seconds of this process so far."""
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


def resident() -> int:
    """The resident set of this process, bytes."""
    with open("/proc/self/statm") as statm:
        return int(statm.read().split()[1]) * _PAGE


class Phases:
    """Per phase: resident set at its (first) start, peak while in it, calls, seconds, CPU seconds."""

    def __init__(self) -> None:
        self.rows: dict[str, dict[str, float]] = {}
        self.current: list[str] = []
        self.peak = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._sample, daemon=True)
        self._thread.start()

    def _sample(self) -> None:
        while not self._stop.wait(0.01):
            now = resident()
            self.peak = max(self.peak, now)
            for name in self.current:
                row = self.rows[name]
                row["peak"] = max(row["peak"], now)

    @contextlib.contextmanager
    def phase(self, name: str):
        now = resident()
        row = self.rows.setdefault(name, {"start": now, "peak": now, "calls": 0, "seconds": 0.0, "cpu": 0.0})
        self.current.append(name)
        began, used = time.perf_counter(), cpu()
        try:
            yield
        finally:
            row["seconds"] += time.perf_counter() - began
            row["cpu"] += cpu() - used
            row["calls"] += 1
            row["peak"] = max(row["peak"], resident())
            self.current.remove(name)

    def wrap(self, owner: type, method: str, name: str, when=None) -> None:
        """Time and sample every call of ``owner.method`` as phase ``name`` (only the calls for whose
        instance ``when`` says so, if given)."""
        original = getattr(owner, method)

        def wrapped(self_, *args, **kwargs):
            if when is not None and not when(self_):
                return original(self_, *args, **kwargs)
            with self.phase(name):
                return original(self_, *args, **kwargs)

        setattr(owner, method, wrapped)

    def close(self) -> None:
        self._stop.set()
        self._thread.join()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("maps")
    parser.add_argument("--no-covariances", action="store_true", help="no marginal covariances (as the option)")
    parser.add_argument("--json", help="also write the rows as JSON here")
    args = parser.parse_args()

    phases = Phases()
    Problem = problem_module.ExactProblem
    phases.wrap(Problem, "_prepare", "pattern (ordering, CSC; in the first linearise)",
                lambda problem: problem._pattern is None)
    for method, name in (("__init__", "set-up (groups, whitening)"), ("linearise", "iterations: linearise"), ("factorise", "iterations: factorise"),
                         ("solve", "iterations: solve"), ("cost", "iterations: cost"),
                         ("marginals", "marginal covariances")):
        phases.wrap(Problem, method, name)
    began, used = time.perf_counter(), cpu()
    with phases.phase("read"):
        maps = mapio.read_maps(args.maps)
    with phases.phase(f"fast join ({DEFAULT_START})"):
        fast = join(maps, strategy=DEFAULT_START)
    with phases.phase("refine (all of it)"):
        result = refine(maps, fast.global_map, covariances=not args.no_covariances)
    with phases.phase("write (CSV to /dev/null)"):
        mapio.write_global_map(result.global_map, "/dev/null", "csv")
    total, total_cpu = time.perf_counter() - began, cpu() - used
    phases.close()
    print(f"{len(maps)} maps, {result.unknowns} unknowns, {result.iterations} iterations, chi^2 {result.cost:.6f} "
          f"({result.reason}), {total:.1f} s; load average {os.getloadavg()[0]:.2f}")
    print("| phase | calls | seconds | CPU seconds | resident at start (MB) | peak (MB) | peak above start (MB) |")
    print("|---|---:|---:|---:|---:|---:|---:|")
    for name, row in phases.rows.items():
        print(f"| {name} | {row['calls']} | {row['seconds']:.2f} | {row['cpu']:.2f} | {row['start'] / 2**20:.0f} | "
              f"{row['peak'] / 2**20:.0f} | {(row['peak'] - row['start']) / 2**20:.0f} |")
    print(f"| whole run | | {total:.2f} | {total_cpu:.2f} | | {phases.peak / 2**20:.0f} | |")
    if args.json:
        with open(args.json, "w") as out:
            json.dump({"rows": phases.rows, "peak": phases.peak, "seconds": total, "cpu": total_cpu,
                       "chi2": result.cost, "iterations": result.iterations, "maps": len(maps)}, out)


if __name__ == "__main__":
    main()
