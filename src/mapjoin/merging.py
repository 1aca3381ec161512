"""Merging global maps that share features but no pose: several robots, or several sessions of one.

Maps A, B, C, ... are global maps, each in its own frame (its run's start pose). B is brought
into A's frame by the one-step problem without the orientation link (chi = 0,
docs/method.md#without-the-orientation-link and #merging): over the features both hold,
``phi* = phi0`` in closed form and Theorem 1 gives ``t*`` and the fused features. Then C is
brought into the frame of the merged A and B, and so on.

- Common features are fused (Theorem 1's X_L, the information-weighted mean) and keep the
  id they have in the map so far.
- B's other features and its poses are placed at ``t* + R(phi*) z`` (headings turned by
  phi*) and keep B's ids, unless the id is already taken by a different entity of the map
  so far: then it gets a new id (the next unused one), which the result lists
  (:class:`Renaming`) and a warning reports. Nothing is merged by id alone in the
  ``associate`` mode, and poses are never merged.
- Variances as after a join (docs/method.md#variance-propagation), with ``var_phi = 1/a0`` and
  ``var_t = 1/W + |m1|^2 var_phi / 2``. The result carries spherical variances only: full
  covariance blocks of the inputs (from ``refine``) are not carried over.

Which features are common: with ``associate=False``, those with the same id in both maps
(at least two are needed, as one point leaves the rotation free). With ``associate=True``
ids mean nothing across maps and the correspondence is searched for globally
(:mod:`mapjoin.registration`); the merge is refused unless the search is sure.

A map that holds a pose of the map so far (same id) at exactly the same place is that map
again (or a copy of part of it), in the same frame: refused.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from .covariance import fuse, placed_variances, squared_norm
from .errors import InputError, JoinError, counted
from .maps import GlobalMap, Provenance
from .onestep import as_complex, solve
from .registration import GATE_PROBABILITY, MIN_COMMON, consensus, registration_problem, transform_variances
from .se2 import wrap

__all__ = ["MergeRecord", "MergeResult", "Renaming", "merge"]

log = logging.getLogger("mapjoin")


@dataclass(frozen=True)
class MergeRecord:
    """One merge of the report: map ``map`` brought into the frame of the maps before it.

    ``phi``, ``x``, ``y``: the pose of ``map``'s frame origin in the merged frame (the chi = 0
    optimum); ``common``: the features fused; ``cost``: the residual cost f_0(phi*) = c0 - 2 a0,
    the weighted sum of squared differences of the common features after the transform;
    ``new``: the map's features placed as new; ``renamed_features``/``renamed_poses``: ids given
    anew because they were taken.
    """

    merge: int
    map: str
    phi: float
    x: float
    y: float
    common: int
    new: int
    cost: float
    renamed_features: int
    renamed_poses: int


@dataclass(frozen=True)
class Renaming:
    """An entity of ``map`` whose id was taken in the map so far: ``kind`` is ``feature`` or ``pose``."""

    map: str
    kind: str
    old_id: int
    new_id: int


@dataclass(frozen=True)
class MergeResult:
    """The merged map (in the frame of the first), one report row per merge, and the ids given anew."""

    global_map: GlobalMap
    report: tuple[MergeRecord, ...]
    renamed: tuple[Renaming, ...]


def _check_other_frame(merged: GlobalMap, other: GlobalMap, names: str) -> None:
    """Refuse ``other`` if it holds a pose of ``merged`` (same id) at the same place: the same run again."""
    shared, in_merged, in_other = np.intersect1d(merged.pose_ids, other.pose_ids, return_indices=True)
    same = np.all(np.abs(merged.poses[in_merged] - other.poses[in_other])
                  <= 1e-9 * (1.0 + np.abs(merged.poses[in_merged])), axis=1)
    if same.any():
        raise JoinError(f"{other.name}: holds pose {int(shared[same][0])} exactly where {names} has it: the same "
                        f"map again, in the same frame (each map merged must be in its own frame)")


#: the largest id a map holds (ids are 64-bit integers)
_MAX_ID = 2**63 - 1


def _fresh(ids: np.ndarray, taken: np.ndarray, start: int, name: str, kind: str
           ) -> tuple[np.ndarray, np.ndarray, int]:
    """``ids`` with those in ``taken`` replaced by new ids from ``start`` on; the mask replaced, the next start.
    JoinError naming map ``name`` when the new ids would not fit the maps' 64-bit ids."""
    clash = np.isin(ids, taken)
    count = int(clash.sum())
    if not count:
        return ids.copy(), clash, start
    if start + count - 1 > _MAX_ID:
        raise JoinError(f"{name}: {counted(count, kind + ' id')} also in the maps before it would be given new ids "
                        f"above {start - 1}, beyond 64-bit ids (at most 2^63 - 1); renumber its {kind}s")
    renamed = ids.copy()
    renamed[clash] = start + np.arange(count)
    return renamed, clash, start + count


def _correspondences(merged: GlobalMap, other: GlobalMap, names: str, associate: bool, min_common: int,
                     probability: float) -> tuple[np.ndarray, np.ndarray]:
    """The common features (indices in ``merged``, in ``other``): by id, or found by the search (``associate``);
    JoinError naming ``other`` when there are fewer than two, or the search is not sure."""
    if associate:
        found = consensus(as_complex(merged.features), merged.feature_variances, as_complex(other.features),
                          other.feature_variances, min_common=min_common, probability=probability)
        if not found.sure:
            raise JoinError(
                f"{other.name}: no sure overlap with {names}: the best transform found matches {found.core} "
                f"features ({found.best} over the overlap); needed: at least {min_common}, twice the "
                f"{found.runner_up} of the strongest rival, and well above the {found.chance:.3g} that chance gives "
                f"(the overlap is too small, the features' variances too wide for their spacing, or the maps too "
                f"self-similar)")
        return found.a, found.b
    _, in_a, in_b = np.intersect1d(merged.feature_ids, other.feature_ids, return_indices=True)
    if len(in_a) < 2:
        raise JoinError(f"{other.name}: shares {len(in_a)} feature id{'s' * (len(in_a) != 1)} with {names}; "
                        f"merging needs at least two common features (one leaves the rotation free), "
                        f"or associate the features without ids")
    return in_a, in_b


def _merged_map(name: str, **fields) -> GlobalMap:
    """The map after merging map ``name`` in; a value outside the global ranges (a variance beyond 1e40, say)
    is an error about that map."""
    try:
        return GlobalMap(**fields, name="merged map")
    except InputError as error:
        raise JoinError(f"{name}: merging it gives {error}") from None


def merge(maps: Sequence[GlobalMap], associate: bool = False, *, min_common: int = MIN_COMMON,
          probability: float = GATE_PROBABILITY) -> MergeResult:
    """Merge global maps, each in its own frame, into the frame of the first (see the module docstring).

    ``associate``: find the common features by a global search instead of by id; ``min_common``
    and ``probability`` (the gates' chi-square level) set when its answer is sure
    (:mod:`mapjoin.registration`). Raises :class:`JoinError` naming the map that cannot be
    merged: fewer than two common features, no sure consensus, or the same map twice.
    """
    if len(maps) < 2:
        raise JoinError(f"merging needs at least two maps, got {len(maps)}")
    merged = maps[0]
    report: list[MergeRecord] = []
    renamed: list[Renaming] = []
    next_feature = max(int(m.feature_ids.max(initial=-1)) for m in maps) + 1
    next_pose = max(int(m.pose_ids.max(initial=-1)) for m in maps) + 1
    for number, other in enumerate(maps[1:], start=1):
        names = maps[0].name if number == 1 else f"the merge of {maps[0].name} to {maps[number - 1].name}"
        _check_other_frame(merged, other, names)
        za, zb = as_complex(merged.features), as_complex(other.features)
        in_a, in_b = _correspondences(merged, other, names, associate, min_common, probability)
        try:
            solution = solve(registration_problem(merged.features[in_a], merged.feature_variances[in_a],
                                                  other.features[in_b], other.feature_variances[in_b]))
        except ValueError:
            raise JoinError(f"{other.name}: its common features with {names} all lie at one point; "
                            f"the rotation is not determined") from None
        t_variance, phi_variance = transform_variances(solution)
        turn, t = np.exp(1j * solution.phi), complex(solution.t[0], solution.t[1])

        fused, fused_variances = fuse(za[in_a], merged.feature_variances[in_a], turn * zb[in_b] + t,
                                      1.0 / other.feature_variances[in_b])
        new = np.ones(len(zb), dtype=bool)
        new[in_b] = False
        placed = turn * zb[new] + t
        placed_var = placed_variances(t_variance, phi_variance, other.feature_variances[new], squared_norm(zb[new]))
        feature_ids, feature_clash, next_feature = _fresh(other.feature_ids[new], merged.feature_ids, next_feature,
                                                              other.name, "feature")

        pose_xy = as_complex(other.poses)
        poses = np.column_stack([(turn * pose_xy + t).real, (turn * pose_xy + t).imag,
                                 wrap(solution.phi + other.poses[:, 2])])
        pose_variances = np.column_stack([
            placed_variances(t_variance, phi_variance, other.pose_variances[:, 0], squared_norm(pose_xy)),
            other.pose_variances[:, 1] + phi_variance])
        pose_ids, pose_clash, next_pose = _fresh(other.pose_ids, merged.pose_ids, next_pose, other.name, "pose")

        features = merged.features.copy()
        variances = merged.feature_variances.copy()
        features[in_a] = np.column_stack([fused.real, fused.imag])
        variances[in_a] = fused_variances
        merged = _merged_map(
            other.name,
            feature_ids=np.concatenate([merged.feature_ids, feature_ids]),
            features=np.concatenate([features, np.column_stack([placed.real, placed.imag])]),
            feature_variances=np.concatenate([variances, placed_var]),
            pose_ids=np.concatenate([merged.pose_ids, pose_ids]),
            poses=np.concatenate([merged.poses, poses]),
            pose_variances=np.concatenate([merged.pose_variances, pose_variances]),
            provenance=Provenance(merged.provenance.maps + other.provenance.maps, merged.provenance.covariance,
                                  merged.provenance.solver, "merge"))
        for kind, old, clash, ids in (("feature", other.feature_ids[new], feature_clash, feature_ids),
                                      ("pose", other.pose_ids, pose_clash, pose_ids)):
            renamed += [Renaming(other.name, kind, o, n) for o, n in zip(old[clash].tolist(), ids[clash].tolist())]
            clashes = int(clash.sum())
            if clashes:
                log.warning("%s: %d %s id%s taken in %s by a different %s: given new ids (%s)", other.name,
                            clashes, kind, "s" * (clashes != 1), names, kind,
                            ", ".join(f"{o} -> {n}" for o, n in zip(old[clash][:3].tolist(), ids[clash][:3].tolist()))
                            + (", ..." if clashes > 3 else ""))
        report.append(MergeRecord(number, other.name, solution.phi, t.real, t.imag, len(in_a), int(new.sum()),
                                  solution.cost, int(feature_clash.sum()), int(pose_clash.sum())))
    return MergeResult(merged, tuple(report), tuple(renamed))
