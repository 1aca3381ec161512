"""The sequential join of a stream of local maps, read as it goes (docs/joining.md, "Streaming").

:func:`join_stream` takes the maps from an iterator a chunk at a time and keeps only what later
joins need: the global map so far (features by compact id, in growable arrays), the chain's
end poses (final once the next map is joined: stored in arrays), the map names (the global
map's provenance) and each join's report entry as numbers in arrays (:class:`CompactReport`).
A map is dropped once its chunk is joined, so memory is bounded by the global map and the
per-map record, not by the input (a stream of 10⁶ maps: docs/benchmarks.md#streaming).

Each chunk is laid out as the in-memory join lays out the whole chain (the joins themselves
are :func:`mapjoin.joining._join_segment`, one implementation for both): the chunk's map 0 is
the previous chunk's last map, rows by id within each map, common features first. So the
result equals :func:`mapjoin.joining.join_sequential` of the same maps exactly, bit for bit.
The tree strategy, refinement and data association need every map at once: they are not
streamed.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass
from itertools import islice
from typing import overload

import numpy as np

from .consistency import DEFAULT_GATE, Policy, degrees_of_freedom, enforce, flags
from .covariance import DEFAULT_COVARIANCE, CovarianceMode, batch_spherical_variances
from .drift import SequentialRecord
from .errors import JoinError
from .joining import JoinRecord, JoinResult, _join_segment, _Pieces, _Segment, check_chain, pose_twice
from .maps import LocalMap, Provenance, joined_map
from .onestep import Solver, as_complex
from .stream_calibration import StreamCalibration

__all__ = ["CHUNK", "KEEP_VALUES", "CompactReport", "KeptMaps", "StreamedJoin", "join_stream"]

#: a streamed join's maps are kept for its confirmation (:class:`KeptMaps`), not read again, while they hold at
#: most this many numbers (states and covariances: 16 MB; DLR 200's hold 0.2 M; reading them again took 30-40 ms
#: of its 0.45 s ``join``)
KEEP_VALUES = 2**21

#: maps joined per chunk: large enough that the per-chunk work on the global map's id index is
#: amortised, small enough that a chunk's maps (with full covariances) take a few tens of MB
CHUNK = 4096

#: a report row's numeric columns (JoinRecord's fields after ``map``, before the consistency check)
_COLUMNS = ("start_id", "end_id", "common", "new", "a", "c_phi", "minima", "phi", "cost", "phi2", "cost2",
            "iterations", "level", "features_cost")
_CHECKS = ("chi2", "variance_factor", "p")  # the consistency check's columns (:mod:`mapjoin.stream_calibration`)
_BLOCK = 4096  # report rows made into records at a time
_INTEGER = frozenset({"start_id", "end_id", "common", "new", "minima", "iterations", "level"})


class CompactReport(Sequence[JoinRecord]):
    """A join report kept as one array per column: a :class:`JoinRecord` is made when it is read.

    A tuple of 10⁶ records would take about 1.5 GB; the columns take about 120 bytes a join.
    ``names[k]`` is the name of local map k (join k joins map k onto maps 0 .. k-1).
    """

    def __init__(self, names: Sequence[str], columns: dict[str, np.ndarray], gate: float):
        self._names = names
        self._chi2, self._variance_factor, self._p = (columns.pop(name) for name in _CHECKS)
        self._columns = columns
        self._dof = degrees_of_freedom(columns["common"])
        self._flag = flags(self._p, columns["minima"], gate)

    def __len__(self) -> int:
        return len(self._chi2)

    @overload
    def __getitem__(self, index: int) -> JoinRecord: ...

    @overload
    def __getitem__(self, index: slice) -> list[JoinRecord]: ...

    def __getitem__(self, index: int | slice) -> JoinRecord | list[JoinRecord]:
        if isinstance(index, slice):
            return list(self._records(range(len(self))[index]))
        numbers = range(len(self))[index:index + 1 or None]
        if not numbers:
            raise IndexError(f"join index {index} out of range for {len(self)} joins")
        return next(self._records(numbers))

    def __iter__(self) -> Iterator[JoinRecord]:
        return self._records(range(len(self)))

    def _records(self, numbers: range) -> Iterator[JoinRecord]:
        """The records of the joins ``numbers`` (0-based), made a block at a time (one ``tolist`` per column)."""
        for first in range(0, len(numbers), _BLOCK):
            rows = np.asarray(numbers[first:first + _BLOCK], dtype=np.intp)
            values = [column[rows].tolist() for column in self._columns.values()]
            checks = (self._chi2[rows].tolist(), self._dof[rows].tolist(), self._variance_factor[rows].tolist(),
                      self._p[rows].tolist(), self._flag[rows].tolist())
            for number, row, (chi2, dof, factor, p, flag) in zip(rows.tolist(), zip(*values), zip(*checks)):
                fields = dict(zip(_COLUMNS, row))
                if fields["phi2"] != fields["phi2"]:  # NaN: one minimum
                    fields["phi2"] = fields["cost2"] = None
                yield JoinRecord(number + 1, self._names[number + 1], **fields, chi2=chi2, dof=dof,
                                 variance_factor=factor, p=p, flag=flag)

    @property
    def flagged(self) -> np.ndarray:
        """Whether each join failed the gate or has two minima."""
        return self._flag


@dataclass(frozen=True)
class StreamedJoin:
    """A streamed join's result, the start pose id of the chain's first map (the trajectory's origin) and
    the seconds spent waiting for the maps (reading), apart from joining them."""

    result: JoinResult
    origin_id: int
    read_seconds: float


class _Columns:
    """Growable columns of numbers: one list of per-chunk arrays per name, concatenated at the end."""

    def __init__(self, names: Sequence[str]):
        self._parts: dict[str, list[np.ndarray]] = {name: [] for name in names}

    def extend(self, **columns: np.ndarray) -> None:
        for name, values in columns.items():
            self._parts[name].append(values)

    def arrays(self, dtypes: dict[str, type]) -> dict[str, np.ndarray]:
        """Each column as one array; its parts are let go as it is made (so the peak holds one column twice)."""
        columns = {}
        for name, parts in self._parts.items():
            columns[name] = np.concatenate(parts) if parts else np.zeros(0, dtypes.get(name, float))
            parts.clear()
        return columns


class _Chain:
    """What the stream keeps between chunks (module docstring)."""

    def __init__(self) -> None:
        self.known_ids = np.zeros(0, dtype=np.int64)    # the global ids seen, sorted ...
        self.known_index = np.zeros(0, dtype=np.intp)   # ... and their compact ids (order of first sighting)
        self.positions = np.zeros(1024, dtype=complex)
        self.position_variances = np.zeros(1024)
        self.pose_ids = np.zeros(0, dtype=np.int64)     # every pose of the chain so far, sorted
        self.names: list[str] = []
        self.poses = _Columns(("id", "xy", "phi", "var_xy", "var_phi"))
        self.rows = _Columns(_COLUMNS + _CHECKS)
        self.calibration = StreamCalibration()
        self.last: LocalMap | None = None               # the previous chunk's last map ...
        self.last_pose: tuple = ()                      # ... and its pose as the joins left it (not final yet)

    def compact_ids(self, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Compact ids of global ``ids`` (new ones numbered on), and whether each was seen in an earlier chunk."""
        unique, inverse = np.unique(ids, return_inverse=True)
        at = np.searchsorted(self.known_ids, unique)
        known = np.zeros(len(unique), dtype=bool)
        inside = at < len(self.known_ids)
        known[inside] = self.known_ids[at[inside]] == unique[inside]
        compact = np.empty(len(unique), dtype=np.intp)
        compact[known] = self.known_index[at[known]]
        fresh = np.flatnonzero(~known)
        count = len(self.known_ids)
        compact[fresh] = np.arange(count, count + len(fresh))
        self.known_ids = np.insert(self.known_ids, at[fresh], unique[fresh])
        self.known_index = np.insert(self.known_index, at[fresh], compact[fresh])
        if len(self.known_ids) > len(self.positions):
            size = max(len(self.known_ids), 2 * len(self.positions))
            self.positions = np.resize(self.positions, size)
            self.position_variances = np.resize(self.position_variances, size)
        return compact[inverse.reshape(-1)], known[inverse.reshape(-1)]

    def check(self, chunk: list[LocalMap]) -> None:
        """The chain's checks (:func:`mapjoin.joining.check_chain`) across chunks: the chunk continues the
        previous one's last map, and no end pose is one the chain already has."""
        if self.last is None:
            self.pose_ids = np.array([chunk[0].start_id], dtype=np.int64)
        check_chain(chunk if self.last is None else [self.last, *chunk])
        ends = np.sort(np.fromiter((m.end_id for m in chunk), np.int64, len(chunk)))
        at = np.searchsorted(self.pose_ids, ends)
        again = np.flatnonzero(self.pose_ids[np.minimum(at, len(self.pose_ids) - 1)] == ends)
        if again.size:
            end_id = ends[again].tolist()
            raise pose_twice(next(m for m in chunk if m.end_id in end_id))
        self.pose_ids = np.insert(self.pose_ids, at, ends)

    def join(self, chunk: list[LocalMap], covariance: CovarianceMode, solver: Solver, number: int,
             progress: Callable[[int], None] | None, gate: float = DEFAULT_GATE) -> None:
        """Join the maps of ``chunk`` onto the chain; ``number`` is the join number of its first map; the joins
        are tested at the chunk's end (:mod:`mapjoin.stream_calibration`)."""
        self.check(chunk)
        maps = chunk if self.last is None else [self.last, *chunk]
        first = len(maps) - len(chunk)  # the piece of chunk[0]: 1 after the first chunk
        feature_variances, pose_variances = batch_spherical_variances(chunk, covariance)
        sizes = np.fromiter((m.size for m in chunk), np.intp, len(chunk))
        piece = np.repeat(np.arange(first, len(maps)), sizes)
        ids = np.concatenate([m.feature_ids for m in chunk])
        order = np.lexsort((ids, piece))  # each map's rows by id, as the in-memory join's compact ids sort them
        piece, ids = piece[order], ids[order]
        compact, known = self.compact_ids(ids)
        _, first_row, inverse = np.unique(compact, return_index=True, return_inverse=True)
        offsets = np.searchsorted(piece, np.arange(len(maps) + 1))
        seen_before = known | (first_row[inverse.reshape(-1)] < offsets[piece])  # seen by an earlier map
        end_poses = np.array([m.end_pose for m in chunk])
        if first:
            end_poses = np.vstack([np.zeros(3), end_poses])  # the previous last map's slot: replaced below
            pose_variances = np.vstack([np.zeros(2), pose_variances])
        pieces = _Pieces(piece, compact, as_complex(np.concatenate([m.features for m in chunk]))[order],
                         feature_variances[order], np.arange(len(maps)), as_complex(end_poses), end_poses[:, 2],
                         pose_variances, np.arange(len(maps)), np.arange(len(maps)))
        segment = _Segment.of(pieces, seen_before, len(maps))
        if first:  # the previous last map's pose as the joins left it (the very objects: bit for bit)
            segment.pose_xy[0], segment.pose_phi[0], segment.var_xy[0], segment.var_phi[0] = self.last_pose
        record = SequentialRecord(pieces)
        rows = _join_segment(segment, maps, self.positions, self.position_variances, solver, number, progress,
                             record=record)
        done = slice(0, len(maps) - 1)  # every pose but the last is final
        self.poses.extend(id=np.fromiter((m.end_id for m in maps[done]), np.int64, len(maps) - 1),
                          xy=np.array(segment.pose_xy[done], dtype=complex), phi=np.array(segment.pose_phi[done]),
                          var_xy=np.array(segment.var_xy[done]), var_phi=np.array(segment.var_phi[done]))
        columns = list(zip(*rows))[1:] or [()] * len(_COLUMNS)  # the map's name is names[join]
        arrays = {name: np.array([np.nan if value is None else value for value in column],
                                 dtype=np.int64 if name in _INTEGER else float)
                  for name, column in zip(_COLUMNS, columns)}
        checks = self.calibration.block(segment, pieces.feature_piece, (pieces.pose_xy, pieces.pose_phi), first,
                                        number, record, arrays["cost"], arrays["features_cost"], gate, solver)
        if rows:
            arrays["chi2"], arrays["features_cost"], arrays["variance_factor"], arrays["p"] = checks
            self.rows.extend(**arrays)
        self.names.extend(m.name for m in chunk)
        self.last = maps[-1]
        self.last_pose = (segment.pose_xy[-1], segment.pose_phi[-1], segment.var_xy[-1], segment.var_phi[-1])

    def result(self, covariance: str, solver: str, gate: float) -> JoinResult:
        """The global map (features by id, as the in-memory join writes them) and the report."""
        assert self.last is not None
        xy, phi, var_xy, var_phi = self.last_pose
        self.poses.extend(id=np.array([self.last.end_id]), xy=np.array([xy], dtype=complex), phi=np.array([phi]),
                          var_xy=np.array([var_xy]), var_phi=np.array([var_phi]))
        poses = self.poses.arrays({"id": np.int64})
        features = self.positions[self.known_index]
        global_map = joined_map(
            feature_ids=self.known_ids, features=np.column_stack([features.real, features.imag]),
            feature_variances=self.position_variances[self.known_index], pose_ids=poses["id"],
            poses=np.column_stack([poses["xy"].real, poses["xy"].imag, poses["phi"]]),
            pose_variances=np.column_stack([poses["var_xy"], poses["var_phi"]]),
            provenance=Provenance(tuple(self.names), covariance, solver, "sequential"))
        report = CompactReport(self.names, self.rows.arrays({name: np.int64 for name in _INTEGER}), gate)
        return JoinResult(global_map, report)  # type: ignore[arg-type]  # a sequence of records, not a tuple


def join_stream(maps: Iterable[LocalMap], covariance: CovarianceMode = DEFAULT_COVARIANCE,
                solver: Solver = "bisection", progress: Callable[[int], None] | None = None, *,
                gate: float = DEFAULT_GATE, on_inconsistent: Policy = "warn", chunk: int | None = None,
                confirm: Callable[[JoinResult], JoinResult] | None = None) -> StreamedJoin:
    """:func:`mapjoin.joining.join` of ``maps`` with the sequential strategy, taking them from the iterable
    ``chunk`` at a time (module docstring): the same global map and report, with memory bounded by the global
    map; ``chunk`` maps at a time (default :data:`CHUNK`). ``on_inconsistent``: ``warn`` or ``stop`` (``skip`` re-joins the whole chain: join a list instead).
    An error in the input (raised by the iterator) or the chain stops the join before anything is returned.
    ``confirm``: applied to the result before the policy when a join is flagged (the stream keeps no maps; a
    caller that can read them again confirms the flagged joins on the exact problem,
    :func:`mapjoin.confirmation.confirm_streamed`).
    """
    if on_inconsistent == "skip":
        raise ValueError("on_inconsistent='skip' re-joins the whole chain: it needs the maps in memory")
    chunk = CHUNK if chunk is None else chunk
    if chunk < 1:
        raise ValueError(f"chunk must be at least 1, got {chunk}")
    chain = _Chain()
    source = iter(maps)
    read = 0.0
    origin = 0
    while True:
        started = time.perf_counter()
        maps_chunk = list(islice(source, chunk))
        read += time.perf_counter() - started
        if not maps_chunk:
            break
        if chain.last is None:
            origin = maps_chunk[0].start_id
        chain.join(maps_chunk, covariance, solver, max(len(chain.names), 1), progress, gate)  # join k: map k
    if chain.last is None:
        raise JoinError("no local maps to join")
    result = chain.result(covariance, solver, gate)
    if confirm is not None and result.report.flagged.any():
        result = confirm(result)
    return StreamedJoin(enforce(result, on_inconsistent, gate, None), origin, read)


class KeptMaps:
    """The maps of a stream, passed on as they come and kept for :func:`mapjoin.confirmation.confirm_streamed`
    (which then need not read them again) while they hold at most ``limit`` numbers (:data:`KEEP_VALUES`); past that they are let go, and the
    stream's memory stays bounded. ``maps``: those kept, None once let go."""

    def __init__(self, maps: Iterable[LocalMap], limit: int = KEEP_VALUES) -> None:
        self._source, self._room = iter(maps), limit
        self.maps: list[LocalMap] | None = []

    def __iter__(self) -> Iterator[LocalMap]:
        for local_map in self._source:
            if self.maps is not None:
                self._room -= local_map.features.size + 3 + (0 if local_map.covariance is None
                                                              else local_map.covariance.size)
                if self._room < 0:
                    self.maps = None
                else:
                    self.maps.append(local_map)
            yield local_map
