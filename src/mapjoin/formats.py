"""Every file mapjoin reads or writes: local maps, global maps, ground truth, tables.

Sources are paths, open text streams (e.g. ``io.StringIO``) or ``"-"`` for stdin; targets
are paths, text streams or ``"-"`` for stdout. Files are written atomically (a temporary
file in the same folder, then ``os.replace``) and inputs are never modified. Bad input
raises :class:`~mapjoin.errors.InputError` naming the file (or ``<stdin>``), the line or
field, and what was expected. Floats are written with ``repr`` precision, so every text
format round-trips exactly. CSV is standard CSV (quoted where needed, LF line ends); CRLF
line ends and a UTF-8 byte-order mark are accepted on reading.

Formats
=======

The format comes from ``--format`` or the extension: ``.yaml``/``.yml``, ``.csv``,
``.mat`` (local maps), ``localmap_<k>.txt`` (Linear SLAM local maps; other ``.txt`` files
need ``--format``), ``.g2o`` (global maps, write-only), ``.json`` (tables only). A stream
without ``--format`` is YAML if it starts with ``format:``, ``---``, ``%YAML`` or ``#``,
CSV if its first line is a header naming a ``kind`` column, Linear SLAM text if its first
two lines are each one integer.

I-SLSJF local map (``localmap_<k>.mat``)
    A MATLAB v5 file as distributed with the I-SLSJF code, holding ``localmap_st``, a
    (3+2m)x2 array of ``[id, value]`` rows (three end-pose rows x, y, phi with id 0, then
    an x row and a y row per feature, both with the feature's id), and ``localmap_P``, the
    full (3+2m)x(3+2m) covariance. Map k runs from pose k-1 to pose k, k taken from the
    file name. The spherical variances are the ``marginal`` summary of ``localmap_P``. As
    in the I-SLSJF code, when an end-pose variance is below 1e-6 (the robot did not move)
    1e-6 is added to the three pose diagonal entries, with a warning. The file is parsed
    by mapjoin itself (numeric matrices, compressed or not, either byte order), not by
    ``scipy.io.loadmat``, which crashes the interpreter on some corrupt files. Written
    uncompressed, little-endian, one map per file named after its end id; only a map from
    pose k-1 to pose k can be written (the format has nowhere else to keep its pose ids),
    and a map without a full covariance is written with its diagonal one.

Linear SLAM local map (``localmap_<k>.txt``)
    Text as distributed with Linear SLAM: line 1 the reference (start) pose id, line 2 the
    state dimension d = 3 + 2m, then d lines ``id value`` (the end pose's x, y, phi with
    id -k, k its pose id; then per feature an x and a y line with its id), then d lines of
    d numbers: the information matrix, the inverse of the covariance, row by row. It must
    be symmetric (up to ``maps.SYMMETRY_TOLERANCE``, then symmetrised) and positive
    definite; the covariance is its inverse by Cholesky factorisation, and writing inverts
    the covariance the same way, so a round trip is exact up to rounding (about the
    condition number times 1e-16, relative). Rows may come in any order as long as the
    pose's three are together and each feature's y follows its x. One map per file; the
    end pose id must not be 0 (it would be -0). Feature id 0 is read and written, with a
    warning on writing, as Linear SLAM's own code expects positive feature ids.

YAML local map (one map per document; a file may hold a stream of documents)::

    format: mapjoin/local-map
    version: 1
    name: map-7                    # optional (see "Map names" below)
    start_id: 6
    end_id: 7
    end_pose: {x: 1.5, y: -0.25, phi: 0.1, var_xy: 0.01, var_phi: 0.001}
    features:
    - {id: 12, x: 3.0, y: 4.0, var: 0.02}
    covariance: [[...], ...]       # optional: full (3+2m)x(3+2m), order x y phi f1x f1y f2x ...

    Unknown fields are errors. Numbers like ``1e-6`` (no dot) are read as numbers.

CSV local maps (one row per entity; any number of maps per file)::

    map,start_id,end_id,kind,id,x,y,phi,var_xy,var_phi
    map-7,6,7,pose,7,1.5,-0.25,0.1,0.01,0.001
    map-7,6,7,feature,12,3.0,4.0,,0.02,

    ``map`` names the map (unique within a file, see "Map names"); its rows are written
    together, in map order. Each map has exactly one ``pose`` row (its end pose, ``id`` = ``end_id``);
    ``feature`` rows carry the spherical variance in ``var_xy`` and leave ``phi`` and
    ``var_phi`` empty. CSV holds spherical variances only: writing maps with full
    covariances drops them, with one warning.

Map names: a local map read from a file is named after the file, so that messages and
provenance point to it: the path when the file holds one map, else ``path#name`` with the
map's own name (``name``, ``map``), or ``path#n`` (its position) when it has none; maps
from stdin are named ``<stdin>`` likewise. Writers store each map's name.

Global map, CSV::

    kind,id,x,y,phi,var_xy,var_phi[,cov_xx,cov_xy,cov_yy,cov_xphi,cov_yphi,cov_phiphi]
    feature,12,3.0,4.0,,0.02,[,c_xx,c_xy,c_yy,,,]
    pose,1,1.5,-0.25,0.1,0.01,0.001[,c_xx,c_xy,c_yy,c_xphi,c_yphi,c_phiphi]

    Features first, then poses. The ``cov_*`` columns (upper triangles of the symmetric
    marginal covariance blocks) are present when the map carries them; per kind they are
    all filled or all empty. CSV does not hold the provenance.

Global map, g2o (write-only; for g2o's viewer and GTSAM's ``readG2o``)::

    # mapjoin global map: VERTEX_SE2 <pose id> x y phi per end pose, VERTEX_XY <feature id + 1000> x y ...
    VERTEX_SE2 1 1.5 -0.25 0.1
    VERTEX_XY 1012 3.0 4.0

    g2o has one id space, so feature ids are offset by :func:`g2o_feature_offset` (the
    smallest power of ten above every pose id, at least 10); the first line says which.
    Vertices only: the variances are not exported.

Global map, YAML::

    format: mapjoin/global-map
    version: 1
    provenance: {maps: [a.mat, b.mat], covariance: marginal, solver: ..., strategy: ...}
    features:
    - {id: 12, x: 3.0, y: 4.0, var: 0.02, cov: [[.., ..], [.., ..]]}   # cov optional
    poses:
    - {id: 1, x: 1.5, y: -0.25, phi: 0.1, var_xy: 0.01, var_phi: 0.001, cov: [[..]x3]}

    ``provenance`` and each of its fields are optional; ``cov`` is on all entries of a
    list or on none. A kind with no entries reads back without covariances.

Ground truth: the global-map formats without variances: CSV ``kind,id,x,y,phi``; YAML
``format: mapjoin/ground-truth``, ``version: 1``, ``features: [{id, x, y}]``,
``poses: [{id, x, y, phi}]``.

Minima queries (``check-minima --batch``, read-only): CSV with header ``a,c_phi`` and one
row per problem of Theorem 2 (``a`` >= 0, ``c_phi`` finite).

Tables (e.g. a per-join report; write-only): rows are dataclass instances. CSV with the
field names as header (``None`` -> empty cell), YAML as a list of mappings or JSON as a
list of objects (``None`` -> null). Numpy scalars and arrays become plain numbers/lists.
"""

from __future__ import annotations

import contextlib
import csv
import dataclasses
import functools
import io
import logging
import math
import os
import re
import reprlib
import stat
import struct
import sys
import zlib
from collections.abc import Callable, Mapping, Sequence
from itertools import chain
from typing import TYPE_CHECKING, Any, NamedTuple, TextIO

import numpy as np

from .errors import InputError
from .covariance import marginal_variances
from .maps import (GlobalMap, GroundTruth, LocalMap, Provenance, StackedMaps, asymmetry, first_duplicate,
                   first_flagged, first_invalid_map, size_groups, unstack)

if TYPE_CHECKING:  # PyYAML is imported when YAML is read or written; pathlib only names a path type here
    from pathlib import Path

    import yaml

__all__ = [
    "MAP_FORMATS",
    "TABLE_FORMATS",
    "MinimaTable",
    "atomic_write",
    "check_not_overwriting",
    "detect_format",
    "g2o_feature_offset",
    "map_file_name",
    "read_global_map",
    "read_map_file",
    "mat_variables",
    "read_map_paths",
    "read_maps",
    "read_minima_table",
    "read_truth",
    "read_truth_folder",
    "resolve_inputs",
    "write_global_map",
    "write_maps",
    "write_table",
    "write_truth",
]

log = logging.getLogger("mapjoin")

MAP_FORMATS: tuple[str, ...] = ("yaml", "csv", "mat", "linearslam")
TABLE_FORMATS: tuple[str, ...] = ("csv", "yaml", "json")
STDIN = "-"
#: I-SLSJF's ``StabNoise``: added to the end-pose variances of a map whose robot did not move.
STAB_NOISE = 1e-6
_TRUTH_FILES = ("truth.yaml", "truth.yml", "truth.csv")  # what `mapjoin simulate` writes into its folder

_EXTENSIONS = {".yaml": "yaml", ".yml": "yaml", ".csv": "csv", ".mat": "mat", ".json": "json", ".g2o": "g2o"}
_FORMATS = ("yaml", "csv", "mat", "linearslam", "json", "g2o")
_LOCAL_MAP_FILE = re.compile(r"localmap_([0-9]+)\.(?:mat|yaml|yml|csv|txt)", re.IGNORECASE)
_LINEARSLAM_FILE = re.compile(r"localmap_[0-9]+\.txt", re.IGNORECASE)  # .txt is Linear SLAM only when so named
_FILE_EXTENSIONS = {"linearslam": "txt"}  # format -> extension, where they differ
_GLOB_CHARACTERS = re.compile(r"[*?[]")

Source = str | os.PathLike | TextIO  # os.PathLike: e.g. a pathlib.Path


class _Codec(NamedTuple):
    """How one format reads (text, or bytes when ``binary``) and writes (``dump``) one kind of data."""

    read: Callable[[Any, str], Any] | None
    dump: Callable[[Any], str | bytes] | None  # bytes for a binary format
    binary: bool = False
    spherical_only: bool = False  # local maps: full covariances are dropped on writing
    one_per_file: bool = False  # local maps: a file holds exactly one map


# ---------------------------------------------------------------------------------------
# Public API


def detect_format(path_or_name: str, explicit: str | None = None) -> str:
    """``explicit`` if given (checked against the known formats), else the format its extension names.

    A ``.txt`` file is a Linear SLAM local map when named ``localmap_<k>.txt``, as Linear SLAM
    names them; other ``.txt`` files need ``explicit``.
    """
    name = "<stdin>" if path_or_name == STDIN else str(path_or_name)
    if explicit is not None:
        if explicit not in _FORMATS:
            raise InputError(f"unknown format {explicit!r}; expected one of {', '.join(_FORMATS)}", name)
        return explicit
    if _LINEARSLAM_FILE.fullmatch(os.path.basename(name)):
        return "linearslam"
    suffix = os.path.splitext(name)[1].lower()
    if suffix not in _EXTENSIONS:
        got = f"the extension {suffix!r}" if suffix else "no extension"
        raise InputError(f"cannot tell the format from {got}; expected one of {', '.join(_EXTENSIONS)}, "
                         "a Linear SLAM localmap_<k>.txt, or pass --format", name)
    return _EXTENSIONS[suffix]


def resolve_inputs(inputs: Sequence[str]) -> list[str]:
    """Input arguments as a list of files: globs expanded (natural order), folders as their local maps.

    A folder contributes its files named ``localmap_<k>.mat|yaml|yml|csv|txt``, ordered by k
    (``localmap_10`` after ``localmap_9``); other files are ignored. ``-`` (stdin) is kept.
    """
    paths: list[str] = []
    for item in inputs:
        item = os.fspath(item)
        if item == STDIN:
            paths.append(item)
        elif (files := _expand(item)) is not None:
            paths.extend(files)
        elif _GLOB_CHARACTERS.search(item):
            from glob import glob

            matches = sorted(glob(item, recursive=True), key=_natural_key)
            if not matches:
                raise InputError("no file matches this pattern", item)
            for match in matches:
                paths.extend(_expand(match) or [match])
        else:
            raise InputError("no such file or folder", item)
    return paths


def read_maps(inputs: Sequence[str], *, stdin: TextIO | None = None, format: str | None = None) -> list[LocalMap]:
    """All local maps of all inputs (see :func:`resolve_inputs`), in order; ``-`` reads ``stdin`` once.

    ``format`` is for the inputs whose names do not tell it (stdin, unknown extensions), so
    e.g. a folder of .mat files and CSV on stdin can be read together. Consecutive .mat files
    (an I-SLSJF folder of thousands) are parsed and checked together, with the errors and
    warnings of reading them one by one.
    """
    return read_map_paths(resolve_inputs(inputs), stdin=stdin, format=format)


def read_map_paths(paths: Sequence[str], *, stdin: TextIO | None = None, format: str | None = None
                   ) -> list[LocalMap]:
    """:func:`read_maps` of inputs that :func:`resolve_inputs` has already resolved (commands resolve
    them first to check their outputs against them; resolving again would stat every file twice)."""
    if paths.count(STDIN) > 1:
        raise InputError("stdin (-) is given more than once; it can be read only once", "<stdin>")
    maps: list[LocalMap] = []
    mat_files: list[str] = []  # consecutive .mat files, read together (a folder of thousands)
    for path in paths:
        suffix = os.path.splitext(path)[1].lower()
        explicit = None if suffix in _EXTENSIONS else format
        if path != STDIN and (explicit or _EXTENSIONS.get(suffix)) == "mat":
            mat_files.append(path)
            continue
        maps.extend(_read_local_mat_files(mat_files))
        mat_files = []
        if path == STDIN:
            maps.extend(read_map_file(stdin or sys.stdin, format, name="<stdin>"))
        else:
            maps.extend(read_map_file(path, explicit))
    return maps + _read_local_mat_files(mat_files)


def read_map_file(source: Source, format: str | None = None, name: str | None = None) -> list[LocalMap]:
    """The local maps of one file or stream (a YAML or CSV file may hold several)."""
    name = name or _source_name(source)
    maps = _read(source, format, name, _LOCAL_MAP_CODECS, "local maps")
    if not maps:
        raise InputError("expected at least one local map, found none", name)
    return maps


def write_maps(maps: Sequence[LocalMap], target: Source, format: str) -> list[str]:
    """Write ``maps`` as ``format`` and return the paths written (none for a stream).

    A folder target (an existing folder, or a path ending in ``/``, created if needed) gets
    one file per map, :func:`map_file_name`; a file path or stream gets one stream, which
    for ``mat`` and ``linearslam`` must hold one map (a .mat file's name must end in its end id).
    """
    name = _source_name(target, "<stdout>")
    codec = _codec(detect_format(name, format), _LOCAL_MAP_CODECS, "local maps", name, writing=True)
    if codec.spherical_only:
        dropped = [local_map.name for local_map in maps if local_map.covariance is not None]
        if dropped:
            log.warning("%s holds spherical variances only: dropped the full covariances of %d map(s) "
                        "(first: %s)", format, len(dropped), dropped[0])
    if isinstance(target, (str, os.PathLike)) and (
            os.path.isdir(target) or os.fspath(target).endswith(("/", os.sep))):
        return _write_map_folder(maps, os.fspath(target), format, codec)
    if codec.one_per_file:
        _check_single_map_file(maps, target, format)
    return _write(codec.dump(maps), target)


def write_global_map(global_map: GlobalMap, target: Source, format: str | None = None) -> None:
    """Write a global map as CSV or YAML (format from ``format`` or the extension)."""
    _write(_writer(target, format, _GLOBAL_MAP_CODECS, "a global map")(global_map), target)


def read_global_map(source: Source, format: str | None = None) -> GlobalMap:
    """Read a global map written by :func:`write_global_map`."""
    return _read(source, format, _source_name(source), _GLOBAL_MAP_CODECS, "a global map")


def write_truth(truth: GroundTruth, target: Source, format: str | None = None) -> None:
    """Write ground truth as CSV or YAML (format from ``format`` or the extension)."""
    _write(_writer(target, format, _TRUTH_CODECS, "ground truth")(truth), target)


def read_truth(source: Source, format: str | None = None) -> GroundTruth:
    """Ground truth: a file written by :func:`write_truth` (or ``-``, a stream), the folder ``mapjoin simulate``
    wrote it into (``truth.yaml``, ``.yml`` or ``.csv`` inside), or an I-SLSJF simulation folder
    (``store_robotTrue.mat``: :func:`read_truth_folder`)."""
    if isinstance(source, (str, os.PathLike)) and os.fspath(source) != STDIN and os.path.isdir(source):
        folder = os.fspath(source)
        if os.path.exists(os.path.join(folder, "store_robotTrue.mat")):
            return read_truth_folder(folder)
        files = [os.path.join(folder, name) for name in _TRUTH_FILES]
        source = next((path for path in files if os.path.isfile(path)), None)
        if source is None:
            raise InputError(f"holds no ground truth; expected {', '.join(_TRUTH_FILES)} (from `mapjoin "
                             "simulate`) or store_robotTrue.mat and store_beaconsTrue.mat (I-SLSJF)", folder)
    return _read(source, format, _source_name(source), _TRUTH_CODECS, "ground truth")


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
        numbers = sorted(int(match[1]) for match in map(_LOCAL_MAP_FILE.fullmatch, os.listdir(folder)) if match)
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
        variables = mat_variables(_read_file(path, path, True), path)
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
    x0, y0, phi0 = robot[:, 0]
    c, s = math.cos(phi0), math.sin(phi0)
    to_start = np.array([[c, s], [-s, c]])                             # R(phi0)^T
    phi = (poses[:, 2] - phi0 + math.pi) % (2 * math.pi) - math.pi
    return GroundTruth(beacons[:, 0].astype(np.int64), (beacons[:, 1:] - (x0, y0)) @ to_start.T, k,
                       np.column_stack([(poses[:, :2] - (x0, y0)) @ to_start.T, phi]), name=folder)


@dataclasses.dataclass(frozen=True)
class MinimaTable:
    """Theorem 2's ``a`` and ``C_phi`` of each row of a table; ``join`` the join numbers when it has a join column."""

    source: str
    a: np.ndarray
    c_phi: np.ndarray
    join: np.ndarray | None = None


def read_minima_table(source: Source) -> MinimaTable:
    """The columns ``a`` and ``c_phi`` (and ``join``) of any table holding them: a ``join --report`` output,
    a ``check-minima --batch`` input or output.

    CSV, YAML or JSON by the extension; otherwise (``-``: stdin, ``.txt``, ...) YAML/JSON when
    the text starts with ``[``, ``{``, ``-``, ``#`` or ``%``, else CSV.
    """
    name = _source_name(source)
    fmt = _EXTENSIONS.get(os.path.splitext(name)[1].lower())
    if fmt is not None and fmt not in TABLE_FORMATS:
        raise InputError(f"expected a table with the columns a and c_phi (.csv, .yaml or .json), not {fmt}", name)
    text = _read_text(source, name)
    if fmt is None:
        fmt = "yaml" if text.lstrip()[:1] in ("[", "{", "-", "#", "%") else "csv"
    table = _read_minima_csv(text, name) if fmt == "csv" else _read_minima_records(text, name)
    if not len(table.a):
        raise InputError("expected at least one row with a and c_phi, found none", name)
    return table


def write_table(rows: Sequence[Any], target: Source, format: str | None = None) -> None:
    """Write dataclass instances (all of one type) as a CSV, YAML or JSON table."""
    _write(_writer(target, format, _TABLE_CODECS, "a table")(rows), target)


def check_not_overwriting(inputs: Sequence[str], outputs: Sequence[str]) -> None:
    """Refuse an output that is an input file: the same file (device and inode, so also a hard or symbolic
    link to it) or the same path after resolving links.

    Pass the input files (:func:`resolve_inputs`); outputs need not exist yet. Each input costs
    one ``stat``; its path is resolved only when that fails or an output cannot be examined
    for another reason than not existing (an existing file is found by its inode).
    """
    targets = [os.fspath(output) for output in outputs if os.fspath(output) != STDIN]
    if not targets:
        return
    resolved = {os.path.realpath(output): output for output in targets}
    identities: dict[tuple[int, int], str] = {}
    resolve_every_input = False
    for output in targets:
        try:
            status = os.stat(output)
        except (FileNotFoundError, NotADirectoryError):
            continue  # no file there yet: only an input that does not exist either can resolve to its path
        except OSError:
            resolve_every_input = True
        else:
            identities[(status.st_dev, status.st_ino)] = output
    clashes: dict[str, str] = {}  # output -> the (last) input it is
    for path in map(os.fspath, inputs):
        if path == STDIN:
            continue
        try:
            status = os.stat(path)
        except OSError:
            status = None
        output = None if status is None else identities.get((status.st_dev, status.st_ino))
        if output is None and (status is None or resolve_every_input):
            output = resolved.get(os.path.realpath(path))
        if output is not None:
            clashes[output] = path
    for output in targets:
        if output in clashes:
            which = "an input file" if clashes[output] == output else f"the input file {clashes[output]}"
            raise InputError(f"is {which}; choose another output so the input is kept", output)


def atomic_write(path: str | Path, text: str | bytes) -> None:
    """Write ``text`` (UTF-8; bytes as they are) to ``path`` via a temporary file in the same folder and ``os.replace``.

    Readers never see a half-written file, and a failed write leaves an existing file as it was.
    """
    path = os.fspath(path)
    folder, base = os.path.split(path)
    temporary = os.path.join(folder, f".{base}.{os.urandom(4).hex()}.tmp")
    try:
        with open(temporary, "xb") if isinstance(text, bytes) else open(
                temporary, "x", encoding="utf-8", newline="") as file:
            file.write(text)
        os.replace(temporary, path)
    except BaseException as error:
        with contextlib.suppress(OSError):
            os.unlink(temporary)
        if isinstance(error, OSError):
            raise InputError(f"cannot write ({error.strerror or error})", path) from error
        raise


# ---------------------------------------------------------------------------------------
# Plumbing: names, formats, reading and writing whole files


def _source_name(source: Source, dash: str = "<stdin>") -> str:
    """How messages name a path, ``-`` (``dash``) or a stream (its ``name``, else ``<stream>``)."""
    if isinstance(source, (str, os.PathLike)):
        path = os.fspath(source)
        return dash if path == STDIN else path
    name = getattr(source, "name", None)
    return name if isinstance(name, str) else "<stream>"


def _codec(fmt: str, codecs: Mapping[str, _Codec], what: str, name: str, *, writing: bool = False) -> _Codec:
    """The codec of ``fmt`` for ``what``; InputError if the format cannot hold it (or cannot be written)."""
    usable = [key for key, codec in codecs.items() if (codec.dump if writing else codec.read)]
    if fmt not in usable:
        verb = "write" if writing else "read"
        raise InputError(f"cannot {verb} {what} as {fmt}; expected one of {', '.join(usable)}", name)
    return codecs[fmt]


def _writer(target: Source, fmt: str | None, codecs: Mapping[str, _Codec], what: str) -> Callable[[Any], str]:
    name = _source_name(target, "<stdout>")
    return _codec(detect_format(name, fmt), codecs, what, name, writing=True).dump


def _read(source: Source, fmt: str | None, name: str, codecs: Mapping[str, _Codec], what: str) -> Any:
    """Read ``source`` with the codec its format (explicit, extension or sniffed) names."""
    if isinstance(source, (str, os.PathLike)) and os.fspath(source) != STDIN:
        codec = _codec(detect_format(os.fspath(source), fmt), codecs, what, name)
        return codec.read(_read_file(os.fspath(source), name, codec.binary), name)
    text = _read_text(source, name)
    codec = _codec(detect_format(name, fmt) if fmt else _sniff(text, name), codecs, what, name)
    if codec.binary:
        raise InputError("a .mat file cannot be read from a text stream; give its path", name)
    return codec.read(text, name)


def _read_text(source: Source, name: str) -> str:
    """The UTF-8 text of a path, ``-`` (stdin) or a stream (text or bytes), without a byte-order mark."""
    if isinstance(source, (str, os.PathLike)) and os.fspath(source) != STDIN:
        return _read_file(os.fspath(source), name, False)
    stream = sys.stdin if isinstance(source, (str, os.PathLike)) else source
    try:
        text = stream.read()
        if isinstance(text, bytes):
            text = text.decode("utf-8")
    except UnicodeDecodeError as error:
        raise _not_utf8(error, name) from None
    return text.removeprefix("\ufeff")


def _read_file(path: str, name: str, binary: bool) -> str | bytes:
    try:
        if binary:
            return _read_bytes(path)
        with open(path, encoding="utf-8-sig", newline="") as file:
            return file.read()
    except UnicodeDecodeError as error:
        raise _not_utf8(error, name) from None
    except OSError as error:
        raise InputError(f"cannot read ({error.strerror or error})", name) from None


def _read_bytes(path: str) -> bytes:
    """The bytes of a file; a regular file in one ``read`` (a file object costs as much as reading a small file)."""
    descriptor = os.open(path, os.O_RDONLY)
    try:
        status = os.fstat(descriptor)
        chunks = [os.read(descriptor, status.st_size + 1)]  # fewer bytes than asked: the end of a regular file
        if len(chunks[0]) > status.st_size or not stat.S_ISREG(status.st_mode):
            while chunks[-1]:
                chunks.append(os.read(descriptor, 1 << 20))
        return chunks[0] if len(chunks) == 1 else b"".join(chunks)
    finally:
        os.close(descriptor)


def _not_utf8(error: UnicodeDecodeError, name: str) -> InputError:
    return InputError(f"expected UTF-8 text ({error.reason} at byte {error.start})", name)


def _sniff(text: str, name: str) -> str:
    """The format of a stream from its start: YAML by its usual openings, CSV by a header naming ``kind``,
    Linear SLAM text by its first two lines, each one integer."""
    start = text.lstrip()
    if start.startswith(("format:", "---", "%YAML", "#")):
        return "yaml"
    header = start.partition("\n")[0]
    if "kind" in (cell.strip().strip('"') for cell in header.split(",")):
        return "csv"
    if re.match(r"[0-9]+[ \t]*\r?\n[ \t]*[0-9]+[ \t]*(?:\r?\n|$)", start):
        return "linearslam"
    raise InputError("cannot tell the format (expected YAML starting with format:, ---, %YAML or #, a CSV "
                     "header naming a kind column, or Linear SLAM text); pass --format", name)


def _write(text: str | bytes, target: Source) -> list[str]:
    """Write ``text`` to a path (atomically), ``-`` (stdout) or a text stream (text only); the paths written."""
    if isinstance(target, (str, os.PathLike)) and os.fspath(target) != STDIN:
        atomic_write(target, text)
        return [os.fspath(target)]
    if isinstance(text, bytes):
        raise InputError("a .mat file cannot be written to stdout or a text stream; give a file path",
                         _source_name(target, "<stdout>"))
    (sys.stdout if isinstance(target, (str, os.PathLike)) else target).write(text)
    return []


def _write_map_folder(maps: Sequence[LocalMap], folder: str, fmt: str, codec: _Codec) -> list[str]:
    """One file per map; every map is encoded first, so a map the format cannot hold writes nothing."""
    paths = [os.path.join(folder, map_file_name(local_map.end_id, fmt)) for local_map in maps]
    duplicate = first_duplicate(np.array([local_map.end_id for local_map in maps], dtype=np.int64))
    if duplicate is not None:
        raise InputError(f"two maps end at pose {maps[duplicate].end_id}, so both would be "
                         f"{os.path.basename(paths[duplicate])}; write them to one file instead", folder)
    contents = [codec.dump([local_map]) for local_map in maps]
    try:
        os.makedirs(folder, exist_ok=True)
    except OSError as error:
        raise InputError(f"cannot create the folder ({error.strerror or error})", folder) from error
    for content, path in zip(contents, paths):
        atomic_write(path, content)
    return paths


def _expand(path: str) -> list[str] | None:
    """The files ``path`` stands for: a folder's local maps, else itself; None if it does not exist (one ``stat``)."""
    try:
        mode = os.stat(path).st_mode
    except (OSError, ValueError):
        return None
    return _folder_maps(path) if stat.S_ISDIR(mode) else [path]


def _folder_maps(folder: str) -> list[str]:
    """The local-map files of ``folder``, ordered by their number k."""
    try:
        with os.scandir(folder) as entries:
            found = [(match, entry.path) for entry in entries
                     if (match := _LOCAL_MAP_FILE.fullmatch(entry.name)) and entry.is_file()]
    except OSError as error:
        raise InputError(f"cannot list the folder ({error.strerror or error})", folder) from None
    numbered: dict[int, tuple[str, str]] = {}  # k -> (file name, path)
    for match, path in found:
        k = int(match[1])
        if k in numbered:
            raise InputError(f"holds both {numbered[k][0]} and {match[0]} for map {k}; keep one", folder)
        numbered[k] = (match[0], path)
    if not numbered:
        raise InputError("expected local-map files named localmap_<k>.mat, .yaml, .yml, .csv or .txt (Linear SLAM); found none",
                         folder)
    return [numbered[k][1] for k in sorted(numbered)]


def _natural_key(text: str) -> list[str | int]:
    """Sort key that orders embedded numbers by value (``a9`` before ``a10``)."""
    return [int(part) if index % 2 else part for index, part in enumerate(re.split(r"([0-9]+)", text))]


# ---------------------------------------------------------------------------------------
# YAML: documents with typed, line-numbered field access


_YAML_FLOAT = re.compile(r"^[-+]?(?:[0-9]+\.?[0-9]*|\.[0-9]+)[eE][-+]?[0-9]+$")
_PLAIN_FLOAT = re.compile(r"[-+]?[0-9]+\.[0-9]*(?:[eE][-+][0-9]+)?")  # as repr writes them; YAML 1.1 floats


@functools.cache
def _yaml_classes() -> tuple[type, type]:
    """mapjoin's YAML loader and dumper, made (and PyYAML imported) on first use: commands that read and write
    no YAML do not pay for importing it."""
    import yaml

    class Loader(getattr(yaml, "CSafeLoader", yaml.SafeLoader)):  # type: ignore[misc]
        """Safe loader that also reads ``1e-6`` (no dot: a string in YAML 1.1) as a float, and reads floats faster."""

        def resolve(self, kind: type, value: str, implicit: tuple[bool, bool]) -> str:
            if kind is yaml.ScalarNode and implicit[0] and _PLAIN_FLOAT.fullmatch(value):
                return "tag:yaml.org,2002:float"  # what PyYAML's resolver says too, without its slow search
            return super().resolve(kind, value, implicit)

        def construct_yaml_float(self, node: yaml.ScalarNode) -> float:
            try:  # the common decimal forms; .inf, .nan and base 60 take PyYAML's slower path
                return float(node.value)
            except ValueError:
                return super().construct_yaml_float(node)

    class Dumper(getattr(yaml, "CSafeDumper", yaml.SafeDumper)):  # type: ignore[misc]
        """Safe dumper that quotes strings the loader would read as floats."""

    Loader.add_implicit_resolver("tag:yaml.org,2002:float", _YAML_FLOAT, list("-+.0123456789"))
    Loader.add_constructor("tag:yaml.org,2002:float", Loader.construct_yaml_float)
    Dumper.add_implicit_resolver("tag:yaml.org,2002:float", _YAML_FLOAT, list("-+.0123456789"))
    return Loader, Dumper


_NUMBER_TYPES = frozenset({int, float})


def _is_number(value: Any) -> bool:
    if type(value) is int:
        return abs(value) <= sys.float_info.max
    return type(value) is float and math.isfinite(value)


_KINDS: dict[str, tuple[Callable[[Any], bool], str]] = {
    "id": (lambda value: type(value) is int and 0 <= value < 2**63, "a non-negative integer"),
    "number": (_is_number, "a finite number"),
    "nonnegative": (lambda value: _is_number(value) and value >= 0, "a non-negative finite number"),
    "variance": (lambda value: _is_number(value) and value > 0, "a positive finite number"),
    "text": (lambda value: type(value) is str, "a string"),
    "list": (lambda value: type(value) is list, "a list"),
    "mapping": (lambda value: type(value) is dict, "a mapping"),
}

_FieldPath = tuple[str | int, ...]


class _YamlDocument:
    """One parsed YAML document; its getters check types, and errors name the field and its line."""

    def __init__(self, data: Any, node: yaml.Node, source: str):
        self.data, self.node, self.source = data, node, source

    def error(self, path: _FieldPath, message: str) -> InputError:
        where = f"line {self._line(path)}" + (f", field {_render(path)}" if path else "")
        return InputError(message, self.source, where)

    def get(self, path: _FieldPath, kind: str, *, optional: bool = False) -> Any:
        """The value at ``path`` (keys and indices; the containers were checked by earlier calls)."""
        check, expected = _KINDS[kind]
        if path:
            parent, key = self._value(path[:-1]), path[-1]
            if isinstance(key, str) and key not in parent:
                if optional:
                    return None
                raise self.error(path, f"missing; expected {expected}")
            value = parent[key]
        else:
            value = self.data
        if not check(value):
            raise self.error(path, f"expected {expected}, got {reprlib.repr(value)}")
        return value

    def only(self, path: _FieldPath, allowed: Sequence[str]) -> None:
        """Reject keys of the mapping at ``path`` other than ``allowed`` (catches typos)."""
        unknown = next((key for key in self._value(path) if key not in allowed), None)
        if unknown is not None:
            raise self.error(path, f"unknown field {reprlib.repr(unknown)}; expected only {', '.join(allowed)}")

    def matrix(self, path: _FieldPath, shape: tuple[int, int], *, optional: bool = False) -> np.ndarray | None:
        """The list of number lists at ``path`` as an array of ``shape``."""
        rows = self.get(path, "list", optional=optional)
        if rows is None:
            return None
        if len(rows) != shape[0]:
            raise self.error(path, f"expected {shape[0]} rows of {shape[1]} numbers, got {len(rows)} rows")
        for i, row in enumerate(rows):
            if type(row) is not list or len(row) != shape[1]:
                raise self.error((*path, i), f"expected a list of {shape[1]} numbers, got {reprlib.repr(row)}")
        values = None
        if all(_NUMBER_TYPES.issuperset(map(type, row)) for row in rows):  # no bools, strings, ...
            with contextlib.suppress(OverflowError):  # an int beyond the float range
                values = np.array(rows, dtype=float).reshape(shape)
        if values is None or not np.isfinite(values).all():
            i, j = next((i, j) for i, row in enumerate(rows)
                        for j, value in enumerate(row) if not _is_number(value))
            raise self.error((*path, i, j), f"expected a finite number, got {reprlib.repr(rows[i][j])}")
        return values

    def record(self, path: _FieldPath, fields: Mapping[str, str],
               matrices: Mapping[str, tuple[int, int]] | None = None) -> dict[str, Any]:
        """The mapping at ``path`` with exactly ``fields`` (name -> kind) and optional ``matrices``."""
        matrices = matrices or {}
        self.get(path, "mapping")
        self.only(path, (*fields, *matrices))
        values = {key: self.get((*path, key), kind) for key, kind in fields.items()}
        values.update({key: self.matrix((*path, key), shape, optional=True) for key, shape in matrices.items()})
        return values

    def records(self, path: _FieldPath, fields: Mapping[str, str],
                matrices: Mapping[str, tuple[int, int]] | None = None) -> dict[str, np.ndarray | None]:
        """The list of records at ``path`` as columns; ids must be unique, matrices on all records or none."""
        matrices = matrices or {}
        count = len(self.get(path, "list"))
        items = [self.record((*path, index), fields, matrices) for index in range(count)]
        columns: dict[str, np.ndarray | None] = {
            key: np.array([item[key] for item in items], dtype=np.int64 if kind == "id" else float)
            for key, kind in fields.items()}
        for key, shape in matrices.items():
            present = [item[key] is not None for item in items]
            if any(present) and not all(present):
                missing = present.index(False)
                raise self.error((*path, missing, key), f"missing; expected a {shape[0]}x{shape[1]} matrix "
                                 f"as on {_render((*path, present.index(True)))}")
            columns[key] = (np.array([item[key] for item in items]).reshape(-1, *shape)
                            if items and all(present) else None)
        if "id" in fields:
            duplicate = first_duplicate(columns["id"])
            if duplicate is not None:
                raise self.error((*path, duplicate, "id"), f"duplicate id {columns['id'][duplicate]}")
        return columns

    def header(self, kind: str, keys: Sequence[str]) -> None:
        """Check the document is a mapping of ``format: kind``, version 1, with no keys beyond ``keys``."""
        self.get((), "mapping")
        found = self.get(("format",), "text")
        if found != kind:
            raise self.error(("format",), f"expected {kind}, got {reprlib.repr(found)}")
        version = self.get(("version",), "id")
        if version != 1:
            raise self.error(("version",), f"unsupported version {version}; this mapjoin reads version 1")
        self.only((), keys)

    def relocated(self, error: InputError) -> InputError:
        """A data-model validation error re-raised naming this file and the field's line."""
        return self.error((error.where,) if error.where else (), error.detail)

    def _value(self, path: _FieldPath) -> Any:
        value = self.data
        for key in path:
            value = value[key]
        return value

    def _line(self, path: _FieldPath) -> int:
        """Line (1-based) of the deepest node of ``path`` that exists."""
        import yaml

        node = self.node
        for key in path:
            if isinstance(node, yaml.MappingNode):
                found = [value for name, value in node.value
                         if isinstance(name, yaml.ScalarNode) and name.value == key]
                if not found:
                    break
                node = found[-1]
            elif isinstance(node, yaml.SequenceNode) and isinstance(key, int) and key < len(node.value):
                node = node.value[key]
            else:
                break
        return node.start_mark.line + 1


def _render(path: _FieldPath) -> str:
    """``("features", 3, "var")`` -> ``features[3].var``."""
    text = ""
    for key in path:
        text += f"[{key}]" if isinstance(key, int) else f".{key}" if text else str(key)
    return text


def _yaml_documents(text: str, source: str) -> list[_YamlDocument]:
    import yaml

    loader = _yaml_classes()[0](text)
    documents = []
    try:
        while loader.check_node():
            node = loader.get_node()
            documents.append(_YamlDocument(loader.construct_document(node), node, source))
    except yaml.MarkedYAMLError as error:
        mark = error.problem_mark or error.context_mark
        raise InputError(f"malformed YAML: {error.problem or error.context}", source,
                         f"line {mark.line + 1}" if mark else None) from None
    except (yaml.YAMLError, ValueError, OverflowError, RecursionError) as error:
        raise InputError(f"malformed YAML: {error}", source) from None
    finally:
        loader.dispose()
    return documents


def _yaml_document(text: str, source: str) -> _YamlDocument:
    documents = _yaml_documents(text, source)
    if len(documents) != 1:
        raise InputError(f"expected one YAML document, got {len(documents)}", source)
    return documents[0]


def _yaml_text(documents: Sequence[Any], *, explicit_start: bool = False) -> str:
    import yaml

    return yaml.dump_all(documents, Dumper=_yaml_classes()[1], sort_keys=False, default_flow_style=None,
                         allow_unicode=True, width=1 << 30, explicit_start=explicit_start)


def _yaml_records(columns: Mapping[str, np.ndarray | None]) -> list[dict[str, Any]]:
    """Columns (arrays, None = absent) as a list of records of plain Python values."""
    present = {key: column.tolist() for key, column in columns.items() if column is not None}
    return [dict(zip(present, values)) for values in zip(*present.values())]


def _stack(columns: Mapping[str, np.ndarray | None], *keys: str) -> np.ndarray:
    return np.column_stack([columns[key] for key in keys]).reshape(-1, len(keys))


# ---------------------------------------------------------------------------------------
# CSV: a body parsed column-wise with numpy, errors naming line and column


class _CsvTable:
    """A CSV file as a 2-D object array of cells with the line of each row.

    ``headers`` are the headers accepted; None accepts any (the reader checks its columns).
    """

    def __init__(self, text: str, source: str, headers: Sequence[tuple[str, ...]] | None):
        self.source = source
        reader = csv.reader(io.StringIO(text, newline=""))
        rows: list[list[str]] = []
        lines: list[int] = []
        try:
            for row in reader:
                if row:
                    rows.append(row)
                    lines.append(reader.line_num)
        except csv.Error as error:
            raise InputError(f"malformed CSV: {error}", source, f"line {reader.line_num}") from None
        header = tuple(cell.strip() for cell in rows[0]) if rows else ()
        self.header_line = lines[0] if lines else 1
        if headers is not None and header not in headers:
            expected = " or ".join(",".join(header) for header in headers)
            raise InputError(f"expected the header {expected}, got {','.join(header) or 'nothing'}", source,
                             f"line {self.header_line}")
        self.header = header
        self.columns = {name: index for index, name in enumerate(header)}
        body = rows[1:]
        self.lines = np.array(lines[1:], dtype=np.int64)
        widths = np.fromiter(map(len, body), dtype=np.int64, count=len(body))
        short = np.flatnonzero(widths != len(header))
        if short.size:
            row = int(short[0])
            raise InputError(f"expected {len(header)} fields, got {widths[row]}", source,
                             f"line {self.lines[row]}")
        self.cells = np.array(body, dtype=object).reshape(len(body), len(header))

    def error(self, row: int, column: str, message: str) -> InputError:
        return InputError(message, self.source, f"line {self.lines[row]}, column {column}")

    def text(self, column: str) -> np.ndarray:
        return self.cells[:, self.columns[column]]

    def kinds(self) -> tuple[np.ndarray, np.ndarray]:
        """Indices of the ``feature`` rows and of the ``pose`` rows."""
        kinds = self.text("kind")
        features, poses = kinds == "feature", kinds == "pose"
        bad = np.flatnonzero(~(features | poses))
        if bad.size:
            raise self.error(int(bad[0]), "kind", f"expected feature or pose, got {reprlib.repr(kinds[bad[0]])}")
        return np.flatnonzero(features), np.flatnonzero(poses)

    def values(self, columns: Sequence[str], rows: np.ndarray | None, kind: str) -> np.ndarray:
        """Cells of ``columns`` at ``rows`` (None: all) as a (rows x columns) array of ``kind``.

        ``kind`` is one of ``_VALID``: ``id`` (non-negative integers), ``number`` (finite),
        ``nonnegative`` or ``variance`` (positive).
        """
        rows = np.arange(len(self.cells)) if rows is None else rows
        cells = self.cells[np.ix_(rows, [self.columns[column] for column in columns])]
        dtype = np.int64 if kind == "id" else float
        try:
            values = cells.astype(dtype)
        except (ValueError, OverflowError):
            valid = np.array([_parses(cell, dtype) for cell in cells.ravel()], dtype=bool).reshape(cells.shape)
        else:
            valid = _VALID[kind](values)
        if not valid.all():
            i, j = (int(index) for index in np.argwhere(~valid)[0])
            raise self.error(int(rows[i]), columns[j],
                             f"expected {_KINDS[kind][1]}, got {reprlib.repr(cells[i, j])}")
        return values

    def ids(self, rows: np.ndarray, groups: np.ndarray | None = None, what: str = "") -> np.ndarray:
        """The ``id`` column at ``rows``, unique within each group."""
        ids = self.values(("id",), rows, "id")[:, 0]
        duplicate = first_duplicate(ids, groups)
        if duplicate is not None:
            raise self.error(int(rows[duplicate]), "id", f"duplicate id {ids[duplicate]}{what}")
        return ids

    def empty(self, columns: Sequence[str], rows: np.ndarray, why: str) -> None:
        """Require empty cells at ``rows`` in ``columns``."""
        cells = self.cells[np.ix_(rows, [self.columns[column] for column in columns])]
        bad = np.argwhere(cells != "")
        if bad.size:
            i, j = (int(index) for index in bad[0])
            raise self.error(int(rows[i]), columns[j],
                             f"expected an empty cell ({why}), got {reprlib.repr(cells[i, j])}")

    def covariances(self, rows: np.ndarray, size: int, what: str) -> np.ndarray | None:
        """Symmetric ``size`` x ``size`` blocks from the ``cov_*`` columns, or None when those are empty."""
        used = [column for column, (i, j) in _COV_ENTRIES.items() if max(i, j) < size]
        self.empty([column for column in _COV_ENTRIES if column not in used], rows,
                   f"a {what} covariance is {size}x{size}")
        if not len(rows) or self.cells[rows[0], self.columns[used[0]]] == "":
            self.empty(used, rows, f"the first {what} row has no covariance, so none may")
            return None
        values = self.values(used, rows, "number")
        blocks = np.empty((len(rows), size, size))
        for k, column in enumerate(used):
            i, j = _COV_ENTRIES[column]
            blocks[:, i, j] = blocks[:, j, i] = values[:, k]
        return blocks


_VALID: dict[str, Callable[[np.ndarray], np.ndarray]] = {
    "id": lambda values: values >= 0,
    "number": np.isfinite,
    "nonnegative": lambda values: np.isfinite(values) & (values >= 0),
    "variance": lambda values: np.isfinite(values) & (values > 0),
}


def _parses(cell: Any, dtype: type) -> bool:
    try:
        np.array([cell], dtype=object).astype(dtype)
    except (ValueError, OverflowError):
        return False
    return True


class _LineSink(list):
    r"""File-like target for ``csv.writer`` keeping each record with ``\n`` instead of ``\r\n``.

    The writer must use ``\r\n``: it quotes only fields holding terminator characters, and
    the reader ends lines at a bare ``\r`` too. ``csv.writer`` writes one record per call.
    """

    def write(self, record: str) -> None:
        self.append(record[:-2] + "\n")


def _csv_text(rows: Sequence[Sequence[Any]]) -> str:
    sink = _LineSink()
    csv.writer(sink, lineterminator="\r\n").writerows(rows)
    return "".join(sink)


def _csv_rows(kind: str, count: int, columns: Sequence[Sequence[Any] | None]) -> list[list[Any]]:
    """Rows ``[kind, *values]`` from columns of length ``count`` (None: an empty column)."""
    filled = [[None] * count if column is None else column for column in columns]
    return [[kind, *values] for values in zip(*filled)]


# ---------------------------------------------------------------------------------------
# Local maps


_LOCAL_MAP_FORMAT = "mapjoin/local-map"
_LOCAL_MAP_KEYS = ("format", "version", "name", "start_id", "end_id", "end_pose", "features", "covariance")
_END_POSE_FIELDS = {"x": "number", "y": "number", "phi": "number", "var_xy": "variance", "var_phi": "variance"}
_FEATURE_FIELDS = {"id": "id", "x": "number", "y": "number", "var": "variance"}
_LOCAL_CSV_HEADER = ("map", "start_id", "end_id", "kind", "id", "x", "y", "phi", "var_xy", "var_phi")
_MAT_VARIABLES = ("localmap_st", "localmap_P")
_MAT_NUMBER = re.compile(r"([0-9]+)(?:\.[^.]*)?$")  # k of localmap_<k>.mat


def _map_name(source: str, label: str | None, number: int | None) -> str:
    """Maps read from a file are named after it (messages and provenance then point to it): the
    path when it holds one map, else ``path#label`` with the map's own name, or its position."""
    return source if number is None else f"{source}#{label or number}"


def _read_local_yaml(text: str, source: str) -> list[LocalMap]:
    documents = _yaml_documents(text, source)
    return [_local_map_from_yaml(document, number if len(documents) > 1 else None)
            for number, document in enumerate(documents, 1)]


def _local_map_from_yaml(document: _YamlDocument, number: int | None) -> LocalMap:
    document.header(_LOCAL_MAP_FORMAT, _LOCAL_MAP_KEYS)
    name = _map_name(document.source, document.get(("name",), "text", optional=True), number)
    start_id, end_id = (document.get((key,), "id") for key in ("start_id", "end_id"))
    pose = document.record(("end_pose",), _END_POSE_FIELDS)
    features = document.records(("features",), _FEATURE_FIELDS)
    size = 3 + 2 * len(features["id"])
    covariance = document.matrix(("covariance",), (size, size), optional=True)
    try:
        return LocalMap(name, start_id, end_id,
                        [pose["x"], pose["y"], pose["phi"]], features["id"], _stack(features, "x", "y"),
                        features["var"], [pose["var_xy"], pose["var_phi"]], covariance)
    except InputError as error:
        raise document.relocated(error) from None


def _dump_local_yaml(maps: Sequence[LocalMap]) -> str:
    """A YAML stream of local maps; covariance rows are formatted here, as PyYAML's float representer
    (a Python call per number) would take seconds for a few hundred maps."""
    parts = []
    for local_map in maps:
        parts.append(_yaml_text([_local_map_document(local_map)], explicit_start=True))
        if local_map.covariance is not None:
            parts.append("covariance:\n" + "".join(f"- [{', '.join(map(_yaml_float, row))}]\n"
                                                   for row in local_map.covariance.tolist()))
    return "".join(parts)


def _yaml_float(value: float) -> str:
    """A finite float as PyYAML writes it: repr, with a dot before an exponent (YAML 1.1 needs one)."""
    text = repr(value)
    return text.replace("e", ".0e") if "e" in text and "." not in text else text


def _local_map_document(local_map: LocalMap) -> dict[str, Any]:
    document: dict[str, Any] = {
        "format": _LOCAL_MAP_FORMAT, "version": 1, "name": local_map.name,
        "start_id": local_map.start_id, "end_id": local_map.end_id,
        "end_pose": dict(zip(_END_POSE_FIELDS,
                             [*local_map.end_pose.tolist(), *local_map.pose_variances.tolist()])),
        "features": _yaml_records({"id": local_map.feature_ids, "x": local_map.features[:, 0],
                                   "y": local_map.features[:, 1], "var": local_map.feature_variances}),
    }
    return document


def _read_local_csv(text: str, source: str) -> list[LocalMap]:
    table = _CsvTable(text, source, [_LOCAL_CSV_HEADER])
    features, poses = table.kinds()
    names = table.text("map")
    _, first, group = np.unique(names, return_index=True, return_inverse=True)
    group = group.reshape(-1)
    ids = table.values(("start_id", "end_id"), None, "id")
    feature_ids = table.ids(features, group[features], " in this map")
    pose_ids = table.values(("id",), poses, "id")[:, 0]
    xy = table.values(("x", "y"), None, "number")
    var_xy = table.values(("var_xy",), None, "variance")[:, 0]
    orientation = table.values(("phi",), poses, "number")[:, 0]
    var_phi = table.values(("var_phi",), poses, "variance")[:, 0]
    table.empty(("phi", "var_phi"), features, "a feature has no orientation")

    changed = np.flatnonzero((ids != ids[first[group]]).any(axis=1))
    if changed.size:
        row = int(changed[0])
        raise table.error(row, "start_id", f"map {reprlib.repr(names[row])} has start_id,end_id "
                          f"{ids[first[group[row]]].tolist()} on line {table.lines[first[group[row]]]}")
    pose_counts = np.bincount(group[poses], minlength=len(first))
    if (pose_counts == 0).any():
        row = int(first[np.flatnonzero(pose_counts == 0)[0]])
        raise table.error(row, "kind",
                          f"map {reprlib.repr(names[row])} has no pose row; expected one (its end pose)")
    second = first_duplicate(group[poses])
    if second is not None:
        raise table.error(int(poses[second]), "kind",
                          f"map {reprlib.repr(names[poses[second]])} has a second pose row; expected one")
    wrong = np.flatnonzero(pose_ids != ids[poses, 1])
    if wrong.size:
        raise table.error(int(poses[wrong[0]]), "id", f"expected the end_id {ids[poses[wrong[0]], 1]} on the pose "
                          f"row, got {pose_ids[wrong[0]]}")

    # the maps in file order, stacked by size and checked at once, as LocalMap(...) checks one
    in_order = np.argsort(first)                      # place -> the map's group
    pose = np.empty(len(first), dtype=np.int64)       # group -> its pose row among ``poses``
    pose[group[poses]] = np.arange(len(poses))
    pose = pose[in_order]
    pose_rows = poses[pose]
    sizes = np.bincount(group[features], minlength=len(first))
    by_map = np.argsort(group[features], kind="stable")  # the feature rows, map after map (groups' order)
    offsets = (np.cumsum(sizes) - sizes)[in_order]
    sizes = sizes[in_order]
    labels = [_map_name(source, label, number if len(first) > 1 else None)
              for number, label in enumerate(names[pose_rows].tolist(), 1)]
    start_ids, end_ids = ids[pose_rows, 0].tolist(), ids[pose_rows, 1].tolist()
    stacks = []
    for places in size_groups(sizes):
        rows = by_map[offsets[places, np.newaxis] + np.arange(sizes[places[0]])]   # maps x features
        end_pose = np.column_stack([xy[pose_rows[places]], orientation[pose[places]]])
        pose_variances = np.column_stack([var_xy[pose_rows[places]], var_phi[pose[places]]])
        stacks.append((places, StackedMaps([labels[i] for i in places], end_pose, feature_ids[rows],
                                           xy[features[rows]], var_xy[features[rows]], pose_variances, None)))
    unmoved = np.flatnonzero(ids[pose_rows, 0] == ids[pose_rows, 1])   # LocalMap's first check
    invalid = first_invalid_map(stacks)
    if unmoved.size and (invalid is None or unmoved[0] <= invalid[0]):
        place = int(unmoved[0])
        invalid = place, InputError(f"end pose id equals start pose id ({end_ids[place]})", labels[place], "end_id")
    if invalid is not None:
        place, error = invalid
        field = f", field {error.where}" if error.where else ""
        raise InputError(error.detail, source, f"line {table.lines[first[in_order[place]]]}, map "
                                               f"{reprlib.repr(names[pose_rows[place]])}{field}")
    return unstack(stacks, start_ids, end_ids)


def _dump_local_csv(maps: Sequence[LocalMap]) -> str:
    rows: list[Sequence[Any]] = [_LOCAL_CSV_HEADER]
    for local_map in maps:
        head = [local_map.name, local_map.start_id, local_map.end_id]
        rows.append([*head, "pose", local_map.end_id, *local_map.end_pose.tolist(),
                     *local_map.pose_variances.tolist()])
        rows.extend([*head, *row] for row in _csv_rows("feature", local_map.size, [
            local_map.feature_ids.tolist(), *local_map.features.T.tolist(), None,
            local_map.feature_variances.tolist(), None]))
    return _csv_text(rows)


def _read_local_mat(data: bytes, source: str) -> list[LocalMap]:
    """One I-SLSJF local map; k from the file name (see the module docstring)."""
    return _mat_local_maps([data], [source])


def _read_local_mat_files(paths: Sequence[str]) -> list[LocalMap]:
    """The I-SLSJF local maps of many .mat files, parsed and checked all at once: a bad file raises the
    error (after the warnings) that reading the files one by one with :func:`_read_local_mat` gives."""
    if not paths:  # read_maps flushes its batch before every other file: nothing to parse then
        return []
    files: list[bytes] = []
    for path in paths:
        try:
            files.append(_read_file(path, path, True))
        except InputError:
            _mat_local_maps(files, paths[:len(files)])  # an error in an earlier file comes first
            raise
    return _mat_local_maps(files, paths)


def _mat_local_maps(files: Sequence[bytes], sources: Sequence[str]) -> list[LocalMap]:
    """The maps of I-SLSJF .mat files, map k from pose k-1 to pose k, as ``LocalMap.from_covariance`` makes
    them after I-SLSJF's stabilisation (see the module docstring).

    All files are parsed, checked and summarised at once, the maps of one size together; the
    first file that fails raises the error that reading the files one by one gives, after the
    warnings that reading logs before it.
    """
    table, errors = _mat_files(files, sources)
    numbers: list[int] = []  # k of each file, up to the first that fails
    failure: tuple[int, Callable[[int], InputError] | InputError | None] = (len(files), None)
    for i, source in enumerate(sources):
        try:
            numbers.append(_mat_map_number(source))
            if i in errors:
                raise errors[i]
        except InputError as error:
            failure = (i, error)
            break
    count = len(numbers)
    state_row, covariance_row = (table.named(key, count) for key in _MAT_VARIABLES)
    (state_matrix, sizes, state_columns), (covariance_matrix, covariance_rows, covariance_columns) = (
        table.matrices(rows) for rows in (state_row, covariance_row))
    count = first_flagged(~state_matrix | ~covariance_matrix | (state_columns != 2) | (sizes < 3)
                          | ((sizes - 3) % 2 != 0), np.arange(count + 1))  # the files whose variables pass
    sizes = sizes[:count]
    starts = np.concatenate([[0], np.cumsum(sizes)])  # map i's localmap_st rows: starts[i] to starts[i + 1]
    first_row = np.repeat(starts[:-1], sizes)
    state = table.floats(state_row[:count])  # map i's ids, then its values, from 2 * starts[i]
    ids = state[np.arange(starts[-1]) + first_row]
    values = state[np.arange(starts[-1]) + first_row + np.repeat(sizes, sizes)]
    failed, error = min([  # (first file failing a check, its error), in the order one file is checked
        failure,
        (count, lambda i: _local_mat_error(table.variables(i), sources[i])),
        *((first_flagged(bad, starts), functools.partial(_mat_id_error, fault, table, state_row, sources))
          for fault, bad in enumerate(_mat_id_faults(ids, np.arange(starts[-1]) - first_row))),
        (first_flagged((covariance_rows[:count] != sizes) | (covariance_columns[:count] != sizes),
                       np.arange(count + 1)),
         lambda i: InputError("expected {0}x{0} (the size of localmap_st), got {1}".format(
             sizes[i], table.array(covariance_row[i]).shape), sources[i], "localmap_P")),
    ], key=lambda failure: failure[0])  # ties: the earlier check

    stacks = []  # (maps, StackedMaps) of each size, before the first failure
    stabilised: list[tuple[int, np.ndarray]] = []  # (map, its end-pose variances) where STAB_NOISE is added
    for group in size_groups(sizes[:failed]):
        n, m = int(sizes[group[0]]), int(sizes[group[0]] - 3) // 2
        rows = starts[group, np.newaxis] + np.arange(n)
        covariances = table.floats(covariance_row[group]).reshape(-1, n, n).transpose(0, 2, 1)  # column-major
        pose_variances = np.diagonal(covariances, axis1=1, axis2=2)[:, :3].copy()
        still = np.flatnonzero(pose_variances.min(axis=1) < STAB_NOISE)
        covariances[still[:, np.newaxis], np.arange(3), np.arange(3)] += STAB_NOISE
        stabilised += zip(group[still].tolist(), pose_variances[still])
        group_values = values[rows]
        stacks.append((group, StackedMaps(
            [sources[i] for i in group.tolist()], group_values[:, :3], ids[rows[:, 3::2]].astype(np.int64),
            group_values[:, 3:].reshape(len(group), m, 2), *marginal_variances(covariances), covariances)))
    invalid = first_invalid_map(stacks)
    last = invalid[0] if invalid else failed - 1  # the last map that one-by-one reading gets to
    for i, pose_variances in sorted(stabilised, key=lambda item: item[0]):
        if i <= last:
            log.warning("%s: end-pose variances %s include one below %g (the robot did not move); added %g to the "
                        "three pose diagonal entries, as I-SLSJF does", sources[i],
                        np.array2string(pose_variances, precision=3), STAB_NOISE, STAB_NOISE)
    if invalid:
        raise invalid[1]
    if error is not None:
        raise error if isinstance(error, InputError) else error(failed)
    return unstack(stacks, [k - 1 for k in numbers], numbers)


def _mat_map_number(source: str) -> int:
    """k of a file named ``localmap_<k>.mat`` (map k runs from pose k-1 to pose k)."""
    match = _MAT_NUMBER.search(os.path.basename(source))
    if not match or int(match[1]) < 1:
        raise InputError("cannot tell the map number k from the file name; name it localmap_<k>.mat with k >= 1 "
                         "(map k runs from pose k-1 to pose k)", source)
    return int(match[1])


def _local_mat_error(variables: Mapping[str, _MatArray | str], source: str) -> InputError | None:
    """What is wrong with the variables of an I-SLSJF .mat file, if anything (their values aside): it must hold
    the real matrices ``localmap_st``, of (3+2m) x 2 [id, value] rows, and ``localmap_P``."""
    for key in _MAT_VARIABLES:
        if key not in variables:
            return InputError(f"missing; expected the I-SLSJF variables {' and '.join(_MAT_VARIABLES)}", source, key)
        value = variables[key]
        if isinstance(value, str) or len(value.shape) != 2:
            got = value if isinstance(value, str) else f"{len(value.shape)}-D array"
            return InputError(f"expected a real numeric matrix, got a {got}", source, key)
    shape = variables["localmap_st"].shape
    if shape[1] != 2 or shape[0] < 3 or (shape[0] - 3) % 2:
        return InputError(f"expected (3+2m)x2 [id, value] rows, got shape {shape}", source, "localmap_st")
    return None


def _mat_id_faults(ids: np.ndarray, row: np.ndarray) -> list[np.ndarray]:
    """Masks over ``localmap_st`` rows (``row``: the row within its map) of each fault of their ids, in the
    order they are checked: a pose row without id 0, a feature id that is not an integer in [0, 2^53), an x
    row whose y row has another id."""
    pose, x = row < 3, (row >= 3) & (row % 2 == 1)
    mismatch = np.zeros(len(ids), dtype=bool)
    mismatch[x] = ids[x] != ids[np.flatnonzero(x) + 1]
    return [pose & (ids != 0), ~pose & ~((ids >= 0) & (ids < 2**53) & (ids == np.round(ids))), mismatch]


def _mat_id_error(fault: int, table: _MatTable, state_row: np.ndarray, sources: Sequence[str], i: int) -> InputError:
    """The error of map i's first ``localmap_st`` row with ``fault`` (an index into :func:`_mat_id_faults`)."""
    ids = table.array(state_row[i]).value()[:, 0]
    row = int(np.argmax(_mat_id_faults(ids, np.arange(len(ids)))[fault]))
    if fault == 0:
        message = f"expected id 0 on the three end-pose rows, got {ids[row]:g}"
    elif fault == 1:
        message = f"expected a non-negative integer feature id, got {ids[row]:g}"
    else:
        message = (f"feature id {ids[row]:g} on the x row but {ids[row + 1]:g} on the y row (row {row + 2}); "
                   "expected the same id on both rows of a feature")
    return InputError(message, sources[i], f"localmap_st row {row + 1}")


# MAT-file level 5 (MathWorks, "MAT-File Format"). scipy.io.loadmat crashes the interpreter
# (segfault) on some corrupt files, e.g. one flipped byte in an element's type code, so the
# few element kinds local maps use are parsed here, checking every length and code. Many
# files are parsed at once (a folder of thousands of small ones): their bytes are joined, each
# walk over data elements reads the k-th tag of every buffer in one numpy step, and the
# variables found form one table.
_MI_INT8, _MI_INT32, _MI_UINT32, _MI_MATRIX, _MI_COMPRESSED = 1, 5, 6, 14, 15
_MI_NUMERIC = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 9: "f8", 12: "i8", 13: "u8"}
_MX_CLASSES = {1: "cell array", 2: "struct", 3: "object", 4: "char array", 5: "sparse matrix", 16: "function",
               17: "opaque object"}
_MX_NUMERIC = range(6, 16)  # double, single, int8 ... uint64
_MX_COMPLEX = 0x800
_MAT_DTYPES = {(big, kind): np.dtype((">" if big else "<") + code) for kind, code in _MI_NUMERIC.items()
               for big in (False, True)}
_MAT_ITEMSIZES = np.array([_MAT_DTYPES.get((False, kind), np.dtype("u1")).itemsize for kind in range(16)])


def mat_variables(data: bytes, source: str) -> dict[str, np.ndarray | str]:
    """The variables of a MATLAB v5 .mat file: real numeric arrays as float arrays, others as a description."""
    table, errors = _mat_files([data], [source])
    if errors:
        raise errors[0]
    return {name: value if isinstance(value, str) else value.value() for name, value in table.variables(0).items()}


class _MatArray(NamedTuple):
    """A real numeric array as a .mat file stores it: its dimensions and its column-major data of ``dtype``."""

    shape: tuple[int, ...]
    dtype: np.dtype
    data: memoryview

    def value(self) -> np.ndarray:
        return np.frombuffer(self.data, self.dtype).astype(float).reshape(self.shape, order="F")


class _MatTable(NamedTuple):
    """The variables of many .mat files, one row each, in file order (all of a file's when it has no error):
    where in ``buffer`` its name and, for a real numeric array, its dimensions and data are."""

    buffer: bytes  # the files' top-level elements, decompressed
    file: np.ndarray  # the file each variable is in
    big: np.ndarray  # its byte order is big-endian
    name: np.ndarray  # (start, end) of its name
    descriptions: dict[int, str]  # the variables that are not real numeric arrays
    kind: np.ndarray  # the data type of a real numeric array
    rank: np.ndarray  # its number of dimensions
    dimensions: np.ndarray  # where they start
    content: np.ndarray  # (start, end) of its data

    def variables(self, file: int) -> dict[str, _MatArray | str]:
        """Name and value of each variable of ``file``, later ones of a name replacing earlier ones."""
        return {self.name_of(row): self.array(row) for row in np.flatnonzero(self.file == file).tolist()}

    def name_of(self, row: int) -> str:
        return str(memoryview(self.buffer)[slice(*self.name[row])], "latin-1")

    def array(self, row: int) -> _MatArray | str:
        """Variable ``row`` as stored, or its description."""
        if row in self.descriptions:
            return self.descriptions[row]
        big, kind = bool(self.big[row]), int(self.kind[row])
        shape = struct.unpack_from(f"{'>' if big else '<'}{self.rank[row]}i", self.buffer, self.dimensions[row])
        return _MatArray(shape, _MAT_DTYPES[big, kind], memoryview(self.buffer)[slice(*self.content[row])])

    def named(self, name: str, files: int) -> np.ndarray:
        """The row of the (last) variable called ``name`` of each of the first ``files`` files; -1 if none."""
        text = np.frombuffer(name.encode("latin-1"), np.uint8)
        rows = np.flatnonzero((self.name[:, 1] - self.name[:, 0] == len(text)) & (self.file < files))
        rows = rows[(np.frombuffer(self.buffer, np.uint8)[self.name[rows, :1] + np.arange(len(text))] == text).all(1)]
        found = np.full(files, -1)
        np.maximum.at(found, self.file[rows], rows)
        return found

    def matrices(self, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Whether each of ``rows`` (-1: none) is a real numeric matrix, and its numbers of rows and columns."""
        matrix = rows >= 0
        matrix[matrix] = (self.rank[rows[matrix]] == 2) & (self.kind[rows[matrix]] >= 0)
        shape = np.zeros((len(rows), 2), dtype=np.int64)
        shape[matrix] = _mat_int32(np.frombuffer(self.buffer, np.uint8), self.dimensions[rows[matrix], np.newaxis]
                                   + [0, 4], self.big[rows[matrix], np.newaxis])
        return matrix, shape[:, 0], shape[:, 1]

    def floats(self, rows: np.ndarray) -> np.ndarray:
        """The data of the real numeric arrays ``rows`` as floats, each column-major, one after the other."""
        view, types = memoryview(self.buffer), set(zip(self.big[rows].tolist(), self.kind[rows].tolist()))
        if len(types) > 1:
            return np.concatenate([self.array(row).value().ravel(order="F") for row in rows.tolist()])
        data = bytearray().join([view[start:end] for start, end in self.content[rows].tolist()])  # writable
        return np.frombuffer(data, _MAT_DTYPES[types.pop()] if types else float).astype(float, copy=False)


def _mat_files(files: Sequence[bytes], sources: Sequence[str]) -> tuple[_MatTable, dict[int, InputError]]:
    """The variables of many .mat files, and the error of each file that has one: the first that reading its
    elements in order meets."""
    errors: dict[int, str] = {}
    big = np.zeros(len(files), dtype=bool)  # big-endian
    for i, data in enumerate(files):
        if len(data) < 128 or data[126:128] not in (b"IM", b"MI"):
            errors[i] = "expected a MATLAB v5 .mat file (no MAT-file header)"
            continue
        big[i] = data[126:128] == b"MI"
        version = struct.unpack_from(">H" if big[i] else "<H", data, 124)[0]
        if version != 0x0100:
            errors[i] = f"expected a MATLAB v5 .mat file, got version {version:#06x} (save with -v7 or -v6)"
    elements, owner, element_errors = _mat_top_level(files, big, errors)
    table = _mat_variables(elements, owner, big[np.array(owner, dtype=np.intp)], element_errors)
    for e, message in sorted(element_errors.items()):
        errors.setdefault(owner[e], message)  # the file's first element with an error
    return table, {i: InputError(message, sources[i]) for i, message in errors.items()}


def _mat_top_level(files: Sequence[bytes], big: np.ndarray, errors: dict[int, str]
                   ) -> tuple[list[bytes | memoryview], list[int], dict[int, str]]:
    """The top-level data elements of the files without ``errors``, each alone (decompressed, or as it is);
    the file of each; and the error of each that cannot be decompressed. A file's walk error goes to ``errors``."""
    joined = b"".join(files)
    end = np.cumsum([len(data) for data in files], dtype=np.int64)
    begin = end - [len(data) - 128 for data in files]
    begin[list(errors)] = end[list(errors)]
    top, walk_errors = _mat_walk(np.frombuffer(joined, np.uint8), begin, end, big, padded=False)
    errors.update(walk_errors)
    elements: list[bytes | memoryview] = []
    owner: list[int] = []
    element_errors: dict[int, str] = {}
    view = memoryview(joined)
    for file, kind, tag, start, size in zip(*(column.tolist() for column in top)):
        if file in errors:
            continue
        if kind == _MI_COMPRESSED:
            try:
                elements.append(zlib.decompress(view[start:start + size]))
            except zlib.error as error:
                element_errors[len(elements)] = f"corrupt compressed data in the .mat file ({error})"
                elements.append(b"")
        else:
            elements.append(view[tag:max(start + size, tag + 8)])
        owner.append(file)
    return elements, owner, element_errors


def _mat_variables(elements: Sequence[bytes | memoryview], owner: Sequence[int], big: np.ndarray,
                   errors: dict[int, str]) -> _MatTable:
    """The variables that top-level data elements hold, each a miMATRIX element; the first error of each
    element that is not one, or not a well-formed one, goes to ``errors``."""
    buffer = b"".join(elements)
    data, count = np.frombuffer(buffer, np.uint8), len(elements)
    end = np.cumsum([len(element) for element in elements], dtype=np.int64)
    inner, walk_errors = _mat_walk(data, end - [len(element) for element in elements], end, big, padded=False)
    found, only = inner.counts(count), inner.nth(0, count)
    for e, message in walk_errors.items():
        errors.setdefault(e, message)
    for e in np.flatnonzero(found != 1).tolist():
        errors.setdefault(e, f"corrupt .mat file: expected 1 element(s), got {found[e]}")
    for e in np.flatnonzero((found == 1) & (only.kind != _MI_MATRIX)).tolist():
        errors.setdefault(e, f"corrupt .mat file: expected a matrix element, got element type {only.kind[e]}")
    matrix = np.ones(count, dtype=bool)
    matrix[list(errors)] = False
    parts, walk_errors = _mat_walk(data, np.where(matrix, only.start, 0), np.where(matrix, only.start + only.size, 0),
                                   big, padded=True)
    for e, message in walk_errors.items():
        errors.setdefault(e, message)
    matrix[list(errors)] = False

    # a miMATRIX element's subelements: array flags, dimensions, name, then a numeric array's data
    flags, dimensions, name, content = (parts.nth(k, count) for k in range(4))
    found = parts.counts(count)
    kinds = np.column_stack([flags.kind, dimensions.kind, name.kind])
    layout = (kinds == [_MI_UINT32, _MI_INT32, _MI_INT8]).all(axis=1) & (flags.size == 8)
    for e in np.flatnonzero(matrix & ~layout).tolist():
        errors[e] = f"corrupt .mat file: matrix subelements of types {kinds[e, :min(found[e], 3)].tolist()}"
    matrix &= layout
    array_flags = np.zeros(count, dtype=np.int64)
    array_flags[matrix] = _mat_int32(data, flags.start[matrix, np.newaxis], big[matrix, np.newaxis])[:, 0]
    real = matrix & np.isin(array_flags & 0xFF, _MX_NUMERIC) & (array_flags & _MX_COMPLEX == 0)
    descriptions = {e: _MX_CLASSES.get(flag & 0xFF, "complex array" if flag & _MX_COMPLEX else "unknown class")
                    for e, flag in zip(np.flatnonzero(matrix & ~real).tolist(), array_flags[matrix & ~real].tolist())}
    malformed = real & ((dimensions.size % 4 != 0) | (found != 4) | ~np.isin(content.kind, list(_MI_NUMERIC)))
    real &= ~malformed
    rank = np.where(real, dimensions.size // 4, 0)
    owner_of_dimension = np.repeat(np.arange(count), rank)
    first_dimension = np.cumsum(rank) - rank
    dimension = _mat_int32(data, (dimensions.start[owner_of_dimension] + 4 * (np.arange(rank.sum())
                                  - first_dimension[owner_of_dimension]))[:, np.newaxis],
                           big[owner_of_dimension, np.newaxis])[:, 0]
    negative = real & (rank == 0)  # min(shape, default=-1) < 0
    negative[owner_of_dimension[dimension < 0]] = True
    entries = np.zeros(count)  # the product of the dimensions (exact: < 2^53 whenever it matters)
    sized = np.flatnonzero(rank > 0)
    entries[sized] = np.multiply.reduceat(dimension.astype(float), first_dimension[sized]) if sized.size else 0
    wrong_size = real & ~negative & (entries * _MAT_ITEMSIZES[np.where(real, content.kind, 0)] != content.size)
    table = _MatTable(buffer, np.array(owner, dtype=np.intp), big,
                      np.column_stack([name.start, name.start + name.size]), descriptions,
                      np.where(real, content.kind, -1), rank, dimensions.start,
                      np.column_stack([content.start, content.start + content.size]))
    for e in np.flatnonzero(malformed).tolist():
        errors[e] = f"corrupt .mat file: numeric array {table.name_of(e)!r} is malformed"
    for e in np.flatnonzero(negative | wrong_size).tolist():
        shape = table.array(e).shape
        errors[e] = (f"corrupt .mat file: {table.name_of(e)!r} has dimensions {shape}" if negative[e] else
                     f"corrupt .mat file: {table.name_of(e)!r} holds {content.size[e]} bytes for shape {shape}")
    return table


class _MatElements(NamedTuple):
    """Data elements found by :func:`_mat_walk`, ordered by buffer, then position."""

    buffer: np.ndarray  # the buffer each is in
    kind: np.ndarray  # its data type
    tag: np.ndarray  # where its tag starts
    start: np.ndarray  # where its data starts
    size: np.ndarray  # its byte count, without padding

    def counts(self, buffers: int) -> np.ndarray:
        """How many elements each of the ``buffers`` holds."""
        return np.bincount(self.buffer, minlength=buffers)

    def nth(self, k: int, buffers: int) -> "_MatElements":
        """Each buffer's k-th element (0-based); -1 in every field for a buffer with fewer."""
        count = self.counts(buffers)
        index = np.where(count > k, np.cumsum(count) - count + k, len(self.buffer))
        return _MatElements(*(np.append(column, -1)[index] for column in self))


def _mat_walk(data: np.ndarray, begin: np.ndarray, end: np.ndarray, big: np.ndarray, *, padded: bool
              ) -> tuple[_MatElements, dict[int, str]]:
    """The data elements in the byte ranges ``data[begin[i]:end[i]]`` (``big``: big-endian), found all at once:
    step k reads the k-th tag of every range. Also the error of each range with a cut-off or corrupt element
    (the elements before it are kept). A step costs some tens of microseconds whatever the number of ranges,
    so a range of thousands of elements (a big cell or struct array, which is only described) is slow."""
    found, errors = [], {}
    ranges = np.flatnonzero(begin < end)
    offset = begin[ranges]
    while len(ranges):
        whole = offset + 8 <= end[ranges]
        errors.update(dict.fromkeys(ranges[~whole].tolist(), "truncated .mat file (an element tag is cut off)"))
        ranges, offset = ranges[whole], offset[whole]
        kind, size = _mat_int32(data, offset[:, np.newaxis] + [0, 4], big[ranges, np.newaxis], unsigned=True).T
        small = kind >> 16 > 0  # a small data element: up to 4 bytes of data inside its tag
        kind, size = np.where(small, kind & 0xFFFF, kind), np.where(small, kind >> 16, size)
        start = offset + np.where(small, 4, 8)
        oversized, cut = small & (size > 4), ~small & (start + size > end[ranges])
        for i, bytes_ in zip(ranges[oversized].tolist(), size[oversized].tolist()):
            errors[i] = f"corrupt .mat file: small element of {bytes_} bytes"
        errors.update(dict.fromkeys(ranges[cut].tolist(), "truncated .mat file (an element is cut off)"))
        good = ~(oversized | cut)
        found.append((ranges[good], kind[good], offset[good], start[good], size[good]))
        following = np.where(small, offset + 8, start + size + (-size % 8 if padded else 0))
        more = good & (following < end[ranges])
        ranges, offset = ranges[more], following[more]
    columns = [np.concatenate(column) for column in zip(*found)] if found else [np.zeros(0, np.int64)] * 5
    order = np.argsort(columns[0], kind="stable")  # by buffer, then position
    return _MatElements(*(column[order] for column in columns)), errors


def _mat_int32(data: np.ndarray, offset: np.ndarray, big: np.ndarray, *, unsigned: bool = False) -> np.ndarray:
    """The 32-bit integers at ``offset`` (any shape) of ``data``, each in the byte order ``big`` (broadcast)."""
    raw = np.ascontiguousarray(data[offset[..., np.newaxis] + np.arange(4)])
    code = "u4" if unsigned else "i4"
    return np.where(big, raw.view(">" + code)[..., 0], raw.view("<" + code)[..., 0]).astype(np.int64)


# ---------------------------------------------------------------------------------------
# Global maps and ground truth


_GLOBAL_MAP_FORMAT = "mapjoin/global-map"
_TRUTH_FORMAT = "mapjoin/ground-truth"
_ENTITY_HEADER = ("kind", "id", "x", "y", "phi")
_GLOBAL_CSV_HEADER = (*_ENTITY_HEADER, "var_xy", "var_phi")
_COV_ENTRIES = {"cov_xx": (0, 0), "cov_xy": (0, 1), "cov_yy": (1, 1),
                "cov_xphi": (0, 2), "cov_yphi": (1, 2), "cov_phiphi": (2, 2)}
_GLOBAL_COV_CSV_HEADER = (*_GLOBAL_CSV_HEADER, *_COV_ENTRIES)
_PROVENANCE_FIELDS = ("covariance", "solver", "strategy")
_GLOBAL_FEATURE_FIELDS = {"id": "id", "x": "number", "y": "number", "var": "variance"}
_GLOBAL_POSE_FIELDS = {"id": "id", "x": "number", "y": "number", "phi": "number",
                       "var_xy": "variance", "var_phi": "variance"}
_TRUTH_FEATURE_FIELDS = {"id": "id", "x": "number", "y": "number"}
_TRUTH_POSE_FIELDS = {"id": "id", "x": "number", "y": "number", "phi": "number"}


def _read_global_yaml(text: str, source: str) -> GlobalMap:
    document = _yaml_document(text, source)
    document.header(_GLOBAL_MAP_FORMAT, ("format", "version", "provenance", "features", "poses"))
    features = document.records(("features",), _GLOBAL_FEATURE_FIELDS, {"cov": (2, 2)})
    poses = document.records(("poses",), _GLOBAL_POSE_FIELDS, {"cov": (3, 3)})
    return GlobalMap(features["id"], _stack(features, "x", "y"), features["var"], poses["id"],
                     _stack(poses, "x", "y", "phi"), _stack(poses, "var_xy", "var_phi"),
                     _provenance(document), features["cov"], poses["cov"], name=source)


def _provenance(document: _YamlDocument) -> Provenance:
    path = ("provenance",)
    if document.get(path, "mapping", optional=True) is None:
        return Provenance()
    document.only(path, ("maps", *_PROVENANCE_FIELDS))
    count = len(document.get((*path, "maps"), "list", optional=True) or ())
    maps = tuple(document.get((*path, "maps", index), "text") for index in range(count))
    fields = {key: document.get((*path, key), "text", optional=True) or "" for key in _PROVENANCE_FIELDS}
    return Provenance(maps, **fields)


def _dump_global_yaml(global_map: GlobalMap) -> str:
    provenance = global_map.provenance
    return _yaml_text([{
        "format": _GLOBAL_MAP_FORMAT, "version": 1,
        "provenance": {"maps": list(provenance.maps),
                       **{key: getattr(provenance, key) for key in _PROVENANCE_FIELDS}},
        "features": _yaml_records({"id": global_map.feature_ids, "x": global_map.features[:, 0],
                                   "y": global_map.features[:, 1], "var": global_map.feature_variances,
                                   "cov": global_map.feature_covariances}),
        "poses": _yaml_records({"id": global_map.pose_ids, "x": global_map.poses[:, 0],
                                "y": global_map.poses[:, 1], "phi": global_map.poses[:, 2],
                                "var_xy": global_map.pose_variances[:, 0],
                                "var_phi": global_map.pose_variances[:, 1], "cov": global_map.pose_covariances}),
    }])


def _read_global_csv(text: str, source: str) -> GlobalMap:
    table = _CsvTable(text, source, [_GLOBAL_CSV_HEADER, _GLOBAL_COV_CSV_HEADER])
    features, poses = table.kinds()
    table.empty(("phi", "var_phi"), features, "a feature has no orientation")
    with_covariances = table.header == _GLOBAL_COV_CSV_HEADER
    return GlobalMap(
        table.ids(features), table.values(("x", "y"), features, "number"),
        table.values(("var_xy",), features, "variance")[:, 0],
        table.ids(poses), table.values(("x", "y", "phi"), poses, "number"),
        table.values(("var_xy", "var_phi"), poses, "variance"), Provenance(),
        table.covariances(features, 2, "feature") if with_covariances else None,
        table.covariances(poses, 3, "pose") if with_covariances else None, name=source)


def _dump_global_csv(global_map: GlobalMap) -> str:
    feature_columns: list[Sequence[Any] | None] = [
        global_map.feature_ids.tolist(), *global_map.features.T.tolist(), None,
        global_map.feature_variances.tolist(), None]
    pose_columns: list[Sequence[Any] | None] = [
        global_map.pose_ids.tolist(), *global_map.poses.T.tolist(), *global_map.pose_variances.T.tolist()]
    header = _GLOBAL_CSV_HEADER
    if global_map.feature_covariances is not None or global_map.pose_covariances is not None:
        header = _GLOBAL_COV_CSV_HEADER
        feature_columns += _covariance_columns(global_map.feature_covariances, 2)
        pose_columns += _covariance_columns(global_map.pose_covariances, 3)
    return _csv_text([header, *_csv_rows("feature", len(global_map.feature_ids), feature_columns),
                      *_csv_rows("pose", len(global_map.pose_ids), pose_columns)])


def _covariance_columns(blocks: np.ndarray | None, size: int) -> list[Sequence[float] | None]:
    """The ``cov_*`` columns of symmetric ``size`` x ``size`` blocks (upper triangle; None: empty)."""
    return [None if blocks is None or max(i, j) >= size else blocks[:, i, j].tolist()
            for i, j in _COV_ENTRIES.values()]


def _read_truth_yaml(text: str, source: str) -> GroundTruth:
    document = _yaml_document(text, source)
    document.header(_TRUTH_FORMAT, ("format", "version", "features", "poses"))
    features = document.records(("features",), _TRUTH_FEATURE_FIELDS)
    poses = document.records(("poses",), _TRUTH_POSE_FIELDS)
    return GroundTruth(features["id"], _stack(features, "x", "y"), poses["id"], _stack(poses, "x", "y", "phi"),
                       name=source)


def _dump_truth_yaml(truth: GroundTruth) -> str:
    return _yaml_text([{
        "format": _TRUTH_FORMAT, "version": 1,
        "features": _yaml_records({"id": truth.feature_ids, "x": truth.features[:, 0], "y": truth.features[:, 1]}),
        "poses": _yaml_records({"id": truth.pose_ids, "x": truth.poses[:, 0], "y": truth.poses[:, 1],
                                "phi": truth.poses[:, 2]}),
    }])


def _read_truth_csv(text: str, source: str) -> GroundTruth:
    table = _CsvTable(text, source, [_ENTITY_HEADER])
    features, poses = table.kinds()
    table.empty(("phi",), features, "a feature has no orientation")
    return GroundTruth(table.ids(features), table.values(("x", "y"), features, "number"),
                       table.ids(poses), table.values(("x", "y", "phi"), poses, "number"), name=source)


def _dump_truth_csv(truth: GroundTruth) -> str:
    return _csv_text([_ENTITY_HEADER,
                      *_csv_rows("feature", len(truth.feature_ids),
                                 [truth.feature_ids.tolist(), *truth.features.T.tolist(), None]),
                      *_csv_rows("pose", len(truth.pose_ids), [truth.pose_ids.tolist(), *truth.poses.T.tolist()])])


# ---------------------------------------------------------------------------------------
# Minima queries and tables


_MINIMA_COLUMNS = {"a": "nonnegative", "c_phi": "number"}  # column -> kind of its values; "join" ("id") optional


def _read_minima_csv(text: str, source: str) -> MinimaTable:
    """A CSV table whose header names a and c_phi (in any order, among any other columns)."""
    table = _CsvTable(text, source, None)
    if not set(_MINIMA_COLUMNS) <= set(table.header):
        raise InputError(f"expected a header with the columns a and c_phi (as `mapjoin join --report` writes "
                         f"them), got {','.join(table.header) or 'nothing'}", source, f"line {table.header_line}")
    a, c_phi = (table.values((column,), None, kind)[:, 0] for column, kind in _MINIMA_COLUMNS.items())
    join = table.values(("join",), None, "id")[:, 0] if "join" in table.header else None
    return MinimaTable(source, a, c_phi, join)


def _read_minima_records(text: str, source: str) -> MinimaTable:
    """A YAML or JSON list of mappings with a and c_phi, and join in every one or none (JSON is read as
    YAML, so that errors name lines)."""
    document = _yaml_document(text, source)
    records = document.get((), "list")
    for row in range(len(records)):
        document.get((row,), "mapping")
    kinds = {**_MINIMA_COLUMNS, **({"join": "id"} if any("join" in record for record in records) else {})}
    columns = {key: [document.get((row, key), kind) for row in range(len(records))] for key, kind in kinds.items()}
    join = np.array(columns["join"], dtype=np.int64) if "join" in columns else None
    return MinimaTable(source, np.array(columns["a"], dtype=float), np.array(columns["c_phi"], dtype=float), join)


def _table(rows: Sequence[Any]) -> tuple[list[str], list[list[Any]]]:
    """Field names and plain-Python values of dataclass instances of one type."""
    if not rows:
        return [], []
    kind = type(rows[0])
    if any(type(row) is not kind for row in rows):
        raise TypeError(f"table rows must all be {kind.__name__} instances")
    names = [field.name for field in dataclasses.fields(kind)]
    return names, [[_plain(getattr(row, name)) for name in names] for row in rows]


def _plain(value: Any) -> Any:
    """Numpy scalars and arrays as Python numbers and lists, tuples as lists."""
    if isinstance(value, (np.ndarray, np.generic)):
        return value.tolist()
    if isinstance(value, (list, tuple)):
        return [_plain(item) for item in value]
    return value


def _dump_table_csv(rows: Sequence[Any]) -> str:
    names, values = _table(rows)
    return _csv_text([names, *values]) if names else ""


def _dump_table_yaml(rows: Sequence[Any]) -> str:
    names, values = _table(rows)
    return _yaml_text([[dict(zip(names, row)) for row in values]])


def _dump_table_json(rows: Sequence[Any]) -> str:
    import json

    names, values = _table(rows)
    return json.dumps([dict(zip(names, row)) for row in values], indent=2) + "\n"


# ---------------------------------------------------------------------------------------
# Linear SLAM text local maps, I-SLSJF .mat writing, g2o export of a global map


_MI_DOUBLE, _MX_DOUBLE = 9, 6  # MAT v5: element type double, array class double
_MAT_HEADER = (b"MATLAB 5.0 MAT-file, written by mapjoin".ljust(116) + bytes(8)  # text, no subsystem data
               + struct.pack("<H", 0x0100) + b"IM")                             # version 1, little-endian
_G2O_MAX_ID = 2**31 - 1  # g2o vertex ids are C ints


def map_file_name(end_id: int, fmt: str) -> str:
    """The name of the file a folder holds the map ending at pose ``end_id`` in, e.g. ``localmap_7.txt``."""
    return f"localmap_{end_id}.{_FILE_EXTENSIONS.get(fmt, fmt)}"


def g2o_feature_offset(pose_ids: np.ndarray) -> int:
    """What the g2o export adds to feature ids so they cannot clash with pose ids (g2o has one id space):
    the smallest power of ten above every pose id, at least 10 (poses 1..200: feature 7 is vertex 1007)."""
    return 10 ** len(str(int(np.max(pose_ids, initial=0))))


def _check_single_map_file(maps: Sequence[LocalMap], target: Source, fmt: str) -> None:
    """A ``mat`` or ``linearslam`` file holds one map, and a .mat file's name ends in its end id (map k)."""
    name = _source_name(target, "<stdout>")
    if len(maps) != 1:
        raise InputError(f"a {fmt} file holds one local map, got {len(maps)}; write them to a folder "
                         "(a path ending in /), one file per map", name)
    if fmt == "mat" and isinstance(target, (str, os.PathLike)) and name != "<stdout>":
        match = _MAT_NUMBER.search(os.path.basename(name))
        if not match or int(match[1]) != maps[0].end_id:
            raise InputError("an I-SLSJF .mat local map takes its number k (its end pose) from the file name; "
                             f"name this one {map_file_name(maps[0].end_id, fmt)}", name)


def _read_local_linearslam(text: str, source: str) -> list[LocalMap]:
    """One Linear SLAM local map (see the module docstring); its covariance is the inverse of the stored information."""
    lines = text.splitlines()
    start_id = _text_integer(lines, 0, "the reference pose index (a non-negative integer)", source)
    size = _text_integer(lines, 1, "the state dimension d = 3 + 2m (m features)", source)
    if size < 3 or (size - 3) % 2:
        raise InputError(f"expected the state dimension d = 3 + 2m (m features), got {size}", source, "line 2")
    state_rows = _text_rows(lines, 2, size, 2, f"`id value`, one of d = {size} state rows", source)
    ids = _text_ids(state_rows[:, 0], 2, source)
    state = _text_numbers(state_rows[:, 1:], 2, source, first_field=2)[:, 0]
    information = _text_numbers(
        _text_rows(lines, 2 + size, size, size, f"a row of the {size}x{size} information matrix", source),
        2 + size, source)
    trailing = next((i for i in range(2 + 2 * size, len(lines)) if lines[i].strip()), None)
    if trailing is not None:
        raise InputError(f"expected nothing after the {size} rows of the information matrix, got "
                         f"{reprlib.repr(lines[trailing].strip())}", source, f"line {trailing + 1}")
    pose, features, end_id = _linearslam_layout(ids, start_id, source)
    order = np.concatenate([pose, features])
    covariance = _covariance_of_information(information, 2 + size, source)[np.ix_(order, order)]
    return [LocalMap.from_covariance(source, start_id, end_id, state[pose], ids[features[0::2]],
                                     state[features].reshape(-1, 2), covariance)]


def _text_integer(lines: Sequence[str], index: int, expected: str, source: str) -> int:
    """Line ``index`` (0-based) as one non-negative integer."""
    text = lines[index].strip() if index < len(lines) else ""
    if not text.isdigit() or not text.isascii():
        raise InputError(f"expected {expected}, got {reprlib.repr(text) if text else 'nothing'}", source,
                         f"line {index + 1}")
    return int(text)


def _text_rows(lines: Sequence[str], first: int, count: int, width: int, expected: str, source: str) -> np.ndarray:
    """Lines ``first .. first+count-1`` (0-based) as a (count x width) array of their whitespace-separated fields."""
    cells = [line.split() for line in lines[first:first + count]]
    bad = next((i for i, row in enumerate(cells) if len(row) != width), None)
    if bad is None and len(cells) < count:
        bad = len(cells)
    if bad is not None:
        got = (f"{len(cells[bad])} fields: {reprlib.repr(lines[first + bad].strip())}" if bad < len(cells)
               else "the end of the file")
        raise InputError(f"expected {expected} ({width} fields), got {got}", source, f"line {first + bad + 1}")
    return np.array(list(chain.from_iterable(cells)), dtype=str).reshape(count, width)


def _text_numbers(cells: np.ndarray, first: int, source: str, first_field: int = 1) -> np.ndarray:
    """Text fields (rows from line ``first`` + 1, columns from field ``first_field``) as finite floats."""
    try:
        values = cells.astype(float)
    except ValueError:
        values = None
    if values is None or not np.isfinite(values).all():
        bad = np.array([not _is_finite_text(cell) for cell in cells.ravel()]).reshape(cells.shape)
        i, j = (int(index) for index in np.argwhere(bad)[0])
        raise InputError(f"expected a finite number in field {j + first_field}, got {reprlib.repr(str(cells[i, j]))}",
                         source, f"line {first + i + 1}")
    return values


def _is_finite_text(text: str) -> bool:
    try:
        return math.isfinite(float(text))
    except ValueError:
        return False


def _text_ids(cells: np.ndarray, first: int, source: str) -> np.ndarray:
    """Text fields (one per row, from line ``first`` + 1) as 64-bit integers."""
    try:
        return cells.astype(np.int64)
    except (ValueError, OverflowError):
        bad = next(i for i, cell in enumerate(cells.tolist())
                   if not re.fullmatch(r"[-+]?[0-9]+", cell) or abs(int(cell)) >= 2**63)
        raise InputError(f"expected an integer id in field 1, got {reprlib.repr(str(cells[bad]))}", source,
                         f"line {first + bad + 1}") from None


def _linearslam_layout(ids: np.ndarray, start_id: int, source: str) -> tuple[np.ndarray, np.ndarray, int]:
    """Rows of the end pose (three, consecutive, one id -k), rows of the features (x then y per id), and k."""
    pose = np.flatnonzero(ids < 0)
    if pose.size != 3 or pose[2] != pose[0] + 2 or (ids[pose] != ids[pose[0]]).any():
        got = ", ".join(f"{ids[row]} on line {row + 3}" for row in pose[:4]) or "none"
        raise InputError("expected one end pose: three consecutive rows with the same negative id -k; got "
                         f"negative ids {got}", source, f"line {(pose[0] if pose.size else 0) + 3}")
    end_id = -int(ids[pose[0]])
    if end_id == start_id:
        raise InputError(f"the end pose id {end_id} (rows with id {-end_id}) equals the reference pose index "
                         "on line 1", source, f"line {pose[0] + 3}")
    features = np.delete(np.arange(len(ids)), pose)
    x, y = features[0::2], features[1::2]
    split = np.flatnonzero(ids[x] != ids[y])
    if split.size:
        i = split[0]
        raise InputError(f"expected the y row of feature {ids[x[i]]} (x on line {x[i] + 3}), got id {ids[y[i]]}",
                         source, f"line {y[i] + 3}")
    duplicate = first_duplicate(ids[x])
    if duplicate is not None:
        earlier = x[np.flatnonzero(ids[x] == ids[x[duplicate]])[0]]
        raise InputError(f"duplicate feature id {ids[x[duplicate]]} (also on line {earlier + 3})", source,
                         f"line {x[duplicate] + 3}")
    return pose, features, end_id


def _covariance_of_information(information: np.ndarray, first: int, source: str) -> np.ndarray:
    """The inverse of an information matrix stored from line ``first`` + 1, checked symmetric positive definite."""
    excess = asymmetry(information)
    if (excess > 0).any():
        i, j = (int(index) for index in np.unravel_index(np.argmax(excess), excess.shape))
        raise InputError(f"expected a symmetric information matrix, but entries ({i + 1}, {j + 1}) and "
                         f"({j + 1}, {i + 1}) differ: {float(information[i, j])!r} vs "
                         f"{float(information[j, i])!r}", source, f"line {first + i + 1}")
    covariance, failed = _spd_inverse((information + information.T) / 2)
    if covariance is None:
        raise InputError(f"expected a positive definite information matrix; its leading {failed}x{failed} block "
                         "is not", source, f"line {first + failed}")
    return covariance


def _spd_inverse(matrix: np.ndarray) -> tuple[np.ndarray | None, int]:
    """The inverse of a symmetric positive definite matrix by Cholesky (exactly symmetric), or None and the
    order of the first leading block that is not positive definite."""
    from scipy.linalg import lapack  # only the formats that store information matrices need it

    factor, failed = lapack.dpotrf(matrix, lower=True)
    if failed:
        return None, failed
    inverse, failed = lapack.dpotri(factor, lower=True)
    if failed:
        return None, failed
    lower = np.tril(inverse)
    return lower + np.tril(lower, -1).T, 0


def _spherical_diagonal(local_map: LocalMap) -> np.ndarray:
    """The covariance diagonal a map without a full covariance stands for: x y phi, then x y per feature."""
    return np.concatenate([local_map.pose_variances[[0, 0, 1]], np.repeat(local_map.feature_variances, 2)])


def _dump_local_linearslam(maps: Sequence[LocalMap]) -> str:
    """One map as Linear SLAM text; the information matrix is the inverse of its covariance."""
    [local_map] = maps
    if local_map.end_id == 0:
        raise InputError("cannot be written as Linear SLAM text: its end pose id 0 would be the row id -0, "
                         "which reads as a feature", local_map.name)
    if local_map.size and local_map.feature_ids.min() == 0:
        log.warning("%s: feature id 0 written as Linear SLAM text (mapjoin reads it back; Linear SLAM's own code "
                    "expects positive feature ids)", local_map.name)
    if local_map.covariance is None:
        information = np.diag(1.0 / _spherical_diagonal(local_map))
    else:
        information, _ = _spd_inverse(local_map.covariance)
    if information is None or not np.isfinite(information).all():
        raise InputError("the covariance is numerically singular, so it has no finite information matrix",
                         local_map.name, "covariance")
    ids = np.concatenate([np.full(3, -local_map.end_id), np.repeat(local_map.feature_ids, 2)])
    values = np.concatenate([local_map.end_pose, local_map.features.ravel()])
    lines = [str(local_map.start_id), str(len(ids)),
             *(f"{i} {value!r}" for i, value in zip(ids.tolist(), values.tolist())),
             *(" ".join(map(repr, row)) for row in information.tolist())]
    return "\n".join(lines) + "\n"


def _dump_local_mat(maps: Sequence[LocalMap]) -> bytes:
    """One map as an I-SLSJF .mat file (MAT v5, little-endian, uncompressed): ``localmap_st``, ``localmap_P``."""
    [local_map] = maps
    if local_map.start_id != local_map.end_id - 1:
        raise InputError("cannot be written as an I-SLSJF .mat file, which holds map k from pose k-1 to pose k; "
                         f"this map runs from pose {local_map.start_id} to {local_map.end_id} (use yaml or "
                         "linearslam)", local_map.name)
    if local_map.size and local_map.feature_ids.max() >= 2**53:
        raise InputError(f"feature id {local_map.feature_ids.max()} is not exact as a double (2^53 or more), "
                         "so it cannot be written to a .mat file", local_map.name)
    covariance = (np.diag(_spherical_diagonal(local_map)) if local_map.covariance is None
                  else local_map.covariance)
    if covariance.diagonal()[:3].min() < STAB_NOISE:
        log.warning("%s: an end-pose variance is below %g; reading the .mat file back adds %g to the pose "
                    "diagonal, as I-SLSJF does", local_map.name, STAB_NOISE, STAB_NOISE)
    ids = np.concatenate([np.zeros(3), np.repeat(local_map.feature_ids, 2)])
    state = np.column_stack([ids, np.concatenate([local_map.end_pose, local_map.features.ravel()])])
    return _MAT_HEADER + _mat_double_array("localmap_st", state) + _mat_double_array("localmap_P", covariance)


def _mat_double_array(name: str, value: np.ndarray) -> bytes:
    """A real double matrix variable: one miMATRIX element of flags, dimensions, name, column-major data."""
    return _mat_element(_MI_MATRIX, _mat_element(_MI_UINT32, struct.pack("<II", _MX_DOUBLE, 0))
                        + _mat_element(_MI_INT32, struct.pack("<ii", *value.shape))
                        + _mat_element(_MI_INT8, name.encode("ascii"))
                        + _mat_element(_MI_DOUBLE, np.asarray(value, "<f8").tobytes(order="F")))


def _mat_element(kind: int, data: bytes) -> bytes:
    """A MAT v5 data element: tag (type, byte count), data, zeros up to a multiple of 8 bytes."""
    return struct.pack("<II", kind, len(data)) + data + bytes(-len(data) % 8)


def _dump_global_g2o(global_map: GlobalMap) -> str:
    """``VERTEX_SE2 id x y phi`` per end pose (its id), ``VERTEX_XY id x y`` per feature (its id plus
    :func:`g2o_feature_offset`), after a comment stating the mapping."""
    offset = g2o_feature_offset(global_map.pose_ids)
    largest = max(int(np.max(global_map.pose_ids, initial=0)), int(np.max(global_map.feature_ids, initial=-1)) + offset)
    if largest > _G2O_MAX_ID:
        raise InputError(f"vertex id {largest} does not fit g2o's 32-bit ids (feature ids are offset by {offset})",
                         global_map.name)
    return "\n".join([
        (f"# mapjoin global map: VERTEX_SE2 <pose id> x y phi per end pose, VERTEX_XY <feature id + {offset}> x y "
         "per feature"),
        *(f"VERTEX_SE2 {i} {x!r} {y!r} {phi!r}" for i, (x, y, phi) in zip(global_map.pose_ids.tolist(),
                                                                           global_map.poses.tolist())),
        *(f"VERTEX_XY {i + offset} {x!r} {y!r}" for i, (x, y) in zip(global_map.feature_ids.tolist(),
                                                                      global_map.features.tolist())),
    ]) + "\n"



# ---------------------------------------------------------------------------------------
# Registries: format name -> codec


_LOCAL_MAP_CODECS: dict[str, _Codec] = {
    "yaml": _Codec(_read_local_yaml, _dump_local_yaml),
    "csv": _Codec(_read_local_csv, _dump_local_csv, spherical_only=True),
    "mat": _Codec(_read_local_mat, _dump_local_mat, binary=True, one_per_file=True),
    "linearslam": _Codec(_read_local_linearslam, _dump_local_linearslam, one_per_file=True),
}
_GLOBAL_MAP_CODECS: dict[str, _Codec] = {
    "csv": _Codec(_read_global_csv, _dump_global_csv),
    "yaml": _Codec(_read_global_yaml, _dump_global_yaml),
    "g2o": _Codec(None, _dump_global_g2o),
}
_TRUTH_CODECS: dict[str, _Codec] = {
    "csv": _Codec(_read_truth_csv, _dump_truth_csv),
    "yaml": _Codec(_read_truth_yaml, _dump_truth_yaml),
}
_TABLE_CODECS: dict[str, _Codec] = {
    "csv": _Codec(None, _dump_table_csv),
    "yaml": _Codec(None, _dump_table_yaml),
    "json": _Codec(None, _dump_table_json),
}
