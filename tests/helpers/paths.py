"""Where things are: the repository, ../shared/data beside it (tests that need data skip when absent)."""
from __future__ import annotations

from pathlib import Path

TESTS = Path(__file__).resolve().parents[1]
ROOT = TESTS.parent                      # the repository (holds smdm_plugin/, configs/, docs/, patches/)
SHARED = ROOT.parent / "shared" / "data"
HML = SHARED / "cmu-humanml3d"
HML_LARGE = SHARED / "cmu-humanml3d-large"
MOCAP = SHARED / "cmu-mocap"
