"""The docs match the code: docs/architecture.md names every command and every package folder, and
no page points at files (links, test files) or people that are not there."""
from __future__ import annotations

import re

from smdm_plugin.apps.cli import COMMANDS

from helpers.paths import ROOT

ARCH = (ROOT / "docs" / "architecture.md").read_text()


def test_architecture_lists_every_command() -> None:
    missing = [c for c in COMMANDS if not re.search(rf"\b{re.escape(c)}\b", ARCH)]
    assert not missing, f"docs/architecture.md does not name the command(s) {missing} (apps/cli.py COMMANDS)"


def test_architecture_shows_every_package_folder() -> None:
    pkg = ROOT / "smdm_plugin"
    folders = sorted(p.relative_to(pkg).as_posix() for p in pkg.rglob("*")
                     if p.is_dir() and "__pycache__" not in p.parts)
    assert "core/kernels" in folders  # the walk itself
    missing = [f for f in folders if f"{f}/" not in ARCH]
    assert not missing, f"docs/architecture.md does not show the folder(s) {missing} of smdm_plugin/"


def test_doc_links_point_at_files_that_exist() -> None:
    pages = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
    bad = []
    for page in pages:
        for target in re.findall(r"\]\(([^)#\s]+)\)", page.read_text()):
            if "://" in target or target.startswith("mailto:"):
                continue
            if not (page.parent / target).exists():
                bad.append(f"{page.relative_to(ROOT)} -> {target}")
    assert not bad, f"links to missing files: {bad}"


def test_pages_name_test_files_that_exist() -> None:
    """A test file a page names (``tests/<layer>/test_x.py``, with or without ``::test``) is there: the
    pages follow the tests when they move."""
    pages = [ROOT / "README.md", ROOT / "DEVELOPING.md", *sorted((ROOT / "docs").glob("*.md"))]
    bad = [f"{page.relative_to(ROOT)} -> {path}" for page in pages
           for path in sorted(set(re.findall(r"\btests/[\w/]+\.py\b", page.read_text())))
           if not (ROOT / path).is_file()]
    assert not bad, f"pages naming test files that are not there: {bad}"
