"""Files and streams to read: a path, ``-`` (stdin) or a stream; how messages name them.

Nothing here knows a format: the readers return text or bytes. Sources are paths, open
streams (e.g. ``io.StringIO``) or ``"-"`` for stdin. Writing is :mod:`.outputs`.
"""

from __future__ import annotations

import os
import stat
import sys
from typing import TextIO

from ..errors import InputError

__all__ = ["STDIN", "Source", "is_path", "map_name", "not_utf8", "read_file", "read_text", "source_name"]

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


def read_text(source: Source, name: str) -> str:
    """The UTF-8 text of a path, ``-`` (stdin) or a stream (text or bytes), without a byte-order mark."""
    if is_path(source):
        return read_file(os.fspath(source), name, False)
    stream = sys.stdin if isinstance(source, (str, os.PathLike)) else source
    try:
        text = stream.read()
        if isinstance(text, bytes):
            text = text.decode("utf-8")
    except UnicodeDecodeError as error:
        raise not_utf8(error, name) from None
    return text.removeprefix("\ufeff")


def read_file(path: str, name: str, binary: bool) -> str | bytes:
    """The bytes (``binary``) or UTF-8 text (byte-order mark dropped) of the file ``path``; errors name ``name``."""
    try:
        if binary:
            return _read_bytes(path)
        with open(path, encoding="utf-8-sig", newline="") as file:
            return file.read()
    except UnicodeDecodeError as error:
        raise not_utf8(error, name) from None
    except OSError as error:
        raise InputError(f"cannot read ({error.strerror or error})", name) from None


def _read_bytes(path: str) -> bytes:
    """The bytes of a file; a regular file in one ``read`` (a file object costs as much as reading a small file)."""
    descriptor = os.open(path, os.O_RDONLY)
    try:
        status = os.fstat(descriptor)
        chunks = [os.read(descriptor, status.st_size + 1)]  # fewer bytes than asked: the end of a regular file
        if len(chunks[0]) > status.st_size or not stat.S_ISREG(status.st_mode):
            while chunks[-1]:
                chunks.append(os.read(descriptor, 1 << 20))
        return chunks[0] if len(chunks) == 1 else b"".join(chunks)
    finally:
        os.close(descriptor)


def not_utf8(error: UnicodeDecodeError, name: str) -> InputError:
    """The error for text of ``name`` that is not UTF-8."""
    return InputError(f"expected UTF-8 text ({error.reason} at byte {error.start})", name)


def map_name(source: str, label: str | None, number: int | None) -> str:
    """Maps read from a file are named after it (messages and provenance then point to it): the
    path when it holds one map, else ``path#label`` with the map's own name, or its position."""
    return source if number is None else f"{source}#{label or number}"
