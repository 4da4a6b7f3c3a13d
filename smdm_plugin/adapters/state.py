"""What a sparsified model carries: one typed object, attached once as ``model._smdm_state``.

Hooks read and write its named fields only; nothing is shared through dicts of string keys.
:class:`SparseState` (defined in :mod:`.family`, beside the :class:`~.family.ModelFamily` it
holds and that receives it) holds what every family shares; what one family keeps besides lives in its
own typed object (:class:`FamilyState`, e.g. ``adapters.mdm.MDMState``), ``state.family_state``.
"""
from __future__ import annotations

from typing import Any, Dict, Optional, Tuple

import torch.nn as nn

from ..core.config import SparseConfig
from .family import FamilyState, SparseState, Variant, family_state_of  # noqa: F401  (defined with ModelFamily)

#: the attribute a sparsified model carries its one state object under
STATE_ATTR = "_smdm_state"


class _Missing:
    def __repr__(self) -> str:
        return "MISSING"


#: marks, in :attr:`SparseState.originals`, an instance attribute that did not exist before
MISSING = _Missing()


def restore_originals(originals: Dict[Tuple[Any, str], Any]) -> None:
    """Put back what :attr:`SparseState.originals` recorded (newest first); :data:`MISSING`
    deletes the instance attribute again."""
    for (owner, name), old in reversed(list(originals.items())):
        if old is MISSING:
            if name in owner.__dict__:
                delattr(owner, name)
            elif isinstance(owner, nn.Module) and name in owner._modules:
                del owner._modules[name]
        else:
            setattr(owner, name, old)


def get_state(model: nn.Module) -> Optional[SparseState]:
    """The :class:`SparseState` of a sparsified model, else None."""
    return getattr(model, STATE_ATTR, None)


def find_sparse_model(model: nn.Module) -> Optional[nn.Module]:
    """The sparsified module inside ``model`` (which may be a DDP, EMA or CFG wrapper)."""
    for m in model.modules():
        if isinstance(getattr(m, STATE_ATTR, None), SparseState):
            return m
    return None


def sparse_config_of(model: nn.Module) -> Optional[SparseConfig]:
    """The :class:`~smdm_plugin.core.config.SparseConfig` of a sparsified ``model`` (or of its first
    sparsified submodule: DDP, EMA wrappers), else None. The one place a model's config lives is its
    state (``model._smdm_state.config``)."""
    sparse = find_sparse_model(model)
    return None if sparse is None else get_state(sparse).config
