"""Which scans of the simulator's figure-eight see which features, found for a few scans at a time.

The simulator (:mod:`mapjoin.simulation`) scans at every pose of its figure-eight and needs, per chunk of
maps, the features each of the chunk's scans sees. Building every (scan, feature) pair of a long run at
once costs memory in proportion to the run (5 GB at 10^6 maps); instead each feature's *window* is kept,
the run of scan indices along each circle that may see it, sorted by where it starts, and a set of scans
looks up the few features whose windows reach it. The pairs found are exactly those the geometry gives
(the window from the circle's angles, then the distance checked exactly), in the same order, so the
simulator's output does not depend on how its scans are grouped.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass

import numpy as np

__all__ = ["SeenFrom", "Sightings"]

_BLOCK = 1 << 16  # windows expanded together when every pair is visited (bounds memory)


@dataclass(frozen=True)
class _Windows:
    """One circle's windows, sorted by ``start``: feature ``feature[i]`` may be seen from the circle's scan
    indices ``low[i] .. low[i] + count[i] - 1`` (taken modulo the scans of a circle), ``start = low mod lobe``."""

    feature: np.ndarray
    low: np.ndarray
    count: np.ndarray
    start: np.ndarray
    widest: int


@dataclass(frozen=True)
class SeenFrom:
    """The features seen from a set of scan phases: ``phases`` (ascending), and for ``phases[i]`` the features
    ``feature[offsets[i]:offsets[i + 1]]`` (ascending)."""

    phases: np.ndarray
    offsets: np.ndarray
    feature: np.ndarray

    def expand(self, phases: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """For each entry of ``phases`` (each one of :attr:`phases`) its features: (index into ``phases``,
        feature) pairs, in the order of ``phases``, then of the features."""
        where = np.searchsorted(self.phases, phases)
        starts, lengths = self.offsets[where], self.offsets[where + 1] - self.offsets[where]
        owner = np.repeat(np.arange(len(phases)), lengths)
        position = np.arange(lengths.sum()) - np.repeat(np.cumsum(lengths) - lengths, lengths)
        return owner, self.feature[np.repeat(starts, lengths) + position]

    def sees(self, phases: np.ndarray, features: np.ndarray) -> np.ndarray:
        """Whether scan ``phases[i]`` (one of :attr:`phases`) sees ``features[i]``, for each i."""
        # the pairs ascend by (phase, feature): search them as numbers with the phase's place as high digit
        width = int(max(self.feature.max(initial=0), np.max(features, initial=0))) + 1
        keys = np.repeat(np.arange(len(self.phases)), np.diff(self.offsets)) * width + self.feature
        probe = np.searchsorted(self.phases, phases) * width + features
        if not len(keys):
            return np.zeros(len(probe), dtype=bool)
        return keys[np.minimum(np.searchsorted(keys, probe), len(keys) - 1)] == probe


class Sightings:
    """The scans of a figure-eight and the features of its world, and which see which.

    ``world``: feature positions (n x 2); ``poses``: the scan poses of phases ``0..len(poses)-1`` (of a lap
    of ``lap`` steps: lobe A's ``lap // 2`` first, then lobe B's); ``radius``: the circles' radius; a scan sees
    the features at distances in ``[min_range, max_range]``. Features are reported by their index in
    ``world`` (:meth:`renumbered`: by other numbers).
    """

    def __init__(self, world: np.ndarray, poses: np.ndarray, lap: int, radius: float, min_range: float,
                 max_range: float):
        self.world, self.poses, self.lobe = world, poses, lap // 2
        self.min_range, self.max_range = min_range, max_range
        self.ids = np.arange(len(world))
        self._windows = [_windows(world, side, self.lobe, radius, max_range) for side in (1.0, -1.0)]

    def renumbered(self, ids: np.ndarray) -> Sightings:
        """The same sightings with feature ``i`` reported as ``ids[i]`` (-1 for a feature no scan sees)."""
        other = copy.copy(self)
        other.ids = ids
        return other

    def first_seen(self) -> np.ndarray:
        """For each feature the first scan phase that sees it; ``len(poses)`` if none does."""
        first = np.full(len(self.world), len(self.poses), dtype=np.int64)
        for side, windows in enumerate(self._windows):
            for lo in range(0, len(windows.feature), _BLOCK):
                phase, feature = self._pairs(side, np.arange(lo, min(lo + _BLOCK, len(windows.feature))))
                np.minimum.at(first, feature, phase)
        return first

    def at(self, phases: np.ndarray) -> SeenFrom:
        """The features seen from each of ``phases`` (scan phases, any order, repeats allowed)."""
        wanted = np.unique(phases)
        found_phase, found_feature = [], []
        for side, windows in enumerate(self._windows):
            offset = side * self.lobe
            index = wanted[(wanted >= offset) & (wanted < offset + self.lobe)] - offset
            if not len(index) or not len(windows.feature):
                continue
            phase, feature = self._pairs(side, _reaching(windows, int(index[0]), int(index[-1]), self.lobe))
            at = np.minimum(np.searchsorted(wanted, phase), len(wanted) - 1)
            keep = wanted[at] == phase
            found_phase.append(phase[keep])
            found_feature.append(self.ids[feature[keep]])
        phase = np.concatenate(found_phase) if found_phase else np.empty(0, dtype=np.int64)
        feature = np.concatenate(found_feature) if found_feature else np.empty(0, dtype=np.int64)
        order = np.lexsort((feature, phase))
        return SeenFrom(wanted, np.r_[np.searchsorted(phase[order], wanted), len(phase)], feature[order])

    def _pairs(self, side: int, which: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The (scan phase, feature) pairs of the windows ``which`` of circle ``side`` that see each other:
        every scan index of the window, then the distance checked exactly."""
        windows = self._windows[side]
        count = windows.count[which]
        total = int(count.sum())
        feature = np.repeat(windows.feature[which], count)
        index = np.repeat(windows.low[which], count) + np.arange(total) - np.repeat(np.cumsum(count) - count, count)
        phase = index % self.lobe + side * self.lobe
        keep = phase < len(self.poses)
        phase, feature = phase[keep], feature[keep]
        world, poses = self.world, self.poses
        distance = np.hypot(world[feature, 0] - poses[phase, 0], world[feature, 1] - poses[phase, 1])
        keep = (distance >= self.min_range) & (distance <= self.max_range)
        return phase[keep], feature[keep]


def _windows(world: np.ndarray, side: float, lobe: int, radius: float, max_range: float) -> _Windows:
    """The windows of circle ``side`` (+1: lobe A, centre ``(0, +radius)``; -1: lobe B).

    On a circle of radius ``rho``, the poses within ``max_range`` of a feature at distance ``d`` from the
    centre span the angles ``beta +- arccos((d^2 + rho^2 - max_range^2) / (2 d rho))``; the pose indices
    there, plus one on each side, are the window (at most a whole circle).
    """
    turn = 2 * np.pi / lobe
    vx, vy = world[:, 0], world[:, 1] - side * radius
    d = np.hypot(vx, vy)
    with np.errstate(divide="ignore", invalid="ignore"):
        cosine = (d * d + radius * radius - max_range * max_range) / (2 * d * radius)
    cosine = np.where(np.isnan(cosine), -1.0, cosine)
    half = np.arccos(np.clip(cosine, -1.0, 1.0))
    # pose i of the lobe sits at polar angle i*turn - pi/2 (A) or pi/2 - i*turn (B)
    centre = np.pi / 2 + side * np.arctan2(vy, vx)
    low = np.floor((centre - half) / turn).astype(np.int64) - 1
    count = np.minimum(np.ceil((centre + half) / turn).astype(np.int64) + 2 - low, lobe)
    count[cosine > 1] = 0
    feature = np.flatnonzero(count > 0)
    start = low[feature] % lobe
    order = np.argsort(start, kind="stable")
    feature = feature[order]
    return _Windows(feature, low[feature], count[feature], start[order], int(count.max(initial=0)))


def _reaching(windows: _Windows, first: int, last: int, lobe: int) -> np.ndarray:
    """The windows (positions in ``windows``) that may hold a scan index in ``first..last`` (0 <= first <=
    last < lobe): those starting at most ``widest - 1`` before ``first`` (modulo ``lobe``) and by ``last``."""
    reach = first - windows.widest + 1
    if windows.widest >= lobe or last - reach + 1 >= lobe:
        return np.arange(len(windows.feature))
    starts = windows.start
    inside = np.arange(np.searchsorted(starts, max(reach, 0)), np.searchsorted(starts, last, side="right"))
    if reach >= 0:
        return inside
    wrapped = np.arange(np.searchsorted(starts, reach + lobe), len(starts))
    return np.concatenate([inside, wrapped])
