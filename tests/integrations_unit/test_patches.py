"""The patches for upstream checkouts (``patches/*.patch``) only add lines, and every plugin name
those lines import still exists (a renamed or removed function would break upstream's code only
when the patch runs, which CI never does: it has no upstream checkout)."""
from __future__ import annotations

import importlib
import re
from pathlib import Path

import pytest

from helpers.paths import ROOT  # noqa: E402

PATCHES = sorted((ROOT / "patches").glob("*.patch"))
IMPORT = re.compile(r"^\s*from (smdm_plugin(?:\.\w+)*) import ([\w ,]+?)\s*(?:#.*)?$")


def added_lines(patch: Path) -> list:
    return [ln[1:] for ln in patch.read_text().splitlines() if ln.startswith("+") and not ln.startswith("+++")]


def plugin_imports(patch: Path) -> list:
    """``(module, name)`` for every ``from smdm_plugin... import a, b as c`` the patch adds."""
    out = []
    for line in added_lines(patch):
        m = IMPORT.match(line)
        if m:
            out += [(m.group(1), part.split(" as ")[0].strip()) for part in m.group(2).split(",")]
    return out


def test_there_are_patches():
    assert {p.name for p in PATCHES} >= {"mdm.patch", "priormdm.patch", "motiondiffuse.patch"}


@pytest.mark.parametrize("patch", PATCHES, ids=lambda p: p.name)
def test_patch_only_adds_and_its_plugin_imports_exist(patch):
    text = patch.read_text().splitlines()
    removed = [ln for ln in text if ln.startswith("-") and not ln.startswith("---")]
    assert not removed, f"{patch.name} removes upstream lines: {removed[:3]}"
    names = plugin_imports(patch)
    assert names, f"{patch.name} imports nothing from smdm_plugin"
    smdm_lines = [ln for ln in added_lines(patch) if "smdm_plugin" in ln and "import" in ln]
    unread = [ln for ln in smdm_lines if not IMPORT.match(ln)]
    assert not unread, f"{patch.name}: smdm_plugin imports this test cannot read: {unread}"
    for module, name in names:
        mod = importlib.import_module(module)
        assert hasattr(mod, name), f"{patch.name} imports {name} from {module}, which has no such name"


def _guard_of(lines: list, k: int) -> tuple:
    """The nearest enclosing added line of ``lines[k]`` (smaller indentation), and its index."""
    indent = len(lines[k]) - len(lines[k].lstrip())
    for j in range(k - 1, -1, -1):
        ln = lines[j]
        if ln.strip() and not ln.lstrip().startswith("#") and len(ln) - len(ln.lstrip()) < indent:
            return ln.strip(), j
    return "", -1


@pytest.mark.parametrize("patch", PATCHES, ids=lambda p: p.name)
def test_patch_degrades_to_upstream_without_the_plugin(patch):
    """Every plugin import a patch adds either sits under a flag only the plugin defines
    (``if getattr(args, 'sparse...``) or alone in a ``try:`` whose ``except ImportError`` falls back
    to upstream, with the calls in its ``else:`` (so an ImportError inside the plugin is not
    swallowed): a colleague without smdm-plugin runs the patched checkout as upstream."""
    lines = added_lines(patch)
    for k, line in enumerate(lines):
        if not IMPORT.match(line):
            continue
        guard, j = _guard_of(lines, k)
        if guard.startswith("if ") and "getattr(" in guard and "sparse" in guard:
            continue
        assert guard.startswith("try:"), f"{patch.name}: {line.strip()!r} is not guarded (enclosing: {guard!r})"
        indent = len(lines[j]) - len(lines[j].lstrip())
        body, m = [], j + 1
        while m < len(lines) and (not lines[m].strip() or len(lines[m]) - len(lines[m].lstrip()) > indent):
            body.append(lines[m].strip())
            m += 1
        assert m < len(lines) and lines[m].strip().startswith("except ImportError"), \
            f"{patch.name}: the try around {line.strip()!r} has no 'except ImportError' next"
        calls = [b for b in body if b and not b.startswith("#") and not IMPORT.match(" " + b)]
        assert not calls, f"{patch.name}: the try around {line.strip()!r} also runs {calls} (move it to 'else:')"
