"""The model-family protocol: what ``sparsify`` needs to know about one kind of model."""
from __future__ import annotations

import weakref
from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from typing import Any, ClassVar, Dict, List, Optional, Sequence, Tuple, Type, TypeVar

import torch
import torch.nn as nn

from ..core.config import SparseConfig
from ..core.plan import KeyframePlan
from ..core.schedule import MaskSchedule
from .call import CallInputs


@dataclass(frozen=True)
class Variant:
    """What a family's :meth:`~smdm_plugin.adapters.family.ModelFamily.variant` found."""

    arch: str               # trans_enc | trans_dec | motiondiffuse
    transformer: str        # attribute of the keyframe-only blocks (seqTransEncoder | seqTransDecoder |
                            # temporal_decoder_blocks)
    prefix_len: int         # DiP context frames kept dense (0 otherwise)
    name: str               # mdm-trans_enc, mdm-trans_dec(-emb), dip, doubletake, motiondiffuse


class ModelFamily(ABC):
    """One kind of model ``sparsify`` can convert. Subclass, then :func:`register_family`."""

    #: a short unique name (``mdm``, ``doubletake``, ``motiondiffuse``)
    name: ClassVar[str] = ""
    #: families with a higher priority are asked first (a specialisation before its base)
    priority: ClassVar[int] = 0

    def __deepcopy__(self, memo: dict) -> "ModelFamily":   # one object per family (EMA copies share it)
        return self

    def __copy__(self) -> "ModelFamily":
        return self

    # ------------------------------------------------------------------ recognising a model
    @abstractmethod
    def matches(self, model: nn.Module) -> bool:
        """Whether ``model`` belongs to this family (by its structure; no side effects)."""

    def mismatch(self, model: nn.Module) -> str:
        """Why ``model`` does not match (for the error message), e.g. the missing attributes."""
        return "does not match"

    @abstractmethod
    def variant(self, model: nn.Module) -> Variant:
        """What ``model`` is (raises ``TypeError`` for an unsupported configuration)."""

    def prepare_config(self, model: nn.Module, config: SparseConfig, variant: Variant) -> SparseConfig:
        """The config this family runs with (e.g. DiP's prefix). A setting the user asked for that
        cannot apply must be a warning or an error, never dropped silently."""
        return config

    # ------------------------------------------------------------------ surgery
    @abstractmethod
    def io_layers(self, model: nn.Module) -> Sequence[Tuple[nn.Module, str]]:
        """``(owner, attribute)`` of the ``nn.Linear`` input / output layers that become Lipschitz
        sine MLPs when ``config.lipschitz`` (attributes that are absent or not linear are skipped)."""

    def latent_dim(self, model: nn.Module) -> int:
        """Hidden width of the Lipschitz MLPs when ``config.lipschitz_hidden`` is None."""
        return int(model.latent_dim)

    @abstractmethod
    def install(self, model: nn.Module, state: "SparseState") -> None:
        """Make the blocks keyframe-only and hook the calls. Record every replaced attribute in
        ``state.originals`` *before* replacing it and every hook in ``state.handles``, so that a
        failure part-way (and ``unsparsify``) can undo it exactly. What the family keeps per model
        goes in its own :class:`~smdm_plugin.adapters.state.FamilyState`, ``state.family_state``."""

    def uninstall(self, model: nn.Module, state: "SparseState") -> None:
        """Before ``unsparsify`` restores ``state.originals``: carry weights trained in sparse mode
        that have a dense equivalent into what will be restored (default nothing). Not called when a
        failed ``sparsify`` is rolled back."""

    # ------------------------------------------------------------------ one model call
    @abstractmethod
    def read_call(self, state: "SparseState", args: tuple, kwargs: Dict[str, Any]) -> CallInputs:
        """The frames, timesteps, lengths, forced frames and given keyframes of one call: the one
        place a family reads the call's :class:`~smdm_plugin.adapters.request.KeyframeRequest`
        (with :func:`~smdm_plugin.adapters.request.request_of`)."""

    # ------------------------------------------------------------------ the diffusion's loss
    @abstractmethod
    def training_inputs(self, state: "SparseState", x_start: torch.Tensor, model_kwargs: Dict[str, Any]
                        ) -> CallInputs:
        """The :class:`CallInputs` of a ``training_losses(model, x_start, t, model_kwargs)`` call
        (frames from ``x_start``, no timesteps): :meth:`read_call` on the arguments the model will
        get, so the request is read in one place."""

    @abstractmethod
    def with_keyframes(self, state: "SparseState", model_kwargs: Dict[str, Any], mask: torch.Tensor,
                       capacity: Optional[int]) -> Dict[str, Any]:
        """A copy of ``model_kwargs`` that hands the training keyframes to the model: the one place
        a family builds the call's :class:`~smdm_plugin.adapters.request.KeyframeRequest` (with
        :func:`~smdm_plugin.adapters.request.with_request`)."""

    # ------------------------------------------------------------------ graph capture
    def traces_whole(self, model: nn.Module) -> bool:
        """Whether graph capture takes a sparse call of ``model`` whole (``fullgraph=True``, the
        default); False where a forward pre-hook says it reads on the host once per call (its
        ``reads_on_host``: DoubleTake's forcing without a bound, on any model it is attached to)."""
        return not any(getattr(h, "reads_on_host", False) for h in model._forward_pre_hooks.values())

    def finish_losses(self, state: "SparseState", model: nn.Module, terms: Dict[str, Any],
                      mask: torch.Tensor) -> Dict[str, Any]:
        """What sparse mode adds to the diffusion's returned ``terms`` (default: nothing)."""
        return terms


# ---------------------------------------------------------------------- the state a family is handed
# (here, beside the family: the state holds its family, the family's methods receive the state)
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
    (in the valid frames, within its capacity by construction: the plan does not check it again),
    and ``schedule_plan``, its plan when the schedule made both in one op (else None: the call builds it).
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
    schedule_plan: Optional[KeyframePlan] = None
