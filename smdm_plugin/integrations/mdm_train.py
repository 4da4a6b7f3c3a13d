"""MDM/DiP training under ``torchrun``: DistributedDataParallel, a sampler per rank, rank-0 writes."""
from __future__ import annotations


def install_hooks() -> None:
    """Register this extension's import hooks (called by :func:`smdm_plugin.integrations.mdm.install_hooks`)."""
