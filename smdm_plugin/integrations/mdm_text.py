"""MDM/DiP text conditioning: the sMDM-stella text-encoder swap and an opt-in text-embedding cache."""
from __future__ import annotations


def install_hooks() -> None:
    """Register this extension's import hooks (called by :func:`smdm_plugin.integrations.mdm.install_hooks`)."""
