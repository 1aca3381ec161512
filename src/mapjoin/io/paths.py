"""Files and streams: reading a path, ``-`` (stdin) or a stream; writing atomically; the overwrite guard.

Nothing here knows a format: the readers get text or bytes, the writers write what they are
given. Sources are paths, open streams (e.g. ``io.StringIO``) or ``"-"`` for stdin; targets
are paths, text streams or ``"-"`` for stdout. Files are written atomically (a temporary
file in the same folder, then ``os.replace``), so readers never see half a file.
"""

from __future__ import annotations

import contextlib
import os
import stat
import sys
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, AnyStr, TextIO

from ..errors import InputError

if TYPE_CHECKING:  # pathlib only names a path type here
    from pathlib import Path

__all__ = ["MAX_STREAM_BYTES", "STDIN", "Source", "atomic_write", "check_not_overwriting", "is_path", "map_name", "not_utf8", "read_file",
           "read_text", "source_name", "write_output"]

STDIN = "-"

Source = str | os.PathLike | TextIO  # os.PathLike: e.g. a pathlib.Path


def is_path(source: Source) -> bool:
    """Whether ``source`` names a file (not ``-`` and not a stream)."""
    return isinstance(source, (str, os.PathLike)) and os.fspath(source) != STDIN


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
        data = os.read(descriptor, status.st_size + 1)  # fewer bytes than asked: the end of a regular file
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


def not_utf8(error: UnicodeDecodeError, name: str) -> InputError:
    """The error for text of ``name`` that is not UTF-8."""
    return InputError(f"expected UTF-8 text ({error.reason} at byte {error.start})", name)


def write_output(content: str | bytes, target: Source) -> list[str]:
    """Write ``content`` to a path (atomically), ``-`` (stdout) or a text stream; the paths written.

    Bytes (a binary format) go to paths only; the caller refuses other targets first.
    """
    if is_path(target):
        atomic_write(target, content)
        return [os.fspath(target)]
    (sys.stdout if isinstance(target, (str, os.PathLike)) else target).write(content)
    return []


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


def check_not_overwriting(inputs: Sequence[str], outputs: Sequence[str]) -> None:
    """Refuse an output that is an input file: the same file (device and inode, so also a hard or symbolic
    link to it) or the same path after resolving links.

    Pass the input files (:func:`mapjoin.io.resolve_inputs`); outputs need not exist yet. Each
    input costs one ``stat``; its path is resolved only when that fails or an output cannot be
    examined for another reason than not existing (an existing file is found by its inode).
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


def map_name(source: str, label: str | None, number: int | None) -> str:
    """Maps read from a file are named after it (messages and provenance then point to it): the
    path when it holds one map, else ``path#label`` with the map's own name, or its position."""
    return source if number is None else f"{source}#{label or number}"
