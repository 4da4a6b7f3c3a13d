"""MDM's ``sample.edit`` in-between mode with user keyframes as forced keyframes of the sparse model."""
from __future__ import annotations


def install_hooks() -> None:
    """Register this extension's import hooks (called by :func:`smdm_plugin.integrations.mdm.install_hooks`)."""
