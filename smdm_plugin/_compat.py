"""Old flat module paths (0.1: ``smdm_plugin.selection``, ``smdm_plugin.bvh`` ...) keep working for
one release: importing one warns (DeprecationWarning) and returns the module at its new place, the
same module object (so monkey-patching and ``isinstance`` checks see one class)."""
from __future__ import annotations

import importlib
import importlib.abc
import importlib.machinery
import sys
import warnings

#: old module name -> new module name (removed in 0.3)
MOVED = {
    **{f"smdm_plugin.{m}": f"smdm_plugin.core.{m}" for m in (
        "config", "selection", "features", "interpolation", "keyframe_transformer",
        "attention_backends", "lipschitz", "fsq", "schedule", "losses")},
    "smdm_plugin.backbone": "smdm_plugin.reference.backbone",
    "smdm_plugin.diffusion": "smdm_plugin.reference.diffusion",
    "smdm_plugin.bvh": "smdm_plugin.io.bvh",
    "smdm_plugin.checkpoint": "smdm_plugin.io.checkpoint",
    **{f"smdm_plugin.{m}": f"smdm_plugin.apps.{m}" for m in ("cli", "bench", "ablate", "demo")},
}


class _AliasLoader(importlib.abc.Loader):
    def __init__(self, new: str) -> None:
        self.new = new

    def create_module(self, spec):  # default module; replaced in exec_module
        return None

    def exec_module(self, module) -> None:
        warnings.warn(f"{module.__name__} moved to {self.new}; the old path is removed in 0.3",
                      DeprecationWarning, stacklevel=2)
        sys.modules[module.__name__] = importlib.import_module(self.new)


class _AliasFinder(importlib.abc.MetaPathFinder):
    def find_spec(self, fullname, path, target=None):
        new = MOVED.get(fullname)
        if new is None:
            return None
        return importlib.machinery.ModuleSpec(fullname, _AliasLoader(new))


def install() -> None:
    if not any(isinstance(f, _AliasFinder) for f in sys.meta_path):
        sys.meta_path.append(_AliasFinder())
