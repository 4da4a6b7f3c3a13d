"""What a sparsified model carries: one typed object, attached once as ``model._smdm_state``.

Hooks read and write its named fields only; nothing is shared through dicts of string keys.
Also MDM's calling convention (``forward(x [B, J, F, N], timesteps [B], y)``), shared by the
model hooks and the diffusion wrapper.
"""
from __future__ import annotations

import weakref
from dataclasses import dataclass, field
from typing import Any, Dict, List, Optional, Tuple

import torch
import torch.nn as nn

from ..core.checks import as_lengths, as_mask, require
from ..core.config import SparseConfig
from ..core.plan import KeyframePlan
from ..core.schedule import MaskSchedule

STATE_ATTR = "_smdm_state"


@dataclass(frozen=True)
class Variant:
    """What :func:`smdm_plugin.adapters.mdm.detect_variant` found."""

    arch: str               # trans_enc | trans_dec
    transformer: str        # attribute name of the transformer (seqTransEncoder | seqTransDecoder)
    prefix_len: int         # DiP context frames kept dense (0 otherwise)
    name: str               # mdm-trans_enc, mdm-trans_dec(-emb), dip, doubletake


@dataclass
class SparseState:
    """Everything sparse mode keeps on one model.

    Set once by ``sparsify``: ``config``, ``variant``, ``transformer`` (the
    :class:`~smdm_plugin.core.keyframe_transformer.KeyframeTransformer` that replaced the dense
    one), ``schedule``, ``originals`` (the replaced modules, for ``unsparsify``), ``handles`` (hooks
    to remove), ``diffusions`` (weak references to the diffusions whose loss was wrapped for this
    model). Per call: ``plan``, the :class:`~smdm_plugin.core.plan.KeyframePlan` of the call (over
    the model's frames, DiP prefix included), written by the model's forward pre-hook and cleared
    by its forward hook; ``embed_rows`` (the frame-major rows the input embedding ran on), written
    and cleared by the embedding hooks.
    """

    config: SparseConfig
    variant: Variant
    transformer: nn.Module
    schedule: MaskSchedule
    originals: Dict[Tuple[nn.Module, str], nn.Module] = field(default_factory=dict)
    handles: List[Any] = field(default_factory=list)
    fsq_layers: int = 0
    diffusions: List["weakref.ref"] = field(default_factory=list)
    plan: Optional[KeyframePlan] = None
    embed_rows: Optional[Tuple[torch.Tensor, int, int]] = None


def get_state(model: nn.Module) -> Optional[SparseState]:
    """The :class:`SparseState` of a sparsified model, else None."""
    return getattr(model, STATE_ATTR, None)


def find_sparse_model(model: nn.Module) -> Optional[nn.Module]:
    """The sparsified module inside ``model`` (which may be a DDP, EMA or CFG wrapper)."""
    for m in model.modules():
        if isinstance(getattr(m, STATE_ATTR, None), SparseState):
            return m
    return None


# ----------------------------------------------------------------------------- MDM conventions
def frames_layout(x: torch.Tensor) -> torch.Tensor:
    """MDM's ``[B, J, F, N]`` motion as ``[B, N, J*F]``; ``[B, N, D]`` passes through."""
    if x.dim() == 4:
        B, J, F_, N = x.shape
        return x.permute(0, 3, 1, 2).reshape(B, N, J * F_)
    return x


def lengths_from_y(y: Dict[str, Any], B: int, N: int, device: torch.device) -> torch.Tensor:
    """Valid frames per sample ``[B]`` long from MDM's ``y``: ``y['mask'] [B, 1, 1, N]`` when it
    covers the frames (at least 2 valid frames each), else ``y['lengths']`` (integers in
    ``[2, N]``), else all ``N``. Bad values are a ``ValueError`` (checked on the host when the data
    is on the CPU, with ``torch._assert_async`` on accelerators: no sync)."""
    mask = y.get("mask")
    if isinstance(mask, torch.Tensor) and mask.shape[-1] == N and mask.numel() == B * N:
        lengths = mask.reshape(B, N).to(device=device, dtype=torch.long).sum(1)
        require(lengths >= 2, f"y['mask'] must mark at least 2 valid frames of the N={N} in every sample")
        return lengths
    if y.get("lengths") is not None:
        return as_lengths(y["lengths"], B, N, device, "y['lengths']")
    return torch.full((B,), N, dtype=torch.long, device=device)


def forced_from_y(y: Dict[str, Any], B: int, N: int, device: torch.device) -> Optional[torch.Tensor]:
    """``y['keyframe_forced']`` as bool ``[B, N]`` on ``device`` (shape checked), or None."""
    return as_mask(y.get("keyframe_forced"), B, N, device, "y['keyframe_forced']")


def protected_count(forced: Optional[torch.Tensor], lengths: torch.Tensor) -> int:
    """The most protected frames (both ends + forced) of any sample: a host read of ``forced``
    (free on the CPU; one device sync on an accelerator — DoubleTake and in-betweening only)."""
    if forced is None:
        return 0
    idx = torch.arange(forced.shape[1], device=forced.device)
    ends = (idx[None] == 0) | (idx[None] == (lengths - 1)[:, None])
    valid = idx[None] < lengths[:, None]
    return int(((forced | ends) & valid).sum(1).max()) if forced.shape[0] else 0
