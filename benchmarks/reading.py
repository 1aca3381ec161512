"""Reading speed: whole ``mapjoin join`` commands on VicPark 200 in each local-map format, and a long YAML stream.

    python benchmarks/reading.py [--repeat N] [--maps N] [--data DIR]

VicPark 200 (converted in a scratch folder with ``mapio.write_maps``) is joined from its
I-SLSJF .mat folder, a folder of YAML files, one YAML stream on stdin, one CSV stream on
stdin and a folder of Linear SLAM text files; each whole command (a fresh interpreter, as
typed) is timed, the inputs in turn for ``--repeat`` rounds (so that a shared machine's load
falls on each alike), with its CPU time and peak resident memory (VmHWM); the medians' ratios
to the .mat run are printed: the same maps, so the ratio is per map. Then ``--maps``
simulated maps (10^4 by default, ``mapjoin simulate``) go as one YAML stream through a
pipe (``cat FILE | mapjoin join -``, timed once). Results are printed and written between
the ``reading`` markers of benchmarks/README.md, with the machine's load (``uptime``).
"""

from __future__ import annotations

import argparse
import logging
import os
import resource
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

from common import DATA, compile_mapjoin, whole_command, write_section

from mapjoin import io as mapio

DATASET = "VicPark_200_local_maps"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=5, help="runs per VicPark measurement (medians)")
    parser.add_argument("--maps", type=int, default=10_000, help="maps of the simulated YAML stream")
    parser.add_argument("--data", type=Path, default=DATA, help="folder of the datasets (default: %(default)s)")
    args = parser.parse_args()
    logging.getLogger("mapjoin").setLevel(logging.ERROR)
    compiled = compile_mapjoin()
    folder = args.data / DATASET
    rows = ["| input | time (s) | vs .mat | CPU (s) | vs .mat | peak RSS (MB) |", "|---|---:|---:|---:|---:|---:|"]
    with tempfile.TemporaryDirectory() as scratch_name:
        scratch = Path(scratch_name)
        maps = mapio.read_maps([str(folder)])
        mapio.write_maps(maps, f"{scratch}/yaml/", "yaml")
        mapio.write_maps(maps, scratch / "maps.yaml", "yaml")
        mapio.write_maps(maps, scratch / "maps.csv", "csv")
        mapio.write_maps(maps, f"{scratch}/txt/", "linearslam")
        output = ["-o", str(scratch / "out.csv")]
        cases = [(".mat folder", [str(folder)], None), ("YAML folder", [str(scratch / "yaml")], None),
                 ("YAML stream on stdin", ["-"], scratch / "maps.yaml"),
                 ("CSV stream on stdin", ["-"], scratch / "maps.csv"),
                 ("Linear SLAM text folder", [str(scratch / "txt")], None)]
        runs: dict[str, list[tuple[float, float, float]]] = {label: [] for label, _, _ in cases}
        for _ in range(args.repeat):  # round by round, so that the machine's load falls on every input alike
            for label, inputs, stdin in cases:
                before = resource.getrusage(resource.RUSAGE_CHILDREN)
                seconds, peak = whole_command(["join", *inputs, *output], 1, stdin)
                after = resource.getrusage(resource.RUSAGE_CHILDREN)
                runs[label].append((seconds, after.ru_utime + after.ru_stime - before.ru_utime - before.ru_stime, peak))
        seconds, cpu = ({label: statistics.median(run[k] for run in times) for label, times in runs.items()}
                        for k in (0, 1))
        reference = cases[0][0]
        for label, _, _ in cases:
            rows.append(f"| {label} | {seconds[label]:.2f} | {seconds[label] / seconds[reference]:.2f} | "
                        f"{cpu[label]:.2f} | {cpu[label] / cpu[reference]:.2f} | "
                        f"{max(run[2] for run in runs[label]):.0f} |")
            print(rows[-1], file=sys.stderr)
        stream = scratch / "simulated.yaml"
        subprocess.run([sys.executable, "-m", "mapjoin", "-q", "simulate", "-o", str(stream), "--maps",
                        str(args.maps)], check=True)
        size = stream.stat().st_size / 2**20
        seconds, peak = whole_command(["join", "-", *output], 1, ["cat", str(stream)])
        long_stream = (f"{args.maps} simulated maps as one YAML stream ({size:.0f} MB) through a pipe, `cat FILE | "
                       f"mapjoin join - -o out.csv`, one run: {seconds:.1f} s ({1e3 * seconds / args.maps:.2f} ms "
                       f"a map), peak RSS {peak:.0f} MB.")
    load = subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()
    text = "\n".join([f"VicPark 200 (200 maps) joined by whole commands as typed (`python -m mapjoin join INPUT -o "
                      f"out.csv`), a fresh `{sys.executable}` per run, {compiled}; the inputs in turn, {args.repeat} "
                      f"rounds: median wall time, median CPU time (user + system, of the command and what it "
                      f"started), each with its ratio to the .mat folder's, and the largest peak RSS. "
                      f"{os.cpu_count()} CPUs visible; `uptime` after the run: {load}.", "", *rows, "", long_stream])
    print(text)
    write_section("reading", text)


if __name__ == "__main__":
    main()
