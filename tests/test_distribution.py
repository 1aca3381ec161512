"""The distribution name: the one in pyproject.toml is the one the code and every install hint use.

"mapjoin" on PyPI is an unrelated project (0.2.0, 2019): a hint naming it installs that project
and then "does not provide the extra 'plot'". The names are read from the files themselves here,
not from mapjoin.distribution, so that a change on one side only fails.
"""

from __future__ import annotations

import importlib.metadata
import re
import subprocess
import sys
from pathlib import Path

import pytest

import mapjoin
from mapjoin.distribution import DISTRIBUTION

ROOT = Path(__file__).resolve().parent.parent
#: an install of the distribution by its import name: ``pip install mapjoin``, ``'mapjoin[plot]'``, ``-U mapjoin``
_WRONG_INSTALL = re.compile(r"pip install\b[^\n`&;|]*?(?<![\w./-])['\"]?mapjoin(?![\w-])")


def _project_name() -> str:
    """``[project] name`` of pyproject.toml, read as text (tomllib is not in Python 3.10)."""
    text = (ROOT / "pyproject.toml").read_text()
    project = text.split("[project]", 1)[1].split("\n[", 1)[0]
    return re.search(r'^name\s*=\s*"([^"]+)"', project, re.MULTILINE)[1]


def test_pyproject_names_the_distribution_the_code_uses():
    assert _project_name() == DISTRIBUTION == "mapjoin-slam"


def _documents() -> list[Path]:
    files = [ROOT / "README.md", ROOT / "pyproject.toml", ROOT / "mkdocs.yml", ROOT / ".ci" / "run",
             *ROOT.glob("docs/**/*.md"), *ROOT.glob("docs/**/*.py"), *ROOT.glob("src/**/*.py"),
             *ROOT.glob("benchmarks/*")]
    return [path for path in files if path.is_file()]


def test_no_file_says_to_install_mapjoin_by_its_import_name():
    wrong = [f"{path.relative_to(ROOT)}:{number}: {line.strip()}" for path in _documents()
             for number, line in enumerate(path.read_text(errors="replace").splitlines(), 1)
             if _WRONG_INSTALL.search(line)]
    assert wrong == []


@pytest.mark.parametrize("line, wrong", [
    ("pip install 'mapjoin[plot]'", True), ("python -m pip install -U mapjoin", True),
    ("pip install mapjoin", True), ("pip install 'mapjoin-slam[plot]'", False),
    ("python -m pip install '.[plot]'", False), ("pip install -e /work/mapjoin", False),
    ("python -m pip install . && mapjoin join examples/sim20", False),
])
def test_the_wrong_install_pattern_itself(line, wrong):
    assert bool(_WRONG_INSTALL.search(line)) is wrong


def test_the_plot_hint_names_the_distribution():
    """The library's error (tests/test_plot.py checks the command's line)."""
    code = ("import sys; sys.modules['matplotlib'] = None\n"    # makes `import matplotlib` fail
            "from mapjoin.plot import _matplotlib\n"
            "try:\n    _matplotlib()\nexcept Exception as error:\n    print(error)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out == "figures need matplotlib, an optional extra: pip install 'mapjoin-slam[plot]'\n"


def test_the_version_is_the_installed_distributions():
    try:
        installed = importlib.metadata.version("mapjoin-slam")
    except importlib.metadata.PackageNotFoundError:
        pytest.skip("mapjoin-slam is not installed here (a source tree on PYTHONPATH)")
    assert mapjoin.__version__ == installed
