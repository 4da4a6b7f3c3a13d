"""Shared fixtures of the upstream integration tests (MDM/DiP, priorMDM, MotionDiffuse).

Every upstream test is skipped unless its ``SMDM_<NAME>_ROOT`` points at a checkout (read-only:
the tests copy it into a temporary directory and patch the copy). Real motion comes from
``SMDM_HUMANML3D_DIR`` (default: ``shared/data/cmu-humanml3d`` beside this repository, or
inside the repository). Helpers: ``_upstream.py``.
"""
from __future__ import annotations

import os
import sys
from typing import Dict, Optional

import pytest

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from _upstream import PATCHES, copy_checkout, find_humanml3d, git_apply, link_humanml3d  # noqa: E402


@pytest.fixture(scope="session")
def humanml3d_dir() -> str:
    d = find_humanml3d()
    if d is None:
        pytest.skip("no HumanML3D-format data (set SMDM_HUMANML3D_DIR)")
    return d


@pytest.fixture(scope="session")
def upstream_copy(tmp_path_factory, humanml3d_dir):
    """Factory: ``upstream_copy(src, name, patch=None)`` -> a fresh copy of the checkout ``src``
    in a session temp dir, with ``dataset/HumanML3D`` linked to the data and ``patch`` (a file
    name under ``patches/`` or a path) applied when given."""
    made: Dict[tuple, str] = {}

    def make(src: str, name: str, patch: Optional[str] = None) -> str:
        key = (os.path.abspath(src), name, patch)
        if key in made:
            return made[key]
        dst = str(tmp_path_factory.mktemp(name))
        copy_checkout(src, dst)
        link_humanml3d(dst, humanml3d_dir)
        if patch:
            path = patch if os.path.isabs(patch) else os.path.join(PATCHES, patch)
            res = git_apply(path, dst)
            if res.returncode != 0:
                pytest.fail(f"git apply {path} failed in a copy of {src}:\n{res.stderr}")
        made[key] = dst
        return dst

    return make

