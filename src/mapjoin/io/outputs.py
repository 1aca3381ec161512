"""Every file mapjoin writes: checked before any input is read, staged, then committed all together or not at all.

A command declares its outputs first (:class:`Outputs`): each file or folder is checked at once,
before any input is read, so a bad output path fails fast (its folder exists and is a folder, it
is writable, a file is not a folder and a folder not a file). Then :meth:`Outputs.guard` checks
them against the inputs. No output may be an input or another output of the same command,
whether named directly, through ``./`` or ``..``, a symbolic or hard link, or by a name that
differs only in letter case (the same file on a case-insensitive file system); nor may an
output folder hold an input file.

Inside the ``with`` block every write (:func:`write_output`, so every writer of
:mod:`mapjoin.io`) is staged: a regular file goes to a temporary file beside its target, fully
written; the files of a new folder go into a hidden temporary folder beside it (so a new folder
appears only when committed); stdout, open streams and targets that are not regular files
(``/dev/null``, a FIFO, a character device) are held in memory. When the block ends without an
error the writes are committed: the staged files are flushed to the disk (``fsync``; one
``sync`` for many files), the streams and special files are written through (opened and
written, never renamed over, so a device stays a device; stdout is flushed, so a closed pipe or
a full disk is noticed before the command's summary), then the temporaries are renamed onto
their targets, with Ctrl-C held back until the last rename is done, and every folder touched is
``fsync``-ed. Any error, Ctrl-C included, removes every temporary: nothing new remains and nothing
old is changed. A write outside a ``with``
block is a transaction of its own.

Symbolic links are written through: the link stays, and the file it points to is replaced
(atomically, by a temporary file beside that file).
"""

from __future__ import annotations

import contextlib
import os
import stat
import sys
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from contextvars import ContextVar
from dataclasses import dataclass, field
from types import FrameType
from typing import TextIO

from ..errors import InputError
from .paths import STDIN, Source, is_path, source_name

__all__ = ["Outputs", "Parts", "check_not_overwriting", "is_special", "transaction", "write_output"]

_STDOUT = "<stdout>"


def is_special(target: Source) -> bool:
    """Whether ``target`` is written as a stream: ``-``, an open stream, or a path to an existing file that is
    neither a regular file nor a folder (a device, a FIFO); such targets are written through, never replaced."""
    if not is_path(target):
        return True
    try:
        mode = os.stat(target).st_mode
    except (OSError, ValueError):
        return False
    return not (stat.S_ISREG(mode) or stat.S_ISDIR(mode))


@dataclass(frozen=True)
class _Entry:
    """A file known to a :class:`_FileIndex`: its path (links resolved when it was added so) and how to name it."""
    path: str
    label: str


class _FileIndex:
    """Files by identity: device and inode (so hard links and symbolic links to them too), and absolute path
    (links resolved on request) with letter case folded, so that names differing only by case are found."""

    def __init__(self) -> None:
        self._inodes: dict[tuple[int, int], _Entry] = {}
        self._names: dict[str, _Entry] = {}

    def add(self, path: str, label: str, *, resolve: bool) -> None:
        """Know ``path`` as ``label``; ``resolve`` also by its path with links resolved (always when it
        does not exist: an existing file is found by its inode)."""
        absolute = os.path.abspath(path)
        entry = _Entry(absolute, label)
        try:
            status = os.stat(path)
        except (OSError, ValueError):
            status = None
            resolve = True
        if status is not None:
            self._inodes.setdefault((status.st_dev, status.st_ino), entry)
        self._names.setdefault(absolute.casefold(), entry)
        if resolve:
            real = os.path.realpath(path)
            self._names.setdefault(real.casefold(), _Entry(real, label))

    def find(self, path: str) -> tuple[_Entry, bool] | None:
        """The file ``path`` is (or may be, on a case-insensitive file system), and whether only by letter case."""
        try:
            status = os.stat(path)
        except (OSError, ValueError):
            pass
        else:
            entry = self._inodes.get((status.st_dev, status.st_ino))
            if entry is not None:
                return entry, False
        for name in dict.fromkeys((os.path.abspath(path), os.path.realpath(path))):
            entry = self._names.get(name.casefold())
            if entry is not None:
                return entry, entry.path != name
        return None


def _clash(output: str, other: str, only_case: bool, remedy: str) -> InputError:
    """The error for ``output`` that is (or differs only in letter case from) ``other``."""
    if only_case:
        return InputError(f"differs only in letter case from {other}, the same file on a case-insensitive file "
                          f"system; {remedy}", output)
    return InputError(f"is {other}; {remedy}", output)


_KEEP_INPUT = "choose another output so the input is kept"


def check_not_overwriting(inputs: Sequence[str], outputs: Sequence[str]) -> None:
    """Refuse an output that is an input file: the same file (device and inode, so also a hard or symbolic link
    to it), the same path once links are resolved, or a name differing only in letter case.

    Pass the input files (:func:`mapjoin.io.resolve_inputs`); outputs need not exist yet. Each input
    costs one ``stat``; its links are resolved only when it does not exist.
    """
    index = _input_index(inputs)
    for output in outputs:
        _refuse_input(index, os.fspath(output))


def _input_index(inputs: Sequence[str]) -> _FileIndex:
    index = _FileIndex()
    for path in map(os.fspath, inputs):
        if path != STDIN:
            index.add(path, path, resolve=False)
    return index


def _refuse_input(index: _FileIndex, output: str) -> None:
    """Raise if ``output`` is a file of ``index`` (inputs)."""
    if output == STDIN:
        return
    found = index.find(output)
    if found is not None:
        entry, only_case = found
        which = "an input file" if entry.label == output else f"the input file {entry.label}"
        raise _clash(output, which, only_case, _KEEP_INPUT)


class Parts:
    """Text made a part at a time (an iterable of ``str``), for an output too long to hold: a file is written as
    the parts come (when staged); stdout and special files get them when the outputs are committed."""

    def __init__(self, parts: Iterable[str]) -> None:
        self._parts = parts

    def __iter__(self) -> Iterator[str]:
        return iter(self._parts)


Content = str | bytes | Parts


def _encoded(content: Content) -> Iterator[bytes]:
    """``content`` as UTF-8 bytes, a part at a time."""
    if isinstance(content, Parts):
        yield from (part.encode("utf-8") for part in content)
    else:
        yield content if isinstance(content, bytes) else content.encode("utf-8")


@dataclass
class _Through:
    """A write held until commit: to a stream (``-``: stdout) or through a special file."""
    target: Source
    content: Content


@dataclass
class _Staging:
    """What a transaction has staged: temporaries to rename, new folders being filled, writes to pass through."""
    renames: list[tuple[str, str, str]] = field(default_factory=list)  # (temporary, target, as named)
    folders: dict[str, str] = field(default_factory=dict)  # new folder (real path) -> its temporary folder
    throughs: list[_Through] = field(default_factory=list)
    written: set[str] = field(default_factory=set)  # real paths staged
    files: list[tuple[str, str]] = field(default_factory=list)  # (staged file, as named): flushed before commit


_active: ContextVar[Outputs | None] = ContextVar("mapjoin_outputs", default=None)


class Outputs:
    """The outputs of one command, checked up front and written all together or not at all.

    ``files`` and ``folders`` map how messages name each output (e.g. its option, ``-o``) to its
    path (None: not given; ``-``: stdout). They are checked when the object is made, before any
    input is read. Use it as a context manager around the writes: they are staged and committed
    when the block ends without an error, discarded otherwise (see the module's docstring)::

        outputs = Outputs(files={"-o": output, "--report": report})
        paths = outputs.guard(resolve_inputs(inputs))
        ...  # read, compute
        with outputs:
            write_global_map(global_map, output)
            write_table(rows, report)
    """

    def __init__(self, files: Mapping[str, str | None] | None = None,
                 folders: Mapping[str, str | None] | None = None) -> None:
        self._outputs = _FileIndex()
        self._inputs = _FileIndex()
        self._declared: set[str] = set()  # real paths of the declared files
        self._new_folders: dict[str, str] = {}  # declared folders that do not exist yet -> the first missing one
        self._folders: dict[str, str] = {}  # declared folders that exist: real path -> as named
        self._staging = _Staging()
        self._stdout: str | None = None
        self._paths: list[str] = []  # the declared files and folders
        for label, folder in (folders or {}).items():
            if folder is not None:
                self._declare(os.fspath(folder), label, folder=True)
        for label, path in (files or {}).items():
            if path is not None:
                self._declare(os.fspath(path), label, folder=False)

    def folder(self, path: str) -> None:
        """Declare the folder ``path`` (unless it is already): the files written into it are committed with the
        others, and a new folder appears only then."""
        real = os.path.realpath(path)
        if real not in self._new_folders and real not in self._folders:
            self._declare(path, "folder", folder=True)

    def _declare(self, path: str, label: str, *, folder: bool) -> None:
        """Check one output and remember it: a usable target, not the same file as an output before it."""
        if not path:  # "" would name the current folder
            raise InputError("is empty; expected a file name (or - for stdout)", label)
        if path == STDIN:
            if self._stdout is not None:
                raise InputError(f"{self._stdout} and {label} both write to stdout; give one of them a file", _STDOUT)
            self._stdout = label
            return
        found = self._outputs.find(path)
        if found is not None:
            entry, only_case = found
            raise _clash(path, f"the {entry.label}", only_case, f"give {label} another name")
        real = os.path.realpath(path)
        if not folder:
            _check_target(path, False, os.path.dirname(real) in self._new_folders)
            self._declared.add(real)
        else:
            top = real  # a new folder is made with its missing parents (as mkdir -p) when committed
            while not os.path.lexists(os.path.dirname(top)):
                top = os.path.dirname(top)
            _check_target(path if top == real else top, True, False)
            if os.path.isdir(real):
                self._folders[real] = path
            else:
                self._new_folders[real] = top
        self._paths.append(path)
        self._outputs.add(path, f"{label} output {path}", resolve=True)

    def guard(self, inputs: Sequence[str]) -> list[str]:
        """Refuse an output that is one of ``inputs`` (resolved input files) or a folder holding one; ``inputs``."""
        self._inputs = _input_index(inputs)
        for path in self._paths:
            _refuse_input(self._inputs, path)
        if self._folders:
            folders = {_identity(real): path for real, path in self._folders.items()}
            parents: dict[str, tuple[int, int] | None] = {}
            for path in inputs:
                if path == STDIN:
                    continue
                parent = os.path.dirname(os.path.abspath(path))
                if parent not in parents:
                    parents[parent] = _identity(parent)
                if parents[parent] in folders:
                    raise InputError(f"holds the input file {path}; write into another folder so the inputs are "
                                     "kept", folders[parents[parent]])
        return list(inputs)

    def write(self, content: Content, target: Source) -> list[str]:
        """Stage ``content`` (text as UTF-8; bytes as they are; :class:`Parts`) for ``target``; the paths it will be
        written to."""
        if is_special(target):
            if is_path(target):
                _refuse_input(self._inputs, os.fspath(target))
            self._staging.throughs.append(_Through(target, content))
            return [os.fspath(target)] if is_path(target) else []
        path = os.fspath(target)
        real = os.path.realpath(path)
        self._check_staged(path, real)
        folder, base = os.path.split(real)
        if real in self._new_folders:
            raise InputError("is a folder being written; expected a file", path)
        if folder in self._new_folders:
            top = self._new_folders[folder]
            if top not in self._staging.folders:
                self._staging.folders[top] = _temporary_name(top)
                _write_error(path, os.mkdir, self._staging.folders[top])
            inside = os.path.normpath(os.path.join(self._staging.folders[top], os.path.relpath(folder, top)))
            _write_error(path, os.makedirs, inside, exist_ok=True)
            self._staging.files.append((os.path.join(inside, base), path))
            _write_file(os.path.join(inside, base), content, path)
        else:
            _check_target(path, False, False)
            temporary = _temporary_name(real)
            self._staging.renames.append((temporary, real, path))
            self._staging.files.append((temporary, path))
            _write_file(temporary, content, path)
        return [path]

    def _check_staged(self, path: str, real: str) -> None:
        """Refuse a staged file that is an input, another output, or staged twice (a declared output was checked
        against the others when it was declared)."""
        _refuse_input(self._inputs, path)
        if real in self._staging.written:
            raise InputError("would be written twice by one command", path)
        self._staging.written.add(real)
        if real in self._declared:
            return
        found = self._outputs.find(path)
        if found is not None:
            entry, only_case = found
            raise _clash(path, f"the {entry.label}", only_case, "give each output its own name")
        self._outputs.add(path, f"output {path}", resolve=False)

    def __enter__(self) -> Outputs:
        self._token = _active.set(self)
        return self

    def __exit__(self, kind: type[BaseException] | None, *_: object) -> None:
        _active.reset(self._token)
        if kind is None:
            self.commit()
        else:
            self._discard()

    def commit(self) -> None:
        """Write the streams and special files through, then rename every staged file and folder into place."""
        staging, self._staging = self._staging, _Staging()
        try:
            _sync_files(staging.files)
            for through in staging.throughs:
                _write_through(through)
            touched: dict[str, None] = {}
            staging.renames.reverse()  # renamed from the end: what is left on an error is what is not renamed
            with _interrupt_held():
                while staging.renames:
                    temporary, target, name = staging.renames[-1]
                    _write_error(name, os.replace, temporary, target)
                    staging.renames.pop()
                    touched[os.path.dirname(target)] = None
                while staging.folders:
                    folder, temporary = next(iter(staging.folders.items()))
                    _write_error(folder, os.rename, temporary, folder)
                    del staging.folders[folder]
                    touched[folder] = touched[os.path.dirname(folder)] = None
            for folder in touched:
                _sync_folder(folder)
        finally:
            self._staging = staging
            self._discard()

    def _discard(self) -> None:
        """Remove every temporary file and folder not committed."""
        for temporary, _, _ in self._staging.renames:
            with contextlib.suppress(OSError):
                os.unlink(temporary)
        if self._staging.folders:
            import shutil  # with bz2, lzma and fnmatch (~2 ms of start-up): only when a folder output was staged

        for temporary in self._staging.folders.values():
            shutil.rmtree(temporary, ignore_errors=True)
        self._staging = _Staging()


@contextlib.contextmanager
def _interrupt_held() -> Iterator[None]:
    """Hold Ctrl-C (SIGINT) back while the staged files are renamed into place, so that the renames of one commit
    happen all or none: a Ctrl-C pressed meanwhile is noted and handed to the previous handler (Python's raises
    KeyboardInterrupt) when they are done. A handler, not a signal mask: the kernel delivers a signal masked in
    the main thread to any other thread (numpy's), and Python runs its handlers in the main thread regardless.
    Only the main thread can set handlers, and only it receives Python's signals, so elsewhere nothing is held."""
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread():
        yield
        return
    pressed: list[FrameType | None] = []
    previous = signal.signal(signal.SIGINT, lambda _number, frame: pressed.append(frame))
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
        if pressed and callable(previous):
            previous(signal.SIGINT, pressed[0])
        elif pressed and previous == signal.SIG_DFL:
            os.kill(os.getpid(), signal.SIGINT)


def write_output(content: Content, target: Source) -> list[str]:
    """Write ``content`` to a path, ``-`` (stdout) or a text stream; the paths written.

    Inside an :class:`Outputs` block the write is staged and committed with the others; outside,
    it is committed at once (a path atomically). Bytes (a binary format) go to paths only; the
    caller refuses other targets first.
    """
    active = _active.get()
    if active is not None:
        return active.write(content, target)
    with Outputs() as outputs:
        return outputs.write(content, target)


@contextlib.contextmanager
def transaction() -> Iterator[Outputs]:
    """The active :class:`Outputs`, else a new one committed when the block ends (e.g. the files of one folder)."""
    active = _active.get()
    if active is not None:
        yield active
        return
    with Outputs() as outputs:
        yield outputs


def _identity(path: str) -> tuple[int, int] | None:
    try:
        status = os.stat(path)
    except (OSError, ValueError):
        return None
    return status.st_dev, status.st_ino


def _check_target(path: str, folder: bool, in_new_folder: bool) -> None:
    """A usable output: its folder exists (or is an output folder being made) and can be written into; a file
    is not a folder; a folder is not a file; a special file (device, FIFO) can be written."""
    try:
        mode = os.stat(os.path.realpath(path)).st_mode  # realpath: "file/" names the file, not an error
    except (FileNotFoundError, NotADirectoryError):  # the folder it goes into is checked below
        mode = None
    except (OSError, ValueError) as error:
        raise InputError(f"cannot write ({getattr(error, 'strerror', None) or error})", path) from None
    if mode is not None:
        if stat.S_ISDIR(mode) != folder:
            raise InputError("is a file; expected a folder" if folder else "is a folder; expected a file", path)
        if not (stat.S_ISREG(mode) or stat.S_ISDIR(mode)):
            if not os.access(path, os.W_OK):
                raise InputError("cannot write (permission denied)", path)
            return
    if in_new_folder:
        return
    parent = os.path.dirname(os.path.realpath(path)) or "."
    if not os.path.exists(parent):
        raise InputError(f"cannot write: the folder {os.path.dirname(path) or '.'} does not exist", path)
    if not os.path.isdir(parent):
        raise InputError(f"cannot write: {os.path.dirname(path)} is not a folder", path)
    if not os.access(parent, os.W_OK | os.X_OK):
        raise InputError(f"cannot write: no permission to write into the folder {parent}", path)


def _temporary_name(path: str) -> str:
    """A new hidden name beside ``path`` for staging it."""
    folder, base = os.path.split(path)
    return os.path.join(folder, f".{base}.{os.urandom(4).hex()}.tmp")


def _write_error(name: str, operation: Callable[..., object], *args: object, **options: object) -> None:
    """Run a file operation; an OSError becomes an InputError naming ``name``."""
    try:
        operation(*args, **options)
    except OSError as error:
        raise InputError(f"cannot write ({error.strerror or error})", name) from error


def _write_file(path: str, content: Content, name: str) -> None:
    """Create ``path`` (it must not exist) holding ``content``; errors name ``name``."""
    try:
        with open(path, "xb") as file:
            file.writelines(_encoded(content))
    except OSError as error:
        raise InputError(f"cannot write ({error.strerror or error})", name) from error


#: up to this many staged files are ``fsync``-ed one by one; more, and one ``sync`` flushes them all
_SYNC_EACH = 32


def _sync_files(files: Sequence[tuple[str, str]]) -> None:
    """Flush the staged files to the disk before they are renamed into place, so that a crash leaves the old
    file or the new one, never an empty one. Each ``fsync`` waits for the disk (~5 ms: 50 s for the 10^4
    files of a large conversion), so many files are flushed by one ``sync`` of all file systems instead."""
    if len(files) > _SYNC_EACH:
        os.sync()
        return
    for path, name in files:
        _write_error(name, _fsync, path)


def _fsync(path: str) -> None:
    """``fsync`` a file or a folder by its path."""
    descriptor = os.open(path, os.O_RDONLY)
    try:
        os.fsync(descriptor)
    finally:
        os.close(descriptor)


def _write_through(through: _Through) -> None:
    """Write to stdout, a text stream, or through a special file (opened and written, not replaced); a reader
    of stdout that has gone raises BrokenPipeError, which the command line ends quietly."""
    target, content = through.target, through.content
    if is_path(target):
        _write_error(os.fspath(target), _write_special, os.fspath(target), content)
        return
    stream: TextIO = sys.stdout if isinstance(target, (str, os.PathLike)) else target
    try:
        if stream is sys.stdout:
            _write_stdout(content)
        else:
            stream.writelines(content if isinstance(content, Parts) else [content])
    except BrokenPipeError:
        raise
    except OSError as error:
        raise InputError(f"cannot write ({error.strerror or error})", source_name(target, _STDOUT)) from error


def _write_stdout(content: Content) -> None:
    """Write ``content`` to stdout, all of it, and flush it. Text goes as UTF-8 to the binary layer, in a loop:
    unbuffered (``python -u``, ``PYTHONUNBUFFERED``), a text write to a pipe whose reader stops drops what the
    one ``write`` call did not take, and the closed pipe would go unnoticed."""
    binary = getattr(sys.stdout, "buffer", None)
    if binary is None:  # a text stream standing in for stdout
        for data in _encoded(content):
            sys.stdout.write(data.decode("utf-8"))
        sys.stdout.flush()
        return
    sys.stdout.flush()
    for part in _encoded(content):
        data = memoryview(part)
        while data:
            data = data[binary.write(data) or 0:]
    binary.flush()


def _write_special(path: str, content: Content) -> None:
    with open(path, "wb") as file:
        file.writelines(_encoded(content))


def _sync_folder(folder: str) -> None:
    """``fsync`` a folder, so that the renames in it survive a crash (not every file system allows it)."""
    with contextlib.suppress(OSError):
        _fsync(folder)
