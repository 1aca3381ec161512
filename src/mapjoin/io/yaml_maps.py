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

Unknown fields are errors. Numbers like ``1e-6`` (no dot) are read as numbers.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from ..errors import InputError
from ..maps import LocalMap
from . import yamldoc
from .paths import map_name

__all__ = ["dump", "read"]

_FORMAT = "mapjoin/local-map"
_KEYS = ("format", "version", "name", "start_id", "end_id", "end_pose", "features", "covariance")
_END_POSE_FIELDS = {"x": "number", "y": "number", "phi": "number", "var_xy": "variance", "var_phi": "variance"}
_FEATURE_FIELDS = {"id": "id", "x": "number", "y": "number", "var": "variance"}


def read(text: str, source: str) -> list[LocalMap]:
    """The local maps of a YAML stream, one per document."""
    documents = yamldoc.documents(text, source)
    return [_local_map_from_yaml(document, number if len(documents) > 1 else None)
            for number, document in enumerate(documents, 1)]


def _local_map_from_yaml(document: yamldoc.Document, number: int | None) -> LocalMap:
    """The local map of one document (``number``: its position in a stream of several, else None)."""
    document.header(_FORMAT, _KEYS)
    name = map_name(document.source, document.get(("name",), "text", optional=True), number)
    start_id, end_id = (document.get((key,), "id") for key in ("start_id", "end_id"))
    pose = document.record(("end_pose",), _END_POSE_FIELDS)
    features = document.records(("features",), _FEATURE_FIELDS)
    size = 3 + 2 * len(features["id"])
    covariance = document.matrix(("covariance",), (size, size), optional=True)
    try:
        return LocalMap(name, start_id, end_id,
                        [pose["x"], pose["y"], pose["phi"]], features["id"], yamldoc.stack(features, "x", "y"),
                        features["var"], [pose["var_xy"], pose["var_phi"]], covariance)
    except InputError as error:
        raise document.relocated(error) from None


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
