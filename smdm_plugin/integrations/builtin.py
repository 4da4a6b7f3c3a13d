"""The built-in integrations, each registered by its own module on import (read by
:data:`smdm_plugin.integrations.registry.INTEGRATIONS` on its first read)."""
from . import mdm, priormdm, motiondiffuse  # noqa: F401,I001  (each calls register_integration; the help lists them so)
