"""The patches for upstream checkouts (``patches/*.patch``) only add lines, and every plugin name
those lines import still exists (a renamed or removed function would break upstream's code only
when the patch runs, which CI never does: it has no upstream checkout)."""
from __future__ import annotations

import importlib
import re
from pathlib import Path

import pytest

PATCHES = sorted((Path(__file__).resolve().parents[1] / "patches").glob("*.patch"))
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
