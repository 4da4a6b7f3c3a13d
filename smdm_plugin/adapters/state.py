"""What a sparsified model carries: one typed object, attached once as ``model._smdm_state``.

Hooks read and write its named fields only; nothing is shared through dicts of string keys.
:class:`SparseState` holds what every family shares; what one family keeps besides lives in its
own typed object (:class:`FamilyState`, e.g. ``adapters.mdm.MDMState``), ``state.family_state``.
"""
from __future__ import annotations

import weakref
from dataclasses import dataclass, field
from typing import Any, Dict, List, Optional, Tuple, Type, TypeVar

import torch
import torch.nn as nn

from ..core.config import SparseConfig
from ..core.plan import KeyframePlan
from ..core.schedule import MaskSchedule
from .family import ModelFamily, Variant

#: the attribute a sparsified model carries its one state object under
STATE_ATTR = "_smdm_state"


class FamilyState:
    """What one family keeps on a sparse model besides :class:`SparseState` (a dataclass
    subclass, defined by the family and set by its ``install``; the base: nothing)."""


S = TypeVar("S", bound=FamilyState)


def family_state_of(state: "SparseState", kind: Type[S]) -> S:
    """``state.family_state``, checked to be a ``kind`` (the family that converted the model wrote
    it); a ``TypeError`` naming both otherwise."""
    family_state = state.family_state
    if not isinstance(family_state, kind):
        raise TypeError(f"{state.family.name}: the model's family state is {type(family_state).__name__}, "
                        f"not {kind.__name__}")
    return family_state


@dataclass
class SparseState:
    """Everything sparse mode keeps on one model, for every family.

    Set once by ``sparsify``: ``config``, ``variant``, ``schedule``, ``family`` (the registered
    :class:`~smdm_plugin.adapters.family.ModelFamily` that converted the model), ``family_state``
    (the family's own :class:`FamilyState`, set by its ``install``), ``originals`` (what was replaced,
    ``(owner, attribute) -> old value`` — :data:`MISSING` when the attribute did not exist on the
    instance — for ``unsparsify``), ``handles`` (hooks to remove), ``diffusions`` (weak references
    to the diffusions whose loss was wrapped for this model), ``lipschitz_mlps`` (the Lipschitz MLPs
    the conversion installed: a call reads them without walking the model). Per call: ``plan``, the
    :class:`~smdm_plugin.core.plan.KeyframePlan` of the running call (over the model's frames, DiP
    prefix included), for families whose hooks share it (MDM: written by the model's forward
    pre-hook, read by the embedding hooks, cleared by the forward hook); ``schedule_mask``, the
    training mask the diffusion wrapper made with the model's own schedule for the running step
    (in the valid frames, within its capacity by construction: the plan does not check it again).
    """

    config: SparseConfig
    variant: Variant
    schedule: MaskSchedule
    family: ModelFamily
    family_state: FamilyState = field(default_factory=FamilyState)
    originals: Dict[Tuple[Any, str], Any] = field(default_factory=dict)
    handles: List[Any] = field(default_factory=list)
    diffusions: List["weakref.ref"] = field(default_factory=list)
    lipschitz_mlps: List[nn.Module] = field(default_factory=list)
    plan: Optional[KeyframePlan] = None
    schedule_mask: Optional[torch.Tensor] = None


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
