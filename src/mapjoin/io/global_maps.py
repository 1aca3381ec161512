"""Global maps and ground truth (a global map without variances) as YAML and CSV.

Global map, CSV::

    kind,id,x,y,phi,var_xy,var_phi[,cov_xx,cov_xy,cov_yy,cov_xphi,cov_yphi,cov_phiphi]
    feature,12,3.0,4.0,,0.02,[,c_xx,c_xy,c_yy,,,]
    pose,1,1.5,-0.25,0.1,0.01,0.001[,c_xx,c_xy,c_yy,c_xphi,c_yphi,c_phiphi]

    Features first, then poses. The ``cov_*`` columns (upper triangles of the symmetric
    marginal covariance blocks) are present when the map carries them; per kind they are
    all filled or all empty. CSV does not hold the provenance.

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

Global map, JSON: the YAML document's fields as one JSON object (read back as YAML, which
JSON is, so that errors name lines).

Ground truth: the same without variances: CSV ``kind,id,x,y,phi``; YAML
``format: mapjoin/ground-truth``, ``version: 1``, ``features: [{id, x, y}]``,
``poses: [{id, x, y, phi}]``.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from ..maps import GlobalMap, GroundTruth, Provenance
from . import csvtable, yamldoc
from .csvtable import COV_ENTRIES

__all__ = ["dump_global_csv", "dump_global_json", "dump_global_yaml", "dump_truth_csv", "dump_truth_yaml",
           "looks_like_json", "read_global_csv", "read_global_yaml", "read_truth_csv", "read_truth_yaml"]

_GLOBAL_MAP_FORMAT = "mapjoin/global-map"
_TRUTH_FORMAT = "mapjoin/ground-truth"
_ENTITY_HEADER = ("kind", "id", "x", "y", "phi")
_GLOBAL_CSV_HEADER = (*_ENTITY_HEADER, "var_xy", "var_phi")
_GLOBAL_COV_CSV_HEADER = (*_GLOBAL_CSV_HEADER, *COV_ENTRIES)
_PROVENANCE_FIELDS = ("covariance", "solver", "strategy")
_GLOBAL_FEATURE_FIELDS = {"id": "id", "x": "number", "y": "number", "var": "variance"}
_GLOBAL_POSE_FIELDS = {"id": "id", "x": "number", "y": "number", "phi": "number",
                       "var_xy": "variance", "var_phi": "variance"}
_TRUTH_FEATURE_FIELDS = {"id": "id", "x": "number", "y": "number"}
_TRUTH_POSE_FIELDS = {"id": "id", "x": "number", "y": "number", "phi": "number"}


def read_global_yaml(text: str, source: str) -> GlobalMap:
    """A global map from its YAML document."""
    document = yamldoc.document(text, source)
    document.header(_GLOBAL_MAP_FORMAT, ("format", "version", "provenance", "features", "poses"))
    features = document.records(("features",), _GLOBAL_FEATURE_FIELDS, {"cov": (2, 2)})
    poses = document.records(("poses",), _GLOBAL_POSE_FIELDS, {"cov": (3, 3)})
    return GlobalMap(features["id"], yamldoc.stack(features, "x", "y"), features["var"], poses["id"],
                     yamldoc.stack(poses, "x", "y", "phi"), yamldoc.stack(poses, "var_xy", "var_phi"),
                     _provenance(document), features["cov"], poses["cov"], name=source)


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
    return {
        "format": _GLOBAL_MAP_FORMAT, "version": 1,
        "provenance": {"maps": list(provenance.maps),
                       **{key: getattr(provenance, key) for key in _PROVENANCE_FIELDS}},
        "features": yamldoc.records({"id": global_map.feature_ids, "x": global_map.features[:, 0],
                                   "y": global_map.features[:, 1], "var": global_map.feature_variances,
                                   "cov": global_map.feature_covariances}),
        "poses": yamldoc.records({"id": global_map.pose_ids, "x": global_map.poses[:, 0],
                                "y": global_map.poses[:, 1], "phi": global_map.poses[:, 2],
                                "var_xy": global_map.pose_variances[:, 0],
                                "var_phi": global_map.pose_variances[:, 1], "cov": global_map.pose_covariances}),
    }


def looks_like_json(text: str) -> bool:
    """Whether a stream without a named format is JSON: it starts with ``{`` (YAML and CSV never do here)."""
    return text.lstrip().startswith("{")


def read_global_csv(text: str, source: str) -> GlobalMap:
    """A global map from CSV, with the cov_* columns when its header has them."""
    table = csvtable.Table(text, source, [_GLOBAL_CSV_HEADER, _GLOBAL_COV_CSV_HEADER])
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


def dump_global_csv(global_map: GlobalMap) -> str:
    """A global map as CSV: features, then poses; cov_* columns when it carries covariances."""
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
    return csvtable.to_text([header, *csvtable.kind_rows("feature", len(global_map.feature_ids), feature_columns),
                      *csvtable.kind_rows("pose", len(global_map.pose_ids), pose_columns)])


def _covariance_columns(blocks: np.ndarray | None, size: int) -> list[Sequence[float] | None]:
    """The ``cov_*`` columns of symmetric ``size`` x ``size`` blocks (upper triangle; None: empty)."""
    return [None if blocks is None or max(i, j) >= size else blocks[:, i, j].tolist()
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
