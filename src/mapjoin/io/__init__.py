"""Every file mapjoin reads or writes: local maps, global maps, ground truth, tables.

Sources are paths, open text streams (e.g. ``io.StringIO``) or ``"-"`` for stdin; targets
are paths, text streams or ``"-"`` for stdout. Files are written atomically, never over an
input, and a symbolic link is written through (:mod:`.outputs`). Bad input raises
:class:`~mapjoin.errors.InputError` naming the file (or ``<stdin>``), the line or field, and
what was expected. Floats are written with ``repr``
precision, so every text format round-trips exactly. CSV is standard CSV (quoted where
needed, LF line ends); CRLF line ends and a UTF-8 byte-order mark are accepted on reading.

The format comes from the ``format`` argument or the extension (:mod:`.registry` lists
them); a stream without a format is recognised by its start (YAML, CSV with a ``kind``
column, Linear SLAM text). The formats, one module each: :mod:`.yaml_maps`,
:mod:`.csv_maps`, :mod:`.mat_maps` (I-SLSJF), :mod:`.linearslam` (local maps);
:mod:`.global_maps` (global maps and ground truth, YAML and CSV), :mod:`.g2o` (global map
export); :mod:`.tables` (reports, minima tables); :mod:`.trajectory` (the trajectory: TUM,
CSV, JSON). Beside them: :mod:`.paths` (reading
files and streams), :mod:`.outputs` (writing: checked up front, all or nothing), :mod:`.inputs` (input arguments to files), :mod:`.yamldoc`
and :mod:`.csvtable` (the YAML and CSV layers), :mod:`.fields` (what a person may add to or
leave out of a local map), :mod:`.matfile` (MAT v5), :mod:`.truth`
(I-SLSJF simulation folders).

A format module provides, for each kind of data it holds, ``read(text, source)`` (bytes for
a binary format; ``source`` names the file in errors) and/or ``dump(data) -> str | bytes``,
optionally a ``read_files(paths)`` reading many files at once, and ``looks_like_...(text)``
when a stream can be recognised; :data:`.registry.FORMATS` gets one line naming them.

Local maps are read one at a time by :func:`iter_maps` (which :func:`read_maps` lists): a YAML
file or stream is read line by line (:mod:`.lines`), document by document, so its length costs
no memory beyond the maps kept.

Map names: a local map read from a file is named after the file, so that messages and
provenance point to it: the path when the file holds one map, else ``path#name`` with the
map's own name (``name``, ``map``), or ``path#n`` (its position) when it has none; maps
from stdin are named ``<stdin>`` likewise. Writers store each map's name.
"""

from __future__ import annotations

import importlib
import logging
import os
import sys
from collections.abc import Iterable, Iterator, Sequence
from itertools import chain
from typing import TYPE_CHECKING, Any, TextIO

import numpy as np

from ..errors import InputError, counted
from ..maps import Correspondence, GlobalMap, GroundTruth, LocalMap, first_duplicate, marginal_variances
from . import registry
from .inputs import resolve_inputs
from .lines import text_lines
from .outputs import Outputs, Parts, check_not_overwriting, is_special, transaction, write_output
from .paths import STDIN, Source, is_path, read_file, read_once, read_text, source_name
from .registry import MAP_FORMATS, TABLE_FORMATS, Codec, Format, Kind, detect_format, map_file_name

if TYPE_CHECKING:
    from .tables import MinimaTable

__all__ = [
    "MAP_FORMATS",
    "STAB_NOISE",
    "TABLE_FORMATS",
    "MinimaTable",
    "Trajectory",
    "Outputs",
    "check_not_overwriting",
    "detect_format",
    "is_special",
    "g2o_feature_offset",
    "iter_map_paths",
    "iter_maps",
    "map_file_name",
    "read_global_map",
    "read_map_file",
    "read_map_paths",
    "read_maps",
    "read_correspondence",
    "read_minima_table",
    "read_once",
    "read_truth",
    "read_truth_folder",
    "resolve_inputs",
    "write_global_map",
    "write_map_stream",
    "write_maps",
    "write_table",
    "write_output",
    "write_trajectory",
    "write_truth",
]

#: names of this package that live in a format's module, imported when first asked for (:func:`__getattr__`)
_FROM_FORMATS = {"STAB_NOISE": "mat_maps", "MinimaTable": "tables", "Trajectory": "trajectory",
                 "g2o_feature_offset": "g2o", "read_truth_folder": "truth"}


def __getattr__(name: str) -> Any:
    """:data:`_FROM_FORMATS`' names, their module imported on first use (PEP 562): reading and writing local and
    global maps needs none of those modules."""
    if name not in _FROM_FORMATS:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(f".{_FROM_FORMATS[name]}", __name__), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))


log = logging.getLogger("mapjoin")

_TRUTH_FILES = ("truth.yaml", "truth.yml", "truth.csv")  # what `mapjoin simulate` writes into its folder


def read_maps(inputs: str | os.PathLike | Sequence[str | os.PathLike], *, stdin: TextIO | None = None,
              format: str | None = None) -> list[LocalMap]:
    """All local maps of one input or a list of inputs (see :func:`resolve_inputs`: files, globs, folders),
    in order; ``-`` reads ``stdin`` once.

    ``format`` is for the inputs whose names do not tell it (stdin, unknown extensions), so
    e.g. a folder of .mat files and CSV on stdin can be read together. Consecutive files of a
    format that reads many files at once (an I-SLSJF folder of thousands of .mat files) are
    parsed and checked together, with the errors and warnings of reading them one by one.
    """
    return list(iter_maps(inputs, stdin=stdin, format=format))


def iter_maps(inputs: str | os.PathLike | Sequence[str | os.PathLike], *, stdin: TextIO | None = None,
              format: str | None = None) -> Iterator[LocalMap]:
    """:func:`read_maps` one map at a time: a YAML stream (a file or stdin) is read document by document, so
    reading it takes the memory of one document beside the maps the caller keeps."""
    if isinstance(inputs, (str, os.PathLike)):
        inputs = [inputs]
    return iter_map_paths(resolve_inputs([os.fspath(path) for path in inputs]), stdin=stdin, format=format)


def read_map_paths(paths: Sequence[str], *, stdin: TextIO | None = None, format: str | None = None
                   ) -> list[LocalMap]:
    """:func:`read_maps` of inputs that :func:`resolve_inputs` has already resolved (commands resolve
    them first to check their outputs against them; resolving again would stat every file twice)."""
    return list(iter_map_paths(paths, stdin=stdin, format=format))


def iter_map_paths(paths: Sequence[str], *, stdin: TextIO | None = None, format: str | None = None
                   ) -> Iterator[LocalMap]:
    """:func:`read_map_paths` one map at a time (:func:`iter_maps`)."""
    if paths.count(STDIN) > 1:
        raise InputError("stdin (-) is given more than once; it can be read only once", "<stdin>")
    runs: list[tuple[Codec | None, list[str]]] = []  # (codec, consecutive files it reads at once) or (None, [file])
    for path in paths:
        codec = _batch_codec(path, format)
        if codec is not None and runs and runs[-1][0] is codec:
            runs[-1][1].append(path)
        else:
            runs.append((codec, [path]))
    for codec, run in runs:
        if codec is not None:
            yield from codec.read_files(run)
        elif run[0] == STDIN:
            yield from iter_map_file(stdin or sys.stdin, format, name="<stdin>")
        else:
            yield from iter_map_file(run[0], None if registry.extension_format(run[0]) else format)


def _batch_codec(path: str, format: str | None) -> Codec | None:
    """The local-map codec of ``path``'s format (its extension's, else ``format``, else its name's:
    ``localmap_<k>.txt``) if it reads many files at once."""
    fmt = registry.extension_format(path) or format or registry.named_format(path)
    if path == STDIN or fmt not in registry.by_name:
        return None
    codec = registry.by_name[fmt].local_maps
    return codec if codec is not None and codec.read_files is not None else None


def read_map_file(source: Source, format: str | None = None, name: str | None = None) -> list[LocalMap]:
    """The local maps of one file or stream (a YAML or CSV file may hold several)."""
    return list(iter_map_file(source, format, name))


def iter_map_file(source: Source, format: str | None = None, name: str | None = None) -> Iterator[LocalMap]:
    """:func:`read_map_file` one map at a time: a format that reads lines (YAML) reads the file or stream
    line by line, yielding each map as soon as it is read."""
    name = name or source_name(source)
    if is_path(source):
        fmt, codec = registry.codec(detect_format(os.fspath(source), format), registry.LOCAL_MAPS, name)
        lines = None if fmt.binary or codec.read_lines is None else text_lines(source, name)
    else:
        lines = text_lines(source, name)
        head = _head_lines(lines)
        fmt, codec = registry.codec(detect_format(name, format) if format else registry.sniff("".join(head), name),
                                    registry.LOCAL_MAPS, name)
        if fmt.binary:
            raise InputError(f"a {fmt.extensions[0]} file cannot be read from a text stream; give its path", name)
        lines = chain(head, lines)
    if lines is None:
        maps = iter(codec.read(read_file(os.fspath(source), name, fmt.binary), name))
    elif codec.read_lines is not None:
        maps = codec.read_lines(lines, name)
    else:
        maps = iter(codec.read("".join(lines), name))
    first = next(maps, None)
    if first is None:
        raise InputError("expected at least one local map, found none", name)
    yield first
    yield from maps


def _head_lines(lines: Iterator[str]) -> list[str]:
    """The first lines of a stream, enough to tell its format (:func:`registry.sniff`): up to its third
    line that is not blank."""
    head: list[str] = []
    for line in lines:
        head.append(line)
        if sum(not text.isspace() for text in head) >= 3:
            break
    return head


def write_maps(maps: Sequence[LocalMap], target: Source, format: str, *, covariances: bool = True) -> list[str]:
    """Write ``maps`` as ``format`` and return the paths written (none for a stream); ``covariances=False``
    writes their spherical variances only (smaller files; one warning says how many covariances were dropped).

    A folder target (an existing folder, or a path ending in ``/``, created if its parent exists) gets
    one file per map, :func:`map_file_name`; a file path or stream gets one stream, which
    for a format of one map per file (``mat``, ``linearslam``) must hold one map (a .mat
    file's name must end in its end id).
    """
    name = source_name(target, "<stdout>")
    fmt, codec = registry.codec(detect_format(name, format), registry.LOCAL_MAPS, name, writing=True)
    if not covariances:
        maps = _spherical(maps)
    if fmt.covariance_only:
        _warn_dropped_variances(maps, fmt)
    if isinstance(target, (str, os.PathLike)) and (
            os.path.isdir(target) or os.fspath(target).endswith(("/", os.sep))):
        return _write_map_folder(maps, os.fspath(target), fmt, codec)
    if fmt.one_map_per_file:
        _check_single_map_file(maps, target, fmt)
    return _write(fmt, codec.dump(maps), target)


def _spherical(maps: Sequence[LocalMap]) -> list[LocalMap]:
    """The maps without their full covariances (already checked: not checked again), with one warning."""
    _warn_dropped_covariances(sum(local_map.covariance is not None for local_map in maps))
    return _without_covariances(maps)


def _warn_dropped_covariances(dropped: int) -> None:
    if dropped:
        log.warning("dropped the full covariances of %s as asked: only their spherical variances are "
                    "written", counted(dropped, "map"))


def _without_covariances(maps: Sequence[LocalMap]) -> list[LocalMap]:
    return [local_map if local_map.covariance is None else
            LocalMap(*(getattr(local_map, key) for key in _LOCAL_MAP_FIELDS), None, checked=True)
            for local_map in maps]


_LOCAL_MAP_FIELDS = ("name", "start_id", "end_id", "end_pose", "feature_ids", "features", "feature_variances",
                     "pose_variances")


def write_map_stream(chunks: Iterable[Sequence[LocalMap]], target: Source, format: str, *,
                     covariances: bool = True) -> list[str]:
    """:func:`write_maps` of maps given a chunk at a time, to one file or stream (YAML or CSV): each chunk is
    encoded as it is written (:class:`.outputs.Parts`), so a run of any length is written with the memory of
    a chunk. The text is the one :func:`write_maps` writes for all the maps at once."""
    name = source_name(target, "<stdout>")
    fmt, codec = registry.codec(detect_format(name, format), registry.LOCAL_MAPS, name, writing=True)
    if fmt.one_map_per_file or fmt.binary:
        raise InputError(f"a {fmt.name} file holds one local map; write a stream of maps as "
                         f"{registry.extensions_text(registry.LOCAL_MAPS)}", name)
    return _write(fmt, Parts(_encoded_chunks(chunks, codec, fmt.name in _HEADED, covariances)), target)


_HEADED = frozenset({"csv"})  # formats whose text starts with a header line: written once


def _encoded_chunks(chunks: Iterable[Sequence[LocalMap]], codec: Codec, headed: bool, covariances: bool
                    ) -> Iterator[str]:
    """Each chunk's text (a headed format's header once: every chunk's must be the first's), then the warning
    for the covariances dropped (``covariances=False``)."""
    dropped, header = 0, None
    for chunk in chunks:
        if not covariances:
            dropped += sum(local_map.covariance is not None for local_map in chunk)
            chunk = _without_covariances(chunk)
        text = codec.dump(chunk)
        if headed:
            head, _, body = text.partition("\n")
            if header is None:
                header = head
            elif head != header:
                raise ValueError("the chunks' headers differ (some maps with a covariance, some without)")
            else:
                text = body
        yield text
    _warn_dropped_covariances(dropped)


def _warn_dropped_variances(maps: Sequence[LocalMap], fmt: Format) -> None:
    """One warning when ``fmt`` stores a map by its full covariance alone and some map's spherical variances
    are not the covariance's marginal ones (which reading gives back): those variances are lost."""
    dropped = [local_map.name for local_map in maps if local_map.covariance is not None
               and not _marginal(local_map)]
    if dropped:
        log.warning("%s stores a map's full covariance, not its spherical variances: the variances of %s "
                    "differ from their covariance's marginal ones, which they read back as (first: %s; the joins "
                    "use the covariance either way)", fmt.name, counted(len(dropped), "map"), dropped[0])


def _marginal(local_map: LocalMap) -> bool:
    """Whether a map's spherical variances are its covariance's marginal ones, up to rounding."""
    features, poses = marginal_variances(local_map.covariance[np.newaxis])
    return bool(np.allclose(features[0], local_map.feature_variances, rtol=1e-12, atol=0)
                and np.allclose(poses[0], local_map.pose_variances, rtol=1e-12, atol=0))


def write_global_map(global_map: GlobalMap, target: Source, format: str | None = None) -> None:
    """Write a global map as CSV, YAML or g2o (format from ``format`` or the extension)."""
    _write_data(global_map, target, format, registry.GLOBAL_MAP)


def read_global_map(source: Source, format: str | None = None) -> GlobalMap:
    """Read a global map written by :func:`write_global_map`."""
    return _read(source, format, source_name(source), registry.GLOBAL_MAP)


def write_truth(truth: GroundTruth, target: Source, format: str | None = None) -> None:
    """Write ground truth as CSV or YAML (format from ``format`` or the extension)."""
    _write_data(truth, target, format, registry.TRUTH)


def read_truth(source: Source, format: str | None = None) -> GroundTruth:
    """Ground truth: a file written by :func:`write_truth` (or ``-``, a stream), the folder ``mapjoin simulate``
    wrote it into (``truth.yaml``, ``.yml`` or ``.csv`` inside), or an I-SLSJF simulation folder
    (``store_robotTrue.mat``: :func:`read_truth_folder`)."""
    if is_path(source) and os.path.isdir(source):
        folder = os.fspath(source)
        if os.path.exists(os.path.join(folder, "store_robotTrue.mat")):
            from .truth import read_truth_folder

            return read_truth_folder(folder)
        files = [os.path.join(folder, name) for name in _TRUTH_FILES]
        source = next((path for path in files if os.path.isfile(path)), None)
        if source is None:
            raise InputError(f"holds no ground truth; expected {', '.join(_TRUTH_FILES)} (from `mapjoin "
                             "simulate`) or store_robotTrue.mat and store_beaconsTrue.mat (I-SLSJF)", folder)
    return _read(source, format, source_name(source), registry.TRUTH)


def write_table(rows: Sequence[Any], target: Source, format: str | None = None) -> None:
    """Write dataclass instances (all of one type), or mappings with the same keys, as a CSV, YAML or JSON table."""
    _write_data(rows, target, format, registry.TABLE)


def write_trajectory(global_map: GlobalMap, origin_id: int, target: Source, format: str | None = None) -> None:
    """Write the trajectory of a global map whose first map starts at pose ``origin_id`` (:class:`Trajectory`:
    the origin, then every end pose) as TUM, CSV or JSON (format from ``format`` or the extension)."""
    from .trajectory import Trajectory

    _write_data(Trajectory.of(global_map, origin_id), target, format, registry.TRAJECTORY)


def read_minima_table(source: Source) -> MinimaTable:
    """The columns ``a`` and ``c_phi`` (and ``join``, ``map``) of any table holding them: a ``join --report`` output,
    a ``check-minima --batch`` input or output.

    CSV, YAML or JSON by the extension; otherwise (``-``: stdin, ``.txt``, ...) YAML/JSON when
    the text starts with ``[``, ``{``, ``-``, ``#`` or ``%``, else CSV.
    """
    from .tables import read_minima_csv, read_minima_records

    text, name, fmt = _table_text(source, "a table with the columns a and c_phi")
    table = read_minima_csv(text, name) if fmt == "csv" else read_minima_records(text, name)
    if not len(table.a):
        raise InputError("expected at least one row with a and c_phi, found none", name)
    return table


def read_correspondence(source: Source) -> Correspondence:
    """A ``map,local_id,global_id`` table (:class:`~mapjoin.maps.Correspondence`): what ``join --associations``
    writes, or the truth ``simulate --local-ids`` writes; CSV, YAML or JSON (:func:`_table_text`)."""
    from .tables import read_correspondence_csv, read_correspondence_records

    text, name, fmt = _table_text(source, "a map,local_id,global_id table")
    return read_correspondence_csv(text, name) if fmt == "csv" else read_correspondence_records(text, name)


def _table_text(source: Source, what: str) -> tuple[str, str, str]:
    """A table's text, name and format (``csv`` or ``yaml``, which reads JSON too): by the extension, else YAML/JSON
    when the text starts with ``[``, ``{``, ``-``, ``#`` or ``%``, else CSV. Another format's extension is refused."""
    name = source_name(source)
    fmt = registry.extension_format(name)
    if fmt is not None and fmt not in TABLE_FORMATS:
        raise InputError(f"expected {what} ({registry.extensions_text(registry.TABLE)}), not {fmt}", name)
    text = read_text(source, name)
    if fmt is None:
        fmt = "yaml" if text.lstrip()[:1] in ("[", "{", "-", "#", "%") else "csv"
    return text, name, fmt


def _read(source: Source, format: str | None, name: str, kind: Kind) -> Any:
    """Read ``source`` with the codec its format (explicit, extension or sniffed) has for ``kind``."""
    if is_path(source):
        fmt, codec = registry.codec(detect_format(os.fspath(source), format), kind, name)
        return codec.read(read_file(os.fspath(source), name, fmt.binary), name)
    text = read_text(source, name)
    fmt, codec = registry.codec(detect_format(name, format) if format else registry.sniff(text, name), kind, name)
    if fmt.binary:
        raise InputError(f"a {fmt.extensions[0]} file cannot be read from a text stream; give its path", name)
    return codec.read(text, name)


def _write_data(data: Any, target: Source, format: str | None, kind: Kind) -> None:
    """Write ``data`` of ``kind`` as ``format`` (else the format the target's extension names)."""
    name = source_name(target, "<stdout>")
    fmt, codec = registry.codec(detect_format(name, format), kind, name, writing=True)
    _write(fmt, codec.dump(data), target)


def _write(fmt: Format, content: str | bytes, target: Source) -> list[str]:
    """Write ``content`` in ``fmt`` to ``target``; a binary format to a file path only."""
    if fmt.binary and not is_path(target):
        raise InputError(f"a {fmt.extensions[0]} file cannot be written to stdout or a text stream; give a file path",
                         source_name(target, "<stdout>"))
    return write_output(content, target)


def _write_map_folder(maps: Sequence[LocalMap], folder: str, fmt: Format, codec: Codec) -> list[str]:
    """One file per map, written all together or not at all (:mod:`.outputs`); every map is encoded first, so a
    map the format cannot hold writes nothing."""
    paths = [os.path.join(folder, map_file_name(local_map.end_id, fmt.name)) for local_map in maps]
    duplicate = first_duplicate(np.array([local_map.end_id for local_map in maps], dtype=np.int64))
    if duplicate is not None:
        raise InputError(f"two maps end at pose {maps[duplicate].end_id}, so both would be "
                         f"{os.path.basename(paths[duplicate])}; write them to one file instead", folder)
    contents = [codec.dump([local_map]) for local_map in maps]
    with transaction() as outputs:
        outputs.folder(folder)
        for content, path in zip(contents, paths):
            outputs.write(content, path)
    return paths


def _check_single_map_file(maps: Sequence[LocalMap], target: Source, fmt: Format) -> None:
    """A file of a one-map-per-file format holds one map, and when the format takes the map's end id from the
    file name (a .mat file: map k), the name gives it."""
    name = source_name(target, "<stdout>")
    if len(maps) != 1:
        raise InputError(f"a {fmt.name} file holds one local map, got {len(maps)}; write them to a folder "
                         "(a path ending in /), one file per map", name)
    if fmt.map_number is not None and is_path(target) and fmt.map_number(name) != maps[0].end_id:
        raise InputError(f"an {fmt.title} local map takes its number k (its end pose) from the file name; "
                         f"name this one {map_file_name(maps[0].end_id, fmt.name)}", name)
