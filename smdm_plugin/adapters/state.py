"""What a sparsified model carries: one typed object, attached once as ``model._smdm_state``.

Hooks read and write its named fields only; nothing is shared through dicts of string keys.
Also MDM's calling convention (``forward(x [B, J, F, N], timesteps [B], y)``), shared by the
model hooks and the diffusion wrapper.
"""
from __future__ import annotations

import warnings
import weakref
from dataclasses import dataclass, field
from typing import Any, Dict, List, Optional, Tuple

import torch
import torch.nn as nn

from ..core import consts
from ..core.attention import compute_dtype
from ..core.checks import as_lengths, compiling, host_checkable, require
from ..core.config import STATE_ATTR, SparseConfig  # STATE_ATTR: the attribute the state lives under
from ..core.plan import KeyframePlan
from ..core.schedule import MaskSchedule



@dataclass(frozen=True)
class Variant:
    """What a family's :meth:`~smdm_plugin.adapters.family.ModelFamily.variant` found."""

    arch: str               # trans_enc | trans_dec | motiondiffuse
    transformer: str        # attribute of the keyframe-only blocks (seqTransEncoder | seqTransDecoder |
                            # temporal_decoder_blocks)
    prefix_len: int         # DiP context frames kept dense (0 otherwise)
    name: str               # mdm-trans_enc, mdm-trans_dec(-emb), dip, doubletake, motiondiffuse


@dataclass
class SparseState:
    """Everything sparse mode keeps on one model.

    Set once by ``sparsify``: ``config``, ``family`` (the registered
    :class:`~smdm_plugin.adapters.family.ModelFamily` that converted the model), ``variant``,
    ``transformer`` (MDM: the :class:`~smdm_plugin.core.keyframe_transformer.KeyframeTransformer`
    that replaced the dense one; None where the family runs its blocks itself), ``schedule``,
    ``originals`` (what was replaced, ``(owner, attribute) -> old value`` — :data:`MISSING` when
    the attribute did not exist on the instance — for ``unsparsify``), ``handles`` (hooks to
    remove), ``diffusions`` (weak references to the diffusions whose loss was wrapped for this
    model). Per call: ``plan``, the :class:`~smdm_plugin.core.plan.KeyframePlan` of the call (over
    the model's frames, DiP prefix included), written by the model's forward pre-hook and cleared
    by its forward hook; ``embed_rows`` (the frame-major rows the input embedding ran on), written
    and cleared by the embedding hooks; ``last_mask`` (bool ``[B, N]``, the keyframes of the latest
    call, for families whose trainer reads them after the call: MotionDiffuse's keyframe-only loss);
    ``extra``: family-specific data fixed at ``sparsify`` (MotionDiffuse: its timestep embedding).
    """

    config: SparseConfig
    variant: Variant
    transformer: Optional[nn.Module]
    schedule: MaskSchedule
    originals: Dict[Tuple[Any, str], Any] = field(default_factory=dict)
    handles: List[Any] = field(default_factory=list)
    fsq_layers: int = 0
    diffusions: List["weakref.ref"] = field(default_factory=list)
    plan: Optional[KeyframePlan] = None
    embed_rows: Optional[Tuple[torch.Tensor, int, int]] = None
    lipschitz_pass: Optional[Any] = None          # core.lipschitz.lipschitz_pass of the running call
    family: Any = None
    last_mask: Optional[torch.Tensor] = None
    extra: Any = None


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
    is on the CPU, with ``torch._assert_async`` on accelerators: no sync).

    One exception, decided from shapes alone: when ``y['mask']`` does not cover the ``N`` frames
    (``[B, 1, 1, M]``, ``M != N``), the conditions describe another length than the window being
    sampled: MDM's ``sample.generate`` with dataset prompts passes a one-frame placeholder mask and
    ``lengths`` 120 whatever ``--motion_length`` is. Then ``y['lengths']`` (still >= 2) are cut to
    ``N``, as the dense model treats every frame of the window as valid, with a warning."""
    mask = y.get("mask")
    if isinstance(mask, torch.Tensor) and mask.shape[-1] == N and mask.numel() == B * N:
        def from_mask() -> torch.Tensor:
            m = mask.reshape(B, N).to(device=device)
            lengths = m.sum(1) if m.dtype == torch.bool else m.to(torch.long).sum(1)   # a bool sum is long
            require(lengths >= 2, f"y['mask'] must mark at least 2 valid frames of the N={N} in every sample")
            return lengths
        return reuse_for(mask, ("mask", B, N, device), from_mask)
    if isinstance(mask, torch.Tensor) and mask.dim() and mask.shape[-1] != N and y.get("lengths") is not None:
        if not compiling():
            warnings.warn(f"y['mask'] covers {mask.shape[-1]} frames but the motion has N={N}: y['lengths'] "
                          f"are cut to N (MDM's sample.generate does this with dataset prompts)", stacklevel=3)
        return as_lengths(y["lengths"], B, N, device, "y['lengths']", clip=True)
    if y.get("lengths") is not None:
        return as_lengths(y["lengths"], B, N, device, "y['lengths']")
    return torch.full((B,), N, dtype=torch.long, device=device)


_REUSED: List[tuple] = []          # (source tensor, its version, key, result): the last few


def reuse_for(source: torch.Tensor, key: tuple, compute) -> torch.Tensor:
    """``compute()``, or its result for the same ``source`` tensor (the same object, unchanged
    since: same version) and ``key`` from one of the last few calls: the lengths of a sampling loop's
    ``y['mask']`` are read and validated once, not at every step and guidance pass (and once per
    training step: the diffusion wrapper's x0 call and the model call share them). Not while
    tracing (the traced graph computes them)."""
    if compiling():
        return compute()
    for src, version, k, out in _REUSED:
        if src is source and version == source._version and k == key:
            return out
    out = compute()
    _REUSED.insert(0, (source, source._version, key, out))
    del _REUSED[4:]
    return out


def keyframe_plan(state: SparseState, frames: torch.Tensor, timesteps: Any, lengths: torch.Tensor,
                  forced: Optional[torch.Tensor], mask: Any = None, capacity: Any = None,
                  mask_name: str = "KeyframeRequest.mask") -> KeyframePlan:
    """The keyframe plan of one model call, for every family.

    Args:
        frames: the call's motion ``[B, N, D]`` (x_t while sampling).
        timesteps: ``[B]`` (or a scalar) diffusion step; None = 0.
        lengths: ``[B]`` long, validated (``2 <= L <= N``).
        forced: bool ``[B, N]`` frames that must be keyframes, or None.
        mask: bool ``[B, N]`` keyframes chosen by the caller (training: the diffusion wrapper from
            x0), else None: the sampling schedule on ``(frames, timesteps)``.
        capacity: the slot count that goes with a given ``mask`` (a Python int); None: the largest
            row of ``mask`` when it can be read without a sync, else ``N``.
        mask_name: how the caller passed ``mask`` (error messages).
    """
    B, N = frames.shape[:2]
    device = frames.device
    taps = None                                            # C¹ fill taps looked up (sampling, uniform mask)
    if mask is not None:                                   # training (or a caller's own mask)
        valid = consts.arange(N, device)[None] < lengths[:, None]
        # a mask chosen while loading (keyframe_collate) is still on the CPU: upstream loops move
        # y's tensors, not the KeyframeRequest; copy it without waiting for the device
        mask = torch.as_tensor(mask).to(device, non_blocking=True)
        if tuple(mask.shape) != (B, N):
            raise ValueError(f"{mask_name} must be bool [B, N]=[{B}, {N}], got {tuple(mask.shape)}")
        mask = mask.to(torch.bool) & valid
        if forced is not None:
            mask = mask | (forced & valid)
        if capacity is None:                               # a mask from elsewhere: size it safely
            capacity = int(mask.sum(1).max()) if host_checkable(mask) and B else N
        check, cubic = True, None
    else:                                                  # sampling: the schedule on x_t
        t = timesteps if timesteps is not None else torch.zeros(B, dtype=torch.long, device=device)
        if forced is None and state.schedule.late_steps == 0:   # the uniform mask: a table lookup
            cubic = state.schedule.cubic_samples(t, B, device, frames.shape[-1])
            if cubic is not None and not state.variant.prefix_len:
                f_tab, w_tab = state.schedule.cubic_taps(N, device)
                taps = (f_tab[lengths], w_tab[lengths])
            return state.schedule.uniform_plan(lengths, N, state.variant.prefix_len, cubic, taps,
                                               compute_dtype(frames))   # the key bias in the attention's dtype
        mask = state.schedule.sampling_mask(frames, t, lengths, forced, checked=True)
        capacity = state.schedule.capacity(N, training=False, forced=protected_count(forced, lengths))
        check = False                                      # 2..capacity keyframes by construction
        cubic = state.schedule.cubic_samples(t, B, device, frames.shape[-1])   # C¹ fill: [B] bool
        if cubic is not None and forced is None and state.schedule.late_steps == 0 and not state.variant.prefix_len:
            f_tab, w_tab = state.schedule.cubic_taps(N, device)            # the uniform mask: look up
            taps = (f_tab[lengths], w_tab[lengths])
    capacity = max(1, min(int(capacity), N))
    prefix = state.variant.prefix_len
    if prefix:
        mask = torch.cat([mask.new_ones(B, prefix), mask], dim=1)
        capacity += prefix
    return KeyframePlan.build(mask, capacity, check=check, cubic=cubic, taps=taps)


def protected_count(forced: Optional[torch.Tensor], lengths: torch.Tensor) -> int:
    """The most protected frames (both ends + forced) of any sample: a host read of ``forced``
    (free on the CPU; one device sync on an accelerator — DoubleTake and in-betweening only)."""
    if forced is None:
        return 0
    idx = torch.arange(forced.shape[1], device=forced.device)
    ends = (idx[None] == 0) | (idx[None] == (lengths - 1)[:, None])
    valid = idx[None] < lengths[:, None]
    return int(((forced | ends) & valid).sum(1).max()) if forced.shape[0] else 0
