"""Seeded ground-truth simulator: one robot run cut into a chain of local maps.

Units: metres and radians throughout; one *step* is one odometry increment.

World
    The robot drives a figure-eight made of two circles that touch at the global
    origin: lobe A (centre ``(0, +rho)``, anticlockwise), then lobe B (centre
    ``(0, -rho)``, clockwise), starting at pose 0 = ``(0, 0, 0)`` heading along +x.
    Every step moves the robot ``step_length`` along a chord of the current circle and
    turns it by ``+-2*pi / (lap_steps / 2)``. The run of ``maps * steps_per_map`` steps
    covers the figure-eight about ``laps`` times (``lap_steps`` is
    ``max(32, 2 * ceil(total_steps / (2 * laps)))``), so with ``laps > 1`` later maps
    drive exactly over earlier ones and re-observe their features (loop closures; the
    crossing at the origin gives more). Point features are scattered uniformly
    (``density`` per m^2, or ``features`` in total) over the band within
    ``sensor_range`` of the path (two annuli). Features no map sees are dropped; feature
    ids are ``0..n-1`` in order of first sighting.

Sensor
    A 360-degree range/bearing sensor scans at every pose and sees the features whose
    distance is in ``[min_range, sensor_range]``.

Local maps
    Local map ``k`` (``1..maps``, name ``sim-<k>``, ``start_id = k-1``, ``end_id = k``)
    covers steps ``(k-1)*s .. k*s`` (``s = steps_per_map``). It uses the scans at its
    start pose and the next ``s - 1`` poses (the scan at its end pose starts map
    ``k+1``), and holds, in the frame of its start pose (``x_local = R(phi_start)^T
    (x_global - t_start)``, angles wrapped to ``[-pi, pi)``), its end pose and the
    features it saw, sorted by id.

    **Guarantee**: every pair of consecutive maps shares at least ``min_shared``
    features (those seen from both the last scan of one and the first scan of the next),
    and every map sees at least ``min_shared`` features. Where the random world falls
    short, features are added at random between the two poses concerned.

Noise model (linearised, exact to first order)
    Odometry: each step's increment, in the robot frame (x forward, y left), has
    independent Gaussian errors with standard deviations ``odometry_noise = (forward,
    lateral, heading)`` (m, m, rad per step); they accumulate by dead reckoning.
    Observations: range and bearing errors with standard deviations
    ``sensor_noise = (range, bearing)`` (m, rad), independent per scan and feature.
    A feature's estimate is the mean, over its observations in the map, of the
    observed point placed from the dead-reckoned pose. Linearising this estimator gives
    the map's state error ``e = J_u xi_u + J_z xi_z`` in the noises; its covariance
    ``P = J_u Q J_u^T + J_z W J_z^T`` is declared in full (``LocalMap.covariance``, state
    ``[x, y, phi, f1x, f1y, ...]``): the features are correlated with the end pose and
    with each other through the shared odometry. ``P`` is symmetric positive definite
    (every feature has its own observation noise, the end pose its own last step).

    The estimate is the true local state plus ``e``, drawn exactly from ``N(0, P)``: the
    odometry part as ``J_u xi`` from per-step standard normals, the observation part with
    the Cholesky factor of each feature's 2x2 block (``noiseless=True``: the true local
    state, with the same declared ``P``). Maps are statistically independent.

Reproducibility: everything is drawn from ``numpy.random.default_rng(seed)``; the same
arguments and seed give bit-identical maps and truth.
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from .maps import (
    GroundTruth,
    LocalMap,
    StackedMaps,
    first_invalid_map,
    locate,
    marginal_variances,
    size_groups,
    unstack,
)
from .se2 import relative, to_frame, wrap
from .sightings import Sightings

__all__ = ["MAX_STEPS", "Robots", "Simulation", "SimulationStream", "simulate", "simulate_robots", "simulate_stream"]

#: the most robot steps one simulation takes (maps x steps per map): 10^7, the largest run benchmarked (10^6 maps
#: of 10 steps, spherical); more is a typo that would exhaust the memory or numpy's sizes, refused at once
MAX_STEPS = 10**7
_MIN_LAP_STEPS = 32   # smallest figure-eight: 16 steps per circle, 22.5 degrees per step
_CHUNK = 512          # maps processed together (bounds memory; results do not depend on it)


@dataclass(frozen=True)
class Simulation:
    """A simulated run: the local maps in chain order and the ground truth.

    ``truth`` holds the true features (ids as in the maps) and the true poses
    ``0..maps`` (pose ``k`` is the end pose of map ``k``; pose 0 is the origin), all in
    the global frame.
    """

    maps: tuple[LocalMap, ...]
    truth: GroundTruth


@dataclass(frozen=True)
class SimulationStream:
    """A simulated run whose local maps are made as they are taken (:func:`simulate_stream`): ``chunks``
    yields them in chain order, a list of a few hundred at a time, once; ``truth`` as in :class:`Simulation`."""

    chunks: Iterator[list[LocalMap]]
    truth: GroundTruth


def simulate(maps: int = 20, **options) -> Simulation:
    """Simulate a seeded run on a figure-eight and cut it into ``maps`` local maps: :func:`simulate_stream`'s
    run (the same arguments), every map made at once."""
    run = simulate_stream(maps, **options)
    return Simulation(tuple(local_map for chunk in run.chunks for local_map in chunk), run.truth)


def simulate_stream(maps: int = 20, *, seed: int = 0, features: int | None = None,
                    steps_per_map: int = 10, laps: float = 2.0, step_length: float = 1.0,
                    sensor_range: float = 5.0, min_range: float = 0.5, density: float = 0.12,
                    odometry_noise: tuple[float, float, float] = (0.05, 0.02, 0.01),
                    sensor_noise: tuple[float, float] = (0.05, 0.01),
                    min_shared: int = 3, noiseless: bool = False,
                    full_covariance: bool = True) -> SimulationStream:
    """Simulate a seeded run on a figure-eight and cut it into ``maps`` local maps, made a chunk at a time as
    they are taken, so that a long run is written without holding its maps (``mapjoin simulate -o -``).

    Parameters (metres, radians; see the module docstring for the model):

    - ``maps``: number of local maps (>= 1); ``steps_per_map``: robot steps per map (>= 1).
    - ``seed``: non-negative integer seed of ``numpy.random.default_rng``.
    - ``features``: number of features scattered over the band around the path;
      default ``density`` (features per m^2) times the band's area. Features no map sees
      are dropped, and a few may be added for the ``min_shared`` guarantee.
    - ``laps``: how many times the run drives around the figure-eight (>= 0.5; short
      runs cover less, as a lap has at least 32 steps).
    - ``step_length``: distance per step (> 0).
    - ``sensor_range``, ``min_range``: the sensor sees features at distances in
      ``[min_range, sensor_range]``; needs ``0 < min_range`` and
      ``sensor_range > min_range + step_length``.
    - ``odometry_noise``: standard deviations (forward m, lateral m, heading rad) per step.
    - ``sensor_noise``: standard deviations (range m, bearing rad) per observation.
    - ``min_shared``: guaranteed number of features shared by consecutive maps (>= 0).
    - ``noiseless``: if true, the maps hold the true local states (covariances unchanged).
    - ``full_covariance``: if false, the maps carry only the spherical ``marginal``
      variances of the same covariance (saves memory for very long runs).

    Raises ``ValueError`` for invalid arguments.
    """
    _check_int(maps, "maps", 1)
    _check_int(seed, "seed", 0)
    _check_int(steps_per_map, "steps_per_map", 1)
    if maps * steps_per_map > MAX_STEPS:
        raise ValueError(f"maps * steps_per_map must be at most {MAX_STEPS} steps, got {maps} * {steps_per_map}")
    _check_int(min_shared, "min_shared", 0)
    if features is not None:
        _check_int(features, "features", 0)
    for value, name in ((laps, "laps"), (step_length, "step_length"), (sensor_range, "sensor_range"),
                        (min_range, "min_range"), (density, "density")):
        _check_positive(value, name)
    if laps < 0.5:
        raise ValueError(f"laps must be >= 0.5 (one circle of the figure-eight), got {laps}")
    if not sensor_range > min_range + step_length:
        raise ValueError(f"sensor_range must exceed min_range + step_length "
                         f"({min_range} + {step_length}), got {sensor_range}")
    sigma_forward, sigma_lateral, sigma_heading = _check_sigmas(odometry_noise, "odometry_noise", 3)
    sigma_range, sigma_bearing = _check_sigmas(sensor_noise, "sensor_noise", 2)

    n = steps_per_map
    total = maps * n
    lap = max(_MIN_LAP_STEPS, 2 * math.ceil(total / (2 * laps)))
    scanned = min(lap, total)                    # distinct scan phases 0..scanned-1
    rng = np.random.default_rng(seed)

    # --- world -----------------------------------------------------------------------
    radius = _radius(lap, step_length)
    scan_poses = _figure_eight(np.arange(scanned), lap, step_length)
    world = _scatter(rng, features, density, radius, sensor_range)
    sightings = Sightings(world, scan_poses, lap, radius, min_range, sensor_range)
    required = _required_pairs(maps, n, lap)
    extra = _top_up(rng, sightings, required, scan_poses, min_shared, min_range, sensor_range, step_length)
    if len(extra):
        world = np.concatenate([world, extra])
        sightings = Sightings(world, scan_poses, lap, radius, min_range, sensor_range)

    # ids in order of first sighting; unseen features dropped
    first_seen = sightings.first_seen()
    seen = np.flatnonzero(first_seen < scanned)
    seen = seen[np.argsort(first_seen[seen], kind="stable")]
    new_id = np.full(len(world), -1, dtype=np.int64)
    new_id[seen] = np.arange(len(seen))
    true_features = world[seen]
    visible = sightings.renumbered(new_id)

    truth = GroundTruth(np.arange(len(seen)), true_features, np.arange(maps + 1),
                        _figure_eight(np.arange(maps + 1) * n, lap, step_length), name="sim truth")

    # --- local maps ------------------------------------------------------------------
    # the odometry noise of every map is drawn first, then each chunk's sensor noise: to make a chunk at a time,
    # a copy of the generator draws the odometry noise chunk by chunk, and rng skips it (drawn and dropped)
    odometry = None
    if not noiseless:
        odometry = np.random.Generator(type(rng.bit_generator)())
        odometry.bit_generator.state = rng.bit_generator.state
        for first in range(0, maps, _CHUNK):
            rng.standard_normal((min(_CHUNK, maps - first), n, 3))
    sigmas = (sigma_forward, sigma_lateral, sigma_heading, sigma_range, sigma_bearing)

    def chunks() -> Iterator[list[LocalMap]]:
        for first in range(0, maps, _CHUNK):
            chunk = np.arange(first, min(first + _CHUNK, maps))
            yield _chunk_maps(chunk, n, lap, step_length, true_features, visible, sigmas, None if noiseless else rng,
                              None if odometry is None else odometry.standard_normal((len(chunk), n, 3)),
                              full_covariance)

    return SimulationStream(chunks(), truth)


@dataclass(frozen=True)
class Robots:
    """Several robots in one world (:func:`simulate_robots`): each robot's run, in its own frame, and the
    world's truth in the frame of the first robot's start (the frame a merge of their maps lands in)."""

    robots: tuple[Simulation, ...]
    truth: GroundTruth


def simulate_robots(robots: int, maps: int = 20, *, laps: float = 1.25, **options) -> Robots:
    """``robots`` robots, ``maps`` local maps each, on one figure-eight: maps to join per robot, then merge.

    The robots drive one after another, each ``laps`` times around the figure-eight (so their
    areas overlap), robot r starting where robot r-1 stopped: one :func:`simulate` run of
    ``robots * maps`` maps (``options`` as there), cut into ``robots`` chains. Each chain is in
    its own frame, its start pose; local maps are relative to their start pose, so they are
    the run's maps as they are, and robot r's truth is the run's truth seen from its start
    (its poses ``(r-1)*maps .. r*maps``, with the ids of the run, and the features its maps
    hold). Feature ids are the world's, shared by all robots; pose ids never repeat.
    """
    _check_int(robots, "robots", 1)
    _check_int(maps, "maps", 1)
    _check_positive(laps, "laps")
    whole = simulate(robots * maps, laps=laps * robots, **options)
    truth = whole.truth
    runs = []
    for r in range(robots):
        chain = whole.maps[r * maps:(r + 1) * maps]
        start = truth.poses[r * maps]
        poses = relative(start, truth.poses[r * maps:(r + 1) * maps + 1])
        poses[:, 2] = wrap(poses[:, 2])
        seen = np.unique(np.concatenate([m.feature_ids for m in chain]))
        where = locate(truth.feature_ids, seen)[0]
        runs.append(Simulation(chain, GroundTruth(seen, to_frame(start, truth.features[where]),
                                                  truth.pose_ids[r * maps:(r + 1) * maps + 1], poses,
                                                  name=f"robot {r + 1} truth")))
    return Robots(tuple(runs), truth)


# --- argument checks -------------------------------------------------------------------

def _check_int(value, name: str, minimum: int) -> None:
    if isinstance(value, bool) or not isinstance(value, numbers.Integral):
        raise ValueError(f"{name} must be an integer, got {value!r}")
    if value < minimum:
        raise ValueError(f"{name} must be >= {minimum}, got {value}")


def _check_positive(value, name: str) -> None:
    if isinstance(value, bool) or not isinstance(value, numbers.Real) or not (0 < value < math.inf):
        raise ValueError(f"{name} must be a positive finite number, got {value!r}")


def _check_sigmas(values, name: str, count: int) -> tuple[float, ...]:
    try:
        sigmas = tuple(float(v) for v in values)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be {count} standard deviations, got {values!r}") from None
    if len(sigmas) != count or not all(0 < s < math.inf for s in sigmas):
        raise ValueError(f"{name} must be {count} positive finite standard deviations, got {values!r}")
    return sigmas


# --- geometry --------------------------------------------------------------------------

def _radius(lap: int, step_length: float) -> float:
    """Radius of the circles on which ``lap / 2`` chords of ``step_length`` close a circle."""
    return step_length / (2 * math.sin(math.pi / (lap // 2)))


def _figure_eight(steps: np.ndarray, lap: int, step_length: float) -> np.ndarray:
    """True global poses (k x 3) after ``steps`` steps; a function of ``steps % lap`` only."""
    lobe = lap // 2
    turn = 2 * np.pi / lobe
    radius = _radius(lap, step_length)
    phase = np.asarray(steps, dtype=np.int64) % lap
    first = phase < lobe
    angle = np.where(first, phase, phase - lobe) * turn
    sign = np.where(first, 1.0, -1.0)
    return np.stack([radius * np.sin(angle), sign * 2 * radius * np.sin(angle / 2) ** 2,
                     wrap(sign * angle)], axis=1)


def _annulus(rng: np.random.Generator, count: int, centre_y: float, inner: float,
             outer: float) -> np.ndarray:
    u = rng.random((count, 2))
    r = np.sqrt(inner ** 2 + u[:, 0] * (outer ** 2 - inner ** 2))
    psi = 2 * np.pi * u[:, 1]
    return np.stack([r * np.cos(psi), centre_y + r * np.sin(psi)], axis=1)


def _scatter(rng: np.random.Generator, count: int | None, density: float, radius: float,
             band: float) -> np.ndarray:
    """Uniform points on the union of the annuli ``|p - (0, +-radius)| in [radius - band, radius + band]``."""
    inner, outer = max(0.0, radius - band), radius + band

    def in_a(points: np.ndarray) -> np.ndarray:
        d = np.hypot(points[:, 0], points[:, 1] - radius)
        return (d >= inner) & (d <= outer)

    if count is None:
        per_lobe = round(density * np.pi * (outer ** 2 - inner ** 2))
        a = _annulus(rng, per_lobe, radius, inner, outer)
        b = _annulus(rng, per_lobe, -radius, inner, outer)
        return np.concatenate([a, b[~in_a(b)]])
    kept: list[np.ndarray] = []
    have = 0
    while have < count:                 # lobe A or B with probability 1/2; B inside A rejected
        lobe_a = rng.random(count) < 0.5
        points = np.where(lobe_a[:, None], _annulus(rng, count, radius, inner, outer),
                          _annulus(rng, count, -radius, inner, outer))
        points = points[lobe_a | ~in_a(points)]
        kept.append(points)
        have += len(points)
    return np.concatenate(kept)[:count] if count else np.empty((0, 2))


def _required_pairs(maps: int, n: int, lap: int) -> np.ndarray:
    """Scan phases (a, c) that must share ``min_shared`` features: the last scan of map k and
    the first of map k+1, and (so that a single map sees features) the first scan twice."""
    boundary = np.arange(1, maps) * n
    pairs = np.stack([(boundary - 1) % lap, boundary % lap], axis=1)
    return np.unique(np.concatenate([[[0, 0]], pairs]), axis=0)


def _top_up(rng: np.random.Generator, sightings: Sightings, required: np.ndarray, poses: np.ndarray,
            min_shared: int, min_range: float, max_range: float, step_length: float) -> np.ndarray:
    """Features to add so that every required pair of scans shares ``min_shared`` features."""
    if min_shared == 0:
        return np.empty((0, 2))
    shared = np.zeros(len(required), dtype=np.int64)
    for lo in range(0, len(required), _CHUNK * 8):   # a block of pairs at a time (bounds memory)
        pairs = required[lo:lo + _CHUNK * 8]
        seen = sightings.at(pairs.ravel())
        owner, feature = seen.expand(pairs[:, 0])
        shared[lo:lo + len(pairs)] = np.bincount(owner[seen.sees(pairs[owner, 1], feature)], minlength=len(pairs))
    deficit = np.maximum(0, min_shared - shared)
    if not deficit.any():
        return np.empty((0, 2))
    where = np.repeat(np.arange(len(required)), deficit)
    middle = (poses[required[where, 0], :2] + poses[required[where, 1], :2]) / 2
    # within [min_range, max_range] of both scans: distance from the midpoint in
    # [min_range + step/2, max_range - step/2], shrunk by a small margin
    margin = 1e-6 * (max_range - min_range)
    inner, outer = min_range + step_length / 2 + margin, max_range - step_length / 2 - margin
    u = rng.random((len(where), 2))
    r = np.sqrt(inner ** 2 + u[:, 0] * (outer ** 2 - inner ** 2))
    psi = 2 * np.pi * u[:, 1]
    return middle + np.stack([r * np.cos(psi), r * np.sin(psi)], axis=1)


# --- local maps ------------------------------------------------------------------------

def _chunk_maps(chunk: np.ndarray, n: int, lap: int, step_length: float, true_features: np.ndarray,
                visible: Sightings, sigmas: tuple[float, ...], rng: np.random.Generator | None,
                odometry_xi: np.ndarray | None, full_covariance: bool) -> list[LocalMap]:
    """The local maps with 0-based indices ``chunk`` (vectorised over maps and features); ``odometry_xi``: their
    odometry noise (len(chunk) x n x 3 standard normal draws)."""
    sf, sl, sh, sr, sb = sigmas
    c = len(chunk)
    steps = chunk[:, None] * n + np.arange(n + 1)                       # c x (n+1)
    poses = _figure_eight(steps.ravel(), lap, step_length).reshape(c, n + 1, 3)
    start = poses[:, 0]
    local = relative(start[:, None], poses)  # c x (n+1) x 3
    local[..., 2] = wrap(local[..., 2])

    # observations: (map, scan i, feature), grouped by (map, feature) in id order
    phases = (steps[:, :n] % lap).ravel()
    scan_index, obs_feature = visible.at(phases).expand(phases)
    obs_map, obs_scan = np.divmod(scan_index, n)
    width = max(len(true_features), 1)
    key = obs_map * width + obs_feature
    order = np.argsort(key, kind="stable")
    sorted_key = key[order]
    starts = np.ones(len(key), dtype=bool)
    starts[1:] = sorted_key[1:] != sorted_key[:-1]
    group = np.empty(len(key), dtype=np.int64)
    group[order] = np.cumsum(starts) - 1
    group_map, group_feature = np.divmod(sorted_key[starts], width)
    g = len(group_map)
    count = np.bincount(group, minlength=g).astype(float)
    per_map = np.bincount(group_map, minlength=c)
    rank = np.arange(g) - np.repeat(np.cumsum(per_map) - per_map, per_map)

    # true local features
    f_local = to_frame(start[group_map], true_features[group_feature])   # g x 2

    # odometry Jacobian (times sqrt(Q)): step l moves every point p attached to a later pose
    # by R(theta_l) [sf xi_f, sl xi_l] + sh xi_h S (p - t_{l+1}),  S = [[0, -1], [1, 0]]
    theta = local[:, :n, 2]
    cl, sn = np.cos(theta), np.sin(theta)
    rot = np.stack([np.stack([cl * sf, -sn * sl], -1), np.stack([sn * sf, cl * sl], -1)], -2)  # c x n x 2 x 2
    after = local[:, 1:, :2]                                              # t_{l+1}: c x n x 2
    rows = 3 + 2 * int(per_map.max(initial=0))
    jac = np.zeros((c, rows, n, 3))
    end_arm = local[:, n, None, :2] - after                               # t_n - t_{l+1}
    jac[:, 0:2, :, 0:2] = rot.transpose(0, 2, 1, 3)
    jac[:, 0, :, 2] = -sh * end_arm[..., 1]
    jac[:, 1, :, 2] = sh * end_arm[..., 0]
    jac[:, 2, :, 2] = sh
    # weight of step l for a feature: share of its observations made after step l
    histogram = np.bincount(group * n + obs_scan, minlength=g * n).reshape(g, n)
    weight = (count[:, None] - np.cumsum(histogram, axis=1)) / count[:, None]   # g x n
    arm = f_local[:, None, :] - after[group_map]                          # g x n x 2
    block = np.empty((g, 2, n, 3))
    block[..., 0:2] = rot[group_map].transpose(0, 2, 1, 3) * weight[:, None, :, None]
    block[:, 0, :, 2] = -sh * arm[..., 1] * weight
    block[:, 1, :, 2] = sh * arm[..., 0] * weight
    row = 3 + 2 * rank
    jac[group_map, row] = block[:, 0]
    jac[group_map, row + 1] = block[:, 1]
    jac = jac.reshape(c, rows, 3 * n)

    # observation noise: per observation d = f - t_i, covariance of its error in the map
    # (range along d/|d|, bearing across): sr^2 d d^T / |d|^2 + sb^2 (S d)(S d)^T; a feature's
    # estimate averages its observations, so its block is the sum divided by count^2
    d = f_local[group] - local[obs_map, obs_scan, :2]
    dx, dy = d[:, 0], d[:, 1]
    a, b = sr * sr / (dx * dx + dy * dy), sb * sb
    terms = (a * dx * dx + b * dy * dy, (a - b) * dx * dy, a * dy * dy + b * dx * dx)
    sxx, sxy, syy = (np.bincount(group, t, minlength=g) / (count * count) for t in terms)
    # its Cholesky factor, to draw the error
    l00 = np.sqrt(sxx)
    l10 = sxy / l00
    l11 = np.sqrt(np.maximum(syy - l10 * l10, 0.0))  # > 0: every observation adds a PD term
    obs_blocks = np.stack([np.stack([sxx, sxy], 1), np.stack([sxy, syy], 1)], 1)   # g x 2 x 2

    # errors drawn with the same Jacobian and factors: exactly N(0, P)
    error = np.zeros((c, rows))
    if rng is not None:
        error = np.einsum("crk,ck->cr", jac, odometry_xi.reshape(c, 3 * n))
        xi = rng.standard_normal((g, 2))
        error[group_map, row] += l00 * xi[:, 0]
        error[group_map, row + 1] += l10 * xi[:, 0] + l11 * xi[:, 1]

    end = local[:, n] + error[:, :3]
    end[:, 2] = wrap(end[:, 2])
    estimate = f_local + np.stack([error[group_map, row], error[group_map, row + 1]], axis=1)
    if not full_covariance:   # the ``marginal`` summary of P only: diagonal of J_u J_u^T + obs
        diagonal = np.einsum("crk,crk->cr", jac, jac)
        feature_variances = (diagonal[group_map, row] + diagonal[group_map, row + 1] + sxx + syy) / 2
        pose_variances = np.stack([(diagonal[:, 0] + diagonal[:, 1]) / 2, diagonal[:, 2]], axis=1)
    names = [f"sim-{k + 1}" for k in chunk.tolist()]
    first_group = np.cumsum(per_map) - per_map
    stacks = []
    for places in size_groups(per_map):   # the maps of one size, made and checked as one stack
        m = int(per_map[places[0]])
        members = first_group[places, None] + np.arange(m)             # their groups (features): k x m
        if full_covariance:
            odometry = jac[places, :3 + 2 * m]
            covariance = odometry @ odometry.transpose(0, 2, 1)         # P = J_u J_u^T + blockdiag(obs)
            diagonal_block = 3 + 2 * np.arange(m)
            for i in range(2):
                for j in range(2):
                    covariance[:, diagonal_block + i, diagonal_block + j] += obs_blocks[members, i, j]
            covariance = (covariance + covariance.transpose(0, 2, 1)) / 2
            variances = marginal_variances(covariance)
        else:
            covariance, variances = None, (feature_variances[members], pose_variances[places])
        stacks.append((places, StackedMaps([names[i] for i in places.tolist()], end[places], group_feature[members],
                                           estimate[members], *variances, covariance)))
    invalid = first_invalid_map(stacks)
    if invalid is not None:
        raise invalid[1]
    return unstack(stacks, chunk.tolist(), (chunk + 1).tolist())
