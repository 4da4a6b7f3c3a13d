"""How keyframe tokens are packed for the wrapped transformer: a small backend registry.

Every backend has the signature ``fn(inner, x, keep, memory=None, memory_key_padding_mask=None)``
with ``x [S, B, d]`` (sequence first), ``keep`` bool ``[B, S]`` and returns ``[S, B, d]`` whose rows
at ``keep`` hold the transformer output of the kept tokens attending to each other only (other rows
are arbitrary).

* ``masked``  — the whole sequence with a key-padding mask: the slow, obviously correct reference
  (costs as much as dense).
* ``compact`` — gather the kept tokens to ``K_max`` slots per sample (padded, key-padding mask),
  run the wrapped module, scatter back. Sort-free (cumsum slots). Used for layers ``varlen``
  cannot re-apply (FSQ attention keys, custom layers).
* ``varlen``  — pack kept tokens with no padding at all ``[T, d]`` and run the layer maths with
  variable-length attention: ``flash_attn`` when importable, else PyTorch's ``varlen_attn`` on CUDA
  (half precision, no attention dropout), else SDPA on a padded ``[B, H, K_max, Dh]`` view of the
  attention only (projections, feed-forward and norms stay packed). The default (``auto``)
  everywhere: on a 2-core CPU it runs ~37% fewer rows than ``compact`` for HumanML3D-like
  lengths, and :class:`~smdm_plugin.keyframe_transformer.KeyframeTransformer` interpolates
  straight from its packed rows.
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
    """The backend called ``name``; ``auto`` picks ``varlen`` (packed rows, no padding in the
    projections / feed-forward; flash or varlen kernels on CUDA, padded SDPA elsewhere) when it is
    available, else ``compact``. ``varlen`` itself falls back to ``compact`` for layers it cannot
    re-apply (FSQ attention, custom layers). A forced backend that cannot run on ``device`` falls
    back to ``compact``."""
    device = torch.device(device)
    if name == "auto":
        name = "varlen" if _REGISTRY["varlen"][1](device) else "compact"
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
    return True  # the padded-attention fallback runs anywhere


class _RowGather(torch.autograd.Function):
    """``t.index_select(0, idx)`` for *distinct* ``idx``; backward is a row copy (``index_copy``)
    instead of autograd's generic scatter-add, which is slow on CPU."""

    @staticmethod
    def forward(ctx, t: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
        ctx.save_for_backward(idx)
        ctx.rows = t.shape[0]
        return t.index_select(0, idx)

    @staticmethod
    def backward(ctx, g: torch.Tensor):
        (idx,) = ctx.saved_tensors
        return g.new_zeros(ctx.rows, *g.shape[1:]).index_copy_(0, idx, g), None


class _RowScatter(torch.autograd.Function):
    """``zeros(rows, ...).index_copy_(0, idx, t)`` for distinct ``idx``; backward ``index_select``."""

    @staticmethod
    def forward(ctx, t: torch.Tensor, idx: torch.Tensor, rows: int) -> torch.Tensor:
        ctx.save_for_backward(idx)
        return t.new_zeros(rows, *t.shape[1:]).index_copy_(0, idx, t)

    @staticmethod
    def backward(ctx, g: torch.Tensor):
        (idx,) = ctx.saved_tensors
        return g.index_select(0, idx), None, None


class _LerpRows(torch.autograd.Function):
    """``torch.lerp(h[prev], h[next], w)`` row-wise, with a backward made of two ``index_add_``
    (autograd's own ``index_select`` backward is a slow scatter-add on CPU)."""

    @staticmethod
    def forward(ctx, h: torch.Tensor, prev: torch.Tensor, nxt: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
        ctx.save_for_backward(prev, nxt, w)
        ctx.rows = h.shape[0]
        return torch.lerp(h.index_select(0, prev), h.index_select(0, nxt), w)

    @staticmethod
    def backward(ctx, g: torch.Tensor):
        prev, nxt, w = ctx.saved_tensors
        grad = g.new_zeros(ctx.rows, *g.shape[1:])
        grad.index_add_(0, prev, g * (1 - w)).index_add_(0, nxt, g * w)
        return grad, None, None, None


def lerp_rows(h: torch.Tensor, prev: torch.Tensor, nxt: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    """Row ``r`` of the result is ``lerp(h[prev[r]], h[nxt[r]], w[r])``; ``w [R, 1]``."""
    return _LerpRows.apply(h, prev, nxt, w)


def gather_rows(t: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
    """Rows ``idx`` (distinct) of ``t``; fast backward."""
    return _RowGather.apply(t, idx)


def scatter_rows(t: torch.Tensor, idx: torch.Tensor, rows: int) -> torch.Tensor:
    """``[rows, ...]`` zeros with row ``idx[i]`` = ``t[i]`` (``idx`` distinct); fast backward."""
    return _RowScatter.apply(t, idx, rows)


class Packing:
    """Where the packed rows ``[T, ...]`` (batch-major, the order of ``keep.nonzero()``) sit.

    ``counts [B]``, ``cu [B+1]`` (cumulative, for flash / varlen kernels), ``max`` (largest count),
    ``seg [T]`` (sample of each row), ``src [T]`` (its position in the sequence), ``valid [B, max]``
    and ``flat [T]`` (padded slot ``b * max + j`` of each row).
    """

    def __init__(self, keep: torch.Tensor) -> None:
        B, S = keep.shape
        self.B = B
        self.counts = keep.sum(1)
        self.cu = F.pad(self.counts.cumsum(0), (1, 0))
        self.max = int(self.counts.max()) if B else 0
        self.seg, self.src = keep.nonzero(as_tuple=True)
        self.T = int(self.seg.shape[0])
        slot = torch.arange(self.T, device=keep.device) - self.cu[self.seg]
        self.flat = self.seg * self.max + slot
        self.valid = torch.arange(self.max, device=keep.device) < self.counts.unsqueeze(1)
        self.full = self.T == B * self.max
        self._bias: Dict[torch.dtype, torch.Tensor] = {}

    def key_bias(self, dtype: torch.dtype) -> Optional[torch.Tensor]:
        """Additive key padding mask ``[B, 1, 1, max]`` (0 / -inf), None when nothing is padded.
        A float mask keeps SDPA on its fused CPU kernel (a bool mask sends it to the math path)."""
        if self.full:
            return None
        if dtype not in self._bias:
            bias = torch.zeros(self.B, 1, 1, self.max, dtype=dtype, device=self.valid.device)
            self._bias[dtype] = bias.masked_fill_(~self.valid[:, None, None, :], float("-inf"))
        return self._bias[dtype]

    def pad(self, t: torch.Tensor) -> torch.Tensor:
        """``[T, ...]`` -> ``[B, max, ...]`` (padded slots hold zeros)."""
        if not self.full:
            t = scatter_rows(t, self.flat, self.B * self.max)
        return t.view(self.B, self.max, *t.shape[1:])

    def unpad(self, t: torch.Tensor) -> torch.Tensor:
        """``[B, max, ...]`` -> ``[T, ...]``."""
        t = t.reshape(self.B * self.max, *t.shape[2:])
        return t if self.full else gather_rows(t, self.flat)


def _use_varlen_kernel(q: torch.Tensor, dropout_p: float) -> bool:
    return (q.is_cuda and dropout_p == 0.0 and q.dtype in (torch.float16, torch.bfloat16)
            and (_flash_attn_fn() is not None or _torch_varlen_fn() is not None))


def _attend(q: torch.Tensor, k: torch.Tensor, v: torch.Tensor, pq: Packing, pk: Packing, dropout_p: float
            ) -> torch.Tensor:
    """Variable-length attention on packed ``q [Tq, H, Dh]``, ``k, v [Tk, H, Dh]``: flash_attn or
    PyTorch's ``varlen_attn`` on CUDA (half precision, no dropout), else SDPA on the padded layout
    ``[B, H, max, Dh]`` with a key padding mask (only the attention itself sees padding; the
    projections, feed-forward and norms run on the packed rows)."""
    if q.is_cuda and dropout_p == 0.0 and q.dtype in (torch.float16, torch.bfloat16):
        fa = _flash_attn_fn()
        if fa is not None:
            return fa(q, k, v, pq.cu.int(), pk.cu.int(), pq.max, pk.max)
        tv = _torch_varlen_fn()
        if tv is not None:
            try:
                return tv(q, k, v, pq.cu.int(), pk.cu.int(), pq.max, pk.max)
            except (RuntimeError, NotImplementedError, TypeError):
                pass
    qp, kp, vp = (p.pad(t).transpose(1, 2) for p, t in ((pq, q), (pk, k), (pk, v)))  # [B, H, L, Dh]
    o = F.scaled_dot_product_attention(qp, kp, vp, attn_mask=pk.key_bias(q.dtype), dropout_p=dropout_p)
    return pq.unpad(o.transpose(1, 2))


def _mha_packed(mha: nn.MultiheadAttention, xq: torch.Tensor, xkv: torch.Tensor, self_attn: bool,
                pq: Packing, pk: Packing, training: bool) -> torch.Tensor:
    d, H = mha.embed_dim, mha.num_heads
    Dh = d // H
    W, b = mha.in_proj_weight, mha.in_proj_bias
    p = mha.dropout if training else 0.0
    if self_attn and not _use_varlen_kernel(xq, p):
        # padded attention: one scatter of the fused q|k|v projection, one gather of the output
        qkv = pq.pad(F.linear(xq, W, b)).view(pq.B, pq.max, 3, H, Dh).permute(2, 0, 3, 1, 4)
        q, k, v = qkv.unbind(0)  # unbind: its backward stacks, no zero-filled [3, ...] per index
        o = F.scaled_dot_product_attention(q, k, v, attn_mask=pq.key_bias(xq.dtype), dropout_p=p)
        return mha.out_proj(pq.unpad(o.transpose(1, 2)).reshape(-1, d))
    if not self_attn and pk.full and pk.max == 1:
        # one memory token per sample (MDM trans_dec: the condition): softmax over a single key is
        # exactly 1, so every query row gets that sample's value row, whatever q is; the query
        # projection has exactly zero gradient (kept as zeros so optimisers treat it as before)
        bkv = b[d:] if b is not None else None
        v = F.linear(xkv, W[2 * d:], bkv[d:] if bkv is not None else None)  # [B, d]
        o = F.embedding(pq.seg, v)  # [Tq, d]
        if p > 0.0:  # dropout on the (single) attention weight, per row and head
            keep = F.dropout(o.new_ones(o.shape[0], H, 1), p, True)
            o = (o.view(-1, H, Dh) * keep).reshape(-1, d)
        zero = W[:d].sum() * 0.0 + (b[:d].sum() * 0.0 if b is not None else 0.0)
        return mha.out_proj(o) + zero
    if self_attn:
        q, k, v = F.linear(xq, W, b).chunk(3, dim=-1)
    else:
        bq, bkv = (b[:d], b[d:]) if b is not None else (None, None)
        q = F.linear(xq, W[:d], bq)
        k, v = F.linear(xkv, W[d:], bkv).chunk(2, dim=-1)
    o = _attend(q.reshape(-1, H, Dh), k.reshape(-1, H, Dh), v.reshape(-1, H, Dh), pq, pk, p)
    return mha.out_proj(o.reshape(-1, d))


def _has_hooks(m: Optional[nn.Module]) -> bool:
    return m is not None and bool(m._forward_hooks or m._forward_pre_hooks or m._backward_hooks
                                  or getattr(m, "_backward_pre_hooks", None))


def _supports_varlen(layer: nn.Module) -> bool:
    """The layer maths can be re-applied to packed rows: plain ``nn.MultiheadAttention`` (packed
    q/k/v projection) and no hooks on the layer or its attention modules (``varlen`` reads their
    weights instead of calling them, which would silently skip the hooks)."""
    if any(_has_hooks(m) for m in (layer, getattr(layer, "self_attn", None),
                                    getattr(layer, "multihead_attn", None))):
        return False
    attn = getattr(layer, "self_attn", None)
    if not (type(attn) is nn.MultiheadAttention and attn._qkv_same_embed_dim and attn.in_proj_weight is not None):
        return False
    cross = getattr(layer, "multihead_attn", None)
    return cross is None or (type(cross) is nn.MultiheadAttention and cross._qkv_same_embed_dim
                             and cross.in_proj_weight is not None)


def _ff(layer: nn.Module, h: torch.Tensor, drop) -> torch.Tensor:
    return drop(layer.linear2(layer.dropout(layer.activation(layer.linear1(h)))))


def varlen_packed(inner: nn.Module, x: torch.Tensor, keep: torch.Tensor,
                  memory: Optional[torch.Tensor] = None,
                  memory_key_padding_mask: Optional[torch.Tensor] = None) -> Tuple[torch.Tensor, Packing]:
    """The transformer on the kept tokens packed with no padding: ``(h [T, d], packing)``."""
    S, B, d = x.shape
    pq = Packing(keep)
    h = gather_rows(x.reshape(S * B, d), pq.src * B + pq.seg)  # [T, d], batch-major
    pk = pq
    mem = None
    if memory is not None:
        M = memory.shape[0]
        mkeep = torch.ones(B, M, dtype=torch.bool, device=x.device)
        if memory_key_padding_mask is not None:
            mkeep = ~memory_key_padding_mask.to(torch.bool)
        pk = Packing(mkeep)
        mem = gather_rows(memory.reshape(M * B, d), pk.src * B + pk.seg)
    for layer in inner.layers:
        first = layer.norm_first
        training = layer.training  # the wrapper's eval()/train() reaches the layers, not ``inner``
        sa = lambda t: layer.dropout1(_mha_packed(layer.self_attn, t, t, True, pq, pq, training))
        if memory is None:
            if first:
                h = h + sa(layer.norm1(h))
                h = h + _ff(layer, layer.norm2(h), layer.dropout2)
            else:
                h = layer.norm1(h + sa(h))
                h = layer.norm2(h + _ff(layer, h, layer.dropout2))
        else:
            ca = lambda t: layer.dropout2(_mha_packed(layer.multihead_attn, t, mem, False, pq, pk, training))
            if first:
                h = h + sa(layer.norm1(h))
                h = h + ca(layer.norm2(h))
                h = h + _ff(layer, layer.norm3(h), layer.dropout3)
            else:
                h = layer.norm1(h + sa(h))
                h = layer.norm2(h + ca(h))
                h = layer.norm3(h + _ff(layer, h, layer.dropout3))
    if inner.norm is not None:
        h = inner.norm(h)
    return h, pq


def varlen_backend(inner: nn.Module, x: torch.Tensor, keep: torch.Tensor,
                   memory: Optional[torch.Tensor] = None,
                   memory_key_padding_mask: Optional[torch.Tensor] = None) -> torch.Tensor:
    """Packed tokens with no padding; the layer maths of ``nn.TransformerEncoderLayer`` /
    ``nn.TransformerDecoderLayer`` (post- or pre-norm) re-applied to ``[T, d]``. Layers it cannot
    re-apply (FSQ attention, custom layers) make it fall back to ``compact``."""
    if not all(_supports_varlen(layer) for layer in inner.layers):
        return compact_backend(inner, x, keep, memory, memory_key_padding_mask)
    S, B, d = x.shape
    h, pq = varlen_packed(inner, x, keep, memory, memory_key_padding_mask)
    return scatter_rows(h, pq.src * B + pq.seg, S * B).view(S, B, d)


def supports_packed(inner: nn.Module) -> bool:
    """Whether :func:`varlen_packed` can run ``inner``'s layers."""
    return all(_supports_varlen(layer) for layer in inner.layers)


register_backend("masked", masked_backend)
register_backend("compact", compact_backend)
register_backend("varlen", varlen_backend, _varlen_available)
