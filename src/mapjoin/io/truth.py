"""Ground truth of an I-SLSJF simulation folder (``store_robotTrue.mat``, ``store_beaconsTrue.mat``)."""

from __future__ import annotations

import os
from typing import TYPE_CHECKING

import numpy as np

from ..errors import InputError
from ..maps import GroundTruth
from ..se2 import relative, to_frame, wrap
from . import matfile
from .paths import read_file
from .registry import LOCAL_MAP_FILE

if TYPE_CHECKING:  # pathlib only names a path type here
    from pathlib import Path

__all__ = ["read_truth_folder"]


def read_truth_folder(folder: str | Path, maps: int | None = None) -> GroundTruth:
    """Ground truth of an I-SLSJF simulation folder (e.g. ``535_data_5_local_maps``).

    Reads ``store_beaconsTrue.mat`` (rows ``[id, x, y]``; the ids are the local maps'
    feature ids) and ``store_robotTrue.mat`` (3 x (S+1): true x, y, phi at steps 0..S).
    The folder does not say at which steps the local maps end. The rule, the one of the
    I-SLSJF code's consistency check (``DoCheckConsistency_SLSJF_each_step.m``): with N
    local maps, pose k (the end pose of map k, k = 0..N) is step ``round(k*S/N)``, halves
    rounded up, so pose N is step S (535/5: every 107 steps; 8240/50: 164 or 165).
    Verified on both shared folders: every map's end pose and features, against the true
    relative motion from its start step, give a full-state NEES per degree of freedom of
    1.08 (535) and 0.89 (8240) at the rule, 1.79 or more one step earlier or later.
    N is the number of ``localmap_<k>`` files (k = 1..N) in the folder unless ``maps``
    is given. The truth is expressed in the frame of step 0 (the first map's start pose;
    the origin in both shared folders). Pose ids are 0..N; feature ids all beacons' ids.
    """
    if maps is not None and (isinstance(maps, bool) or not isinstance(maps, int) or maps < 1):
        raise ValueError(f"maps must be a positive integer, got {maps!r}")
    folder = os.fspath(folder)
    files = {name: os.path.join(folder, f"{name}.mat") for name in ("store_robotTrue", "store_beaconsTrue")}
    if not os.path.isdir(folder):
        raise InputError("expected a simulation folder holding store_robotTrue.mat and store_beaconsTrue.mat",
                         folder)
    if maps is None:
        numbers = sorted(int(match[1]) for match in map(LOCAL_MAP_FILE.fullmatch, os.listdir(folder)) if match)
        if not numbers:
            raise InputError("holds no localmap_<k> files, so the number of local maps (which fixes the steps "
                             "they end at) is unknown", folder)
        if numbers != list(range(1, len(numbers) + 1)):
            raise InputError(f"expected local maps numbered 1..{len(numbers)}, got {numbers[:3]}..{numbers[-1]}",
                             folder)
        maps = len(numbers)
    values = {}
    for name, path in files.items():
        if not os.path.isfile(path):
            raise InputError("missing; a simulation folder with ground truth holds store_robotTrue.mat "
                             "(3 x (steps+1)) and store_beaconsTrue.mat (rows [id, x, y])", path)
        variables = matfile.variables(read_file(path, path, True), path)
        value = variables.get(name)
        if value is None or isinstance(value, str) or value.ndim != 2:
            raise InputError(f"expected a numeric matrix variable {name}, got "
                             f"{', '.join(variables) or 'no variables'}", path, name)
        values[name] = value
    robot, beacons = values["store_robotTrue"], values["store_beaconsTrue"]
    steps = robot.shape[1] - 1
    if robot.shape[0] != 3 or steps < maps:
        raise InputError(f"expected 3 x (steps+1) true poses with at least {maps} steps for {maps} local maps, "
                         f"got {robot.shape[0]} x {robot.shape[1]}", files["store_robotTrue"], "store_robotTrue")
    if beacons.shape[1] != 3 or not np.array_equal(beacons[:, 0], np.round(beacons[:, 0])):
        raise InputError(f"expected rows [integer id, x, y], got shape {beacons.shape}",
                         files["store_beaconsTrue"], "store_beaconsTrue")
    k = np.arange(maps + 1)
    poses = robot[:, (2 * k * steps + maps) // (2 * maps)].T           # round(k*S/N), halves up
    origin = robot[:, 0]                                               # the frame of the first local map
    relative_poses = relative(origin, poses)
    return GroundTruth(beacons[:, 0].astype(np.int64), to_frame(origin, beacons[:, 1:]), k,
                       np.column_stack([relative_poses[:, :2], wrap(relative_poses[:, 2])]), name=folder)
