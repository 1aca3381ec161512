"""``mapjoin build`` on the real raw data, written into benchmarks/README.md (section "build").

1. Speed: reading the raw files; building VicPark's 200 local maps (the paper: 0.8 s with
   g2o, C++) in one process and in two (``jobs=2``, runs interleaved); the full batch solution (``--maps 1``; from the 200 built maps), iSAM too.
2. The 200 built maps against the shipped ``VicPark_200_local_maps``, map by map.
3. ``build`` then ``join`` (fast, and ``--refine``) against the batch solution: the
   paper's metric (mean |dx|, |dy| over features and end poses, |dphi| over poses).
4. The noise numbers: chi^2 at the optimum against its degrees of freedom for each
   format's reading and for the opposite one (covariance <-> information), and the iSAM
   file under GTSAM's reading (each LANDMARK converted to bearing and range with
   sigmas sqrt(c11/10) and sqrt(c11)), solved by an independent Gauss-Newton here
   (scipy only).

    python benchmarks/build.py [--repeat N]

In-process medians of N runs (default 5), raw data already read, one thread
(``OPENBLAS_NUM_THREADS=1`` is set here); the machine is shared, so compare ratios.
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import os
import sys
import time

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np
import scipy.sparse as sp
from common import DATA, median_seconds, write_section
from scipy.sparse.linalg import splu

from mapjoin import io as mapio
from mapjoin.build import batch, build, cut
from mapjoin.evaluation import compare
from mapjoin.joining import join_sequential
from mapjoin.raw import RawData, read_raw
from mapjoin.refine import refine

VICPARK = DATA / "VicPark_200_local_maps" / "VicPark_clean_data.mat"
ISAM = DATA / "victoria_park_raw" / "victoria_park_isam.txt"


def speed_rows(repeat: int) -> tuple[list[str], dict]:
    rows, kept = [], {}
    for label, path in (("VicPark_clean_data.mat", VICPARK), ("victoria_park_isam.txt", ISAM)):
        rows_of, kept[label] = speed_of(path, label, repeat)
        rows += rows_of
        print(label, file=sys.stderr)
    return rows, kept


def speed_of(path, label: str, repeat: int) -> tuple[list[str], tuple]:
    """Reading, building 200 maps, with the batch solution from them, and one map."""
    seconds, raw = median_seconds(lambda: read_raw(str(path)), repeat)
    features = len(np.unique(raw.feature_ids))
    rows = [(f"| {label} | read ({raw.steps} steps, {len(raw.observations)} observations, {features} features) | "
             f"{seconds:.3f} | |")]
    bounds = cut(raw.steps, maps=200)
    times, results = {1: [], 2: []}, {}
    for _ in range(repeat):                       # interleaved: both see the same machine load
        for jobs in (1, 2):
            seconds, results[jobs] = median_seconds(lambda jobs=jobs: build(raw, bounds, jobs=jobs), 1)
            times[jobs].append(seconds)
    built = results[1]
    for jobs, what in ((1, "one process"), (2, "2 processes (`-j 2`; solve, covariances: the slower worker)")):
        run = results[jobs]
        rows.append(f"| {label} | build 200 maps, {what} | {np.median(times[jobs]):.3f} | solve {run.seconds:.3f} s "
                    f"({run.iterations} iterations), covariances {run.covariance_seconds:.3f} s; chi^2 "
                    f"{run.cost:.2f} for {int(run.degrees_of_freedom.sum())} dof |")
    seconds, both = median_seconds(lambda: build(raw, bounds, with_batch=True), max(1, repeat // 2))
    whole = both.batch
    rows.append(f"| {label} | build 200 maps and the batch from them | {seconds:.3f} | batch: chi^2 "
                f"{whole.cost:.4f} (half {whole.cost / 2:.4f}) for {whole.degrees_of_freedom} dof, "
                f"{whole.iterations} iterations |")
    seconds, one = median_seconds(lambda: build(raw, cut(raw.steps, maps=1)), max(1, repeat // 2))
    rows.append(f"| {label} | build 1 map (--maps 1: pieces of 50 steps, joined, refined) | {seconds:.3f} | "
                f"{one.pieces} pieces, chi^2 {one.cost:.4f}, {one.iterations} iterations |")
    return rows, (raw, built, whole)


def shipped_rows(built) -> list[str]:
    """Differences of the built maps from the shipped ones, map by map (features by id)."""
    shipped = mapio.read_maps([str(DATA / "VicPark_200_local_maps")])
    pose, phi, feature, covariance, same_features, differing = [], [], [], [], 0, []
    for k, (b, s) in enumerate(zip(built.maps, shipped), start=1):
        order = np.argsort(s.feature_ids)
        pose.append(float(np.hypot(*(b.end_pose[:2] - s.end_pose[:2]))))
        phi.append(abs(float(np.remainder(b.end_pose[2] - s.end_pose[2] + np.pi, 2 * np.pi) - np.pi)))
        if np.array_equal(b.feature_ids, s.feature_ids[order]):
            same_features += 1
            feature.append(float(np.hypot(*(b.features - s.features[order]).T).max(initial=0)))
            state = np.concatenate([np.arange(3), (3 + 2 * order[:, None] + np.arange(2)).ravel()])
            c = s.covariance[np.ix_(state, state)]
            deviation = np.sqrt(np.diag(c))
            covariance.append(float(np.abs(b.covariance - c).max() / np.outer(deviation, deviation).max()))
        else:
            feature.append(np.nan)
            covariance.append(np.nan)
        if pose[-1] > 1e-5 or not feature[-1] <= 1e-4:
            differing.append(k)
    pose, phi, feature, covariance = map(np.array, (pose, phi, feature, covariance))
    agree = [k - 1 for k in range(1, 201) if k not in differing]
    rows = [f"| maps with the same feature ids | {same_features} of 200 |",
            (f"| end pose, distance: median / max over the {len(agree)} agreeing maps | {np.median(pose[agree]):.2g} / "
             f"{pose[agree].max():.2g} m |"),
            f"| end pose, orientation: max over those | {phi[agree].max():.2g} rad |",
            f"| features, distance: max over those | {np.nanmax(feature[agree]):.2g} m |",
            f"| covariance, max abs difference / max sigma_i sigma_j, over those | {np.nanmax(covariance[agree]):.2g} |"]
    for k in differing:
        b, s = built.maps[k - 1], shipped[k - 1]
        extra = np.setdiff1d(b.feature_ids, s.feature_ids)
        rows.append(f"| map {k} differs | end pose {pose[k - 1]:.3f} m, {phi[k - 1]:.4f} rad apart"
                    + (f"; features {', '.join(map(str, extra))} only in the built map" if extra.size else "")
                    + (f"; features up to {feature[k - 1]:.3f} m apart" if feature[k - 1] > 1e-4 else "") + " |")
    return rows


def metric_rows(raw: RawData, built, whole) -> list[str]:
    """Fast and exact joins of the built (and the shipped) maps against the batch solution."""
    reference = whole.global_map
    rows = []
    shipped = mapio.read_maps([str(DATA / "VicPark_200_local_maps")])
    for label, maps in (("built", list(built.maps)), ("shipped", shipped)):
        for method, global_map in (("join", join_sequential(maps).global_map),
                                   ("join --refine", refine(maps, covariances=False).global_map)):
            d = compare(reference, global_map)
            rows.append(f"| {label} 200 maps | {method} | {d.mean_abs_x:.4f} | {d.mean_abs_y:.4f} | "
                        f"{d.mean_abs_phi:.5f} | {d.max_xy:.3f} |")
    return rows


def interpretation_rows(kept: dict) -> list[str]:
    rows = []
    for label, (raw, _, whole) in kept.items():
        reading = "covariance"
        rows.append(f"| {label} | {reading} (mapjoin's) | {whole.cost:.2f} | {whole.degrees_of_freedom} | "
                    f"{whole.cost / whole.degrees_of_freedom:.3f} |")
        swapped = dataclasses.replace(raw, odometry_covariances=np.linalg.inv(raw.odometry_covariances),
                                      observation_covariances=np.linalg.inv(raw.observation_covariances))
        other = batch(swapped, cut(raw.steps, maps=200), covariances=False)
        rows.append(f"| {label} | information (the opposite) | {other.cost:.4g} | {other.degrees_of_freedom} | "
                    f"{other.cost / other.degrees_of_freedom:.2g} |")
    raw, _, whole = kept["victoria_park_isam.txt"]
    cost, iterations = bearing_range_optimum(raw, batch(raw, covariances=False).global_map)
    rows.append(f"| victoria_park_isam.txt | GTSAM's: LANDMARK as bearing/range, sigmas sqrt(c11/10), sqrt(c11) "
                f"(independent Gauss-Newton, {iterations} iterations) | {cost:.2f} (half {cost / 2:.2f}) | "
                f"{whole.degrees_of_freedom} | {cost / whole.degrees_of_freedom:.3f} |")
    return rows


def bearing_range_optimum(raw: RawData, start) -> tuple[float, int]:
    """chi^2 at the optimum of the iSAM data read as GTSAM's load2D reads it: odometry with its
    covariance, each landmark (x, y) as bearing and range with sigmas sqrt(v1/10), sqrt(v1).
    Levenberg-Marquardt on the sparse analytic Jacobian, from ``start`` (a global map of every
    pose and feature); independent of mapjoin's solver."""
    P = raw.steps
    ids = start.feature_ids
    which = np.searchsorted(ids, raw.feature_ids)
    n = 3 * P + 2 * len(ids)
    Wo = np.linalg.inv(np.linalg.cholesky(raw.odometry_covariances))
    z = raw.observations
    bearing, distance = np.arctan2(z[:, 1], z[:, 0]), np.hypot(z[:, 0], z[:, 1])
    v1 = raw.observation_covariances[:, 0, 0]
    sigma = np.stack([np.sqrt(v1 / 10), np.sqrt(v1)], axis=1)
    M = len(z)

    def wrap(a):
        return (a + np.pi) % (2 * np.pi) - np.pi

    def evaluate(x, jacobian=True):
        poses = np.vstack([np.zeros(3), x[:3 * P].reshape(P, 3)])
        f = x[3 * P:].reshape(-1, 2)
        a, b = poses[:-1], poses[1:]
        c, s = np.cos(a[:, 2]), np.sin(a[:, 2])
        d = b[:, :2] - a[:, :2]
        local = np.stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]], axis=1)
        e = np.concatenate([local - raw.odometry[:, :2], wrap(b[:, 2] - a[:, 2] - raw.odometry[:, 2])[:, None]], 1)
        ro = np.einsum("kij,kj->ki", Wo, e)
        o = poses[raw.observers]
        co, so = np.cos(o[:, 2]), np.sin(o[:, 2])
        g = f[which] - o[:, :2]
        lx, ly = co * g[:, 0] + so * g[:, 1], -so * g[:, 0] + co * g[:, 1]
        rho = np.hypot(lx, ly)
        rl = np.stack([wrap(np.arctan2(ly, lx) - bearing), rho - distance], axis=1) / sigma
        r = np.concatenate([ro.ravel(), rl.ravel()])
        if not jacobian:
            return r
        # odometry rows: d e / d (pose a, pose b), then whitened
        block = np.zeros((P, 3, 6))
        block[:, 0, 0], block[:, 0, 1], block[:, 1, 0], block[:, 1, 1] = -c, -s, s, -c
        block[:, 0, 2], block[:, 1, 2] = local[:, 1], -local[:, 0]
        block[:, 0, 3], block[:, 0, 4], block[:, 1, 3], block[:, 1, 4] = c, s, -s, c
        block[:, 2, 2], block[:, 2, 5] = -1.0, 1.0
        block = np.matmul(Wo, block)
        k = np.arange(P)
        cols = np.concatenate([3 * (k - 1)[:, None] + np.arange(3), 3 * k[:, None] + np.arange(3)], axis=1)
        rows = np.broadcast_to((3 * k[:, None] + np.arange(3))[:, :, None], (P, 3, 6))
        colsb = np.broadcast_to(cols[:, None, :], (P, 3, 6))
        keep = colsb >= 0
        # landmark rows: d (bearing, range) / d l, d l / d (pose, feature)
        dl_dt = np.stack([np.stack([-co, -so], -1), np.stack([so, -co], -1)], 1)         # (M, 2, 2)
        dl_dphi = np.stack([ly, -lx], axis=1)[:, :, None]
        dl_df = -dl_dt
        dz_dl = np.stack([np.stack([-ly, lx], -1) / rho[:, None] ** 2, np.stack([lx, ly], -1) / rho[:, None]], 1)
        dz = np.matmul(dz_dl / sigma[:, :, None], np.concatenate([dl_dt, dl_dphi, dl_df], axis=2))   # (M, 2, 5)
        obs_cols = np.concatenate([3 * (raw.observers - 1)[:, None] + np.arange(3),
                                   3 * P + 2 * which[:, None] + np.arange(2)], axis=1)
        obs_rows = np.broadcast_to((3 * P + 2 * np.arange(M)[:, None] + np.arange(2))[:, :, None], (M, 2, 5))
        obs_colsb = np.broadcast_to(obs_cols[:, None, :], (M, 2, 5))
        obs_keep = obs_colsb >= 0
        J = sp.csr_matrix((np.concatenate([block[keep], dz[obs_keep]]),
                           (np.concatenate([rows[keep], obs_rows[obs_keep]]),
                            np.concatenate([colsb[keep], obs_colsb[obs_keep]]))), shape=(len(r), n))
        return r, J

    x = np.concatenate([start.poses.ravel(), start.features.ravel()])
    damping, iterations = 1e-4, 0
    r, J = evaluate(x)
    cost = r @ r
    while iterations < 200:
        A = (J.T @ J).tocsc()
        g = J.T @ r
        step = splu(A + sp.diags(damping * A.diagonal()), permc_spec="MMD_AT_PLUS_A").solve(-g)
        trial = evaluate(x + step, jacobian=False)
        if trial @ trial < cost:
            x, previous = x + step, cost
            r, J = evaluate(x)
            cost = r @ r
            iterations += 1
            damping = max(damping / 10, 1e-12)
            if previous - cost < 1e-12 * cost:
                break
        else:
            damping *= 10
            if damping > 1e12:
                break
    return float(cost), iterations


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=5)
    args = parser.parse_args()
    logging.getLogger("mapjoin").setLevel(logging.ERROR)
    started = time.perf_counter()
    load = os.getloadavg()[0]
    speed, kept = speed_rows(args.repeat)
    raw, built, whole = kept["VicPark_clean_data.mat"]
    lines = ["### Speed (seconds, medians)", "",
             (f"`python benchmarks/build.py --repeat {args.repeat}`, in-process, one BLAS thread, on "
              f"{os.cpu_count()} cores with load average {load:.2f} before the run (other jobs share the machine: "
              "with load near 1, the two processes compete with them for the cores)."), "",
             "| raw data | what | s | result |", "|---|---|---:|---|", *speed, "",
             "### The 200 built maps against the shipped `VicPark_200_local_maps`", "",
             "| statistic | value |", "|---|---|", *shipped_rows(built), "",
             "### Build, then join, against the batch solution (paper's metric)", "",
             (f"Over the 299 features and the 200 maps' end poses; the batch solution is chi^2 {whole.cost:.2f}."),
             "",
             "| maps | method | mean abs x (m) | mean abs y (m) | mean abs phi (rad) | max xy (m) |",
             "|---|---|---:|---:|---:|---:|", *metric_rows(raw, built, whole), "",
             "### Noise numbers: chi^2 at the batch optimum against its degrees of freedom", "",
             "| raw data | reading | chi^2 | dof | chi^2 / dof |", "|---|---|---:|---:|---:|",
             *interpretation_rows(kept)]
    text = "\n".join(lines)
    print(text)
    print(f"({time.perf_counter() - started:.0f} s)", file=sys.stderr)
    write_section("build", text)


if __name__ == "__main__":
    main()
