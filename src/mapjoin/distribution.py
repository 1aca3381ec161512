"""The name under which mapjoin is installed from the package registry, and the install hints that use it.

The name ``mapjoin`` on PyPI belongs to an unrelated project, so this one is distributed as
``mapjoin-slam`` (pyproject.toml's ``[project] name``); the import package and the command
stay ``mapjoin``. The installed version is looked up under this name, and every message that
says how to install an extra names it, so that following a hint never installs the other project.
"""

from __future__ import annotations

__all__ = ["DISTRIBUTION", "install_hint"]

#: pyproject.toml's ``[project] name`` (tests/test_distribution.py checks that the two agree)
DISTRIBUTION = "mapjoin-slam"


def install_hint(extra: str) -> str:
    """The command that installs mapjoin with an optional extra from the registry, e.g. ``plot``."""
    return f"pip install '{DISTRIBUTION}[{extra}]'"
