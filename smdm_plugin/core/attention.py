"""The attention maths the package writes itself, in one place.

Attention modules keep ``nn.MultiheadAttention``'s parameter layout (``in_proj_weight [3E, E]``,
``in_proj_bias [3E]``, ``out_proj``); the attention itself is PyTorch's
``F.scaled_dot_product_attention``. :class:`~smdm_plugin.core.fsq.FSQMultiheadAttention` and the
``varlen`` backend (which runs PyTorch's own transformer layers on packed rows) both project with
:func:`project_qkv` and attend with :func:`attend`.
"""
from __future__ import annotations

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
    bk, bv = (bkv[:E], bkv[E:]) if bkv is not None else (None, None)
    return q, F.linear(key, W[E:2 * E], bk), F.linear(value, W[2 * E:], bv)


def attend(attn: nn.Module, q: Tensor, k: Tensor, v: Tensor, mask: Optional[Tensor]) -> Tensor:
    """``F.scaled_dot_product_attention`` of heads ``q [B, H, L, hd]``, ``k, v [B, H, S, hd]`` with
    an additive ``mask`` broadcastable to ``[B, H, L, S]`` (or None) and ``attn``'s dropout in
    training: ``[B, H, L, hd]``."""
    p = attn.dropout if attn.training else 0.0
    return F.scaled_dot_product_attention(q, k, v, attn_mask=mask, dropout_p=p)


def float_mask(mask: Optional[Tensor], dtype: torch.dtype) -> Optional[Tensor]:
    """Bool (True = masked out) or float (additive) mask -> additive float mask (None stays None)."""
    if mask is None:
        return None
    if mask.dtype == torch.bool:
        return torch.zeros(mask.shape, dtype=dtype, device=mask.device).masked_fill(mask, float("-inf"))
    return mask.to(dtype)
