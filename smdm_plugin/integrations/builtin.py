"""The built-in integrations, each registered in
:data:`smdm_plugin.integrations.registry.INTEGRATIONS` by its own module on import (the launcher
imports this module)."""
from . import mdm, priormdm, motiondiffuse  # noqa: F401,I001  (each calls register_integration; the help lists them so)
