"""What one join of the sequential strategy costs on Python numbers, and would cost as a numpy batch of one.

    python benchmarks/batch_of_one.py [--repeat N]

Each one-step algorithm is written once over an arithmetic backend (``onestep.FLOATS`` for one
problem on Python numbers, ``onestep.ARRAYS`` for a batch). This prints, in one run (so the
ratios hold on a loaded machine):

* the sequential and tree joins of VicPark 6898 (in-process, maps loaded once), and the
  sequential join's time per join: 10 % of it is what the one-problem path may add per join;
* one problem on Python numbers (``point_constants``, ``global_orientation`` of floats) and
  as a batch of one (``problem_of`` given; arrays of length 1);
* the floor of any lockstep search in numpy: a bisection of 43 steps on one problem with the
  fewest numpy calls a step (in place, no stopping rule), and a 255-section that takes 8 of
  bisection's steps a round in 6 rounds, against the bisection of the same bracket on numbers.

The problem is a VicPark-like one (20 common features, a = 3, C_phi = 0.02).
"""

from __future__ import annotations

import argparse
import logging
import os
import time
import timeit

import numpy as np

from mapjoin import io as mapio
from mapjoin.arithmetic import FLOATS
from mapjoin.joining import join
from mapjoin.onestep import _bisection, global_orientation, point_constants

DATA = os.environ.get("MAPJOIN_DATA", os.path.join(os.path.dirname(__file__), "..", "..", "shared", "data"))


def microseconds(function, repeat: int, number: int = 2000) -> float:
    """The best of ``repeat`` runs of ``number`` calls, per call (us)."""
    return min(timeit.repeat(function, number=number, repeat=repeat)) / number * 1e6


def lockstep_bisection(a: np.ndarray, c_phi: np.ndarray, low: float, high: float, steps: int = 43) -> np.ndarray:
    """Bisection of h = a sin(x + c_phi) + x in lockstep, in place: nine numpy calls a step."""
    low, high = np.array([low]), np.array([high])
    middle, h, below = np.empty(1), np.empty(1), np.empty(1, dtype=bool)
    for _ in range(steps):
        np.add(low, high, out=middle)
        middle *= 0.5
        np.add(middle, c_phi, out=h)
        np.sin(h, out=h)
        h *= a
        h += middle
        np.less(h, 0.0, out=below)
        np.copyto(low, middle, where=below)
        np.copyto(high, middle, where=~below)
    return middle


def multisection(a: np.ndarray, c_phi: np.ndarray, low: float, high: float, bits: int = 8, steps: int = 43
                 ) -> np.ndarray:
    """``bits`` bisection steps a round: h on 2^bits - 1 points of the bracket, the sign change counted."""
    grid = np.arange(1, 2**bits) / 2**bits
    low_, width = np.array([low]), np.array([high - low])
    for _ in range(-(-steps // bits)):
        x = low_[:, None] + width[:, None] * grid
        below = np.count_nonzero(a[:, None] * np.sin(x + c_phi[:, None]) + x < 0, axis=1)
        width = width / 2**bits
        low_ = low_ + below * width
    return low_


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--repeat", type=int, default=3)
    repeat = parser.parse_args().repeat
    logging.disable(logging.WARNING)
    print(f"load average {os.getloadavg()[0]:.2f}")

    maps = mapio.read_maps([os.path.join(DATA, "VicPark_6898_local_maps")])
    for strategy in ("sequential", "tree"):
        times = []
        for _ in range(repeat):
            start = time.perf_counter()
            join(maps, strategy=strategy)
            times.append(time.perf_counter() - start)
        best = min(times)
        print(f"{strategy} join of VicPark 6898: {best:.3f} s, {best / (len(maps) - 1) * 1e6:.1f} us a join")

    rng = np.random.default_rng(0)
    n = 20
    z0 = 30 * (rng.normal(size=n) + 1j * rng.normal(size=n))
    z1, var0, var1 = z0 * np.exp(-0.1j) + 1, rng.uniform(0.1, 1, n), rng.uniform(0.1, 1, n)
    one = np.zeros(n, dtype=np.intp)
    array = np.array
    rows = [
        ("constants: point_constants on numbers", lambda: point_constants(z0, var0, z1, var1, 1 + 1j, 0.3)),
        ("constants: point_constants, a batch of 1",
         lambda: point_constants(z0, var0, z1, var1, array([1 + 1j]), array([0.3]), one)),
    ]
    for solver in ("bisection", "golden"):
        rows += [
            (f"orientation ({solver}): global_orientation on numbers",
             lambda s=solver: global_orientation(300.0, 0.1, 0.12, 0.01, s)),
            (f"orientation ({solver}): global_orientation, a batch of 1",
             lambda s=solver: global_orientation(array([300.0]), array([0.1]), array([0.12]), array([0.01]), s)),
        ]
    a, c_phi = array([3.0]), array([0.02])
    rows += [
        ("search: _bisection on numbers, 43 steps", lambda: _bisection(FLOATS, 3.0, 0.02, -3.14, 3.14, 1e-12)),
        ("search floor: numpy lockstep bisection, 43 steps", lambda: lockstep_bisection(a, c_phi, -3.14, 3.14)),
        ("search floor: numpy 255-section, 6 rounds", lambda: multisection(a, c_phi, -3.14, 3.14)),
    ]
    for name, function in rows:
        print(f"{name}: {microseconds(function, repeat, 200 if 'batch of 1' in name or 'floor' in name else 2000):.1f} us")


if __name__ == "__main__":
    main()
