"""Global maps and ground truth (a global map without variances) as YAML and CSV.

Spherical numbers are named by what they are (docs/method.md#uncertainty-columns): a map
carrying marginal covariance blocks (the exact join) has ``var_*`` columns, their spherical
summaries; a map without them (the fast join) has ``weight_*`` columns, the spherical
weights the one-step method propagates, which are not covariances. Files written before
this distinction, with ``var_*`` columns and no covariance blocks, are read as weights.

Global map, CSV::

    kind,id,x,y,phi,weight_xy,weight_phi                        (fast join: weights)
    kind,id,x,y,phi,var_xy,var_phi,cov_xx,cov_xy,cov_yy,cov_xphi,cov_yphi,cov_phiphi
    feature,12,3.0,4.0,,0.02,,c_xx,c_xy,c_yy,,,
    pose,1,1.5,-0.25,0.1,0.01,0.001,c_xx,c_xy,c_yy,c_xphi,c_yphi,c_phiphi

    Features first, then poses. The ``cov_*`` columns (upper triangles of the symmetric
    marginal covariance blocks) come with the ``var_*`` columns; per kind they are all
    filled or all empty. Read also: ``kind,id,x,y,phi,var_xy,var_phi`` (older files; weights).
    CSV does not hold the provenance.

Global map, YAML::

    format: mapjoin/global-map
    version: 1
    provenance: {maps: [a.mat, b.mat], covariance: marginal, solver: ..., strategy: ...}
    features:
    - {id: 12, x: 3.0, y: 4.0, var: 0.02, cov: [[.., ..], [.., ..]]}   # with covariances
    - {id: 12, x: 3.0, y: 4.0, weight: 0.02}                          # without (fast join)
    poses:
    - {id: 1, x: 1.5, y: -0.25, phi: 0.1, var_xy: 0.01, var_phi: 0.001, cov: [[..]x3]}
    - {id: 1, x: 1.5, y: -0.25, phi: 0.1, weight_xy: 0.01, weight_phi: 0.001}

    ``provenance`` and each of its fields are optional; ``cov`` is on all entries of a
    list or on none, and ``var*`` or ``weight*`` names are used by all entries of a list
    (older files: ``var*`` without ``cov``, read as weights). A kind with no entries reads
    back without covariances.

Global map, JSON: the YAML document's fields as one JSON object (read back as YAML, which
JSON is, so that errors name lines).

Ground truth: the same without variances: CSV ``kind,id,x,y,phi``; YAML
``format: mapjoin/ground-truth``, ``version: 1``, ``features: [{id, x, y}]``,
``poses: [{id, x, y, phi}]``.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import numpy as np

from ..maps import GlobalMap, GroundTruth, Provenance
from . import csvtable, yamldoc
from .csvtable import COV_ENTRIES
from .outputs import Parts

__all__ = ["dump_global_csv", "dump_global_json", "dump_global_yaml", "dump_truth_csv", "dump_truth_yaml",
           "looks_like_json", "read_global_csv", "read_global_yaml", "read_truth_csv", "read_truth_yaml"]

_GLOBAL_MAP_FORMAT = "mapjoin/global-map"
_TRUTH_FORMAT = "mapjoin/ground-truth"
_ENTITY_HEADER = ("kind", "id", "x", "y", "phi")
_GLOBAL_CSV_HEADER = (*_ENTITY_HEADER, "var_xy", "var_phi")   # read only: older files, weights
_GLOBAL_WEIGHT_CSV_HEADER = (*_ENTITY_HEADER, "weight_xy", "weight_phi")
_GLOBAL_COV_CSV_HEADER = (*_GLOBAL_CSV_HEADER, *COV_ENTRIES)
_PROVENANCE_FIELDS = ("covariance", "solver", "strategy")
_GLOBAL_FEATURE_FIELDS = {"id": "id", "x": "number", "y": "number", "var": "variance"}
_GLOBAL_POSE_FIELDS = {"id": "id", "x": "number", "y": "number", "phi": "number",
                       "var_xy": "variance", "var_phi": "variance"}
#: the spherical fields' names by meaning: covariance summaries (``var*``) or weights (``weight*``)
_SPHERICAL_NAMES = {"var": {"var": "var", "var_xy": "var_xy", "var_phi": "var_phi"},
                    "weight": {"var": "weight", "var_xy": "weight_xy", "var_phi": "weight_phi"}}
_TRUTH_FEATURE_FIELDS = {"id": "id", "x": "number", "y": "number"}
_TRUTH_POSE_FIELDS = {"id": "id", "x": "number", "y": "number", "phi": "number"}


def read_global_yaml(text: str, source: str) -> GlobalMap:
    """A global map from its YAML document."""
    document = yamldoc.document(text, source)
    document.header(_GLOBAL_MAP_FORMAT, ("format", "version", "provenance", "features", "poses"))
    features = _spherical_records(document, ("features",), _GLOBAL_FEATURE_FIELDS, (2, 2))
    poses = _spherical_records(document, ("poses",), _GLOBAL_POSE_FIELDS, (3, 3))
    return GlobalMap(features["id"], yamldoc.stack(features, "x", "y"), features["var"], poses["id"],
                     yamldoc.stack(poses, "x", "y", "phi"), yamldoc.stack(poses, "var_xy", "var_phi"),
                     _provenance(document), features["cov"], poses["cov"], name=source)


def _spherical_records(document: yamldoc.Document, path: tuple[str], fields: dict[str, str],
                       shape: tuple[int, int]) -> dict[str, np.ndarray | None]:
    """The records at ``path`` with their spherical fields named ``weight*`` (when the first
    record has ``weight*`` names) or ``var*``, returned under the ``var*`` keys."""
    weights = any(key.startswith("weight") for key in document.first_record_keys(path))
    names = _SPHERICAL_NAMES["weight" if weights else "var"]
    records = document.records(path, {names.get(key, key): kind for key, kind in fields.items()}, {"cov": shape})
    return {key: records[names.get(key, key)] for key in (*fields, "cov")}


def _provenance(document: yamldoc.Document) -> Provenance:
    """The optional ``provenance`` mapping of a global-map document (absent fields empty)."""
    path = ("provenance",)
    if document.get(path, "mapping", optional=True) is None:
        return Provenance()
    document.only(path, ("maps", *_PROVENANCE_FIELDS))
    count = len(document.get((*path, "maps"), "list", optional=True) or ())
    maps = tuple(document.get((*path, "maps", index), "text") for index in range(count))
    fields = {key: document.get((*path, key), "text", optional=True) or "" for key in _PROVENANCE_FIELDS}
    return Provenance(maps, **fields)


def dump_global_yaml(global_map: GlobalMap) -> str:
    """A global map as one YAML document, with its provenance."""
    return yamldoc.dump([_global_document(global_map)])


def dump_global_json(global_map: GlobalMap) -> str:
    """A global map as one JSON object: the fields of its YAML document."""
    import json

    return json.dumps(_global_document(global_map), indent=1) + "\n"


def _global_document(global_map: GlobalMap) -> dict[str, Any]:
    """The fields of a global map's document (YAML, JSON), with its provenance."""
    provenance = global_map.provenance
    names = _SPHERICAL_NAMES["var" if global_map.has_covariances else "weight"]
    return {
        "format": _GLOBAL_MAP_FORMAT, "version": 1,
        "provenance": {"maps": list(provenance.maps),
                       **{key: getattr(provenance, key) for key in _PROVENANCE_FIELDS}},
        "features": yamldoc.records({"id": global_map.feature_ids, "x": global_map.features[:, 0],
                                   "y": global_map.features[:, 1], names["var"]: global_map.feature_variances,
                                   "cov": global_map.feature_covariances}),
        "poses": yamldoc.records({"id": global_map.pose_ids, "x": global_map.poses[:, 0],
                                "y": global_map.poses[:, 1], "phi": global_map.poses[:, 2],
                                names["var_xy"]: global_map.pose_variances[:, 0],
                                names["var_phi"]: global_map.pose_variances[:, 1],
                                "cov": global_map.pose_covariances}),
    }


def looks_like_json(text: str) -> bool:
    """Whether a stream without a named format is JSON: it starts with ``{`` (YAML and CSV never do here)."""
    return text.lstrip().startswith("{")


def read_global_csv(text: str, source: str) -> GlobalMap:
    """A global map from CSV (weight_* columns, or var_* and cov_* columns, or older var_* alone)."""
    table = csvtable.Table(text, source, [_GLOBAL_WEIGHT_CSV_HEADER, _GLOBAL_COV_CSV_HEADER, _GLOBAL_CSV_HEADER])
    xy_column, phi_column = table.header[5:7]     # var_* or weight_*
    features, poses = table.kinds()
    table.empty(("phi", phi_column), features, "a feature has no orientation")
    with_covariances = table.header == _GLOBAL_COV_CSV_HEADER
    return GlobalMap(
        table.ids(features), table.values(("x", "y"), features, "number"),
        table.values((xy_column,), features, "variance")[:, 0],
        table.ids(poses), table.values(("x", "y", "phi"), poses, "number"),
        table.values((xy_column, phi_column), poses, "variance"), Provenance(),
        table.covariances(features, 2, "feature") if with_covariances else None,
        table.covariances(poses, 3, "pose") if with_covariances else None, name=source)


def dump_global_csv(global_map: GlobalMap) -> Parts:
    """A global map as CSV: features, then poses; var_* and cov_* columns when it carries
    covariances, else weight_* columns. Made a block of rows at a time as it is written
    (:class:`.outputs.Parts`): the text of millions of features is never held at once."""
    feature_columns: list[np.ndarray | None] = [
        global_map.feature_ids, *global_map.features.T, None, global_map.feature_variances, None]
    pose_columns: list[np.ndarray | None] = [global_map.pose_ids, *global_map.poses.T, *global_map.pose_variances.T]
    header = _GLOBAL_WEIGHT_CSV_HEADER
    if global_map.has_covariances:
        header = _GLOBAL_COV_CSV_HEADER
        feature_columns += _covariance_columns(global_map.feature_covariances, 2)
        pose_columns += _covariance_columns(global_map.pose_covariances, 3)
    return Parts(_csv_parts(header, [("feature", feature_columns), ("pose", pose_columns)]))


_ROWS_PER_PART = 1 << 16  # rows made into text at a time


def _csv_parts(header: tuple[str, ...], kinds: list[tuple[str, list[np.ndarray | None]]]) -> Iterator[str]:
    """The header, then each kind's rows (columns of equal length; None: an empty column), a block at a time."""
    yield csvtable.to_text([header])
    for kind, columns in kinds:
        count = len(columns[0])
        for start in range(0, count, _ROWS_PER_PART):
            block = [None if column is None else column[start:start + _ROWS_PER_PART] for column in columns]
            yield csvtable.numeric_kind_text(kind, min(_ROWS_PER_PART, count - start), block)


def _covariance_columns(blocks: np.ndarray | None, size: int) -> list[np.ndarray | None]:
    """The ``cov_*`` columns of symmetric ``size`` x ``size`` blocks (upper triangle; None: empty)."""
    return [None if blocks is None or max(i, j) >= size else blocks[:, i, j]
            for i, j in COV_ENTRIES.values()]


def read_truth_yaml(text: str, source: str) -> GroundTruth:
    """Ground truth from its YAML document."""
    document = yamldoc.document(text, source)
    document.header(_TRUTH_FORMAT, ("format", "version", "features", "poses"))
    features = document.records(("features",), _TRUTH_FEATURE_FIELDS)
    poses = document.records(("poses",), _TRUTH_POSE_FIELDS)
    return GroundTruth(features["id"], yamldoc.stack(features, "x", "y"), poses["id"], yamldoc.stack(poses, "x", "y", "phi"),
                       name=source)


def dump_truth_yaml(truth: GroundTruth) -> str:
    """Ground truth as one YAML document."""
    return yamldoc.dump([{
        "format": _TRUTH_FORMAT, "version": 1,
        "features": yamldoc.records({"id": truth.feature_ids, "x": truth.features[:, 0], "y": truth.features[:, 1]}),
        "poses": yamldoc.records({"id": truth.pose_ids, "x": truth.poses[:, 0], "y": truth.poses[:, 1],
                                "phi": truth.poses[:, 2]}),
    }])


def read_truth_csv(text: str, source: str) -> GroundTruth:
    """Ground truth from CSV (kind,id,x,y,phi)."""
    table = csvtable.Table(text, source, [_ENTITY_HEADER])
    features, poses = table.kinds()
    table.empty(("phi",), features, "a feature has no orientation")
    return GroundTruth(table.ids(features), table.values(("x", "y"), features, "number"),
                       table.ids(poses), table.values(("x", "y", "phi"), poses, "number"), name=source)


def dump_truth_csv(truth: GroundTruth) -> str:
    """Ground truth as CSV: features, then poses."""
    return csvtable.to_text([_ENTITY_HEADER,
                      *csvtable.kind_rows("feature", len(truth.feature_ids),
                                 [truth.feature_ids.tolist(), *truth.features.T.tolist(), None]),
                      *csvtable.kind_rows("pose", len(truth.pose_ids), [truth.pose_ids.tolist(), *truth.poses.T.tolist()])])
