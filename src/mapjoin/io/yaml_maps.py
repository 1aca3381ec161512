"""YAML local maps: one map per document, any number of documents per file.

::

    format: mapjoin/local-map
    version: 1
    name: map-7                    # optional (see "Map names" in mapjoin.io)
    start_id: 6
    end_id: 7
    end_pose: {x: 1.5, y: -0.25, phi: 0.1, var_xy: 0.01, var_phi: 0.001}
    features:
    - {id: 12, x: 3.0, y: 4.0, var: 0.02}
    covariance: [[...], ...]       # optional: full (3+2m)x(3+2m), order x y phi f1x f1y f2x ...

Units: metres and radians; ``var`` and ``var_xy`` are the variance sigma^2 (m^2) of each of x and y
(the covariance sigma^2 I_2), ``var_phi`` the heading's (rad^2). With ``covariance`` the variances may
be left out (they are then its marginal ones); given both, the covariance wins (every covariance mode
and the refinement use it; the variances are kept as written). Fields mapjoin does not know are
ignored, with one warning per file naming them; a near miss of a known field (``covarience``)
is an error, as is a missing ``format`` (it says what to write). Numbers like ``1e-6`` (no dot)
are read as numbers.

Documents laid out exactly as :func:`dump` writes them are parsed without PyYAML (regular
expressions check the layout, ``float`` reads the numbers: the values PyYAML gives) and then
checked by the same :class:`~mapjoin.io.yamldoc.Document` getters; any other document, and
any document with an error to report, is parsed by PyYAML with lines, so errors name them.
"""

from __future__ import annotations

import io
import re
from collections.abc import Iterable, Iterator, Sequence
from typing import Any

import numpy as np

from ..errors import InputError
from ..maps import LocalMap, marginal_variances
from . import yamldoc
from .fields import filled_variances, warn_ignored
from .numbers import lower_matrix, mirrored_lower
from .paths import map_name

__all__ = ["dump", "read", "read_lines"]

_FORMAT = "mapjoin/local-map"
_KEYS = ("format", "version", "name", "start_id", "end_id", "end_pose", "features", "covariance")
_END_POSE_FIELDS = {"x": "number", "y": "number", "phi": "number", "var_xy": "variance", "var_phi": "variance"}
_FEATURE_FIELDS = {"id": "id", "x": "number", "y": "number", "var": "variance"}
_VARIANCES = ("var", "var_xy", "var_phi")  # may be left out when the map has a covariance


_ID = r"(?:0|[1-9][0-9]*)"  # YAML 1.1 reads 012 as octal: not here
_FLOAT = yamldoc.PLAIN_FLOAT
_NAME = re.compile(r"(?:\.\.?/|[A-Za-z/<_])[A-Za-z0-9_./<>#+-]*")  # plain scalars YAML reads as this string,
_RESOLVED = frozenset({"yes", "no", "true", "false", "on", "off", "null", "<<"})  # unless one of these (lower case)
_FAST_HEAD = re.compile(
    rf"(?:---\n)?format: {_FORMAT}\nversion: 1\n(?:name: ([^\n]*)\n)?start_id: ({_ID})\nend_id: ({_ID})\n"
    rf"end_pose: \{{x: ({_FLOAT}), y: ({_FLOAT}), phi: ({_FLOAT}), var_xy: ({_FLOAT}), var_phi: ({_FLOAT})\}}\n"
    r"features:(?: (\[\])\n|\n)")
_FAST_FEATURES = re.compile(rf"(?:- \{{id: {_ID}, x: {_FLOAT}, y: {_FLOAT}, var: {_FLOAT}\}}\n)+")
_FEATURE_SEPARATORS = re.compile(r"\}\n- \{id: |, x: |, y: |, var: ")
_COVARIANCE_HEAD, _ROW_BREAK, _COVARIANCE_END = "covariance:\n- [", "]\n- [", "]\n"


def read(text: str, source: str) -> list[LocalMap]:
    """The local maps of a YAML stream, one per document."""
    return list(read_lines(io.StringIO(text, newline=""), source))


def read_lines(lines: Iterable[str], source: str) -> Iterator[LocalMap]:
    """The local maps of a YAML stream given line by line, one per document, each as soon as it is read
    (and the next document's start, which says whether the first map is numbered: "Map names" in mapjoin.io)."""
    pending: tuple[yamldoc.Document, str] | None = None  # read, not yet made a map
    number = 0
    ignored: list[str] = []  # the unknown fields warned about (once per stream)
    for first_line, text in yamldoc.split_documents(lines):
        for document in _documents(text, source, first_line):
            number += 1
            if pending is not None:
                yield _local_map(*pending, number - 1, ignored)
            pending = document, text
    if pending is not None:
        yield _local_map(*pending, None if number == 1 else number, ignored)


def _documents(text: str, source: str, first_line: int) -> list[yamldoc.Document]:
    """The document(s) of one text of :func:`yamldoc.split_documents`: parsed by :func:`_fast_document` if it can."""
    data = _fast_document(text)
    if data is None:
        return yamldoc.documents(text, source, first_line)
    return [yamldoc.Document(data, None, source, first_line)]


def _local_map(document: yamldoc.Document, text: str, number: int | None, ignored: list[str]) -> LocalMap:
    """The local map of ``document`` (parsed from ``text``); when a fast-parsed one has an error to report,
    it is parsed again with lines, to report it naming its line. Unknown fields not in ``ignored`` yet are
    warned about and added."""
    try:
        local_map = _local_map_from_yaml(document, number)
    except yamldoc.NeedsLines:
        [document] = yamldoc.documents(text, document.source, document.first_line)
        local_map = _local_map_from_yaml(document, number)
    new = [field for field in dict.fromkeys(document.ignored or ()) if field not in ignored]
    if new:
        warn_ignored(document.source, "field", new)
        ignored.extend(new)
    return local_map


def _fast_document(text: str) -> dict[str, Any] | None:
    """The data of a document laid out exactly as :func:`dump` writes it, read without PyYAML, with the
    features as :class:`yamldoc.Columns` and the covariance as an array; None for any other text."""
    head = _FAST_HEAD.match(text)
    if head is None:
        return None
    name, start_id, end_id, *pose, no_features = head.groups()
    if name is not None:
        name = name if _NAME.fullmatch(name) and name.lower() not in _RESOLVED else yamldoc.one_line_string(name)
        if name is None:
            return None
    end = head.end()
    if no_features:
        tokens: list[str] = []
    else:
        block = _FAST_FEATURES.match(text, end)
        if block is None:
            return None
        end = block.end()
        tokens = _FEATURE_SEPARATORS.split(text[head.end() + len("- {id: "):end - len("}\n")])
    try:
        ids = np.array(list(map(int, tokens[0::4])), dtype=np.int64)
    except OverflowError:
        return None
    data: dict[str, Any] = {
        "format": _FORMAT, "version": 1, **({"name": name} if name is not None else {}),
        "start_id": int(start_id), "end_id": int(end_id), "end_pose": dict(zip(_END_POSE_FIELDS, map(float, pose))),
        "features": yamldoc.Columns(id=ids, x=_floats(tokens[1::4]), y=_floats(tokens[2::4]),
                                    var=_floats(tokens[3::4]))}
    if end < len(text):
        covariance = _fast_covariance(text[end:], 3 + 2 * len(ids))
        if covariance is None:
            return None
        data["covariance"] = covariance
    return data


def _fast_covariance(text: str, size: int) -> np.ndarray | None:
    """The covariance of a document's last lines ``text`` laid out as :func:`dump` writes it
    (``covariance:``, then ``size`` rows ``- [a, b, ...]`` of ``size`` numbers, mirroring themselves across
    the diagonal as a symmetric matrix's do), or None.

    Rows are split at ``]\\n- [``; only the lower triangle is split at ``, ``, the rest compared as
    text (:func:`.numbers.mirrored_lower`); its numbers are checked by :func:`_yaml_floats`, together,
    in C, and read.
    """
    if not (text.startswith(_COVARIANCE_HEAD) and text.endswith(_COVARIANCE_END)):
        return None
    lower = mirrored_lower(text[len(_COVARIANCE_HEAD):-len(_COVARIANCE_END)].split(_ROW_BREAK), ", ", size)
    return None if lower is None or not _yaml_floats(lower) else lower_matrix(lower, size)


def _yaml_floats(tokens: Sequence[str]) -> bool:
    """Whether number tokens are floats that mapjoin's YAML loader reads as ``float`` does, if ``float`` reads
    them (the caller's try): checked on their concatenation, by characters and counts, not token by token.

    Only ``[-+0-9.eE]`` (so no separator, blank or bracket hides in a token), one point per token
    (``float`` reads none with two) and none right after a sign. What ``float`` reads of these is
    ``[-+]?[0-9]+\\.[0-9]*`` or ``\\.[0-9]+``, then an optional exponent ``[eE][-+]?[0-9]+``: YAML
    floats, also to PyYAML's resolver with mapjoin's for exponents (:mod:`.yamldoc`). Left to PyYAML:
    integers (ints to it, ``08`` a string), ``-.5`` (a string), ``.inf``.
    """
    joined = "".join(tokens)
    return (joined.isascii() and not joined.encode().translate(None, b"0123456789.eE+-")
            and joined.count(".") == len(tokens) and "-." not in joined and "+." not in joined)


def _floats(tokens: Sequence[str]) -> np.ndarray:
    """Number tokens as PyYAML's loader reads them here (:data:`yamldoc.PLAIN_FLOAT`: ``float``)."""
    return np.fromiter(map(float, tokens), dtype=float, count=len(tokens))


def _local_map_from_yaml(document: yamldoc.Document, number: int | None) -> LocalMap:
    """The local map of one document (``number``: its position in a stream of several, else None). Unknown
    fields are collected in ``document.ignored``; the variances may be left out when ``covariance`` is given
    (:mod:`.fields`)."""
    document.ignored = []
    document.header(_FORMAT, _KEYS)
    name = map_name(document.source, document.get(("name",), "text", optional=True), number)
    start_id, end_id = (document.get((key,), "id") for key in ("start_id", "end_id"))
    pose = document.record(("end_pose",), _END_POSE_FIELDS, optional=_VARIANCES)
    features = document.records(("features",), _FEATURE_FIELDS, optional=_VARIANCES)
    size = 3 + 2 * len(features["id"])
    covariance = document.matrix(("covariance",), (size, size), optional=True)
    pose_variances = np.array([np.nan if pose[key] is None else pose[key] for key in ("var_xy", "var_phi")], dtype=float)
    feature_variances = features["var"]
    if covariance is None:
        _require_variances(document, pose_variances, feature_variances)
    elif np.isnan(pose_variances).any() or np.isnan(feature_variances).any():
        marginal_features, marginal_pose = marginal_variances(covariance[np.newaxis])
        pose_variances = filled_variances(pose_variances, marginal_pose[0])
        feature_variances = filled_variances(feature_variances, marginal_features[0])
    try:
        return LocalMap(name, start_id, end_id,
                        [pose["x"], pose["y"], pose["phi"]], features["id"], yamldoc.stack(features, "x", "y"),
                        feature_variances, pose_variances, covariance)
    except InputError as error:
        raise document.relocated(error) from None


def _require_variances(document: yamldoc.Document, pose_variances: np.ndarray, feature_variances: np.ndarray) -> None:
    """Without a covariance every variance must be given: the error names the first left out."""
    missing = np.flatnonzero(np.isnan(pose_variances))
    path: tuple[str | int, ...] | None = ("end_pose", ("var_xy", "var_phi")[missing[0]]) if missing.size else None
    if path is None and np.isnan(feature_variances).any():
        path = ("features", int(np.argmax(np.isnan(feature_variances))), "var")
    if path is not None:
        raise document.error(path, "missing; expected a positive finite number (it may be left out only when the "
                                   "map gives its full covariance)")


def dump(maps: Sequence[LocalMap]) -> str:
    """A YAML stream of local maps; covariance rows are formatted here, as PyYAML's float representer
    (a Python call per number) would take seconds for a few hundred maps."""
    parts = []
    for local_map in maps:
        parts.append(yamldoc.dump([_local_map_document(local_map)], explicit_start=True))
        if local_map.covariance is not None:
            parts.append("covariance:\n" + "".join(f"- [{', '.join(map(_yaml_float, row))}]\n"
                                                   for row in local_map.covariance.tolist()))
    return "".join(parts)


def _yaml_float(value: float) -> str:
    """A finite float as PyYAML writes it: repr, with a dot before an exponent (YAML 1.1 needs one)."""
    text = repr(value)
    return text.replace("e", ".0e") if "e" in text and "." not in text else text


def _local_map_document(local_map: LocalMap) -> dict[str, Any]:
    """A local map's document without its covariance (:func:`dump` appends that)."""
    document: dict[str, Any] = {
        "format": _FORMAT, "version": 1, "name": local_map.name,
        "start_id": local_map.start_id, "end_id": local_map.end_id,
        "end_pose": dict(zip(_END_POSE_FIELDS,
                             [*local_map.end_pose.tolist(), *local_map.pose_variances.tolist()])),
        "features": yamldoc.records({"id": local_map.feature_ids, "x": local_map.features[:, 0],
                                   "y": local_map.features[:, 1], "var": local_map.feature_variances}),
    }
    return document
