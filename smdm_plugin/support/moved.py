"""Module paths that 0.9 moved: importing an old one fails with one line that names the new one
(an upstream checkout patched by an older ``patches/*.patch`` imports them; the finder is
``smdm_plugin/__init__.py``'s, which loads this module only on a miss)."""
from __future__ import annotations

from typing import Dict, Optional

#: old module -> new module, both below ``smdm_plugin.`` (CHANGELOG, 0.9.0 "Layout")
MOVED: Dict[str, str] = {
    "adapters.mdm": "families.mdm.model",
    "adapters.doubletake": "families.doubletake.model",
    "adapters.motiondiffuse": "families.motiondiffuse.model",
    "adapters.diffusion": "adapters.diffusion_wrapper",
    "adapters.inbetween": "adapters.inbetween_sampling",
    "integrations.mdm": "families.mdm.upstream",
    "integrations.mdm_train": "families.mdm.upstream_train",
    "integrations.mdm_text": "families.mdm.upstream_text",
    "integrations.mdm_edit": "families.mdm.upstream_edit",
    "integrations.priormdm": "families.doubletake.upstream",
    "integrations.motiondiffuse": "families.motiondiffuse.upstream",
    "integrations.compile": "runtime.compile",
    "integrations.distributed": "runtime.distributed",
    "integrations.registry": "integrations.checkouts",
    "core.launches": "runtime.launches",
    "core.atomic": "support.atomic",
    "core.config_files": "support.config_files",
    "core.argtypes": "support.argtypes",
    "core.values": "support.values",
    "core.embedding": "reference.embedding",
    "core.features": "core.selection_features",
    "metrics.features": "metrics.feature_measures",
    "metrics.inbetween": "metrics.inbetween_metrics",
    "apps.common.inbetween": "apps.common.bundle_inbetween",
    "io.checkpoint": "io.checkpoint_files",
    "reference.diffusion": "reference.simple_diffusion",
}
_ROOT = "smdm_plugin."


def moved_message(old: str) -> Optional[str]:
    """The one-line message for the old module ``old`` (``smdm_plugin.x.y``), or None if it did not move."""
    new = MOVED.get(old[len(_ROOT):]) if old.startswith(_ROOT) else None
    if new is None:
        return None
    return (f"{old} moved to {_ROOT}{new} in smdm-plugin 0.9 (CHANGELOG, 0.9.0 'Layout'); an upstream "
            f"checkout patched by an older patches/*.patch: restore the patched files (git checkout -- <files>) "
            f"and apply the patch of this version")

