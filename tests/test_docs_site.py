"""The docs site's wiring: CI builds it strictly after nothing else than the README's test command changed,
the README's links resolve, and the generated API page covers every public name.

The site itself is built by .ci/run (``mkdocs build --strict``), which fails on a broken link, anchor or
reference; these tests check what that build cannot see.
"""

from __future__ import annotations

import importlib
import importlib.util
import re
from pathlib import Path

import mapjoin

ROOT = Path(__file__).resolve().parent.parent


def _readme_commands() -> list[str]:
    """The commands of the README's ``sh`` blocks under "Set-up"."""
    readme = (ROOT / "README.md").read_text()
    setup = readme.split("## Set-up", 1)[1].split("\n## ", 1)[0]
    return re.findall(r"```sh\n(.*?)\n```", setup, re.DOTALL)


def test_ci_runs_exactly_the_readme_test_command_and_builds_the_docs_strictly():
    install_and_join, test_command = _readme_commands()
    assert test_command == "python -m pip install -q -e '.[test]' && python -m pytest"
    assert "examples/" in install_and_join and install_and_join.startswith("python -m pip install . && mapjoin ")
    lines = [line for line in (ROOT / ".ci" / "run").read_text().splitlines() if line and not line.startswith("#")]
    assert lines[-1] == test_command  # last, so that pytest's summary closes CI's output
    assert any(re.fullmatch(r"python -m mkdocs build --strict .*", line) for line in lines)
    assert "- mkdocs-click" in (ROOT / "mkdocs.yml").read_text()


def test_every_relative_link_of_the_readme_resolves():
    readme = (ROOT / "README.md").read_text()
    targets = [target.split("#")[0] for target in re.findall(r"\]\(([^)]+)\)", readme)
               if "://" not in target and not target.startswith("#")]
    assert targets and [target for target in targets if not (ROOT / target).exists()] == []


def test_every_docs_page_is_in_the_site_navigation():
    config = (ROOT / "mkdocs.yml").read_text()
    pages = sorted(path.name for path in (ROOT / "docs").glob("*.md"))
    assert [page for page in pages if f": {page}" not in config] == []


def test_the_generated_api_page_documents_every_public_name():
    spec = importlib.util.spec_from_file_location("docs_pages_hook", ROOT / "docs" / "_hooks" / "pages.py")
    hook = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(hook)
    blocks = hook.public_api_blocks()
    documented = re.findall(r"^## `mapjoin\.(\w+)`$", blocks, re.MULTILINE)
    assert sorted(documented) == sorted(name for name in mapjoin.__all__ if name != "__version__")
    for target in re.findall(r"^::: (\S+)$", blocks, re.MULTILINE):  # each names where the object is defined
        module, _, attribute = target.rpartition(".")
        assert hasattr(importlib.import_module(module), attribute), target


def test_the_include_hook_inlines_the_benchmarks_readme():
    spec = importlib.util.spec_from_file_location("docs_pages_hook", ROOT / "docs" / "_hooks" / "pages.py")
    hook = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(hook)
    page = hook.on_page_markdown((ROOT / "docs" / "benchmarks.md").read_text(), None, None, None)
    assert page.startswith((ROOT / "benchmarks" / "README.md").read_text())
