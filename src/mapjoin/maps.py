"""Local and global maps: immutable dataclasses of numpy arrays, validated on creation.

A local map holds, in the frame of its start pose, the estimate of its end pose
``(x, y, phi)`` and of the point features it saw, with spherical variances (one
``sigma^2`` per feature, ``(sigma_xy^2, p_phi)`` for the end pose) and optionally the
full covariance of its state vector ``[x, y, phi, f1x, f1y, f2x, ...]``.

The joiner needs spherical covariances (method.md, Definition 2). ``spherical_variances``
derives them from a map in one of the documented ``COVARIANCE_MODES``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from .errors import InputError

__all__ = [
    "COVARIANCE_MODES",
    "CovarianceMode",
    "LocalMap",
    "GlobalMap",
    "GroundTruth",
    "Provenance",
    "batch_spherical_variances",
    "spherical_variances",
]

CovarianceMode = Literal["identity", "marginal", "information"]
COVARIANCE_MODES: tuple[str, ...] = ("identity", "marginal", "information")
SYMMETRY_TOLERANCE = 1e-6  # |P_ij - P_ji| allowed, relative to sqrt(P_ii P_jj); rounding in stored files


def _checked(value, name: str, source: str, shape: tuple[int | None, ...], *,
             dtype=float, positive: bool = False) -> np.ndarray:
    """A read-only copy of ``value`` as an array of ``shape`` (None = any length), finite, optionally > 0."""
    try:
        array = np.array(value, dtype=dtype)
    except (TypeError, ValueError) as error:
        raise InputError(f"expected numbers, got {value!r:.80}", source, name) from error
    if array.ndim != len(shape) or any(s is not None and s != n for s, n in zip(shape, array.shape)):
        expected = "x".join("n" if s is None else str(s) for s in shape) or "a scalar"
        raise InputError(f"expected shape {expected}, got {array.shape}", source, name)
    # two reductions in the common case (NaN fails both); the element at fault is looked for only on failure
    if dtype is float and array.size and not (array.min() > (0.0 if positive else -math.inf)
                                              and array.max() < math.inf):
        bad = ~np.isfinite(array)
        if bad.any():
            index = tuple(int(i) for i in np.argwhere(bad)[0])
            raise InputError(f"expected finite numbers, got {array[index]} at index {index}", source, name)
        if positive and not (array > 0).all():
            index = tuple(int(i) for i in np.argwhere(~(array > 0))[0])
            raise InputError(f"expected positive variances, got {array[index]} at index {index}",
                             source, name)
    array.flags.writeable = False
    return array


def _unique_ids(ids: np.ndarray, name: str, source: str) -> None:
    if len(ids) < 2 or (ids[1:] > ids[:-1]).all():  # sorted ids (the common case) need no sort
        return
    unique, counts = np.unique(ids, return_counts=True)
    if (counts > 1).any():
        raise InputError(f"duplicate id {int(unique[counts > 1][0])}", source, name)


@dataclass(frozen=True)
class LocalMap:
    """One local map, everything in the frame of its start pose.

    ``covariance`` (optional) is the full covariance of ``[end_pose, features.ravel()]``;
    when present it must be symmetric positive definite (rounding-level asymmetry, within
    ``SYMMETRY_TOLERANCE``, is averaged away).
    """

    name: str
    start_id: int
    end_id: int
    end_pose: np.ndarray
    feature_ids: np.ndarray
    features: np.ndarray
    feature_variances: np.ndarray
    pose_variances: np.ndarray
    covariance: np.ndarray | None = None

    def __post_init__(self) -> None:
        source = self.name
        for key in ("start_id", "end_id"):
            value = getattr(self, key)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 0:
                raise InputError(f"expected a non-negative integer, got {value!r}", source, key)
            object.__setattr__(self, key, int(value))
        if self.end_id == self.start_id:
            raise InputError(f"end pose id equals start pose id ({self.end_id})", source, "end_id")
        set_ = lambda key, array: object.__setattr__(self, key, array)  # noqa: E731
        set_("end_pose", _checked(self.end_pose, "end_pose", source, (3,)))
        set_("features", _checked(self.features, "features", source, (None, 2)))
        m = len(self.features)
        ids = np.asarray(self.feature_ids)
        if ids.shape != (m,) or (m and not np.issubdtype(ids.dtype, np.integer)
                                 and not np.array_equal(ids, np.round(ids))):
            raise InputError(f"expected {m} integer ids, got {ids!r:.80}", source, "feature_ids")
        set_("feature_ids", _checked(ids, "feature_ids", source, (m,), dtype=np.int64))
        if m and self.feature_ids.min() < 0:
            raise InputError(f"expected non-negative ids, got {int(self.feature_ids.min())}",
                             source, "feature_ids")
        _unique_ids(self.feature_ids, "feature_ids", source)
        set_("feature_variances",
             _checked(self.feature_variances, "feature_variances", source, (m,), positive=True))
        set_("pose_variances", _checked(self.pose_variances, "pose_variances", source, (2,), positive=True))
        if self.covariance is not None:
            n = 3 + 2 * m
            covariance = _checked(self.covariance, "covariance", source, (n, n))
            if not (covariance == covariance.T).all():  # rounding-level asymmetry is averaged away
                deviation = np.sqrt(np.abs(np.diagonal(covariance)))
                excess = np.abs(covariance - covariance.T) - SYMMETRY_TOLERANCE * np.outer(deviation, deviation)
                if (excess > 0).any():
                    i, j = (int(v) for v in np.unravel_index(np.argmax(excess), excess.shape))
                    raise InputError(f"expected a symmetric matrix, but entries ({i}, {j}) and ({j}, {i}) "
                                     f"differ: {covariance[i, j]!r} vs {covariance[j, i]!r}", source, "covariance")
                covariance = (covariance + covariance.T) / 2
                covariance.flags.writeable = False
            try:
                np.linalg.cholesky(covariance)
            except np.linalg.LinAlgError as error:
                raise InputError("expected a positive definite matrix", source, "covariance") from error
            set_("covariance", covariance)

    @classmethod
    def from_covariance(cls, name: str, start_id: int, end_id: int, end_pose, feature_ids,
                        features, covariance) -> "LocalMap":
        """A map whose spherical variances are the ``marginal`` summary of its full covariance."""
        covariance = np.asarray(covariance, dtype=float)
        feature_variances, pose_variances = _summary(np.diagonal(covariance), 1.0)
        return cls(name, start_id, end_id, end_pose, feature_ids, features,
                   feature_variances, pose_variances, covariance)

    @property
    def size(self) -> int:
        """Number of features."""
        return len(self.feature_ids)


def spherical_variances(local_map: LocalMap, mode: CovarianceMode) -> tuple[np.ndarray, np.ndarray]:
    """Spherical ``(feature_variances, pose_variances)`` of ``local_map`` in ``mode``.

    - ``identity``: every variance 1, as in the paper's experiment (Section 7).
    - ``marginal``: the mean of the diagonal of each 2x2 block of the covariance (the
      average marginal variance of x and y), and ``P_phiphi`` for the orientation.
    - ``information``: the same from the information matrix ``P^-1``: ``sigma^2 =
      2 / trace(Lambda_jj)``, the conditional variance of a block given the rest of the map.

    A map without a full covariance is block-diagonal spherical already, so
    ``marginal`` and ``information`` both return its stored variances.
    """
    features, poses = batch_spherical_variances([local_map], mode)
    return features, poses[0]


def _summary(diagonal: np.ndarray, power: float) -> tuple[np.ndarray, np.ndarray]:
    """Mean of each x/y pair of ``diagonal`` (the last axis: pose x, y, phi, then features), the phi entry as is; ``**power``."""
    features = (diagonal[..., 3::2] + diagonal[..., 4::2]) / 2
    poses = diagonal[..., 1:3].copy()
    poses[..., 0] = (diagonal[..., 0] + diagonal[..., 1]) / 2
    return features**power, poses**power


def batch_spherical_variances(maps: Sequence[LocalMap], mode: CovarianceMode) -> tuple[np.ndarray, np.ndarray]:
    """:func:`spherical_variances` of many maps: all feature variances concatenated, and (len(maps), 2) pose ones.

    Maps with full covariances of one size are summarised together (one batched inverse
    per size for ``information``), so the cost is not a Python loop of matrix calls.
    """
    if mode not in COVARIANCE_MODES:
        raise ValueError(f"unknown covariance mode {mode!r}; expected one of {', '.join(COVARIANCE_MODES)}")
    sizes = np.array([m.size for m in maps], dtype=np.intp)
    offsets = np.concatenate([[0], np.cumsum(sizes)])
    if mode == "identity":
        return np.ones(offsets[-1]), np.ones((len(maps), 2))
    features = np.concatenate([m.feature_variances for m in maps]) if maps else np.zeros(0)
    poses = np.array([m.pose_variances for m in maps]).reshape(-1, 2)
    full = [i for i, m in enumerate(maps) if m.covariance is not None]
    by_size: dict[int, list[int]] = {}
    for i in full:
        by_size.setdefault(int(sizes[i]), []).append(i)
    for size, group in by_size.items():
        stacked = np.stack([maps[i].covariance for i in group])
        if mode == "information":  # sigma^2 = 2 / trace of each block of P^-1 = 1 / its mean
            feature_part, pose_part = _summary(np.diagonal(np.linalg.inv(stacked), axis1=1, axis2=2), -1.0)
        else:
            feature_part, pose_part = _summary(np.diagonal(stacked, axis1=1, axis2=2), 1.0)
        rows = (offsets[group][:, None] + np.arange(size)).ravel()
        features[rows] = feature_part.ravel()
        poses[group] = pose_part
    return features, poses


@dataclass(frozen=True)
class Provenance:
    """Where a global map came from: the input maps in join order and the settings used."""

    maps: tuple[str, ...] = ()
    covariance: str = ""
    solver: str = ""
    strategy: str = ""


@dataclass(frozen=True)
class GlobalMap:
    """Features and end poses in the global frame (the start pose of the first map).

    Pose ``k`` is the end pose of the k-th joined local map. Variances are spherical
    (``sigma^2`` per feature; ``(sigma_xy^2, p_phi)`` per pose). ``feature_covariances``
    (n x 2 x 2) and ``pose_covariances`` (p x 3 x 3) are full marginal blocks when a
    method computed them (exact refinement), else None.
    """

    feature_ids: np.ndarray
    features: np.ndarray
    feature_variances: np.ndarray
    pose_ids: np.ndarray
    poses: np.ndarray
    pose_variances: np.ndarray
    provenance: Provenance = field(default_factory=Provenance)
    feature_covariances: np.ndarray | None = None
    pose_covariances: np.ndarray | None = None
    name: str = "global map"

    def __post_init__(self) -> None:
        source = self.name
        set_ = lambda key, array: object.__setattr__(self, key, array)  # noqa: E731
        set_("features", _checked(self.features, "features", source, (None, 2)))
        n = len(self.features)
        set_("feature_ids", _checked(self.feature_ids, "feature_ids", source, (n,), dtype=np.int64))
        _unique_ids(self.feature_ids, "feature_ids", source)
        set_("feature_variances",
             _checked(self.feature_variances, "feature_variances", source, (n,), positive=True))
        set_("poses", _checked(self.poses, "poses", source, (None, 3)))
        p = len(self.poses)
        set_("pose_ids", _checked(self.pose_ids, "pose_ids", source, (p,), dtype=np.int64))
        _unique_ids(self.pose_ids, "pose_ids", source)
        set_("pose_variances", _checked(self.pose_variances, "pose_variances", source, (p, 2), positive=True))
        if self.feature_covariances is not None:
            set_("feature_covariances",
                 _checked(self.feature_covariances, "feature_covariances", source, (n, 2, 2)))
        if self.pose_covariances is not None:
            set_("pose_covariances", _checked(self.pose_covariances, "pose_covariances", source, (p, 3, 3)))


@dataclass(frozen=True)
class GroundTruth:
    """True feature positions and poses in the global frame (simulations); pose 0 is the origin."""

    feature_ids: np.ndarray
    features: np.ndarray
    pose_ids: np.ndarray
    poses: np.ndarray
    name: str = "ground truth"

    def __post_init__(self) -> None:
        source = self.name
        set_ = lambda key, array: object.__setattr__(self, key, array)  # noqa: E731
        set_("features", _checked(self.features, "features", source, (None, 2)))
        set_("feature_ids", _checked(self.feature_ids, "feature_ids", source, (len(self.features),),
                                     dtype=np.int64))
        _unique_ids(self.feature_ids, "feature_ids", source)
        set_("poses", _checked(self.poses, "poses", source, (None, 3)))
        set_("pose_ids", _checked(self.pose_ids, "pose_ids", source, (len(self.poses),), dtype=np.int64))
        _unique_ids(self.pose_ids, "pose_ids", source)
