"""How far apart two global maps are (``compare``), and how accurate and consistent a map is
against ground truth (``evaluate``).

Entities are matched by id: features by feature id, poses by pose id (pose k is the end
pose of the k-th local map; a truth's pose 0 is the start pose of the first map). Only
ids present in both are compared. Angle differences are wrapped into ``[-pi, pi)``.

Frames: a global map lives in the frame of its first map's start pose, which is the
truth's pose 0, so by default nothing is aligned. ``align="rigid"`` first moves the map
by the 2D rigid transform that best fits (least squares, Kabsch/Umeyama without scale)
its shared feature and pose positions onto the truth's, e.g. for maps expressed in
another frame; the statement in ``Evaluation.alignment`` says which was done.

NEES (normalised estimation error squared) of an entity with error ``e`` and reported
covariance ``P`` is ``e^T P^-1 e``: ``P`` is the map's full marginal block (2x2 per
feature, 3x3 per pose) when it has them, else its spherical numbers (``sigma^2 I2``;
``diag(sigma_xy^2, sigma_xy^2, p_phi)``). A fast join's spherical numbers are the
one-step method's weights, not covariances (:attr:`GlobalMap.has_covariances`): the NEES
against them is computed the same way but is no consistency test (on the simulations it
is 10^3-10^4, docs/method.md#uncertainty-columns); the CLI labels it so. The average NEES over N entities of d degrees
of freedom is, for a consistent estimator with independent errors, distributed as
``chi2(d N) / N``; its two-sided 95% bounds are ``chi2.ppf(0.025, dN)/N`` and
``chi2.ppf(0.975, dN)/N``. Errors of one map are correlated (every entity shares the
errors of the poses before it), which widens the true spread of the average, so a
value just outside the bounds is weak evidence; an order of magnitude is not.

Ids that are not the truth's: a map joined with data association numbers its features itself (by first sighting),
so that matched by id they are compared with unrelated true features. A map's errors often exceed its features'
spacing (the default simulation: 1.2-3 m against 1.3 m), but then they are a drift, alike between neighbouring
features; compared by unrelated ids they are not. So ``evaluate`` logs one warning naming the map when, of up to
``SAMPLE`` compared features taken evenly, more than half (and at least ``STRANGER_FEATURES``) lie nearer to another
true feature than to their own *and* their errors are incoherent: the median difference of a feature's error from
its nearest compared neighbour's is at least ``INCOHERENT`` times their median size (measured: 0.01-0.09 for joins of
the default simulations and of 8240 with the truth's ids or through their associations, 0.58-0.66 for associating
joins and their merge compared by id). The warning says to compare through the association (``feature_truth``, the
CLI's ``--associations``). Distances are computed densely for the sample (:mod:`mapjoin.neighbours`: evaluate
imports no scipy).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np

from .consistency import chi2_quantile
from .errors import InputError
from .maps import GlobalMap, GroundTruth, locate
from .neighbours import nearest
from .se2 import compose, rotation, transform, wrap

log = logging.getLogger("mapjoin")

#: fewest compared features nearer to another true feature than to their own before ``evaluate`` warns (fewer say
#: nothing of the ids)
STRANGER_FEATURES = 5
#: errors whose neighbours differ by at least this share of their median size are no drift (module docstring)
INCOHERENT = 0.5
#: compared features (taken evenly) the test of unrelated ids looks at: its cost is SAMPLE x (features + truth)
SAMPLE = 128

__all__ = ["ALIGNMENTS", "CHI2_LEVEL", "Alignment", "Chi2Verdict", "Difference", "Evaluation", "chi2_interval",
           "chi2_surely_inside", "chi2_verdict", "compare", "evaluate", "nees_bounds"]

Alignment = Literal["none", "rigid"]
ALIGNMENTS: tuple[str, ...] = ("none", "rigid")
CONFIDENCE = 0.95  # two-sided: the bounds are the 2.5% and 97.5% quantiles
CHI2_LEVEL = 0.999  # the interval a solve's chi^2 is checked against (refine, build): 0.05% in each tail


@dataclass(frozen=True)
class Difference:
    """Differences between two global maps over the ids they share (no alignment).

    ``mean_abs_x``/``mean_abs_y`` average ``|x_b - x_a|``, ``|y_b - y_a|`` over the shared
    features and poses together, ``mean_abs_phi`` ``|wrap(phi_b - phi_a)|`` over the
    shared poses: the metric of the paper's Section 7. ``rms_xy``/``max_xy`` are the RMS
    and maximum of the position difference's norm over features and poses,
    ``rms_phi``/``max_phi`` of the wrapped orientation difference over poses. Statistics
    over no entity (e.g. orientation without shared poses) are NaN.
    """

    features: int
    poses: int
    mean_abs_x: float
    mean_abs_y: float
    mean_abs_phi: float
    rms_xy: float
    max_xy: float
    rms_phi: float
    max_phi: float


@dataclass(frozen=True)
class Evaluation:
    """A global map against ground truth, over the ids both hold.

    Errors are Euclidean position errors (m) and wrapped orientation errors (rad), as
    RMS and maximum; NaN when there is no shared entity of that kind. ``nees_*`` is
    the average NEES (see the module docstring), with its two-sided 95% chi-square
    bounds; None when there is nothing to test. ``consistent`` is True when every
    available average NEES lies within its bounds, None when none is available.
    """

    alignment: str
    features: int
    poses: int
    feature_rms: float
    feature_max: float
    pose_rms_xy: float
    pose_max_xy: float
    pose_rms_phi: float
    pose_max_phi: float
    nees_features: float | None
    nees_poses: float | None
    nees_bounds_features: tuple[float, float] | None
    nees_bounds_poses: tuple[float, float] | None
    consistent: bool | None


def compare(a: GlobalMap, b: GlobalMap) -> Difference:
    """How far ``b`` is from ``a``, over the feature and pose ids they share.

    Raises InputError when they share no id.
    """
    fa, fb = _shared(a.feature_ids, b.feature_ids)
    pa, pb = _shared(a.pose_ids, b.pose_ids)
    if not len(fa) and not len(pa):
        raise InputError(f"shares no feature or pose id with {b.name}, so there is nothing to compare", a.name)
    xy = np.concatenate([b.features[fb] - a.features[fa], b.poses[pb, :2] - a.poses[pa, :2]])
    phi = np.abs(wrap(b.poses[pb, 2] - a.poses[pa, 2]))
    distance = np.hypot(xy[:, 0], xy[:, 1])
    return Difference(
        features=len(fa), poses=len(pa),
        mean_abs_x=_mean(np.abs(xy[:, 0])), mean_abs_y=_mean(np.abs(xy[:, 1])), mean_abs_phi=_mean(phi),
        rms_xy=_rms(distance), max_xy=_max(distance), rms_phi=_rms(phi), max_phi=_max(phi))


def evaluate(global_map: GlobalMap, truth: GroundTruth, align: Alignment = "none", *,
             feature_truth: tuple[np.ndarray, np.ndarray] | None = None) -> Evaluation:
    """Errors and NEES of ``global_map`` against ``truth``, over the ids both hold.

    ``align``: ``"none"`` (default; the map and the truth are both in the frame of pose
    0, the first map's start pose) or ``"rigid"`` (first fit the map onto the truth by a
    2D rigid transform; the fit absorbs about 3 of the 2F+3P degrees of freedom, so the
    NEES comes out slightly low, which matters only for very few entities).
    ``feature_truth``: for a map whose feature ids are not the truth's (a join with data association), the truth's
    id of each of its feature ids (two arrays, e.g. :func:`mapjoin.association.truth_of_found`); features are then
    compared through it, several of the map's features with one true feature when the association split it.
    Raises InputError when the map and the truth share no id, ValueError for an unknown
    ``align``.
    """
    if align not in ALIGNMENTS:
        raise ValueError(f"unknown alignment {align!r}; expected one of {', '.join(ALIGNMENTS)}")
    fm, ft = (_shared(global_map.feature_ids, truth.feature_ids) if feature_truth is None
              else _through(global_map.feature_ids, *feature_truth, truth.feature_ids))
    pm, pt = _shared(global_map.pose_ids, truth.pose_ids)
    if not len(fm) and not len(pm):
        raise InputError(f"shares no feature or pose id with the ground truth ({truth.name}), so there is "
                         "nothing to evaluate", global_map.name)
    features, poses = global_map.features[fm], global_map.poses[pm]
    if align == "rigid":
        motion = _rigid_fit(
            np.concatenate([features, poses[:, :2]]), np.concatenate([truth.features[ft], truth.poses[pt, :2]]))
        features, poses = transform(motion, features), compose(motion, poses)
        poses[:, 2] = wrap(poses[:, 2])
        translation, angle = motion[:2], motion[2]
        alignment = (f"rigid: the map moved onto the truth by the least-squares 2D rigid fit of its "
                     f"{len(fm)} feature and {len(pm)} pose positions (rotation {angle:+.6f} rad, "
                     f"translation ({translation[0]:+.6g}, {translation[1]:+.6g}) m)")
    else:
        alignment = "none: map and truth both in the frame of pose 0 (the first local map's start pose)"
    feature_error = features - truth.features[ft]
    _warn_if_unrelated(global_map.name, features, truth.features, ft, feature_error, feature_truth is not None)
    pose_error = np.column_stack([poses[:, :2] - truth.poses[pt, :2], wrap(poses[:, 2] - truth.poses[pt, 2])])
    feature_distance = np.hypot(feature_error[:, 0], feature_error[:, 1])
    pose_distance = np.hypot(pose_error[:, 0], pose_error[:, 1])
    pose_angle = np.abs(pose_error[:, 2])

    feature_blocks = (global_map.feature_covariances[fm] if global_map.feature_covariances is not None
                      else global_map.feature_variances[fm, None, None] * np.eye(2))
    if global_map.pose_covariances is not None:
        pose_blocks = global_map.pose_covariances[pm]
    else:
        variances = global_map.pose_variances[pm]
        pose_blocks = np.zeros((len(pm), 3, 3))
        pose_blocks[:, 0, 0] = pose_blocks[:, 1, 1] = variances[:, 0]
        pose_blocks[:, 2, 2] = variances[:, 1]
    nees_features, bounds_features = _average_nees(feature_error, feature_blocks, global_map.name)
    nees_poses, bounds_poses = _average_nees(pose_error, pose_blocks, global_map.name)
    tests = [(value, bounds) for value, bounds in ((nees_features, bounds_features), (nees_poses, bounds_poses))
             if value is not None]
    consistent = all(low <= value <= high for value, (low, high) in tests) if tests else None
    return Evaluation(
        alignment=alignment, features=len(fm), poses=len(pm),
        feature_rms=_rms(feature_distance), feature_max=_max(feature_distance),
        pose_rms_xy=_rms(pose_distance), pose_max_xy=_max(pose_distance),
        pose_rms_phi=_rms(pose_angle), pose_max_phi=_max(pose_angle),
        nees_features=nees_features, nees_poses=nees_poses,
        nees_bounds_features=bounds_features, nees_bounds_poses=bounds_poses, consistent=consistent)


def _warn_if_unrelated(name: str, features: np.ndarray, truth_features: np.ndarray, compared: np.ndarray,
                       errors: np.ndarray, through: bool) -> None:
    """One warning when the compared features look compared with unrelated true ones (module docstring): of a
    sample, more than half nearer to another true feature than to their own, and their errors incoherent."""
    sample = np.unique(np.linspace(0, len(features) - 1, min(len(features), SAMPLE)).astype(np.intp))
    if len(sample) < STRANGER_FEATURES or len(truth_features) < 2:
        return
    nearer = _nearer_another(features[sample], truth_features, compared[sample])
    if 2 * nearer <= len(sample) or nearer < STRANGER_FEATURES:
        return
    neighbour = nearest(_complex(features[sample]), _complex(features), exclude=sample)[0][:, 0]
    size = float(np.median(np.hypot(*errors[sample].T)))
    if not (size > 0 and np.median(np.hypot(*(errors[sample] - errors[neighbour]).T)) >= INCOHERENT * size):
        return
    log.warning("%s: %d of %d features compared with the truth lie nearer to another true feature than to the one "
                "%s, and their errors differ between neighbours as much as they are large (no drift): its feature "
                "ids are likely not the truth's (a join with --associate numbers its own: evaluate through its "
                "--associations)", name, nearer, len(sample),
                "they are compared with" if through else "of their id")


def _complex(xy: np.ndarray) -> np.ndarray:
    return xy[:, 0] + 1j * xy[:, 1]


def _nearer_another(features: np.ndarray, truth_features: np.ndarray, compared: np.ndarray) -> int:
    """How many of ``features`` lie strictly nearer to some row of ``truth_features`` than to
    ``truth_features[compared]``, the true feature each is compared with (a tie is none)."""
    which, squared = nearest(_complex(features), _complex(truth_features))
    own = np.hypot(*(features - truth_features[compared]).T)
    return int(np.count_nonzero((which[:, 0] != compared) & (np.sqrt(squared[:, 0]) < own * (1 - 1e-12))))


def chi2_interval(dof: int | np.ndarray, confidence: float = CONFIDENCE
                  ) -> tuple[float, float] | tuple[np.ndarray, np.ndarray]:
    """The central ``confidence`` interval of a chi-square distribution with ``dof`` degrees of
    freedom (floats; arrays of bounds for an array of ``dof``), by :func:`mapjoin.consistency.chi2_quantile`."""
    tail = (1 - confidence) / 2
    low, high = chi2_quantile(tail, dof), chi2_quantile(1 - tail, dof)
    return (low, high) if np.ndim(low) else (float(low), float(high))


def chi2_surely_inside(cost: float, dof: int, level: float = CHI2_LEVEL) -> bool:
    """Whether ``cost`` is certainly inside the central ``level`` interval of a chi-square with ``dof``
    degrees of freedom, decided without the interval (:func:`chi2_interval`'s Newton steps cost O(dof) each:
    0.1-0.4 s in all at 10^6 degrees of freedom): True only when a lower bound of each tail's probability beyond ``cost`` is at
    least twice the tail's share ``(1 - level) / 2`` (the factor 2 a margin far above the rounding of the
    bound). The chi-square density f is unimodal, so on an interval [a, b] it is at least min(f(a), f(b)):
    a lower Riemann sum over steps of sigma / 8 (sigma = sqrt(2 dof), the standard deviation), four sigma
    into each tail, is a lower bound of its probability. It certifies about dof +- 3 sigma (the interval is
    about +- 3.3 sigma); False says nothing, ask :func:`chi2_verdict`."""
    if not (dof > 0 and 0 < cost < math.inf):
        return False
    half = dof / 2
    sigma = math.sqrt(2 * dof)
    steps = np.arange(33) * (sigma / 8)

    def lower_sum(points: np.ndarray) -> float:
        density = np.exp((half - 1) * np.log(points) - points / 2 - half * math.log(2) - math.lgamma(half))
        return float(np.sum(np.abs(np.diff(points)) * np.minimum(density[1:], density[:-1])))

    below = cost - steps
    needed = 1 - level
    return lower_sum(cost + steps) >= needed and lower_sum(below[below > 0]) >= needed


@dataclass(frozen=True)
class Chi2Verdict:
    """Values of chi^2 (``costs``) against the central ``level`` interval ``[low, high]`` of a
    chi-square with their degrees of freedom ``dofs`` (the distribution of chi^2 at the
    optimum of a least-squares problem whose covariances are right; bounds NaN where
    ``dofs <= 0``: not tested). Below the interval, the covariances look pessimistic (too
    large); above, optimistic (too small), or the data disagree (outliers)."""

    costs: np.ndarray
    dofs: np.ndarray
    low: np.ndarray
    high: np.ndarray
    level: float

    @property
    def too_small(self) -> np.ndarray:
        """Which values are below their interval."""
        return self.costs < self.low

    @property
    def too_large(self) -> np.ndarray:
        """Which values are above their interval."""
        return self.costs > self.high

    @property
    def outside(self) -> np.ndarray:
        """Indices of the values outside their interval."""
        return np.flatnonzero(self.too_small | self.too_large)


def chi2_verdict(costs: Sequence[float] | np.ndarray, dofs: Sequence[int] | np.ndarray,
                 level: float = CHI2_LEVEL) -> Chi2Verdict:
    """Whether each chi^2 in ``costs`` is plausible for its degrees of freedom ``dofs``: see
    :class:`Chi2Verdict`."""
    costs, dofs = np.asarray(costs, dtype=float).ravel(), np.asarray(dofs, dtype=np.int64).ravel()
    tested = dofs > 0
    low, high = np.full(len(costs), math.nan), np.full(len(costs), math.nan)
    if tested.any():
        low[tested], high[tested] = chi2_interval(dofs[tested], level)
    return Chi2Verdict(costs, dofs, low, high, level)


def nees_bounds(dof: int, count: int, confidence: float = CONFIDENCE) -> tuple[float, float]:
    """Two-sided ``confidence`` bounds of the average NEES of ``count`` entities of ``dof`` each:
    the chi-square interval of ``dof * count`` degrees of freedom, divided by ``count``."""
    low, high = chi2_interval(dof * count, confidence)
    return low / count, high / count


# ---------------------------------------------------------------------------------------


def _shared(ids_a: np.ndarray, ids_b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Indices into ``ids_a`` and ``ids_b`` of the ids both hold, in increasing id order."""
    _, index_a, index_b = np.intersect1d(ids_a, ids_b, assume_unique=True, return_indices=True)
    return index_a, index_b


def _through(map_ids: np.ndarray, found: np.ndarray, real: np.ndarray, truth_ids: np.ndarray
             ) -> tuple[np.ndarray, np.ndarray]:
    """Indices into ``map_ids`` and ``truth_ids`` of the map's features whose id ``found`` names as ``real`` (an id
    the truth holds), in the map's order; a true feature may stand for several of the map's."""
    at, named = locate(found, map_ids, np.argsort(found))
    where, held = locate(truth_ids, real[at[named]], np.argsort(truth_ids))
    return np.flatnonzero(named)[held], where[held]


def _mean(values: np.ndarray) -> float:
    return float(np.mean(values)) if len(values) else math.nan


def _rms(values: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(values)))) if len(values) else math.nan


def _max(values: np.ndarray) -> float:
    return float(np.max(values)) if len(values) else math.nan


def _average_nees(errors: np.ndarray, blocks: np.ndarray,
                  name: str) -> tuple[float | None, tuple[float, float] | None]:
    """Average of ``e_i^T P_i^-1 e_i`` and its chi-square bounds; (None, None) for no entity."""
    count = len(errors)
    if not count:
        return None, None
    try:
        np.linalg.cholesky(blocks)
    except np.linalg.LinAlgError:
        raise InputError("a reported covariance block is not positive definite, so NEES is undefined",
                         name) from None
    nees = np.einsum("ni,ni->n", errors, np.linalg.solve(blocks, errors[..., None])[..., 0])
    return float(nees.mean()), nees_bounds(errors.shape[1], count)


def _rigid_fit(source: np.ndarray, target: np.ndarray) -> np.ndarray:
    """The rigid motion ``(t, angle)`` minimising ``sum |R(angle) s_i + t - t_i|^2``, as a pose (x, y, angle)."""
    source_mean, target_mean = source.mean(axis=0), target.mean(axis=0)
    s, t = source - source_mean, target - target_mean
    # the optimal angle maximises sum t_i . R s_i = cos(a) sum(s.t) + sin(a) sum(s x t)
    angle = math.atan2(float(np.sum(s[:, 0] * t[:, 1] - s[:, 1] * t[:, 0])), float(np.sum(s * t)))
    return np.array([*(target_mean - rotation(angle) @ source_mean), angle])
