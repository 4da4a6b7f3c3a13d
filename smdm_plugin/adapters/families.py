"""The registry of model families: the built-in ones (MDM, priorMDM's DoubleTake, MotionDiffuse)
registered here, others with :func:`register_family`; ``sparsify`` asks them in priority order."""
from __future__ import annotations

from typing import List

import torch.nn as nn

from ..core.registry import Registry
from ..families.doubletake.model import DoubleTakeFamily
from .family import ModelFamily
from ..families.mdm.model import MDMFamily
from ..families.motiondiffuse.model import MotionDiffuseFamily

#: the model families by name
FAMILIES: Registry[ModelFamily] = Registry("model family")


def register_family(family: ModelFamily, *, replace: bool = False) -> ModelFamily:
    """Register ``family`` under ``family.name`` (a name taken is a ``ValueError`` unless
    ``replace``). Returns it."""
    if not isinstance(family, ModelFamily):
        raise TypeError(f"register_family: family must be a ModelFamily instance, got {type(family).__name__}")
    return FAMILIES.register(family.name, family, replace=replace)


for _builtin in (MDMFamily(), DoubleTakeFamily(), MotionDiffuseFamily()):
    register_family(_builtin)


def families() -> List[ModelFamily]:
    """The registered families, in the order they are asked (priority, then registration)."""
    return sorted(FAMILIES.entries(), key=lambda f: -f.priority)


def get_family(name: str) -> ModelFamily:
    return FAMILIES.get(name)


def family_for(model: nn.Module, fn: str = "sparsify") -> ModelFamily:
    """The first registered family that matches ``model``; a ``TypeError`` says why none does."""
    if not isinstance(model, nn.Module):
        raise TypeError(f"{fn}: model must be a torch.nn.Module, got {type(model).__name__}")
    fams = families()
    for fam in fams:
        if fam.matches(model):
            return fam
    why = "; ".join(f"{f.name}: {f.mismatch(model)}" for f in fams)
    raise TypeError(f"{fn}: {type(model).__name__} belongs to no registered model family ({why}). "
                    "Register one with smdm_plugin.register_family")
