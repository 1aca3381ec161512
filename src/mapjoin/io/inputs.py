"""Input arguments to files: paths, globs, folders of local maps and ``-`` (stdin)."""

from __future__ import annotations

import os
import re
import stat
from collections.abc import Sequence

from ..errors import InputError
from .paths import STDIN
from .registry import LOCAL_MAP_FILE, local_map_files_text

__all__ = ["resolve_inputs"]

_GLOB_CHARACTERS = re.compile(r"[*?[]")


def resolve_inputs(inputs: Sequence[str]) -> list[str]:
    """Input arguments as a list of files: globs expanded (natural order), folders as their local maps.

    A folder contributes its local-map files, ``localmap_<k>`` with a local-map format's extension, ordered by k
    (``localmap_10`` after ``localmap_9``); other files are ignored. ``-`` (stdin) is kept.
    """
    paths: list[str] = []
    for item in inputs:
        item = os.fspath(item)
        if item == STDIN:
            paths.append(item)
        elif (files := _expand(item)) is not None:
            paths.extend(files)
        elif _GLOB_CHARACTERS.search(item):
            from glob import glob

            matches = sorted(glob(item, recursive=True), key=_natural_key)
            if not matches:
                raise InputError("no file matches this pattern", item)
            for match in matches:
                paths.extend(_expand(match) or [match])
        else:
            raise InputError("no such file or folder", item)
    return paths


def _expand(path: str) -> list[str] | None:
    """The files ``path`` stands for: a folder's local maps, else itself; None if it does not exist (one ``stat``)."""
    try:
        mode = os.stat(path).st_mode
    except (OSError, ValueError):
        return None
    return _folder_maps(path) if stat.S_ISDIR(mode) else [path]


def _folder_maps(folder: str) -> list[str]:
    """The local-map files of ``folder``, ordered by their number k."""
    try:
        with os.scandir(folder) as entries:
            found = [(match, entry.path) for entry in entries
                     if (match := LOCAL_MAP_FILE.fullmatch(entry.name)) and entry.is_file()]
    except OSError as error:
        raise InputError(f"cannot list the folder ({error.strerror or error})", folder) from None
    numbered: dict[int, tuple[str, str]] = {}  # k -> (file name, path)
    for match, path in found:
        k = int(match[1])
        if k in numbered:
            raise InputError(f"holds both {numbered[k][0]} and {match[0]} for map {k}; keep one", folder)
        numbered[k] = (match[0], path)
    if not numbered:
        raise InputError(f"expected local-map files named {local_map_files_text()}; found none", folder)
    return [numbered[k][1] for k in sorted(numbered)]


def _natural_key(text: str) -> list[str | int]:
    """Sort key that orders embedded numbers by value (``a9`` before ``a10``)."""
    return [int(part) if index % 2 else part for index, part in enumerate(re.split(r"([0-9]+)", text))]
