"""YAML documents with typed, line-numbered field access: mapjoin's YAML layer.

The YAML formats (local maps, global maps, ground truth, minima tables) read a document
through :class:`Document`, whose getters check each field's kind and raise
:class:`~mapjoin.errors.InputError` naming the file, the field and its line. PyYAML is
imported on first use, so commands that read and write no YAML do not pay for it. Numbers
like ``1e-6`` (no dot: a string in YAML 1.1) are read as numbers, and written so.
"""

from __future__ import annotations

import contextlib
import functools
import math
import re
import sys
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

from ..errors import InputError, shown
from ..maps import first_duplicate
from .fields import typo_message, typo_of

if TYPE_CHECKING:  # PyYAML is imported when YAML is read or written
    import yaml

__all__ = ["COLUMN_CHECKS", "FIELD_KINDS", "PLAIN_FLOAT", "Columns", "Document", "NeedsLines", "document", "documents",
           "dump", "looks_like_yaml", "one_line_string", "records", "split_documents", "stack"]


_YAML_FLOAT = re.compile(r"^[-+]?(?:[0-9]+\.?[0-9]*|\.[0-9]+)[eE][-+]?[0-9]+$")
#: a float as repr writes it (and a YAML 1.1 float): the loader reads these with ``float``, and so may a fast path
PLAIN_FLOAT = r"[-+]?[0-9]+\.[0-9]*(?:[eE][-+][0-9]+)?"
_PLAIN_FLOAT = re.compile(PLAIN_FLOAT)
#: the numbers mapjoin reads from YAML: decimal, ASCII digits only; YAML 1.1's other forms (0x10, 0b101, 010
#: in octal (= 8), 1_000, 1:30 in base 60) are read as text, so the field's check refuses them naming the value
_DECIMAL_INT = re.compile(r"[-+]?[0-9]+")
_DECIMAL_FLOAT = re.compile(r"[-+]?(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][-+]?[0-9]+)?")
_SPECIAL_FLOAT = re.compile(r"[-+]?\.(?:inf|Inf|INF)|\.(?:nan|NaN|NAN)")


@functools.cache
def _yaml_classes() -> tuple[type, type]:
    """mapjoin's YAML loader and dumper, made (and PyYAML imported) on first use: commands that read and write
    no YAML do not pay for importing it."""
    import yaml

    class Loader(getattr(yaml, "CSafeLoader", yaml.SafeLoader)):  # type: ignore[misc]
        """Safe loader that also reads ``1e-6`` (no dot: a string in YAML 1.1) as a float, and reads floats faster."""

        def resolve(self, kind: type, value: str, implicit: tuple[bool, bool]) -> str:
            if kind is yaml.ScalarNode and implicit[0] and _PLAIN_FLOAT.fullmatch(value):
                return "tag:yaml.org,2002:float"  # what PyYAML's resolver says too, without its slow search
            return super().resolve(kind, value, implicit)

        def construct_mapping(self, node: yaml.MappingNode, deep: bool = False) -> dict:
            """A mapping whose keys are distinct (PyYAML keeps the last of a repeated key without a word)."""
            keys = [key.value for key, _ in node.value if isinstance(key, yaml.ScalarNode)]
            if len(set(keys)) != len(keys):
                seen: set[str] = set()
                key = next(key for key, _ in node.value if isinstance(key, yaml.ScalarNode)
                           and (key.value in seen or seen.add(key.value)))
                raise yaml.constructor.ConstructorError(None, None, f"the key {shown(key.value)} appears twice",
                                                        key.start_mark)
            return super().construct_mapping(node, deep)

        def construct_yaml_int(self, node: yaml.ScalarNode) -> int | str:
            """A decimal integer (``010`` is ten, not YAML 1.1's octal eight); any other form stays text."""
            return int(node.value) if _DECIMAL_INT.fullmatch(node.value) else self.construct_scalar(node)

        def construct_yaml_float(self, node: yaml.ScalarNode) -> float | str:
            """A decimal float, or .inf/.nan (which the field checks refuse as not finite); any other form stays
            text (``float`` alone would also read ``1_0.5`` and fullwidth digits)."""
            if _DECIMAL_FLOAT.fullmatch(node.value):
                return float(node.value)
            if _SPECIAL_FLOAT.fullmatch(node.value):
                return super().construct_yaml_float(node)
            return self.construct_scalar(node)

    class Dumper(getattr(yaml, "CSafeDumper", yaml.SafeDumper)):  # type: ignore[misc]
        """Safe dumper that quotes strings the loader would read as floats."""

    Loader.add_implicit_resolver("tag:yaml.org,2002:float", _YAML_FLOAT, list("-+.0123456789"))
    Loader.add_constructor("tag:yaml.org,2002:float", Loader.construct_yaml_float)
    Loader.add_constructor("tag:yaml.org,2002:int", Loader.construct_yaml_int)
    Dumper.add_implicit_resolver("tag:yaml.org,2002:float", _YAML_FLOAT, list("-+.0123456789"))
    return Loader, Dumper


_NUMBER_TYPES = frozenset({int, float})


def _is_number(value: Any) -> bool:
    """A finite number, not a bool (an int beyond the float range is not)."""
    if type(value) is int:
        return abs(value) <= sys.float_info.max
    return type(value) is float and math.isfinite(value)


#: kind of a field -> (its check, what the error says was expected); the CSV layer says the same
FIELD_KINDS: dict[str, tuple[Callable[[Any], bool], str]] = {
    "id": (lambda value: type(value) is int and 0 <= value < 2**63, "a non-negative integer"),
    "number": (_is_number, "a finite number"),
    "nonnegative": (lambda value: _is_number(value) and value >= 0, "a non-negative finite number"),
    "variance": (lambda value: _is_number(value) and value > 0, "a positive finite number"),
    "text": (lambda value: type(value) is str, "a string"),
    "list": (lambda value: type(value) is list, "a list"),
    "mapping": (lambda value: type(value) is dict, "a mapping"),
}

#: kind of a field -> the check of FIELD_KINDS on a whole column of values at once (the same verdicts)
COLUMN_CHECKS: dict[str, Callable[[np.ndarray], np.ndarray]] = {
    "id": lambda values: values >= 0,
    "number": np.isfinite,
    "nonnegative": lambda values: np.isfinite(values) & (values >= 0),
    "variance": lambda values: np.isfinite(values) & (values > 0),
}

_FieldPath = tuple[str | int, ...]


class NeedsLines(Exception):  # noqa: N818 -- a signal to the reader, not an error shown to anyone
    """Raised where a :class:`Document` without lines (parsed by a fast path) would report an error: the
    reader parses that document again with lines, so that the error names the line as always."""


class Columns(dict):
    """A list of records that a fast path parsed straight into columns (field -> array), in place of the list."""


class Document:
    """One parsed YAML document; its getters check types, and errors name the field and its line.

    A document a fast path parsed (``node`` None) has no lines: its errors raise :class:`NeedsLines`
    instead, and it may hold :class:`Columns` for a list of records and arrays for matrices.
    ``first_line`` is the line (0-based) the parsed text starts at in its file.
    """

    def __init__(self, data: Any, node: yaml.Node | None, source: str, first_line: int = 0):
        self.data, self.node, self.source, self.first_line = data, node, source, first_line
        #: None: an unknown key is an error; a list: unknown keys not close to a known one are ignored, their
        #: paths (``features[].stamp``) collected here (a near miss of a known key is still an error)
        self.ignored: list[str] | None = None

    def error(self, path: _FieldPath, message: str) -> InputError:
        """The error of the field at ``path``, naming it and its line (:class:`NeedsLines` if it has none)."""
        if self.node is None:
            raise NeedsLines
        where = f"line {self._line(path)}" + (f", field {_render(path)}" if path else "")
        return InputError(message, self.source, where)

    def get(self, path: _FieldPath, kind: str, *, optional: bool = False) -> Any:
        """The value at ``path`` (keys and indices; the containers were checked by earlier calls)."""
        check, expected = FIELD_KINDS[kind]
        if path:
            parent, key = self._value(path[:-1]), path[-1]
            if isinstance(key, str) and key not in parent:
                if optional:
                    return None
                raise self.error(path, f"missing; expected {expected}")
            value = parent[key]
        else:
            value = self.data
        if not check(value):
            raise self.error(path, f"expected {expected}, got {shown(value)}")
        return value

    def only(self, path: _FieldPath, allowed: Sequence[str]) -> None:
        """Reject keys of the mapping at ``path`` other than ``allowed`` (catches typos); with :attr:`ignored`,
        collect those that are no near miss of an allowed one instead."""
        for unknown in (key for key in self._value(path) if key not in allowed):
            if self.ignored is None:
                raise self.error(path, f"unknown field {shown(unknown)}; expected only {', '.join(allowed)}")
            close = typo_of(unknown, allowed)
            if close is not None:
                raise self.error(path, typo_message("field", unknown, close, allowed))
            self.ignored.append(re.sub(r"\[[0-9]+\]", "[]", _render((*path, str(unknown)))))

    def matrix(self, path: _FieldPath, shape: tuple[int, int], *, optional: bool = False) -> np.ndarray | None:
        """The list of number lists at ``path`` as an array of ``shape``."""
        if self.node is None and isinstance(parsed := self._value(path[:-1]).get(path[-1]), np.ndarray):
            if parsed.shape != shape or not np.isfinite(parsed).all():
                raise NeedsLines  # the line-tracking path says which entry and where
            return parsed
        rows = self.get(path, "list", optional=optional)
        if rows is None:
            return None
        if len(rows) != shape[0]:
            raise self.error(path, f"expected {shape[0]} rows of {shape[1]} numbers, got {len(rows)} rows")
        for i, row in enumerate(rows):
            if type(row) is not list or len(row) != shape[1]:
                raise self.error((*path, i), f"expected a list of {shape[1]} numbers, got {shown(row)}")
        values = None
        if all(_NUMBER_TYPES.issuperset(map(type, row)) for row in rows):  # no bools, strings, ...
            with contextlib.suppress(OverflowError):  # an int beyond the float range
                values = np.array(rows, dtype=float).reshape(shape)
        if values is None or not np.isfinite(values).all():
            i, j = next((i, j) for i, row in enumerate(rows)
                        for j, value in enumerate(row) if not _is_number(value))
            raise self.error((*path, i, j), f"expected a finite number, got {shown(rows[i][j])}")
        return values

    def record(self, path: _FieldPath, fields: Mapping[str, str],
               matrices: Mapping[str, tuple[int, int]] | None = None, optional: Sequence[str] = ()) -> dict[str, Any]:
        """The mapping at ``path`` with exactly ``fields`` (name -> kind; those in ``optional`` may be missing:
        None) and optional ``matrices``."""
        matrices = matrices or {}
        self.get(path, "mapping")
        self.only(path, (*fields, *matrices))
        values = {key: self.get((*path, key), kind, optional=key in optional) for key, kind in fields.items()}
        values.update({key: self.matrix((*path, key), shape, optional=True) for key, shape in matrices.items()})
        return values

    def first_record_keys(self, path: _FieldPath) -> tuple[str, ...]:
        """The keys of the first record of the list at ``path`` (none when it is absent, empty or
        not a list of mappings): for formats whose field names tell a record's meaning."""
        parent = self._value(path[:-1])
        value = parent.get(path[-1]) if isinstance(parent, dict) else None
        if isinstance(value, Columns):
            return tuple(value)
        if isinstance(value, list) and value and isinstance(value[0], dict):
            return tuple(str(key) for key in value[0])
        return ()

    def records(self, path: _FieldPath, fields: Mapping[str, str],
                matrices: Mapping[str, tuple[int, int]] | None = None,
                optional: Sequence[str] = ()) -> dict[str, np.ndarray | None]:
        """The list of records at ``path`` as columns; ids must be unique, matrices on all records or none; the
        number ``fields`` in ``optional`` may be missing (NaN)."""
        matrices = matrices or {}
        if self.node is None and isinstance(parsed := self._value(path), Columns):
            return self._checked_columns(path, parsed, fields, matrices)
        count = len(self.get(path, "list"))
        items = [self.record((*path, index), fields, matrices, optional) for index in range(count)]
        columns: dict[str, np.ndarray | None] = {
            key: np.array([math.nan if item[key] is None else item[key] for item in items],
                          dtype=np.int64 if kind == "id" else float)
            for key, kind in fields.items()}
        for key, shape in matrices.items():
            present = [item[key] is not None for item in items]
            if any(present) and not all(present):
                missing = present.index(False)
                raise self.error((*path, missing, key), f"missing; expected a {shape[0]}x{shape[1]} matrix "
                                 f"as on {_render((*path, present.index(True)))}")
            columns[key] = (np.array([item[key] for item in items]).reshape(-1, *shape)
                            if items and all(present) else None)
        self._check_unique(path, columns, fields)
        return columns

    def _checked_columns(self, path: _FieldPath, columns: Columns, fields: Mapping[str, str],
                         matrices: Mapping[str, tuple[int, int]]) -> dict[str, np.ndarray | None]:
        """:meth:`records` of columns a fast path parsed: the same checks, column by column."""
        if set(columns) != set(fields) or not all(COLUMN_CHECKS[kind](columns[key]).all()
                                                  for key, kind in fields.items()):
            raise NeedsLines  # the line-tracking path says which entry and where
        self._check_unique(path, columns, fields)
        return {**columns, **dict.fromkeys(matrices)}

    def _check_unique(self, path: _FieldPath, columns: Mapping[str, np.ndarray | None], fields: Mapping[str, str]
                      ) -> None:
        """Ids (when the records have them) must be unique."""
        if "id" in fields:
            duplicate = first_duplicate(columns["id"])
            if duplicate is not None:
                raise self.error((*path, duplicate, "id"), f"duplicate id {columns['id'][duplicate]}")

    def header(self, kind: str, keys: Sequence[str]) -> None:
        """Check the document is a mapping of ``format: kind``, version 1, with no keys beyond ``keys``."""
        self.get((), "mapping")
        for key, value in (("format", kind), ("version", 1)):
            if key not in self.data:
                raise self.error((), f"missing field {shown(key)} (expected {shown(value)})")
        found = self.get(("format",), "text")
        if found != kind:
            raise self.error(("format",), f"expected {kind}, got {shown(found)}")
        version = self.get(("version",), "id")
        if version != 1:
            raise self.error(("version",), f"unsupported version {version}; this mapjoin reads version 1")
        self.only((), keys)

    def relocated(self, error: InputError) -> InputError:
        """A data-model validation error re-raised naming this file and the field's line."""
        return self.error((error.where,) if error.where else (), error.detail)

    def _value(self, path: _FieldPath) -> Any:
        """The value at ``path``, which exists."""
        value = self.data
        for key in path:
            value = value[key]
        return value

    def _line(self, path: _FieldPath) -> int:
        """Line (1-based) of the deepest node of ``path`` that exists."""
        import yaml

        node = self.node
        for key in path:
            if isinstance(node, yaml.MappingNode):
                found = [value for name, value in node.value
                         if isinstance(name, yaml.ScalarNode) and name.value == key]
                if not found:
                    break
                node = found[-1]
            elif isinstance(node, yaml.SequenceNode) and isinstance(key, int) and key < len(node.value):
                node = node.value[key]
            else:
                break
        return self.first_line + node.start_mark.line + 1


def _render(path: _FieldPath) -> str:
    """``("features", 3, "var")`` -> ``features[3].var``."""
    text = ""
    for key in path:
        text += f"[{key}]" if isinstance(key, int) else f".{key}" if text else str(key)
    return text


def documents(text: str, source: str, first_line: int = 0) -> list[Document]:
    """The documents of a YAML stream (malformed YAML raises, naming the line); ``text`` starts at line
    ``first_line`` (0-based) of the file (:func:`split_documents`)."""
    import yaml

    loader = _yaml_classes()[0](text)
    parsed = []
    try:
        while loader.check_node():
            node = loader.get_node()
            parsed.append(Document(loader.construct_document(node), node, source, first_line))
    except yaml.MarkedYAMLError as error:
        mark = error.problem_mark or error.context_mark
        raise InputError(f"malformed YAML: {_one_line(error.problem or error.context)}", source,
                         f"line {first_line + mark.line + 1}" if mark else None) from None
    except yaml.reader.ReaderError as error:  # a control character; its message runs over two lines
        raise InputError(f"malformed YAML: {_one_line(error.reason)} (character #x{error.character:04x})", source,
                         f"line {first_line + text.count(chr(10), 0, error.position) + 1}") from None
    except (yaml.YAMLError, ValueError, OverflowError, RecursionError) as error:
        raise InputError(f"malformed YAML: {_one_line(error)}", source) from None
    finally:
        loader.dispose()
    return parsed


def one_line_string(text: str) -> str | None:
    """The string that the one-line YAML value ``text`` (quoted, say, or with a comment) reads as; None when it
    reads as anything else (a number, a boolean, null, a list) or is not valid YAML on its own line."""
    import yaml

    try:
        value = yaml.load(text, Loader=_yaml_classes()[0])  # noqa: S506 -- mapjoin's loader is a safe loader
    except (yaml.YAMLError, ValueError, OverflowError, RecursionError):
        return None
    return value if type(value) is str else None


def _one_line(message: object) -> str:
    """A parser's message on one line (PyYAML's may span several), cut to a readable length."""
    return shown(" ".join(str(message).split()), 200, quoted=False)


_DOCUMENT_START = re.compile(r"---(?:[ \t\r\n]|$)")
_YAML_BREAKS = re.compile("\r\n|[\n\r\x85\u2028\u2029]")


def split_documents(lines: Iterable[str]) -> Iterator[tuple[int, str]]:
    """The texts of a YAML stream's documents, one at a time, each with the line (0-based) it starts at.

    ``lines`` are the stream's lines with their line ends. A document starts at a ``---`` line
    (column 0, then a space, a tab or the line end: YAML's document start, which no scalar
    can hold), or at the directives (``%`` at column 0) before it; comments and blank lines
    between two documents go with the first. So each text holds one document and is read as
    the stream would be, and a stream of any length is read with the memory of one document.
    """
    chunk: list[str] = []
    has_document = False  # whether ``chunk`` holds a document start or content yet
    line = 0
    for text in lines:
        starts = text.startswith("%") or text.startswith("---") and _DOCUMENT_START.match(text) is not None
        if starts and has_document:
            content = "".join(chunk)
            yield line, content
            line += _line_breaks(content)
            chunk, has_document = [], False
        chunk.append(text)
        has_document = has_document or not (text.startswith("%") or text.lstrip().startswith("#") or text.isspace())
    if chunk:
        yield line, "".join(chunk)


def _line_breaks(text: str) -> int:
    """How many line breaks YAML counts in ``text``."""
    if text.isascii() and "\r" not in text:
        return text.count("\n")
    return len(_YAML_BREAKS.findall(text))


def document(text: str, source: str) -> Document:
    """The one document of a YAML stream."""
    parsed = documents(text, source)
    if len(parsed) != 1:
        raise InputError(f"expected one YAML document, got {len(parsed)}", source)
    return parsed[0]


def dump(data: Sequence[Any], *, explicit_start: bool = False) -> str:
    """``data`` (plain Python values) as a YAML stream of one document each, in mapjoin's style."""
    import yaml

    return yaml.dump_all(data, Dumper=_yaml_classes()[1], sort_keys=False, default_flow_style=None,
                         allow_unicode=True, width=1 << 30, explicit_start=explicit_start)


def records(columns: Mapping[str, np.ndarray | None]) -> list[dict[str, Any]]:
    """Columns (arrays, None = absent) as a list of records of plain Python values."""
    present = {key: column.tolist() for key, column in columns.items() if column is not None}
    return [dict(zip(present, values)) for values in zip(*present.values())]


def stack(columns: Mapping[str, np.ndarray | None], *keys: str) -> np.ndarray:
    """The columns ``keys`` side by side, as a (rows x keys) array."""
    return np.column_stack([columns[key] for key in keys]).reshape(-1, len(keys))


def looks_like_yaml(text: str) -> bool:
    """Whether a stream without a named format is YAML: it starts with ``format:``, ``---``, ``%YAML`` or ``#``."""
    return text.lstrip().startswith(("format:", "---", "%YAML", "#"))
