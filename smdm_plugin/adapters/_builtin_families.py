"""The built-in model families (each module registers its own on import)."""
from . import doubletake, mdm, motiondiffuse  # noqa: F401
