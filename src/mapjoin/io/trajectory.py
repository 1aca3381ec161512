"""The trajectory: every pose mapjoin knows, from the origin, as TUM, CSV or JSON (write-only).

A global map holds the end pose of each joined local map; the trajectory puts the origin
first: the start pose of the first map (``start_id``, usually pose 0), at ``(0, 0, 0)``, the
global frame. mapjoin knows no times, so the time of a pose is its id (pose k ends map k).

TUM (``.tum``; what evo's ``evo_traj tum`` and ``evo_ape tum`` read), one pose a line::

    # mapjoin trajectory: timestamp = pose id; tx ty tz qx qy qz qw (planar: tz = qx = qy = 0)
    0 0.0 0.0 0.0 0.0 0.0 0.0 1.0
    1 1.5 -0.25 0.0 0.0 0.0 0.04997916927067833 0.9987502603949663

with the heading ``phi`` as the unit quaternion about z, ``(0, 0, sin(phi/2), cos(phi/2))``.

CSV::

    id,x,y,phi
    0,0.0,0.0,0.0
    1,1.5,-0.25,0.1

JSON: ``{"format": "mapjoin/trajectory", "version": 1, "poses": [{"id": 0, "x": 0.0, "y": 0.0,
"phi": 0.0}, ...]}``.
"""

from __future__ import annotations

import json
from dataclasses import dataclass

import numpy as np

from ..errors import InputError
from ..maps import GLOBAL_POSE, GlobalMap, outside
from . import csvtable

__all__ = ["Trajectory", "dump_csv", "dump_json", "dump_tum"]

_FORMAT = "mapjoin/trajectory"


@dataclass(frozen=True)
class Trajectory:
    """Poses in the global frame in the order of the chain of maps: ``ids`` (n, unique) and ``poses`` (n x 3)."""

    ids: np.ndarray
    poses: np.ndarray

    def __post_init__(self) -> None:
        ids = np.asarray(self.ids, dtype=np.int64).reshape(-1)
        poses = np.asarray(self.poses, dtype=float)
        if poses.shape != (len(ids), 3):
            raise InputError(f"expected {len(ids)} x 3 poses, got shape {poses.shape}", "trajectory", "poses")
        if outside(poses, GLOBAL_POSE).any():
            raise InputError("expected finite poses within the global ranges", "trajectory", "poses")
        if len(np.unique(ids)) != len(ids):
            raise InputError("expected unique pose ids", "trajectory", "ids")
        object.__setattr__(self, "ids", ids)
        object.__setattr__(self, "poses", poses)

    @classmethod
    def of(cls, global_map: GlobalMap, origin_id: int) -> Trajectory:
        """The origin (pose ``origin_id``, the first map's start) at ``(0, 0, 0)``, then the global map's poses
        (the end poses of the maps, in join order)."""
        keep = global_map.pose_ids != origin_id  # a loop's last map may end at the origin's id: keep one
        return cls(np.concatenate([[origin_id], global_map.pose_ids[keep]]),
                   np.vstack([np.zeros((1, 3)), global_map.poses[keep]]))


def dump_tum(trajectory: Trajectory) -> str:
    """TUM lines ``timestamp tx ty tz qx qy qz qw``: the timestamp is the pose id, the heading a rotation about z."""
    half = trajectory.poses[:, 2] / 2
    zeros = np.zeros(len(half))
    columns = [trajectory.poses[:, 0], trajectory.poses[:, 1], zeros, zeros, zeros, np.sin(half), np.cos(half)]
    lines = [f"{i} " + " ".join(map(repr, values))
             for i, *values in zip(trajectory.ids.tolist(), *(column.tolist() for column in columns))]
    return "\n".join(["# mapjoin trajectory: timestamp = pose id; tx ty tz qx qy qz qw (planar: tz = qx = qy = 0)",
                      *lines]) + "\n"


def dump_csv(trajectory: Trajectory) -> str:
    """CSV ``id,x,y,phi``, one pose a row."""
    return csvtable.to_text([("id", "x", "y", "phi"),
                             *zip(trajectory.ids.tolist(), *trajectory.poses.T.tolist())])


def dump_json(trajectory: Trajectory) -> str:
    """A JSON object with ``format``, ``version`` and the ``poses`` as a list of ``{id, x, y, phi}``."""
    poses = [{"id": i, "x": x, "y": y, "phi": phi}
             for i, (x, y, phi) in zip(trajectory.ids.tolist(), trajectory.poses.tolist())]
    return json.dumps({"format": _FORMAT, "version": 1, "poses": poses}, indent=1) + "\n"
