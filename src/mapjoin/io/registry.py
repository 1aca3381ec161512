"""The one table of mapjoin's file formats, and everything derived from it.

:data:`FORMATS` says per format its name, extensions, how a stream is recognised, what it
reads and writes (local maps, a global map, ground truth, tables) and how (text or binary,
one map per file or a stream). Extension lookup, the names of local-map files in a folder,
stream sniffing, the command line's format choices and help, and every error text listing
formats are derived from it. Adding a format: one module (see :mod:`mapjoin.io`) and one
:class:`Format` line in :data:`FORMATS`.
"""

from __future__ import annotations

import importlib
import os
import re
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass
from typing import Any, NamedTuple

from ..errors import InputError
from .paths import STDIN

__all__ = ["FORMATS", "GLOBAL_MAP", "LOCAL_MAPS", "LOCAL_MAP_FILE", "MAP_FORMATS", "TABLE", "TABLE_FORMATS", "TRAJECTORY",
           "TRUTH",
           "Codec", "Format", "Kind", "by_name", "codec", "detect_format", "extension_format", "extensions_text",
           "local_map_files_text",
           "map_file_name", "named_format", "names", "sniff"]


class Codec(NamedTuple):
    """How a format reads and writes one kind of data; None where it cannot."""

    read: Callable[[Any, str], Any] | None = None  # (text, or bytes when binary; source name) -> data
    dump: Callable[[Any], str | bytes] | None = None  # data -> text, or bytes when binary
    read_files: Callable[[Sequence[str]], list[Any]] | None = None  # many files at once, as one by one, faster
    read_lines: Callable[[Iterable[str], str], Iterator[Any]] | None = None  # as read, from lines, yielding as it goes


class Kind(NamedTuple):
    """A kind of data formats hold."""

    field: str  # the Format field holding its codec
    what: str  # how messages name it
    default: str  # the format written when nothing names one (stdout); listed first


LOCAL_MAPS = Kind("local_maps", "local maps", "yaml")
GLOBAL_MAP = Kind("global_map", "a global map", "csv")
TRUTH = Kind("truth", "ground truth", "csv")
TABLE = Kind("table", "a table", "csv")
TRAJECTORY = Kind("trajectory", "a trajectory", "tum")


@dataclass(frozen=True)
class Format:
    """One file format: its names, how it is recognised, and its codec for each kind of data it holds."""

    name: str  # as --format, --to and --input-format take it
    title: str  # how messages name it
    extensions: tuple[str, ...]  # the first is the one written
    named_only: bool = False  # the extension tells the format only in a file named localmap_<k><extension>
    sniff: Callable[[str], bool] | None = None  # whether a stream's text is in this format
    sniff_text: str = ""  # what sniff looks for, for the error when no format's does match
    binary: bool = False  # bytes (files only), not text
    note: str = ""  # for command-line help: what to know when choosing it
    local_maps: Codec | None = None
    global_map: Codec | None = None
    truth: Codec | None = None
    table: Codec | None = None
    trajectory: Codec | None = None
    covariance_only: bool = False  # local maps: a map's full covariance is stored alone, not its spherical variances
    one_map_per_file: bool = False  # local maps: a file holds exactly one map
    map_number: Callable[[str], int | None] | None = None  # local maps: the end id k a file's name must give

    def codec(self, kind: Kind) -> Codec | None:
        """Its codec for ``kind``, None if it holds no such data."""
        return getattr(self, kind.field)


class _OnUse:
    """A format module's function named ``module.function`` (``"yaml_maps.read"``), the module imported on the
    first call: a command imports the readers and writers of the formats it reads and writes, not every
    format's (a join of .mat files no YAML, CSV, Linear SLAM, g2o, trajectory or table module: ~7 ms of its
    start-up; tests/test_startup.py)."""

    __slots__ = ("reference", "_function")

    def __init__(self, reference: str):
        self.reference = reference
        self._function: Callable | None = None

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        if self._function is None:
            module, name = self.reference.rsplit(".", 1)
            self._function = getattr(importlib.import_module(f"{__package__}.{module}"), name)
        return self._function(*args, **kwargs)

    def __repr__(self) -> str:
        return f"<mapjoin.io.{self.reference}, imported on use>"


def _codec(module: str, read: str | None = None, dump: str | None = None, *, read_files: str | None = None,
           read_lines: str | None = None) -> Codec:
    """The :class:`Codec` of the functions so named (``read_lines``: ``module.function`` when another module's)."""
    def on_use(name: str | None) -> _OnUse | None:
        return None if name is None else _OnUse(name if "." in name else f"{module}.{name}")
    return Codec(on_use(read), on_use(dump), on_use(read_files), on_use(read_lines))


FORMATS: tuple[Format, ...] = (
    Format("yaml", "YAML", (".yaml", ".yml"), sniff=_OnUse("yamldoc.looks_like_yaml"),
           sniff_text="YAML starting with format:, ---, %YAML or #",
           local_maps=_codec("yaml_maps", "read", "dump", read_lines="read_lines"),
           global_map=_codec("global_maps", "read_global_yaml", "dump_global_yaml"),
           truth=_codec("global_maps", "read_truth_yaml", "dump_truth_yaml"), table=_codec("tables", None, "dump_yaml")),
    Format("csv", "CSV", (".csv",), sniff=_OnUse("csvtable.names_kind_column"),
           sniff_text="a CSV header naming a kind column",
           local_maps=_codec("csv_maps", "read", "dump", read_lines="csv_blocks.read_lines"),
           global_map=_codec("global_maps", "read_global_csv", "dump_global_csv"),
           truth=_codec("global_maps", "read_truth_csv", "dump_truth_csv"), table=_codec("tables", None, "dump_csv"),
           trajectory=_codec("trajectory", None, "dump_csv")),
    Format("mat", "I-SLSJF .mat", (".mat",), binary=True,
           local_maps=_codec("mat_maps", "read", "dump", read_files="read_files"), one_map_per_file=True,
           covariance_only=True, map_number=_OnUse("mat_maps.map_number")),
    Format("linearslam", "Linear SLAM", (".txt",), named_only=True, sniff=_OnUse("linearslam.looks_like_linearslam"),
           sniff_text="Linear SLAM text", local_maps=_codec("linearslam", "read", "dump", read_files="read_files"),
           one_map_per_file=True, covariance_only=True),
    Format("json", "JSON", (".json",), sniff=_OnUse("global_maps.looks_like_json"), sniff_text="JSON starting with {",
           table=_codec("tables", None, "dump_json"),
           global_map=_codec("global_maps", "read_global_yaml", "dump_global_json"),  # JSON is read as YAML
           trajectory=_codec("trajectory", None, "dump_json")),
    Format("tum", "TUM trajectory", (".tum",), note="timestamp (the pose id) tx ty tz qx qy qz qw, as evo reads it",
           trajectory=_codec("trajectory", None, "dump_tum")),
    Format("g2o", "g2o", (".g2o",), note="VERTEX_SE2 poses and VERTEX_XY features, for g2o's viewer or GTSAM",
           global_map=_codec("g2o", None, "dump")),
)

by_name: dict[str, Format] = {fmt.name: fmt for fmt in FORMATS}
_EXTENSIONS = {extension: fmt.name for fmt in FORMATS if not fmt.named_only for extension in fmt.extensions}
_MAP_STEM = "localmap_"
_NAMED_FILES = [(re.compile(rf"{_MAP_STEM}[0-9]+{re.escape(extension)}", re.IGNORECASE), fmt)
                for fmt in FORMATS if fmt.named_only for extension in fmt.extensions]
#: the files a folder of local maps holds: ``localmap_<k>`` and a local-map format's extension (k: group 1)
LOCAL_MAP_FILE = re.compile(rf"{_MAP_STEM}([0-9]+)(?:"
                            + "|".join(re.escape(extension) for fmt in FORMATS if fmt.local_maps
                                       for extension in fmt.extensions) + ")", re.IGNORECASE)


def names(kind: Kind, *, writing: bool = False) -> tuple[str, ...]:
    """The formats that read (``writing``: write) ``kind``: its default first, then in :data:`FORMATS` order."""
    usable = [fmt.name for fmt in FORMATS if (codec := fmt.codec(kind)) and (codec.dump if writing else codec.read)]
    return tuple(sorted(usable, key=lambda name: name != kind.default))


MAP_FORMATS: tuple[str, ...] = names(LOCAL_MAPS)
TABLE_FORMATS: tuple[str, ...] = names(TABLE, writing=True)


def _or(items: Sequence[str]) -> str:
    """``a, b or c``."""
    return " or ".join([", ".join(items[:-1]), items[-1]] if len(items) > 1 else items)


def extensions_text(kind: Kind, *, writing: bool = True) -> str:
    """The extensions of the formats that write (or read) ``kind``, e.g. ``.csv, .yaml or .g2o``."""
    return _or([by_name[name].extensions[0] for name in names(kind, writing=writing)])


def local_map_files_text() -> str:
    """The names of local-map files in a folder, e.g. ``localmap_<k>.yaml, .yml, ... or .txt (Linear SLAM)``."""
    return _MAP_STEM + "<k>" + _or([extension + (f" ({fmt.title})" if fmt.named_only else "")
                                    for fmt in FORMATS if fmt.local_maps for extension in fmt.extensions])


def map_file_name(end_id: int, fmt: str) -> str:
    """The name of the file a folder holds the map ending at pose ``end_id`` in, e.g. ``localmap_7.txt``."""
    return f"{_MAP_STEM}{end_id}{by_name[fmt].extensions[0]}"


def detect_format(path_or_name: str, explicit: str | None = None) -> str:
    """``explicit`` if given (checked against the known formats), else the format its extension names.

    A ``.txt`` file is a Linear SLAM local map when named ``localmap_<k>.txt``, as Linear SLAM
    names them; other ``.txt`` files need ``explicit``.
    """
    name = "<stdin>" if path_or_name == STDIN else str(path_or_name)
    if explicit is not None:
        if explicit not in by_name:
            raise InputError(f"unknown format {explicit!r}; expected one of {', '.join(by_name)}", name)
        return explicit
    named = named_format(name)
    if named is not None:
        return named
    suffix = os.path.splitext(name)[1].lower()
    if suffix not in _EXTENSIONS:
        got = f"the extension {suffix!r}" if suffix else "no extension"
        named_files = "".join(f", a {fmt.title} {_MAP_STEM}<k>{extension}" for _, fmt in _NAMED_FILES
                              for extension in fmt.extensions)
        raise InputError(f"cannot tell the format from {got}; expected one of {', '.join(_EXTENSIONS)}{named_files}, "
                         "or ", name, argument="format")
    return _EXTENSIONS[suffix]


def extension_format(name: str) -> str | None:
    """The format the extension of ``name`` alone names, if any."""
    return _EXTENSIONS.get(os.path.splitext(name)[1].lower())


def named_format(name: str) -> str | None:
    """The format a file named ``localmap_<k><extension>`` is in when its extension alone does not tell it
    (``.txt``: Linear SLAM), if any."""
    return next((fmt.name for pattern, fmt in _NAMED_FILES if pattern.fullmatch(os.path.basename(name))), None)


def sniff(text: str, name: str) -> str:
    """The format of a stream, from its text (the first format whose ``sniff`` says yes). An empty stream is
    said to be empty: no format would read anything from it, so naming one is no remedy."""
    if not text.strip():
        raise InputError("is empty", name)
    found = next((fmt.name for fmt in FORMATS if fmt.sniff and fmt.sniff(text)), None)
    if found is None:
        expected = [fmt.sniff_text for fmt in FORMATS if fmt.sniff]
        raise InputError(f"cannot tell the format (expected {', '.join(expected[:-1])}, or {expected[-1]}); ", name,
                         argument="format")
    return found


def codec(fmt: str, kind: Kind, name: str, *, writing: bool = False) -> tuple[Format, Codec]:
    """The format ``fmt`` and its codec for ``kind``; InputError if it cannot hold it (or cannot write it)."""
    usable = names(kind, writing=writing)
    if fmt not in usable:
        raise InputError(f"cannot {'write' if writing else 'read'} {kind.what} as {fmt}; expected one of "
                         f"{', '.join(usable)}", name)
    return by_name[fmt], by_name[fmt].codec(kind)
