"""The attention maths the package writes itself, in one place.

Attention modules keep ``nn.MultiheadAttention``'s parameter layout (``in_proj_weight [3E, E]``,
``in_proj_bias [3E]``, ``out_proj``); the attention itself is PyTorch's
``F.scaled_dot_product_attention``. :class:`~smdm_plugin.core.fsq.FSQMultiheadAttention` and the
``varlen`` backend (which runs PyTorch's own transformer layers on packed rows) both project with
:func:`project_qkv` and attend with :func:`attend`.
"""
from __future__ import annotations

import math
from typing import List, Optional, Tuple

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from .checks import compiling, static_shapes


def project_qkv(attn: nn.Module, query: Tensor, key: Tensor, value: Tensor) -> Tuple[Tensor, Tensor, Tensor]:
    """``q, k, v [..., E]``: ``attn``'s in-projection of ``query`` / ``key`` / ``value`` (any
    leading shape, in the input's own layout). Self-attention (``query is key is value``) is one
    matmul, a shared memory (``key is value``) two; the results may be views of one tensor."""
    W, b = attn.in_proj_weight, attn.in_proj_bias
    E = W.shape[1]
    if query is key and key is value:
        q, k, v = F.linear(query, W, b).chunk(3, dim=-1)
        return q, k, v
    bq, bkv = (b[:E], b[E:]) if b is not None else (None, None)
    q = F.linear(query, W[:E], bq)
    if key is value:
        k, v = F.linear(key, W[E:], bkv).chunk(2, dim=-1)
        return q, k, v
    bk = bkv[:E] if bkv is not None else None
    return q, F.linear(key, W[E:2 * E], bk), project_value(attn, value)


def project_value(attn: nn.Module, value: Tensor) -> Tensor:
    """``v [..., E]``: ``attn``'s value projection alone."""
    W, b = attn.in_proj_weight, attn.in_proj_bias
    E = W.shape[1]
    return F.linear(value, W[2 * E:], b[2 * E:] if b is not None else None)


def attend_single_key(attn: nn.Module, value: Tensor, sample: Tensor) -> Tensor:
    """Attention when each sample has exactly one key (MDM trans_dec: the condition token):
    softmax over one key is exactly 1, so query row ``r`` gets the value row of its sample
    ``sample[r]`` whatever the query is (its projection gets zero gradient, as in the full maths).
    ``value [B, E]`` (the module's input), ``sample [T]`` long; returns ``[T, E]`` before
    ``out_proj``. In training the module's dropout drops that one weight per row and head, as SDPA
    does."""
    o = F.embedding(sample, project_value(attn, value))                  # [T, E]
    if attn.training and attn.dropout > 0.0:
        H = attn.num_heads
        keep = F.dropout(o.new_ones(o.shape[0], H, 1), attn.dropout, True)
        o = (o.view(o.shape[0], H, -1) * keep).reshape(o.shape)
    return o


def attend(attn: nn.Module, q: Tensor, k: Tensor, v: Tensor, mask: Optional[Tensor],
           scale: Optional[float] = None) -> Tensor:
    """``F.scaled_dot_product_attention`` of heads ``q, k [B, H, L|S, e]``, ``v [B, H, S, hd]``
    with an additive ``mask`` broadcastable to ``[B, H, L, S]`` (or None), ``scale`` (None:
    ``1/sqrt(e)``) and ``attn``'s dropout in training: ``[B, H, L, hd]``."""
    p = attn.dropout if attn.training else 0.0
    return F.scaled_dot_product_attention(q, k, v, attn_mask=mask, dropout_p=p, scale=scale)


def attend_with_weights(attn: nn.Module, q: Tensor, k: Tensor, v: Tensor, mask: Optional[Tensor],
                        scale: Optional[float] = None) -> Tuple[Tensor, Tensor]:
    """:func:`attend` that also returns the attention weights ``[B, H, L, S]`` (before dropout),
    written out (SDPA does not return them): ``(out [B, H, L, hd], weights)``."""
    scores = q @ k.transpose(-2, -1)
    scores = scores / math.sqrt(q.shape[-1]) if scale is None else scores * scale
    if mask is not None:
        scores = scores + mask
    weights = torch.softmax(scores, dim=-1)
    return F.dropout(weights, p=attn.dropout, training=attn.training) @ v, weights


#: elements a key mask's rows are aligned to (the memory-efficient kernel's alignment: no padded copy)
MASK_ALIGN = 16


def aligned_key_bias(bias: Tensor) -> Tensor:
    """An additive key mask ``[B, S]`` as ``[B, 1, 1, S]`` (a 4-D mask as it is) whose rows start
    every :data:`MASK_ALIGN` elements: a copy into a padded buffer when they do not already (the
    stride every SDPA kernel reads without a padded copy of its own; cuDNN reads it as given). While
    tracing, the view as it is: a graph's layouts are its compiler's (inductor aligns SDPA's mask
    itself), and an intermediate's storage offset is not known to the trace."""
    if bias.dim() == 2:
        bias = bias[:, None, None, :]
    if compiling():
        return bias
    if bias.stride(-1) == 1 and all(s % MASK_ALIGN == 0 for s in bias.stride()[:-1]) \
            and bias.storage_offset() % MASK_ALIGN == 0:
        return bias
    S = bias.shape[-1]
    out = bias.new_empty(*bias.shape[:-1], -(-S // MASK_ALIGN) * MASK_ALIGN)[..., :S]
    return out.copy_(bias)


def sdpa_layout_problems(q: Tensor, k: Tensor, v: Tensor, mask: Optional[Tensor]) -> List[str]:
    """What keeps ``F.scaled_dot_product_attention(q, k, v, attn_mask=mask)`` from the layout every
    SDPA kernel (flash, memory-efficient, cuDNN, math) accepts: in half precision (where cuDNN's
    kernel runs) ``q, k, v [B, H, S, e]`` of unit last stride whose other strides and storage
    offset are multiples of 8 elements (16 bytes: views of one projection qualify, sequence-first
    or batch-first); head sizes multiples of 8; an additive mask broadcast from ``[B, 1, 1, S]`` rows
    of unit stride starting every :data:`MASK_ALIGN` elements. Empty when it is met (a check for
    tests; what the H200 took: docs/gpu.md, section 0.9.3)."""
    out = []
    half = q.dtype in (torch.float16, torch.bfloat16)
    for name, t in (("q", q), ("k", k), ("v", v)):
        if half and (t.stride(-1) != 1 or t.storage_offset() % 8
                     or any(n > 1 and s % 8 for n, s in zip(t.shape[:-1], t.stride()[:-1]))):
            out.append(f"{name} {tuple(t.shape)} strides {t.stride()} offset {t.storage_offset()} "
                       "is not aligned to 8 elements")
        if t.shape[-1] % 8:
            out.append(f"{name}'s head size {t.shape[-1]} is not a multiple of 8")
    if mask is not None:
        if mask.stride(-1) != 1 or any(s % MASK_ALIGN for s in mask.stride()[:-1]) \
                or mask.storage_offset() % MASK_ALIGN:
            out.append(f"mask {tuple(mask.shape)} strides {mask.stride()} offset {mask.storage_offset()} "
                       f"is not aligned to {MASK_ALIGN} elements")
    return out


def accelerator_path(t: Tensor) -> bool:
    """Whether ``t`` takes the accelerators' code path: not on the CPU, or on the CPU standing for
    one (:func:`~smdm_plugin.core.checks.static_mode`, tracing)."""
    return t.device.type != "cpu" or static_shapes()


#: :func:`layout_copies`' setting (:func:`use_layout_copies`)
_LAYOUT_COPIES: List[bool] = [False]


def use_layout_copies(on: Optional[bool]) -> None:
    """Switch :func:`heads`' copies into ``[B, S, H·e]``: ``True`` on, ``False`` or ``None`` (the
    default) off: every head a view of its projection, which every SDPA kernel of the H200 took in
    bf16 and which saved the copies' time (``scripts/gpu_diagnose.py --sections layout``, docs/gpu.md,
    section 0.9.3); on (every device and dtype), for a GPU whose kernels would not."""
    if on is not None and not isinstance(on, bool):
        raise TypeError(f"use_layout_copies: expected True, False or None, got {on!r}")
    _LAYOUT_COPIES[0] = bool(on)


def layout_copies() -> bool:
    """Whether :func:`heads` copies (:func:`use_layout_copies`; off by default)."""
    return _LAYOUT_COPIES[0]


def heads(t: Tensor, H: int, copy: bool) -> Tensor:
    """``[S, B, H·e]`` (any strides) -> ``[B, H, S, e]``: a view; with ``copy`` a view of a
    contiguous ``[B, S, H·e]`` copy (:func:`use_layout_copies`)."""
    S, B, _ = t.shape                              # (views by shape: no Python of Tensor.unflatten)
    if copy:
        return t.transpose(0, 1).contiguous().view(B, S, H, -1).transpose(1, 2)
    return t.view(S, B, H, -1).permute(1, 2, 0, 3)


def compute_dtype(t: Tensor) -> torch.dtype:
    """The dtype a matmul on ``t`` runs in: autocast's for ``t``'s device when it is on, else
    ``t``'s."""
    if t.device.type != "meta" and torch.is_autocast_enabled(t.device.type):   # meta: no autocast state
        return torch.get_autocast_dtype(t.device.type)
    return t.dtype


def float_mask(mask: Optional[Tensor], dtype: torch.dtype) -> Optional[Tensor]:
    """Bool (True = masked out) or float (additive) mask -> additive float mask (None stays None)."""
    if mask is None:
        return None
    if mask.dtype == torch.bool:
        return torch.zeros(mask.shape, dtype=dtype, device=mask.device).masked_fill(mask, float("-inf"))
    return mask.to(dtype)
