"""The attention maths the package writes itself, in one place.

Attention modules keep ``nn.MultiheadAttention``'s parameter layout (``in_proj_weight [3E, E]``,
``in_proj_bias [3E]``, ``out_proj``); the attention itself is PyTorch's
``F.scaled_dot_product_attention``. :class:`~smdm_plugin.core.fsq.FSQMultiheadAttention` and the
``varlen`` backend (which runs PyTorch's own transformer layers on packed rows) both project with
:func:`project_qkv` and attend with :func:`attend`.
"""
from __future__ import annotations

import math
from typing import Optional, Tuple

import torch
import torch.nn.functional as F
from torch import Tensor, nn


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
