"""Griffe extension for the API reference: Sphinx roles in docstrings, such as :func:`join` or
:data:`COORDINATE`, shown as code (`join`) instead of as literal role markup.

mapjoin's docstrings use these roles (they read well in the source and in ``help()``); mkdocstrings renders
docstrings as Markdown, which has no roles. The docstring's text changes only in the built site.
"""

from __future__ import annotations

import re
from typing import Any

import griffe

_ROLE = re.compile(r":(?:py:)?[a-z]+:`~?\.?([^`]+)`")


class SphinxRolesAsCode(griffe.Extension):
    """Rewrites ``:role:`target``` to ```target``` in every docstring as it is loaded."""

    def on_instance(self, *, obj: Any, **kwargs: Any) -> None:  # noqa: ARG002 (griffe's hook signature)
        """Rewrite the roles of ``obj``'s docstring, if it has one."""
        if obj.docstring is not None:
            obj.docstring.value = _ROLE.sub(r"`\1`", obj.docstring.value)
