"""Raw 2D pose-feature data: odometry and feature observations with their noise, read from
the formats people have, into one :class:`RawData` of numpy arrays.

The odometry must be one chain: each relative pose starts where the previous one ended
(its ``from`` pose is the previous ``to`` pose, in file order) and ends at a pose not seen
before. Observations (a feature's x, y in the frame of the observing pose, with its known
id) may come anywhere in the file and refer to any pose of the chain.

Noise numbers (docs/build.md, "Raw data formats"):

VicPark preprocessed (``VicPark_clean_data.mat``, variable ``VicPark_clean_data``, I-SLSJF)
    12 columns per row. Odometry ``[1, i, j, dx, dy, dphi, Pxx, Pxy, Pxphi, Pyy, Pyphi,
    Pphiphi]``; observation ``[0, i, feature, x, y, Pxx, Pxy, Pyy, 0, 0, 0, 0]``: the
    **covariance**'s upper triangle.
iSAM text (``ODOMETRY i j dx dy dphi c11 c12 c13 c22 c23 c33``, ``LANDMARK i l x y c11 c12 c22``)
    The **covariance**'s upper triangle, row by row (what GTSAM's loader detects for this
    layout). Pose and landmark ids share one numbering; they may skip.
g2o 2D (``VERTEX_SE2 i x y phi``, ``VERTEX_XY l x y``, ``EDGE_SE2 i j dx dy dphi I11 I12 I13
I22 I23 I33``, ``EDGE_SE2_XY i l x y I11 I12 I22``, ``FIX i``)
    The **information** matrix's upper triangle, row by row (g2o's convention); the
    covariance is its inverse. Vertices declare the ids edges may use; their values
    (g2o's initial guess) and ``FIX`` (a choice of gauge) are not used.

Where an odometry covariance has a diagonal entry below 1e-6 (the robot did not move: a
noise model proportional to the motion gives zero), 1e-6 is added to its three diagonal
entries, as I-SLSJF does for local maps, with a warning. Anything else that is not a
positive definite covariance or information matrix is an error naming the line.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass

import numpy as np

from .errors import InputError, counted, shown
from .io import STAB_NOISE, matfile
from .io.numbers import first_unplain
from .io.paths import read_file, read_text
from .maps import COORDINATE, COVARIANCE_ENTRY, POSE, VARIANCE, Range, Ranges, locate, outside

__all__ = ["RAW_FORMATS", "RawData", "read_raw"]

log = logging.getLogger("mapjoin")

RAW_FORMATS: tuple[str, ...] = ("vicpark", "isam", "g2o")
_VICPARK_VARIABLE = "VicPark_clean_data"
_ISAM_TAGS = {"ODOMETRY": 12, "LANDMARK": 8}          # tag -> tokens on the line, tag included
_G2O_TAGS = {"VERTEX_SE2": 5, "VERTEX_XY": 4, "EDGE_SE2": 12, "EDGE_SE2_XY": 8, "FIX": 2}
_UPPER3 = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))
_UPPER2 = ((0, 0), (0, 1), (1, 1))
_MAX_ID = 2**53  # ids are read as floats first: beyond this they are not exact


@dataclass(frozen=True)
class RawData:
    """Odometry chain and feature observations of one file.

    ``pose_ids[k]`` is the k-th pose of the chain (``pose_ids[0]`` its start, the origin);
    ``odometry[k]`` is pose k+1 in the frame of pose k (dx, dy, dphi), with covariance
    ``odometry_covariances[k]``. Observation i: feature ``feature_ids[i]`` at
    ``observations[i]`` (x, y) in the frame of chain pose ``observers[i]`` (an index into
    ``pose_ids``), with covariance ``observation_covariances[i]``. ``*_lines`` are where
    each came from in the file (``unit`` says what they count: lines or rows).
    """

    name: str
    pose_ids: np.ndarray
    odometry: np.ndarray
    odometry_covariances: np.ndarray
    observers: np.ndarray
    feature_ids: np.ndarray
    observations: np.ndarray
    observation_covariances: np.ndarray
    odometry_lines: np.ndarray
    observation_lines: np.ndarray
    unit: str = "line"

    @property
    def steps(self) -> int:
        """Number of odometry steps (poses after the origin)."""
        return len(self.odometry)

    def where(self, line: int) -> str:
        """How messages name a line (or row) of the file."""
        return f"{self.unit} {int(line)}"


def read_raw(path: str, format: str | None = None) -> RawData:
    """Read raw data from ``path`` (``-``: stdin, text formats only) in ``format`` (one of
    :data:`RAW_FORMATS`), else the format the extension (``.mat``: vicpark, ``.g2o``) or
    the first tag of the text tells."""
    name = "<stdin>" if path == "-" else path
    if format is not None and format not in RAW_FORMATS:
        raise InputError(f"unknown raw format {shown(format)}; expected one of {', '.join(RAW_FORMATS)}", name)
    extension = os.path.splitext(path)[1].lower()
    if format == "vicpark" or (format is None and extension == ".mat"):
        if path == "-":
            raise InputError("a .mat file cannot be read from stdin; give its path", name)
        return _read_vicpark(read_file(path, name, True), name)
    text = read_text(path, name)
    fields = [line.split() for line in text.splitlines()]
    if format is None:
        format = "g2o" if extension == ".g2o" else _sniff(fields, name)
    return (_read_isam if format == "isam" else _read_g2o)(fields, name)


# ---------------------------------------------------------------------------------------
# The three formats


def _read_vicpark(data: bytes, name: str) -> RawData:
    """I-SLSJF's preprocessed Victoria Park rows (see the module docstring)."""
    variables = matfile.variables(data, name)
    table = variables.get(_VICPARK_VARIABLE)
    if table is None:
        raise InputError(f"missing; expected the variable {_VICPARK_VARIABLE} (found: "
                         f"{', '.join(variables) or 'none'})", name, _VICPARK_VARIABLE)
    if isinstance(table, str) or table.ndim != 2 or table.shape[1] != 12:
        got = table if isinstance(table, str) else f"shape {table.shape}"
        raise InputError(f"expected a real matrix of 12 columns, got {got}", name, _VICPARK_VARIABLE)
    rows = np.arange(1, len(table) + 1)
    unit = f"{_VICPARK_VARIABLE} row"
    bad = np.flatnonzero(~np.all(np.isfinite(table), axis=1))
    if bad.size:
        raise InputError("expected finite numbers", name, f"{unit} {rows[bad[0]]}")
    kind = table[:, 0]
    bad = np.flatnonzero((kind != 0) & (kind != 1))
    if bad.size:
        raise InputError(f"expected 1 (odometry) or 0 (observation) in column 1, got {kind[bad[0]]:g}", name,
                         f"{unit} {rows[bad[0]]}")
    odometry, observation = table[kind == 1], table[kind == 0]
    where = _Where(name, unit)
    return _assemble(
        name, unit,
        odometry_ids=_ids(odometry[:, 1:3], rows[kind == 1], where, "pose id"),
        odometry=odometry[:, 3:6], odometry_covariances=_symmetric(odometry[:, 6:12], _UPPER3),
        odometry_lines=rows[kind == 1],
        observer_ids=_ids(observation[:, 1], rows[kind == 0], where, "pose id"),
        feature_ids=_ids(observation[:, 2], rows[kind == 0], where, "feature id"),
        observations=observation[:, 3:5], observation_covariances=_symmetric(observation[:, 5:8], _UPPER2),
        observation_lines=rows[kind == 0])


def _read_isam(fields: list[list[str]], name: str) -> RawData:
    """iSAM text: ODOMETRY and LANDMARK lines with covariances (see the module docstring)."""
    records = _records(fields, name, _ISAM_TAGS, "iSAM text")
    odometry, odometry_lines = records["ODOMETRY"]
    landmarks, landmark_lines = records["LANDMARK"]
    where = _Where(name, "line")
    return _assemble(
        name, "line",
        odometry_ids=_ids(odometry[:, :2], odometry_lines, where, "pose id"),
        odometry=odometry[:, 2:5], odometry_covariances=_symmetric(odometry[:, 5:11], _UPPER3),
        odometry_lines=odometry_lines,
        observer_ids=_ids(landmarks[:, 0], landmark_lines, where, "pose id"),
        feature_ids=_ids(landmarks[:, 1], landmark_lines, where, "landmark id"),
        observations=landmarks[:, 2:4], observation_covariances=_symmetric(landmarks[:, 4:7], _UPPER2),
        observation_lines=landmark_lines)


def _read_g2o(fields: list[list[str]], name: str) -> RawData:
    """g2o 2D: vertices declare ids, edges carry information matrices (see the module docstring)."""
    records = _records(fields, name, _G2O_TAGS, "g2o 2D")
    where = _Where(name, "line")
    vertices, vertex_lines = records["VERTEX_SE2"]
    points, point_lines = records["VERTEX_XY"]
    edges, edge_lines = records["EDGE_SE2"]
    sightings, sighting_lines = records["EDGE_SE2_XY"]
    pose_vertices = _ids(vertices[:, 0], vertex_lines, where, "vertex id")
    point_vertices = _ids(points[:, 0], point_lines, where, "vertex id")
    declared = np.concatenate([pose_vertices, point_vertices])
    repeated = _first_repeat(declared)
    if repeated is not None:
        lines = np.concatenate([vertex_lines, point_lines])
        raise InputError(f"vertex {declared[repeated]} is declared twice", name, where.at(lines[repeated]))
    edge_ids = _ids(edges[:, :2], edge_lines, where, "pose id")
    sighting_poses = _ids(sightings[:, 0], sighting_lines, where, "pose id")
    sighting_points = _ids(sightings[:, 1], sighting_lines, where, "landmark id")
    _require_declared(edge_ids, edge_lines, pose_vertices, "VERTEX_SE2", where)
    _require_declared(sighting_poses, sighting_lines, pose_vertices, "VERTEX_SE2", where)
    _require_declared(sighting_points, sighting_lines, point_vertices, "VERTEX_XY", where)
    # the vertices' estimates are not used (each map is solved from its odometry), but are input all the same
    _require_within(vertices[:, 1:], vertex_lines, where, "VERTEX_SE2 estimate", POSE)
    _require_within(points[:, 1:], point_lines, where, "VERTEX_XY estimate", COORDINATE)
    return _assemble(
        name, "line",
        odometry_ids=edge_ids, odometry=edges[:, 2:5],
        odometry_covariances=_covariance_of(_symmetric(edges[:, 5:11], _UPPER3), edge_lines, where, "EDGE_SE2"),
        odometry_lines=edge_lines,
        observer_ids=sighting_poses, feature_ids=sighting_points, observations=sightings[:, 2:4],
        observation_covariances=_covariance_of(_symmetric(sightings[:, 4:7], _UPPER2), sighting_lines, where,
                                               "EDGE_SE2_XY"),
        observation_lines=sighting_lines)


# ---------------------------------------------------------------------------------------
# Checks shared by the formats


class _Where:
    """Names a file's lines (or rows) in errors."""

    def __init__(self, name: str, unit: str):
        self.name, self.unit = name, unit

    def at(self, line) -> str:
        return f"{self.unit} {int(line)}"

    def error(self, line, message: str) -> InputError:
        return InputError(message, self.name, self.at(line))


def _assemble(name: str, unit: str, *, odometry_ids: np.ndarray, odometry: np.ndarray,
              odometry_covariances: np.ndarray, odometry_lines: np.ndarray, observer_ids: np.ndarray,
              feature_ids: np.ndarray, observations: np.ndarray, observation_covariances: np.ndarray,
              observation_lines: np.ndarray) -> RawData:
    """Check the chain, the observations and the covariances; the :class:`RawData`."""
    where = _Where(name, unit)
    if not len(odometry):
        raise InputError("no odometry: build needs a chain of relative poses to cut into local maps", name)
    start, end = odometry_ids[:, 0], odometry_ids[:, 1]
    broken = np.flatnonzero(start[1:] != end[:-1])
    if broken.size:
        k = int(broken[0]) + 1
        raise where.error(odometry_lines[k], f"odometry from pose {start[k]} to pose {end[k]}: expected it to start "
                                             f"at pose {end[k - 1]}, where the previous odometry "
                                             f"({where.at(odometry_lines[k - 1])}) ends; the odometry must be one "
                                             "chain in file order (pose-to-pose loop closures are not supported)")
    pose_ids = np.concatenate([start[:1], end])
    repeated = _first_repeat(pose_ids)
    if repeated is not None:
        raise where.error(odometry_lines[repeated - 1], f"odometry to pose {pose_ids[repeated]}, which is already "
                                                        "a pose of the chain; each step must reach a new pose")
    observers, found = locate(pose_ids, observer_ids, np.argsort(pose_ids))
    missing = np.flatnonzero(~found)
    if missing.size:
        i = int(missing[0])
        raise where.error(observation_lines[i], f"observation of feature {feature_ids[i]} from pose "
                                                f"{observer_ids[i]}, which is not a pose of the odometry chain")
    distinct, compact = np.unique(feature_ids, return_inverse=True)
    pair = observers.astype(np.int64) * len(distinct) + compact.ravel()
    repeated = _first_repeat(pair)
    if repeated is not None:
        first = np.flatnonzero(pair == pair[repeated])[0]
        raise where.error(observation_lines[repeated],
                          f"feature {feature_ids[repeated]} is observed from pose {observer_ids[repeated]} twice "
                          f"(also {where.at(observation_lines[first])}); expected one observation per pose and "
                          "feature")
    for values, lines, what, ranges in ((odometry, odometry_lines, "odometry", POSE),
                                        (observations, observation_lines, "observation", COORDINATE),
                                        (odometry_covariances, odometry_lines, "odometry covariance", COVARIANCE_ENTRY),
                                        (observation_covariances, observation_lines, "observation covariance",
                                         COVARIANCE_ENTRY)):
        _require_within(values, lines, where, what, ranges)
    odometry_covariances = _stabilised(odometry_covariances, odometry_lines, where)
    for values, lines, what in ((odometry_covariances, odometry_lines, "odometry covariance"),
                                (observation_covariances, observation_lines, "observation covariance")):
        _require_positive_definite(values, lines, where, what)
        _require_within(np.diagonal(values, axis1=1, axis2=2), lines, where, f"{what} diagonal", VARIANCE)
    return RawData(name=name, pose_ids=pose_ids, odometry=np.asarray(odometry, dtype=float),
                   odometry_covariances=odometry_covariances, observers=observers.astype(np.int64),
                   feature_ids=feature_ids, observations=np.asarray(observations, dtype=float),
                   observation_covariances=observation_covariances, odometry_lines=odometry_lines,
                   observation_lines=observation_lines, unit=unit)


def _require_within(values: np.ndarray, lines: np.ndarray, where: _Where, what: str, ranges: Ranges) -> None:
    """InputError naming the first line with a value outside ``ranges`` (docs/formats.md, "Accepted values")."""
    bad = outside(values, ranges)
    if bad.any():
        i, *index = (int(k) for k in np.argwhere(bad)[0])
        if not np.isfinite(values[i]).all():
            raise where.error(lines[i], f"expected a finite {what}, got {shown(values[i].tolist())}")
        flagged = tuple(index)
        limits = ranges if isinstance(ranges, Range) else ranges[flagged[-1]]
        raise where.error(lines[i], f"expected {what} {limits.expected()}, got {shown(values[i][flagged])}")


def _stabilised(covariances: np.ndarray, lines: np.ndarray, where: _Where) -> np.ndarray:
    """Odometry covariances with STAB_NOISE added to the diagonal where a variance is below it."""
    diagonal = np.diagonal(covariances, axis1=1, axis2=2)
    still = np.flatnonzero(((diagonal < STAB_NOISE) & (diagonal >= 0)).any(axis=1)
                           & (diagonal >= 0).all(axis=1))
    if still.size:
        log.warning("%s: %s with a variance below %g (the robot did not move; first at %s): "
                    "added %g to the three diagonal entries of each, as I-SLSJF does", where.name,
                    counted(still.size, "odometry covariance"), STAB_NOISE,
                    where.at(lines[still[0]]), STAB_NOISE)
        covariances = covariances.copy()
        covariances[still[:, None], np.arange(3), np.arange(3)] += STAB_NOISE
    return covariances


def _require_positive_definite(matrices: np.ndarray, lines: np.ndarray, where: _Where, what: str) -> None:
    """InputError naming the first line whose matrix is not symmetric positive definite."""
    if not len(matrices):
        return
    # smallest eigenvalue > 1e-12 of the largest diagonal entry: A minus that is positive definite
    scale = np.abs(np.diagonal(matrices, axis1=1, axis2=2)).max(axis=1)
    bad = np.flatnonzero(~_positive_definite(matrices - (1e-12 * scale)[:, None, None] * np.eye(matrices.shape[1])))
    if bad.size:
        i = int(bad[0])
        smallest = np.linalg.eigvalsh(matrices[i])[0]
        raise where.error(lines[i], f"{what} is not positive definite (smallest eigenvalue {smallest:.3g}): "
                                    f"{matrices[i].tolist()}")


def _positive_definite(matrices: np.ndarray) -> np.ndarray:
    """Which of a stack of small symmetric matrices are positive definite: every pivot of
    Gaussian elimination without pivoting (elementwise over the stack, no per-matrix call)
    is positive (NaN is not)."""
    A = np.array(matrices, dtype=float)
    positive = np.ones(len(A), dtype=bool)
    for j in range(A.shape[1]):
        positive &= A[:, j, j] > 0
        pivot = np.where(positive, A[:, j, j], 1.0)
        A[:, j + 1:, j + 1:] -= A[:, j + 1:, j, None] * A[:, None, j, j + 1:] / pivot[:, None, None]
    return positive


def _covariance_of(information: np.ndarray, lines: np.ndarray, where: _Where, tag: str) -> np.ndarray:
    """Covariances from g2o information matrices, which must be positive definite."""
    _require_within(information, lines, where, f"{tag} information matrix entries", COVARIANCE_ENTRY)
    _require_positive_definite(information, lines, where, f"{tag} information matrix")
    return np.linalg.inv(information)


def _require_declared(ids: np.ndarray, lines: np.ndarray, declared: np.ndarray, tag: str, where: _Where) -> None:
    flat = ids if ids.ndim == 2 else ids[:, None]
    missing = ~np.isin(flat, declared)
    if missing.any():
        i, j = np.argwhere(missing)[0]
        raise where.error(lines[i], f"vertex {flat[i, j]} is not declared by a {tag} line")


def _symmetric(upper: np.ndarray, entries: tuple[tuple[int, int], ...]) -> np.ndarray:
    """Stack of symmetric matrices from their upper triangles (row by row)."""
    size = entries[-1][0] + 1
    matrices = np.empty((len(upper), size, size))
    for column, (i, j) in enumerate(entries):
        matrices[:, i, j] = matrices[:, j, i] = upper[:, column]
    return matrices


def _ids(values: np.ndarray, lines: np.ndarray, where: _Where, what: str) -> np.ndarray:
    """Non-negative integer ids from floats, or an error naming the line."""
    flat = values if values.ndim == 2 else values[:, None]
    bad = ~((flat >= 0) & (flat < _MAX_ID) & (flat == np.round(flat)))      # NaN fails
    if bad.any():
        i, j = np.argwhere(bad)[0]
        raise where.error(lines[i], f"expected a non-negative integer {what}, got {flat[i, j]:g}")
    return values.astype(np.int64)


def _first_repeat(values: np.ndarray) -> int | None:
    """Index of the first entry equal to an earlier one (None if all differ)."""
    if len(values) < 2:
        return None
    order = np.argsort(values, kind="stable")
    ordered = values[order]
    again = np.flatnonzero(ordered[1:] == ordered[:-1])
    return int(order[again + 1].min()) if again.size else None


# ---------------------------------------------------------------------------------------
# Text


def _sniff(fields: list[list[str]], name: str) -> str:
    """The text format from its first tag."""
    for line in fields:
        if line and not line[0].startswith("#"):
            if line[0] in _ISAM_TAGS:
                return "isam"
            if line[0] in _G2O_TAGS:
                return "g2o"
            break
    raise InputError("cannot tell the raw format (expected iSAM text starting with ODOMETRY or LANDMARK, or g2o "
                     "starting with VERTEX_SE2, VERTEX_XY, EDGE_SE2 or EDGE_SE2_XY); ", name, argument="format")


def _records(fields: list[list[str]], name: str, tags: dict[str, int],
             what: str) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Per tag, ``(values (n, tokens - 1) without the tag, 1-based line numbers)``; blank lines and
    ``#`` comments are skipped, anything else is an error naming the line."""
    where = _Where(name, "line")
    first = np.array([line[0] if line else "#" for line in fields])
    count = np.fromiter(map(len, fields), dtype=np.int64, count=len(fields))
    comment = np.char.startswith(first, "#") if len(first) else np.zeros(0, bool)
    known = np.isin(first, list(tags)) | comment
    if not known.all():
        i = int(np.flatnonzero(~known)[0])
        raise where.error(i + 1, f"unknown tag {shown(str(first[i]))}; expected one of {', '.join(tags)} ({what})")
    result = {}
    for tag, tokens in tags.items():
        rows = np.flatnonzero(first == tag)
        wrong = np.flatnonzero(count[rows] != tokens)
        if wrong.size:
            i = rows[wrong[0]]
            raise where.error(i + 1, f"expected {tokens - 1} numbers after {tag}, got {count[i] - 1}")
        result[tag] = (_numbers(fields, rows, tokens - 1, where), rows + 1)
    return result


def _numbers(fields: list[list[str]], rows: np.ndarray, width: int, where: _Where) -> np.ndarray:
    """The numbers after the tag on ``rows``, as an (n, width) float array."""
    tokens = [token for i in rows.tolist() for token in fields[i][1:]]
    unplain = first_unplain(tokens)
    try:
        if unplain is not None:
            raise ValueError("not ASCII")
        return np.array(tokens, dtype=float).reshape(len(rows), width)
    except ValueError:
        for k, token in enumerate(tokens):                # only to name the culprit
            if k == unplain or not _is_float(token):
                raise where.error(rows[k // width] + 1, f"expected a number, got {shown(token)}") from None
        raise


def _is_float(token: str) -> bool:
    try:
        float(token)
    except ValueError:
        return False
    return True

