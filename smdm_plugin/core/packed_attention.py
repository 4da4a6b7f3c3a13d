"""PyTorch's own transformer layers run on packed rows (the ``varlen`` backend): each layer's
attention modules stood in for by one that pads only the heads (:class:`_AttentionOnPackedRows`),
the layers that can run that way (:func:`supports_packed`), the packed run (:func:`varlen_packed`)."""
from __future__ import annotations

import copy
from typing import Optional, Tuple

import torch
import torch.nn as nn

from .attention import attend, attend_single_key, float_mask, project_qkv
from .fsq import FSQMultiheadAttention, _disable_transformer_fast_path
from .packing import Packing
from .rows import gather_rows


class _AttentionOnPackedRows:
    """Stands in for a layer's attention module while PyTorch's own layer runs on packed rows.

    The layer calls it as it calls ``nn.MultiheadAttention`` (unbatched: ``query [T, d]``). The
    module's own projections run on the packed rows (:func:`~smdm_plugin.core.attention.project_qkv`;
    FSQ keys through the module's ``quantize_keys``), the heads are padded to ``[B, H, max, hd]``
    for :func:`~smdm_plugin.core.attention.attend` (``scaled_dot_product_attention``) with a key
    padding mask, and the output is packed again for the module's ``out_proj``: only the attention
    sees padded rows. Cross-attention keys are the memory as given (``[M, B, d]``
    sequence-first) with its own padding mask.
    """

    def __init__(self, attn: nn.Module, packing: Packing, memory_padding: Optional[torch.Tensor] = None) -> None:
        self.attn, self.packing, self.memory_padding = attn, packing, memory_padding
        self.batch_first = attn.batch_first        # read by nn.TransformerEncoder's fast-path checks

    def __call__(self, query: torch.Tensor, key: torch.Tensor, value: torch.Tensor, *args, **kwargs
                 ) -> Tuple[torch.Tensor, None]:
        attn, p = self.attn, self.packing
        H = attn.num_heads
        if key is not query and key.shape[0] == 1 and self.memory_padding is None:
            return attn.out_proj(attend_single_key(attn, value[0], p.seg)), None
        q, k, v = project_qkv(attn, query, key, value)                  # [T, E] / [M, B, E]
        E = q.shape[-1]
        hd = E // H
        if key is query:                                                # self-attention
            if isinstance(attn, FSQMultiheadAttention) and attn.quantize:
                k = attn.quantize_keys(k.reshape(-1, H, hd)).reshape(-1, E)
            k, v = (p.pad(t).view(p.B, p.max, H, hd).transpose(1, 2) for t in (k, v))
            mask = p.key_padding(q.dtype)
            mask = None if mask is None else mask[:, None, None, :]
        else:                                                           # memory [M, B, E]
            k, v = (t.reshape(t.shape[0], p.B, H, hd).permute(1, 2, 0, 3) for t in (k, v))
            mask = float_mask(self.memory_padding, q.dtype)
            mask = None if mask is None else mask[:, None, None, :]
        q = p.pad(q).view(p.B, p.max, H, hd).transpose(1, 2)           # [B, H, max, hd]
        o = attend(attn, q, k, v, mask)
        return attn.out_proj(p.unpad(o.transpose(1, 2)).reshape(-1, E)), None


def _packed_twin(layer: nn.Module, packing: Packing, memory_padding: Optional[torch.Tensor]) -> nn.Module:
    """A shallow copy of ``layer`` (same parameters and submodules; the layer itself is not
    changed) whose attention modules are called on packed rows."""
    twin = copy.copy(layer)
    twin.__dict__["self_attn"] = _AttentionOnPackedRows(layer.self_attn, packing)
    if getattr(layer, "multihead_attn", None) is not None:
        twin.__dict__["multihead_attn"] = _AttentionOnPackedRows(layer.multihead_attn, packing, memory_padding)
    return twin


def _has_hooks(m: nn.Module) -> bool:
    pre = [h for h in m._forward_pre_hooks.values() if h is not _disable_transformer_fast_path]
    return bool(m._forward_hooks or pre or m._backward_hooks or m._backward_pre_hooks)


def _supports_varlen(layer: nn.Module) -> bool:
    """PyTorch's own ``nn.TransformerEncoderLayer`` / ``DecoderLayer`` (whose ``forward`` calls its
    attention modules once each, as :class:`_AttentionOnPackedRows` expects) with
    ``nn.MultiheadAttention`` / FSQ attention (packed in-projection) and no hooks on the layer or its
    attention modules (the layer's would see packed rows; the attention modules' parameters are
    used, the modules not called, which would skip their hooks silently)."""
    if type(layer) not in (nn.TransformerEncoderLayer, nn.TransformerDecoderLayer):
        return False
    attns = [layer.self_attn] + ([layer.multihead_attn] if hasattr(layer, "multihead_attn") else [])
    return not any(_has_hooks(m) for m in [layer, *attns]) and all(
        type(a) in (nn.MultiheadAttention, FSQMultiheadAttention) and a._qkv_same_embed_dim
        and a.in_proj_weight is not None for a in attns)


def varlen_packed(inner: nn.Module, x: torch.Tensor, keep: torch.Tensor,
                  memory: Optional[torch.Tensor] = None,
                  memory_key_padding_mask: Optional[torch.Tensor] = None) -> Tuple[torch.Tensor, Packing]:
    """The wrapped module on the kept tokens packed with no padding: ``(h [T, d], packing)``.

    PyTorch's own ``inner.forward`` runs (on a shallow copy whose layers call their attention
    through :class:`_AttentionOnPackedRows`) on the packed rows as one unbatched sequence."""
    S, B, d = x.shape
    pq = Packing(keep)
    h = gather_rows(x.reshape(S * B, d), pq.src * B + pq.seg)  # [T, d], batch-major
    twin = copy.copy(inner)
    twin.__dict__["layers"] = [_packed_twin(layer, pq, memory_key_padding_mask) for layer in inner.layers]
    h = twin(h) if memory is None else twin(h, memory)
    return h, pq


def supports_packed(inner: nn.Module) -> bool:
    """Whether :func:`varlen_packed` can run ``inner``'s layers."""
    return all(_supports_varlen(layer) for layer in inner.layers)
