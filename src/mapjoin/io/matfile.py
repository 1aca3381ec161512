"""MATLAB MAT-file level 5 (MathWorks, "MAT-File Format"): reading real numeric variables, writing doubles.

scipy.io.loadmat crashes the interpreter (segfault) on some corrupt files, e.g. one flipped
byte in an element's type code, so the few element kinds mapjoin needs are parsed here,
checking every length and code (numeric matrices, compressed or not, either byte order).
Many files are parsed at once (a folder of thousands of small ones): their bytes are joined,
each walk over data elements reads the k-th tag of every buffer in one numpy step, and the
variables found form one :class:`Variables` table. Writing is uncompressed, little-endian.
"""

from __future__ import annotations

import struct
import zlib
from collections.abc import Mapping, Sequence
from typing import NamedTuple

import numpy as np

from ..errors import InputError, shown
from .paths import MAX_STREAM_BYTES

__all__ = ["Array", "Variables", "dump", "parse", "variables"]

_MI_INT8, _MI_INT32, _MI_UINT32, _MI_MATRIX, _MI_COMPRESSED = 1, 5, 6, 14, 15
_MI_NUMERIC = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 9: "f8", 12: "i8", 13: "u8"}
_MX_CLASSES = {1: "cell array", 2: "struct", 3: "object", 4: "char array", 5: "sparse matrix", 16: "function",
               17: "opaque object"}
_MX_NUMERIC = range(6, 16)  # double, single, int8 ... uint64
_MX_COMPLEX = 0x800
_DTYPES = {(big, kind): np.dtype((">" if big else "<") + code) for kind, code in _MI_NUMERIC.items()
               for big in (False, True)}
_ITEMSIZES = np.array([_DTYPES.get((False, kind), np.dtype("u1")).itemsize for kind in range(16)])
_MI_DOUBLE, _MX_DOUBLE = 9, 6  # element type double, array class double
#: the most bytes a compressed variable may inflate to: as much as a stream may hold (a zip bomb of a few MB
#: would otherwise inflate to many GB)
MAX_DECOMPRESSED = MAX_STREAM_BYTES
_HEADER = (b"MATLAB 5.0 MAT-file, written by mapjoin".ljust(116) + bytes(8)  # text, no subsystem data
           + struct.pack("<H", 0x0100) + b"IM")                             # version 1, little-endian



def variables(data: bytes, source: str) -> dict[str, np.ndarray | str]:
    """The variables of a MATLAB v5 .mat file: real numeric arrays as float arrays, others as a description."""
    table, errors = parse([data], [source])
    if errors:
        raise errors[0]
    return {name: value if isinstance(value, str) else value.value() for name, value in table.variables(0).items()}


class Array(NamedTuple):
    """A real numeric array as a .mat file stores it: its dimensions and its column-major data of ``dtype``."""

    shape: tuple[int, ...]
    dtype: np.dtype
    data: memoryview

    def value(self) -> np.ndarray:
        """The array as floats, in its shape."""
        return np.frombuffer(self.data, self.dtype).astype(float).reshape(self.shape, order="F")


class Variables(NamedTuple):
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

    def variables(self, file: int) -> dict[str, Array | str]:
        """Name and value of each variable of ``file``, later ones of a name replacing earlier ones."""
        return {self.name_of(row): self.array(row) for row in np.flatnonzero(self.file == file).tolist()}

    def name_of(self, row: int) -> str:
        """The name of variable ``row``."""
        return str(memoryview(self.buffer)[slice(*self.name[row])], "latin-1")

    def array(self, row: int) -> Array | str:
        """Variable ``row`` as stored, or its description."""
        if row in self.descriptions:
            return self.descriptions[row]
        big, kind = bool(self.big[row]), int(self.kind[row])
        shape = struct.unpack_from(f"{'>' if big else '<'}{self.rank[row]}i", self.buffer, self.dimensions[row])
        return Array(shape, _DTYPES[big, kind], memoryview(self.buffer)[slice(*self.content[row])])

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
        shape[matrix] = _int32(np.frombuffer(self.buffer, np.uint8), self.dimensions[rows[matrix], np.newaxis]
                                   + [0, 4], self.big[rows[matrix], np.newaxis])
        return matrix, shape[:, 0], shape[:, 1]

    def floats(self, rows: np.ndarray) -> np.ndarray:
        """The data of the real numeric arrays ``rows`` as floats, each column-major, one after the other."""
        view, types = memoryview(self.buffer), set(zip(self.big[rows].tolist(), self.kind[rows].tolist()))
        if len(types) > 1:
            return np.concatenate([self.array(row).value().ravel(order="F") for row in rows.tolist()])
        data = bytearray().join([view[start:end] for start, end in self.content[rows].tolist()])  # writable
        return np.frombuffer(data, _DTYPES[types.pop()] if types else float).astype(float, copy=False)


def parse(files: Sequence[bytes], sources: Sequence[str]) -> tuple[Variables, dict[int, InputError]]:
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
    elements, owner, element_errors = _top_level(files, big, errors)
    table = _variables(elements, owner, big[np.array(owner, dtype=np.intp)], element_errors)
    for e, message in sorted(element_errors.items()):
        errors.setdefault(owner[e], message)  # the file's first element with an error
    return table, {i: InputError(message, sources[i]) for i, message in errors.items()}


def _top_level(files: Sequence[bytes], big: np.ndarray, errors: dict[int, str]
                   ) -> tuple[list[bytes | memoryview], list[int], dict[int, str]]:
    """The top-level data elements of the files without ``errors``, each alone (decompressed, or as it is);
    the file of each; and the error of each that cannot be decompressed. A file's walk error goes to ``errors``."""
    joined = b"".join(files)
    end = np.cumsum([len(data) for data in files], dtype=np.int64)
    begin = end - [len(data) - 128 for data in files]
    begin[list(errors)] = end[list(errors)]
    top, walk_errors = _walk(np.frombuffer(joined, np.uint8), begin, end, big, padded=False)
    errors.update(walk_errors)
    elements: list[bytes | memoryview] = []
    owner: list[int] = []
    element_errors: dict[int, str] = {}
    view = memoryview(joined)
    for file, kind, tag, start, size in zip(*(column.tolist() for column in top)):
        if file in errors:
            continue
        if kind == _MI_COMPRESSED:
            decompressor = zlib.decompressobj()
            try:
                elements.append(decompressor.decompress(view[start:start + size], MAX_DECOMPRESSED + 1))
            except zlib.error as error:
                element_errors[len(elements)] = f"corrupt compressed data in the .mat file ({error})"
                elements.append(b"")
            else:
                if len(elements[-1]) > MAX_DECOMPRESSED:
                    element_errors[len(elements) - 1] = (f"a compressed variable of the .mat file holds more than "
                                                         f"{MAX_DECOMPRESSED} bytes, the most mapjoin reads")
                    elements[-1] = b""
        else:
            elements.append(view[tag:max(start + size, tag + 8)])
        owner.append(file)
    return elements, owner, element_errors


def _variables(elements: Sequence[bytes | memoryview], owner: Sequence[int], big: np.ndarray,
                   errors: dict[int, str]) -> Variables:
    """The variables that top-level data elements hold, each a miMATRIX element; the first error of each
    element that is not one, or not a well-formed one, goes to ``errors``."""
    buffer = b"".join(elements)
    data, count = np.frombuffer(buffer, np.uint8), len(elements)
    end = np.cumsum([len(element) for element in elements], dtype=np.int64)
    inner, walk_errors = _walk(data, end - [len(element) for element in elements], end, big, padded=False)
    found, only = inner.counts(count), inner.nth(0, count)
    for e, message in walk_errors.items():
        errors.setdefault(e, message)
    for e in np.flatnonzero(found != 1).tolist():
        errors.setdefault(e, f"corrupt .mat file: expected 1 element(s), got {found[e]}")
    for e in np.flatnonzero((found == 1) & (only.kind != _MI_MATRIX)).tolist():
        errors.setdefault(e, f"corrupt .mat file: expected a matrix element, got element type {only.kind[e]}")
    matrix = np.ones(count, dtype=bool)
    matrix[list(errors)] = False
    parts, walk_errors = _walk(data, np.where(matrix, only.start, 0), np.where(matrix, only.start + only.size, 0),
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
    array_flags[matrix] = _int32(data, flags.start[matrix, np.newaxis], big[matrix, np.newaxis])[:, 0]
    real = matrix & np.isin(array_flags & 0xFF, _MX_NUMERIC) & (array_flags & _MX_COMPLEX == 0)
    descriptions = {e: _MX_CLASSES.get(flag & 0xFF, "complex array" if flag & _MX_COMPLEX else "unknown class")
                    for e, flag in zip(np.flatnonzero(matrix & ~real).tolist(), array_flags[matrix & ~real].tolist())}
    malformed = real & ((dimensions.size % 4 != 0) | (found != 4) | ~np.isin(content.kind, list(_MI_NUMERIC)))
    real &= ~malformed
    rank = np.where(real, dimensions.size // 4, 0)
    owner_of_dimension = np.repeat(np.arange(count), rank)
    first_dimension = np.cumsum(rank) - rank
    dimension = _int32(data, (dimensions.start[owner_of_dimension] + 4 * (np.arange(rank.sum())
                                  - first_dimension[owner_of_dimension]))[:, np.newaxis],
                           big[owner_of_dimension, np.newaxis])[:, 0]
    negative = real & (rank == 0)  # min(shape, default=-1) < 0
    negative[owner_of_dimension[dimension < 0]] = True
    entries = np.zeros(count)  # the product of the dimensions (exact: < 2^53 whenever it matters)
    sized = np.flatnonzero(rank > 0)
    entries[sized] = np.multiply.reduceat(dimension.astype(float), first_dimension[sized]) if sized.size else 0
    wrong_size = real & ~negative & (entries * _ITEMSIZES[np.where(real, content.kind, 0)] != content.size)
    table = Variables(buffer, np.array(owner, dtype=np.intp), big,
                      np.column_stack([name.start, name.start + name.size]), descriptions,
                      np.where(real, content.kind, -1), rank, dimensions.start,
                      np.column_stack([content.start, content.start + content.size]))
    for e in np.flatnonzero(malformed).tolist():
        errors[e] = f"corrupt .mat file: numeric array {shown(table.name_of(e))} is malformed"
    for e in np.flatnonzero(negative | wrong_size).tolist():
        shape = table.array(e).shape
        errors[e] = (f"corrupt .mat file: {shown(table.name_of(e))} has dimensions {shape}" if negative[e] else
                     f"corrupt .mat file: {shown(table.name_of(e))} holds {content.size[e]} bytes for shape {shape}")
    return table


class _Elements(NamedTuple):
    """Data elements found by :func:`_walk`, ordered by buffer, then position."""

    buffer: np.ndarray  # the buffer each is in
    kind: np.ndarray  # its data type
    tag: np.ndarray  # where its tag starts
    start: np.ndarray  # where its data starts
    size: np.ndarray  # its byte count, without padding

    def counts(self, buffers: int) -> np.ndarray:
        """How many elements each of the ``buffers`` holds."""
        return np.bincount(self.buffer, minlength=buffers)

    def nth(self, k: int, buffers: int) -> "_Elements":
        """Each buffer's k-th element (0-based); -1 in every field for a buffer with fewer."""
        count = self.counts(buffers)
        index = np.where(count > k, np.cumsum(count) - count + k, len(self.buffer))
        return _Elements(*(np.append(column, -1)[index] for column in self))


def _walk(data: np.ndarray, begin: np.ndarray, end: np.ndarray, big: np.ndarray, *, padded: bool
              ) -> tuple[_Elements, dict[int, str]]:
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
        kind, size = _int32(data, offset[:, np.newaxis] + [0, 4], big[ranges, np.newaxis], unsigned=True).T
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
    return _Elements(*(column[order] for column in columns)), errors


def _int32(data: np.ndarray, offset: np.ndarray, big: np.ndarray, *, unsigned: bool = False) -> np.ndarray:
    """The 32-bit integers at ``offset`` (any shape) of ``data``, each in the byte order ``big`` (broadcast)."""
    raw = np.ascontiguousarray(data[offset[..., np.newaxis] + np.arange(4)])
    code = "u4" if unsigned else "i4"
    return np.where(big, raw.view(">" + code)[..., 0], raw.view("<" + code)[..., 0]).astype(np.int64)




def dump(arrays: Mapping[str, np.ndarray]) -> bytes:
    """A .mat file (uncompressed, little-endian) holding each of ``arrays`` as a real double matrix."""
    return _HEADER + b"".join(_double_array(name, value) for name, value in arrays.items())


def _double_array(name: str, value: np.ndarray) -> bytes:
    """A real double matrix variable: one miMATRIX element of flags, dimensions, name, column-major data."""
    return _element(_MI_MATRIX, _element(_MI_UINT32, struct.pack("<II", _MX_DOUBLE, 0))
                        + _element(_MI_INT32, struct.pack("<ii", *value.shape))
                        + _element(_MI_INT8, name.encode("ascii"))
                        + _element(_MI_DOUBLE, np.asarray(value, "<f8").tobytes(order="F")))


def _element(kind: int, data: bytes) -> bytes:
    """A MAT v5 data element: tag (type, byte count), data, zeros up to a multiple of 8 bytes."""
    return struct.pack("<II", kind, len(data)) + data + bytes(-len(data) % 8)
