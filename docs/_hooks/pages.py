"""MkDocs hook: page text generated from the repository when the site is built, so that it cannot go stale.

- ``<!-- include: PATH -->`` on a line of its own is replaced by the text of PATH (relative to the
  repository root): pages kept beside the code, such as benchmarks/README.md, appear without a copy.
- ``<!-- public-api -->`` is replaced by one mkdocstrings block per public name of ``mapjoin``
  (``mapjoin._LAZY``, the table behind ``mapjoin.__all__``), documented where it is defined.

A missing file or name fails the build.
"""

from __future__ import annotations

import re
from pathlib import Path

_ROOT = Path(__file__).resolve().parents[2]
_INCLUDE = re.compile(r"^<!-- include: (\S+) -->$", re.MULTILINE)
_PUBLIC_API = re.compile(r"^<!-- public-api -->$", re.MULTILINE)


def public_api_blocks() -> str:
    """A ``::: mapjoin.<module>.<name>`` block per public name, errors first, in the order of ``mapjoin._LAZY``."""
    import mapjoin

    targets = [f"mapjoin.errors.{name}" for name in ("MapjoinError", "InputError", "JoinError")]
    targets += [f"mapjoin.{module}.{attribute}" for module, attribute in mapjoin._LAZY.values()]
    names = ["MapjoinError", "InputError", "JoinError", *mapjoin._LAZY]
    return "\n\n".join(f"## `mapjoin.{name}`\n\n::: {target}\n    options:\n      show_root_heading: false"
                       for name, target in zip(names, targets))


def on_page_markdown(markdown: str, page, config, files) -> str:  # noqa: ARG001 (MkDocs' hook signature)
    """The page with its include and public-api lines replaced."""
    markdown = _INCLUDE.sub(lambda match: (_ROOT / match[1]).read_text(encoding="utf-8"), markdown)
    return _PUBLIC_API.sub(lambda _match: public_api_blocks(), markdown)
