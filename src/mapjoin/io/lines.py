"""Text sources read line by line: a stream of any length is read with the memory of a block.

The lines are those :func:`.paths.read_text` would give joined (UTF-8, a byte-order mark
dropped, line ends kept as they are), so a reader gets the same text either way.
"""

from __future__ import annotations

import codecs
import io
import os
import sys
from collections.abc import Iterator
from typing import IO

import numpy as np

from ..errors import InputError
from . import paths
from .paths import Source, is_path, not_utf8

__all__ = ["text_lines"]

_BLOCK = 1 << 16  # characters read at a time


def text_lines(source: Source, name: str) -> Iterator[str]:
    """The lines of a path, ``-`` (stdin) or a stream (text or bytes), with their line ends, read a block at a time;
    errors name ``name``."""
    if not is_path(source):
        stream = sys.stdin if isinstance(source, (str, os.PathLike)) else source
        if stream is None:  # the process was started with stdin closed (`mapjoin join - <&-`)
            raise InputError("cannot read: stdin is closed", name)
        # a text stream's bytes, decoded strictly here: stdin's own decoding may let bad bytes through as
        # surrogates (errors="surrogateescape" under a C or POSIX locale), which no parser can take
        yield from _lines(getattr(stream, "buffer", stream), name)
        return
    try:
        file = open(os.fspath(source), "rb")  # noqa: SIM115 -- closed below; decoded by _lines, which knows where
    except OSError as error:
        raise InputError(f"cannot read ({error.strerror or error})", name) from None
    with file:
        yield from _lines(file, name)


def _lines(stream: IO, name: str) -> Iterator[str]:
    """The lines of an open stream; a block is split after its last ``\n``, so a ``\r\n`` stays whole. A line
    longer than :data:`.paths.MAX_STREAM_BYTES` (an endless stream without line ends, e.g. /dev/zero) is an error,
    and a long line is gathered in pieces, so that reading it costs time in proportion to its length."""
    decoder = codecs.getincrementaldecoder("utf-8")()
    pending: list[str] = []  # the start of the line being read
    pending_size, first = 0, True
    offset, start, line = 0, 0, 1  # bytes read, where the bytes decoded next start, the line reached: for errors
    while True:
        try:
            raw = stream.read(_BLOCK)
            if isinstance(raw, bytes):
                start = offset - len(decoder.getstate()[0])  # a character cut by the last block comes first
                block = decoder.decode(raw, final=not raw)
                offset += len(raw)
                line += int(np.count_nonzero(np.frombuffer(raw, np.uint8) == 10))  # "\n": twice as fast as count
            else:
                block = raw
        except UnicodeDecodeError as error:
            raise not_utf8(error, name, start, line) from None
        except OSError as error:
            raise InputError(f"cannot read ({error.strerror or error})", name) from None
        if not raw:
            break
        if first and block:
            block, first = block.removeprefix("\ufeff"), False
        cut = block.rfind("\n") + 1
        if cut:
            yield from io.StringIO("".join(pending) + block[:cut], newline="")
            pending, pending_size = [], 0
        pending.append(block[cut:])
        pending_size += len(block) - cut
        if pending_size > paths.MAX_STREAM_BYTES:
            raise InputError(f"holds a line of more than {paths.MAX_STREAM_BYTES} characters, the most read at once "
                             "from a stream (an endless stream?)", name)
    yield from io.StringIO("".join(pending), newline="")
