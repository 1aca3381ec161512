"""Files and streams to read: a path, ``-`` (stdin) or a stream; how messages name them.

Nothing here knows a format: the readers return text or bytes. Sources are paths, open
streams (e.g. ``io.StringIO``) or ``"-"`` for stdin. Writing is :mod:`.outputs`.
"""

from __future__ import annotations

import os
import stat
import sys
from collections.abc import Callable
from typing import AnyStr, TextIO

from ..errors import InputError

__all__ = ["MAX_STREAM_BYTES", "STDIN", "Source", "is_path", "map_name", "not_utf8", "read_file", "read_once",
           "read_text", "source_name"]

STDIN = "-"

Source = str | os.PathLike | TextIO  # os.PathLike: e.g. a pathlib.Path


def is_path(source: Source) -> bool:
    """Whether ``source`` names a file (not ``-`` and not a stream)."""
    return isinstance(source, (str, os.PathLike)) and os.fspath(source) != STDIN


def read_once(source: Source) -> bool:
    """Whether ``source`` gives its data only once: ``-`` (stdin), an open stream, or a path that is not a
    regular file (a FIFO, a process substitution's ``/dev/fd/N``, a device). Reading such a source again
    blocks or gives other data, so a second reading (a streamed join's confirmation) is not tried."""
    if not is_path(source):
        return True
    try:
        return not stat.S_ISREG(os.stat(source).st_mode)
    except (OSError, ValueError):
        return True


def source_name(source: Source, dash: str = "<stdin>") -> str:
    """How messages name a path, ``-`` (``dash``) or a stream (its ``name``, else ``<stream>``)."""
    if isinstance(source, (str, os.PathLike)):
        path = os.fspath(source)
        return dash if path == STDIN else path
    name = getattr(source, "name", None)
    return name if isinstance(name, str) else "<stream>"


#: The most bytes read from a stream or special file (stdin, a FIFO, /dev/zero), whose size is not known
#: before reading: 1 GiB, some ten times the largest input mapjoin is used on (10^5 local maps as CSV are
#: ~100 MB), and small enough that an endless stream stops with an error instead of exhausting memory.
MAX_STREAM_BYTES = 1 << 30
_CHUNK = 1 << 20


def read_text(source: Source, name: str) -> str:
    """The UTF-8 text of a path, ``-`` (stdin) or a stream (text or bytes), without a byte-order mark; a stream
    is read up to :data:`MAX_STREAM_BYTES`."""
    if is_path(source):
        return read_file(os.fspath(source), name, False)
    stream = sys.stdin if isinstance(source, (str, os.PathLike)) else source
    if stream is None:  # the process was started with stdin closed (`mapjoin ... - <&-`)
        raise InputError("cannot read: stdin is closed", name)
    stream = getattr(stream, "buffer", stream)  # stdin's bytes: bounded in bytes, decoded once
    try:
        text = _bounded(stream.read)
        if isinstance(text, bytes):
            text = text.decode("utf-8")
    except _TooLong as error:
        raise InputError(str(error), name) from None
    except UnicodeDecodeError as error:
        raise not_utf8(error, name) from None
    return text.removeprefix("\ufeff")


def read_file(path: str, name: str, binary: bool) -> str | bytes:
    """The bytes (``binary``) or UTF-8 text (byte-order mark dropped) of the file ``path``; errors name ``name``.
    A special file (a FIFO, a device) is read up to :data:`MAX_STREAM_BYTES`."""
    try:
        data = _read_bytes(path)
        return data if binary else data.decode("utf-8").removeprefix("\ufeff")
    except _TooLong as error:
        raise InputError(str(error), name) from None
    except UnicodeDecodeError as error:
        raise not_utf8(error, name) from None
    except OSError as error:
        raise InputError(f"cannot read ({error.strerror or error})", name) from None


def _read_bytes(path: str) -> bytes:
    """The bytes of a file; a regular file in one ``read`` (a file object costs as much as reading a small file)."""
    descriptor = os.open(path, os.O_RDONLY)
    try:
        status = os.fstat(descriptor)
        if not stat.S_ISREG(status.st_mode):
            return _bounded(lambda size: os.read(descriptor, size))
        data = os.read(descriptor, status.st_size + 1)  # fewer bytes than asked: the end of a regular file ...
        if 0 < len(data) < status.st_size:  # ... or the most one read gives (2 GiB on Linux): read on to the end
            parts = [data]
            while parts[-1] and sum(map(len, parts)) <= status.st_size:
                parts.append(os.read(descriptor, status.st_size + 1 - sum(map(len, parts))))
            data = b"".join(parts)
        if len(data) > status.st_size:  # it grew while being read
            data += _bounded(lambda size: os.read(descriptor, size))
        return data
    finally:
        os.close(descriptor)


class _TooLong(Exception):
    """A stream holds more than :data:`MAX_STREAM_BYTES`; the reader names it in an :class:`InputError`."""


def _bounded(read: Callable[[int], AnyStr]) -> AnyStr:
    """All that ``read(size)`` gives until it gives nothing, up to :data:`MAX_STREAM_BYTES` (e.g. /dev/zero,
    an endless stream, raises :class:`_TooLong`)."""
    chunks = [read(_CHUNK)]
    total = len(chunks[0])
    while chunks[-1]:
        if total > MAX_STREAM_BYTES:
            raise _TooLong(f"holds more than {MAX_STREAM_BYTES} bytes, the most read from a stream or special file "
                           "(an endless stream?)")
        chunks.append(read(_CHUNK))
        total += len(chunks[-1])
    return chunks[0][:0].join(chunks)


def not_utf8(error: UnicodeDecodeError, name: str, offset: int = 0, line: int = 1) -> InputError:
    """The error for text of ``name`` that is not UTF-8: the line, the bytes and their offset in the source.
    ``offset``, ``line``: where ``error.object`` starts in the source (a block of a stream read a block at a time)."""
    line += error.object.count(b"\n", 0, error.start)
    found = bytes(error.object[error.start:error.end])
    return InputError(f"expected UTF-8 text, got {found!r} at byte {offset + error.start} ({error.reason})", name,
                      f"line {line}")


def map_name(source: str, label: str | None, number: int | None) -> str:
    """Maps read from a file are named after it (messages and provenance then point to it): the
    path when it holds one map, else ``path#label`` with the map's own name, or its position."""
    return source if number is None else f"{source}#{label or number}"
