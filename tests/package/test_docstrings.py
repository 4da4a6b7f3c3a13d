"""Every module of the package opens with a short docstring saying what it is (the design notes
that explain it at length are docs/modules.md), and no source file names an issue number: the
code says what it does, the history lives in git and CHANGELOG.md."""
from __future__ import annotations

import ast
import re
from pathlib import Path

import smdm_plugin

PKG = Path(smdm_plugin.__file__).resolve().parent
#: the most lines a module docstring spans, its quotes included
MAX_LINES = 12
#: "issue 27", "issues 12 and 36", "issue #36", "(#36)", "gh-36"
ISSUE = re.compile(r"(?i)\bissues?\s*#?\d+|(?<![\w&])#\d{1,4}\b(?![0-9a-f])|\bgh-\d+")


def modules():
    return sorted(p for p in PKG.rglob("*.py") if "__pycache__" not in p.parts)


def test_every_module_has_a_short_docstring() -> None:
    missing, long = [], []
    for path in modules():
        tree = ast.parse(path.read_text(encoding="utf-8"))
        first = tree.body[0] if tree.body else None
        if ast.get_docstring(tree) is None or first is None:
            missing.append(str(path.relative_to(PKG)))
            continue
        n = first.end_lineno - first.lineno + 1
        if n > MAX_LINES:
            long.append(f"{path.relative_to(PKG)} ({n} lines)")
    assert not missing, f"modules without a docstring: {missing}"
    assert not long, f"module docstrings over {MAX_LINES} lines (move the essay to docs/modules.md): {long}"


def test_no_source_names_an_issue_number() -> None:
    bad = [f"{path.relative_to(PKG)}:{i}: {line.strip()}" for path in modules()
           for i, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1) if ISSUE.search(line)]
    assert not bad, f"issue numbers in the source (say what the code does instead): {bad}"


def test_the_issue_pattern_sees_what_it_should() -> None:
    hits = ["see issue 27", "(issue #36)", "fixed in #36.", "Issues 12 and 36", "gh-39"]
    misses = ["colour #1f77b4", "caption#word/POS", "``0#0``", "# comment 36", "tissue 3"]
    assert all(ISSUE.search(h) for h in hits) and not any(ISSUE.search(m) for m in misses)
