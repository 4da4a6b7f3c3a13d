"""How keyframe tokens are packed for the wrapped transformer: a small backend registry.

Every backend has the signature ``fn(inner, x, keep, memory=None, memory_key_padding_mask=None)``
with ``x [S, B, d]`` (sequence first), ``keep`` bool ``[B, S]`` and returns ``[S, B, d]`` whose rows
at ``keep`` hold the transformer output of the kept tokens attending to each other only (other rows
are arbitrary).

* ``masked``  — the whole sequence with a key-padding mask: the slow, obviously correct reference
  (costs as much as dense).
* ``compact`` — gather the kept tokens to ``K_max`` slots per sample (padded, key-padding mask),
  run the wrapped module, scatter back. Sort-free (cumsum slots). Default on CPU/MPS.
* ``varlen``  — pack kept tokens with no padding at all ``[T, d]`` and run the layer maths with
  variable-length attention: ``flash_attn`` when importable, else PyTorch's ``varlen_attn`` on CUDA,
  else SDPA with a block-diagonal mask (CPU fallback, for testing). Default on CUDA.
"""
from __future__ import annotations

from typing import Callable, Dict, Optional, Tuple

import torch
import torch.nn as nn
import torch.nn.functional as F

Backend = Callable[..., torch.Tensor]
_REGISTRY: Dict[str, Tuple[Backend, Callable[[torch.device], bool]]] = {}


def register_backend(name: str, fn: Backend, available: Callable[[torch.device], bool] = lambda d: True
                     ) -> None:
    """Register ``fn`` under ``name``; ``available(device)`` says whether it can run there."""
    _REGISTRY[name] = (fn, available)


def available_backends(device: torch.device) -> list:
    return [n for n, (_, ok) in _REGISTRY.items() if ok(torch.device(device))]


def get_backend(name: str, device: torch.device, training: bool = False) -> Backend:
    """The backend called ``name``; ``auto`` picks ``varlen`` on CUDA when it is available, else
    ``compact``. A forced backend that cannot run on ``device`` falls back to ``compact``."""
    device = torch.device(device)
    if name == "auto":
        name = "varlen" if device.type == "cuda" and _REGISTRY["varlen"][1](device) else "compact"
    if name not in _REGISTRY:
        raise ValueError(f"attention backend {name!r} unknown; registered: {sorted(_REGISTRY)}")
    fn, ok = _REGISTRY[name]
    return fn if ok(device) else _REGISTRY["compact"][0]


# ---------------------------------------------------------------------------------- helpers
def _call_inner(inner: nn.Module, x: torch.Tensor, pad: Optional[torch.Tensor], memory: Optional[torch.Tensor],
                memory_key_padding_mask: Optional[torch.Tensor]) -> torch.Tensor:
    """Run the wrapped module on sequence-first ``x [S, B, d]`` whatever its own layout."""
    bf = bool(getattr(inner.layers[0].self_attn, "batch_first", False))
    if bf:
        x = x.transpose(0, 1)
        memory = memory.transpose(0, 1) if memory is not None else None
    if memory is None:
        out = inner(x, src_key_padding_mask=pad)
    else:
        out = inner(x, memory, tgt_key_padding_mask=pad, memory_key_padding_mask=memory_key_padding_mask)
    return out.transpose(0, 1) if bf else out


def compact_indices(keep: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor]:
    """Slots of the kept tokens, sort-free.

    Args:
        keep: bool ``[B, S]``.
    Returns:
        ``pos [B, K]`` long (source position of slot k; ``S`` for padded slots) and
        ``valid [B, K]`` bool, with ``K = max kept count``.
    """
    B, S = keep.shape
    counts = keep.sum(1)
    K = int(counts.max())
    slot = keep.cumsum(1) - 1
    slot = torch.where(keep, slot, torch.full_like(slot, K))  # dropped tokens go to a dump column
    pos = torch.full((B, K + 1), S, dtype=torch.long, device=keep.device)
    src = torch.arange(S, device=keep.device).expand(B, S)
    pos.scatter_(1, slot, src)  # dump column gets any value, cut below
    pos = pos[:, :K]
    valid = torch.arange(K, device=keep.device) < counts.unsqueeze(1)
    return pos, valid


# ---------------------------------------------------------------------------------- masked
def masked_backend(inner: nn.Module, x: torch.Tensor, keep: torch.Tensor,
                   memory: Optional[torch.Tensor] = None,
                   memory_key_padding_mask: Optional[torch.Tensor] = None) -> torch.Tensor:
    return _call_inner(inner, x, ~keep, memory, memory_key_padding_mask)


# ---------------------------------------------------------------------------------- compact
def compact_backend(inner: nn.Module, x: torch.Tensor, keep: torch.Tensor,
                    memory: Optional[torch.Tensor] = None,
                    memory_key_padding_mask: Optional[torch.Tensor] = None) -> torch.Tensor:
    S, B, d = x.shape
    pos, valid = compact_indices(keep)  # [B, K]
    K = pos.shape[1]
    idx = pos.clamp(max=S - 1).t().unsqueeze(-1).expand(K, B, d)
    xc = x.gather(0, idx)  # [K, B, d]
    pad = ~valid
    out_c = _call_inner(inner, xc, pad if bool(pad.any()) else None, memory, memory_key_padding_mask)
    out = x.new_zeros(S + 1, B, d)
    out = out.scatter(0, pos.t().unsqueeze(-1).expand(K, B, d), out_c)
    return out[:S]


# ---------------------------------------------------------------------------------- varlen
def _flash_attn_fn() -> Optional[Callable]:
    try:
        from flash_attn import flash_attn_varlen_func  # type: ignore
        return flash_attn_varlen_func
    except Exception:
        return None


def _torch_varlen_fn() -> Optional[Callable]:
    try:
        from torch.nn.attention.varlen import varlen_attn  # type: ignore
        return varlen_attn
    except Exception:
        return None


def _varlen_available(device: torch.device) -> bool:
    return True  # the block-diagonal SDPA fallback runs anywhere


def _attend(q: torch.Tensor, k: torch.Tensor, v: torch.Tensor, cu_q: torch.Tensor, cu_k: torch.Tensor,
            max_q: int, max_k: int, seg_q: torch.Tensor, seg_k: torch.Tensor, dropout_p: float
            ) -> torch.Tensor:
    """Variable-length attention on packed ``q [Tq, H, Dh]``, ``k, v [Tk, H, Dh]``."""
    if q.is_cuda and dropout_p == 0.0 and q.dtype in (torch.float16, torch.bfloat16):
        fa = _flash_attn_fn()
        if fa is not None:
            return fa(q, k, v, cu_q.int(), cu_k.int(), max_q, max_k)
        tv = _torch_varlen_fn()
        if tv is not None:
            try:
                return tv(q, k, v, cu_q.int(), cu_k.int(), max_q, max_k)
            except (RuntimeError, NotImplementedError):
                pass
    block = seg_q.unsqueeze(1) == seg_k.unsqueeze(0)  # [Tq, Tk] block-diagonal
    o = F.scaled_dot_product_attention(q.transpose(0, 1), k.transpose(0, 1), v.transpose(0, 1),
                                       attn_mask=block, dropout_p=dropout_p)
    return o.transpose(0, 1)


def _mha_packed(mha: nn.MultiheadAttention, xq: torch.Tensor, xkv: torch.Tensor, self_attn: bool,
                cu_q, cu_k, max_q, max_k, seg_q, seg_k, training: bool) -> torch.Tensor:
    d, H = mha.embed_dim, mha.num_heads
    W, b = mha.in_proj_weight, mha.in_proj_bias
    if self_attn:
        q, k, v = F.linear(xq, W, b).chunk(3, dim=-1)
    else:
        bq, bkv = (b[:d], b[d:]) if b is not None else (None, None)
        q = F.linear(xq, W[:d], bq)
        k, v = F.linear(xkv, W[d:], bkv).chunk(2, dim=-1)
    Dh = d // H
    o = _attend(q.reshape(-1, H, Dh), k.reshape(-1, H, Dh), v.reshape(-1, H, Dh), cu_q, cu_k, max_q, max_k,
                seg_q, seg_k, mha.dropout if training else 0.0)
    return mha.out_proj(o.reshape(-1, d))


def _supports_varlen(layer: nn.Module) -> bool:
    attn = getattr(layer, "self_attn", None)
    return type(attn) is nn.MultiheadAttention and attn._qkv_same_embed_dim and attn.in_proj_weight is not None


def _ff(layer: nn.Module, h: torch.Tensor) -> torch.Tensor:
    return layer.dropout2(layer.linear2(layer.dropout(layer.activation(layer.linear1(h)))))


def varlen_backend(inner: nn.Module, x: torch.Tensor, keep: torch.Tensor,
                   memory: Optional[torch.Tensor] = None,
                   memory_key_padding_mask: Optional[torch.Tensor] = None) -> torch.Tensor:
    """Packed tokens with no padding; the layer maths of ``nn.TransformerEncoderLayer`` /
    ``nn.TransformerDecoderLayer`` (post- or pre-norm) re-applied to ``[T, d]``."""
    if not all(_supports_varlen(layer) for layer in inner.layers):
        return compact_backend(inner, x, keep, memory, memory_key_padding_mask)
    S, B, d = x.shape
    training = inner.training
    b_idx, s_idx = keep.nonzero(as_tuple=True)  # row-major: packed batch-major
    h = x[s_idx, b_idx]  # [T, d]
    counts = keep.sum(1)
    cu_q = F.pad(counts.cumsum(0), (1, 0))
    max_q = int(counts.max())
    seg_q = b_idx
    if memory is not None:
        M = memory.shape[0]
        mkeep = torch.ones(B, M, dtype=torch.bool, device=x.device)
        if memory_key_padding_mask is not None:
            mkeep = ~memory_key_padding_mask.to(torch.bool)
        mb, ms = mkeep.nonzero(as_tuple=True)  # row-major = batch-major
        mem = memory[ms, mb]
        mcounts = mkeep.sum(1)
        cu_k = F.pad(mcounts.cumsum(0), (1, 0))
        max_k, seg_k = int(mcounts.max()), mb
    for layer in inner.layers:
        first = layer.norm_first
        sa = lambda t: layer.dropout1(_mha_packed(layer.self_attn, t, t, True, cu_q, cu_q, max_q, max_q,
                                                  seg_q, seg_q, training))
        if memory is None:
            if first:
                h = h + sa(layer.norm1(h))
                h = h + _ff(layer, layer.norm2(h))
            else:
                h = layer.norm1(h + sa(h))
                h = layer.norm2(h + _ff(layer, h))
        else:
            ca = lambda t: layer.dropout2(_mha_packed(layer.multihead_attn, t, mem, False, cu_q, cu_k, max_q,
                                                      max_k, seg_q, seg_k, training))
            ff = lambda t: layer.dropout3(layer.linear2(layer.dropout(layer.activation(layer.linear1(t)))))
            if first:
                h = h + sa(layer.norm1(h))
                h = h + ca(layer.norm2(h))
                h = h + ff(layer.norm3(h))
            else:
                h = layer.norm1(h + sa(h))
                h = layer.norm2(h + ca(h))
                h = layer.norm3(h + ff(h))
    if inner.norm is not None:
        h = inner.norm(h)
    out = x.new_zeros(S, B, d)
    out[s_idx, b_idx] = h
    return out


register_backend("masked", masked_backend)
register_backend("compact", compact_backend)
register_backend("varlen", varlen_backend, _varlen_available)
