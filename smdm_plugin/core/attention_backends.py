"""How keyframe tokens go through the wrapped transformer: a small backend registry.

A backend runs the kept tokens of one call (the ``lead`` tokens before the frames — MDM
trans_enc's timestep/text token — and the keyframes of a :class:`~smdm_plugin.core.plan.KeyframePlan`)
through the wrapped ``nn.TransformerEncoder`` / ``nn.TransformerDecoder`` so that they attend to each
other only. Signature::

    fn(inner, x, plan, lead, memory=None, memory_key_padding_mask=None, lead_padding=None)
        -> (h [R, d], rows [lead + K, B] long)

with ``x [S, B, d]`` sequence-first (``S = lead + N``). ``h`` holds output rows and ``rows[s, b]`` is
the row of lead token ``s`` / keyframe slot ``s - lead`` of sample ``b`` (padded slots may point
anywhere valid). The keyframe transformer interpolates every frame from these rows.

* ``masked``  — the whole sequence with a key-padding mask: the slow, obviously correct reference
  (costs as much as dense).
* ``compact`` — the lead tokens and the ``K`` plan slots gathered to ``[lead + K, B, d]`` with a key
  padding mask over the empty slots, the wrapped module called as it is. Static shapes, no host
  sync: the default on accelerators and under ``torch.compile``; also the fallback for layers
  ``varlen`` cannot run (custom layer classes, hooks on layers).
* ``varlen``  — kept tokens packed with no padding at all ``[T, d]`` through PyTorch's own
  ``nn.TransformerEncoder`` / ``Decoder`` and layer ``forward`` (run on the packed rows as one
  unbatched sequence; the wrapped module is not changed); each layer's attention module is called
  through :class:`_AttentionOnPackedRows`, which pads only the heads for
  ``scaled_dot_product_attention`` (:mod:`smdm_plugin.core.attention`, the package's one copy of
  the attention maths). No padded rows in projections, feed-forward and norms, but the packed size
  ``T`` is data-dependent (host syncs, dynamic shapes): the default in eager mode on the CPU, where
  rows, not launches, cost time.
"""
from __future__ import annotations

import copy
from dataclasses import dataclass
from typing import Callable, Dict, Optional, Tuple

import torch
import torch.nn as nn
import torch.nn.functional as F

from .attention import attend, attend_single_key, compute_dtype, float_mask, project_qkv
from . import consts
from .checks import compiling as static_compiling, static_shapes
from .registry import Registry
from .fsq import FSQMultiheadAttention, _disable_transformer_fast_path
from .plan import KeyframePlan

Backend = Callable[..., Tuple[torch.Tensor, torch.Tensor]]


@dataclass(frozen=True)
class AttentionBackend:
    """A registered backend and its capabilities: ``available(device)`` (it can run there),
    ``static_shapes`` (no data-dependent shapes or host syncs: usable under ``torch.compile`` and
    on the static path), ``supports(inner)`` (it can run that wrapped module's layers)."""

    fn: Backend
    available: Callable[[torch.device], bool] = lambda d: True
    static_shapes: bool = True
    supports: Callable[[nn.Module], bool] = lambda inner: True


#: the attention backends by name (``SparseConfig.attention_backend`` is validated against it + auto)
BACKENDS: Registry[AttentionBackend] = Registry("attention backend")
#: where a backend cannot run (capability check failed): the backend that always can
FALLBACK = "compact"


def register_backend(name: str, fn: Backend, available: Callable[[torch.device], bool] = lambda d: True, *,
                     static_shapes: bool = True, supports: Callable[[nn.Module], bool] = lambda inner: True,
                     replace: bool = True) -> AttentionBackend:
    """Register ``fn`` (signature in the module docstring) under ``name`` with its capabilities
    (see :class:`AttentionBackend`)."""
    return BACKENDS.register(name, AttentionBackend(fn, available, static_shapes, supports), replace=replace)


def available_backends(device: torch.device) -> list:
    return [n for n in BACKENDS.names() if BACKENDS.get(n).available(torch.device(device))]


def resolve_backend_name(name: str, device: torch.device, inner: Optional[nn.Module] = None) -> str:
    """The backend a call uses — the one dispatch: ``auto`` is ``varlen`` in eager mode on the CPU
    and ``compact`` elsewhere (accelerators, where launches and syncs cost more than padded rows,
    and under ``torch.compile``, which needs static shapes); a backend whose capabilities do not
    fit (not available on ``device``, dynamic shapes while tracing or on the static path, cannot
    run ``inner``'s layers) becomes :data:`FALLBACK`."""
    device = torch.device(device)
    if name == "auto":
        name = "varlen" if device.type == "cpu" and not static_shapes() else FALLBACK
    b = BACKENDS.get(name)
    if (not b.available(device) or (static_shapes() and not b.static_shapes)
            or (inner is not None and not b.supports(inner))):
        return FALLBACK
    return name


def get_backend(name: str, device: torch.device, training: bool = False,
                inner: Optional[nn.Module] = None) -> Backend:
    """The backend function :func:`resolve_backend_name` picks for ``name`` on ``device``."""
    return BACKENDS.get(resolve_backend_name(name, device, inner)).fn


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


def _slot_rows(plan: KeyframePlan, lead: int) -> torch.Tensor:
    """``[lead + K, B]`` long: the row ``position * B + b`` of every lead token and plan slot in a
    sequence-first ``[(lead + N) * B, ...]`` tensor."""
    if not lead:
        return plan.rows
    B = plan.batch
    return torch.cat([arange_rows(lead, B, plan.rows.device), plan.rows + lead * B], 0)


def arange_rows(n: int, B: int, device: torch.device) -> torch.Tensor:
    """``arange(n * B).view(n, B)`` on ``device``: made once per shape and device (outside tracing),
    a per-call constant (never written to)."""
    return consts.arange(n * B, device).view(n, B)


def _lead_keep(plan: KeyframePlan, lead: int, lead_padding: Optional[torch.Tensor]) -> torch.Tensor:
    """bool ``[B, lead]``: lead tokens that take part (all, unless the caller pads some)."""
    if lead_padding is not None:
        return ~lead_padding.to(torch.bool)
    return plan.mask.new_ones(plan.batch, lead)


def _key_bias(plan: KeyframePlan, lead: int, lead_padding: Optional[torch.Tensor], dtype: torch.dtype
              ) -> torch.Tensor:
    """Additive key padding mask ``[B, lead + K]`` (0 kept / -inf padded lead tokens and empty
    slots), made once per call: a float mask goes through every layer's attention as it is (a
    bool one is converted again in each layer). A looked-up plan carries it (``plan.key_bias``)."""
    if plan.key_bias is not None and lead <= 1:
        bias = plan.key_bias[:, 1 - lead:]
        if lead and lead_padding is not None:                       # the caller's padding of its lead token
            bias = torch.cat([bias[:, :1].masked_fill(lead_padding.to(torch.bool), float("-inf")), bias[:, 1:]], 1)
        return bias if bias.dtype == dtype else bias.to(dtype)
    pad = ~plan.valid
    if lead:
        lead_pad = plan.valid.new_zeros(plan.batch, lead) if lead_padding is None else lead_padding.to(torch.bool)
        pad = torch.cat([lead_pad, pad], 1)
    return torch.zeros(pad.shape, dtype=dtype, device=pad.device).masked_fill_(pad, float("-inf"))


# ---------------------------------------------------------------------------------- masked
def masked_backend(inner: nn.Module, x: torch.Tensor, plan: KeyframePlan, lead: int,
                   memory: Optional[torch.Tensor] = None, memory_key_padding_mask: Optional[torch.Tensor] = None,
                   lead_padding: Optional[torch.Tensor] = None) -> Tuple[torch.Tensor, torch.Tensor]:
    S, B, d = x.shape
    keep = torch.cat([_lead_keep(plan, lead, lead_padding), plan.mask], 1)
    out = _call_inner(inner, x, ~keep, memory, memory_key_padding_mask)
    rows = _slot_rows(plan, lead)
    return out.reshape(S * B, d), rows


# ---------------------------------------------------------------------------------- compact
def compact_backend(inner: nn.Module, x: torch.Tensor, plan: KeyframePlan, lead: int,
                    memory: Optional[torch.Tensor] = None, memory_key_padding_mask: Optional[torch.Tensor] = None,
                    lead_padding: Optional[torch.Tensor] = None) -> Tuple[torch.Tensor, torch.Tensor]:
    S, B, d = x.shape
    R = lead + plan.capacity
    if not (torch.is_grad_enabled() and x.requires_grad):   # the slots' frames by index; lead tokens as they are
        slots = torch.gather(x[lead:], 0, plan.index.t().unsqueeze(-1).expand(R - lead, B, d))
        xc = torch.cat([x[:lead], slots]) if lead else slots
    else:                                  # one gather (with autograd: one scatter back, not two + a sum)
        xc = gather_rows(x.reshape(S * B, d), _slot_rows(plan, lead).reshape(-1)).view(R, B, d)
    # the key bias in the dtype the attention runs in (autocast's): cast once, not in every layer
    out = _call_inner(inner, xc, _key_bias(plan, lead, lead_padding, compute_dtype(x)), memory, memory_key_padding_mask)
    return out.reshape(R * B, d), arange_rows(R, B, x.device)


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
        shape = (*w.shape[:-1], -1)                       # w [..., 1] may be a strided view
        out = torch.lerp(h.index_select(0, prev).view(shape), h.index_select(0, nxt).view(shape), w)
        return out.reshape(prev.shape[0], *h.shape[1:])

    @staticmethod
    def backward(ctx, g: torch.Tensor):
        prev, nxt, w = ctx.saved_tensors
        grad = g.new_zeros(ctx.rows, *g.shape[1:])
        gw = g.view(*w.shape[:-1], -1)
        grad.index_add_(0, prev, (gw * (1 - w)).reshape(g.shape)).index_add_(0, nxt, (gw * w).reshape(g.shape))
        return grad, None, None, None


class _LerpRowPairs(torch.autograd.Function):
    """:class:`_LerpRows` with the rows of both ends in one index ``[2R]`` (``prev`` then ``next``):
    one row gather forward, one ``index_add_`` backward."""

    @staticmethod
    def forward(ctx, h: torch.Tensor, pairs: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
        ctx.save_for_backward(pairs, w)
        ctx.rows = h.shape[0]
        R = pairs.shape[0] // 2
        shape = (*w.shape[:-1], -1)                       # w [..., 1] may be a strided view
        ends = h.index_select(0, pairs)
        return torch.lerp(ends[:R].view(shape), ends[R:].view(shape), w).reshape(R, *h.shape[1:])

    @staticmethod
    def backward(ctx, g: torch.Tensor):
        pairs, w = ctx.saved_tensors
        gw = g.view(*w.shape[:-1], -1)
        both = g.new_empty(2, *gw.shape)
        torch.mul(gw, 1 - w, out=both[0])
        torch.mul(gw, w, out=both[1])
        grad = g.new_zeros(ctx.rows, *g.shape[1:])
        return grad.index_add_(0, pairs, both.view(-1, *g.shape[1:])), None, None


def lerp_rows(h: torch.Tensor, prev: torch.Tensor, nxt: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    """Row ``r`` of the result is ``lerp(h[prev[r]], h[nxt[r]], w[r])``; ``w [R, 1]`` (or any
    ``[..., 1]`` whose leading dims flatten to the ``R`` rows, e.g. a transposed ``[N, B, 1]``)."""
    return _LerpRows.apply(h, prev, nxt, w)


def gather_rows(t: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
    """Rows ``idx`` (distinct) of ``t``; fast backward."""
    return _RowGather.apply(t, idx)


def scatter_rows(t: torch.Tensor, idx: torch.Tensor, rows: int) -> torch.Tensor:
    """``[rows, ...]`` zeros with row ``idx[i]`` = ``t[i]`` (``idx`` distinct); fast backward."""
    return _RowScatter.apply(t, idx, rows)


class Packing:
    """Where the packed rows ``[T, ...]`` (batch-major, the order of ``keep.nonzero()``) sit.

    ``counts [B]``, ``cu [B+1]`` (cumulative), ``max`` (largest count), ``seg [T]`` (sample of
    each row), ``src [T]`` (its position in the sequence), ``valid [B, max]`` and ``flat [T]``
    (padded slot ``b * max + j`` of each row).
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
        self._padding: Dict[torch.dtype, torch.Tensor] = {}

    def key_padding(self, dtype: torch.dtype) -> Optional[torch.Tensor]:
        """Additive key padding mask ``[B, max]`` (0 / -inf), None when nothing is padded; made
        once per call and dtype (a float mask goes through every layer's attention as it is)."""
        if self.full:
            return None
        if dtype not in self._padding:
            pad = torch.zeros(self.B, self.max, dtype=dtype, device=self.valid.device)
            self._padding[dtype] = pad.masked_fill_(~self.valid, float("-inf"))
        return self._padding[dtype]

    def pad(self, t: torch.Tensor) -> torch.Tensor:
        """``[T, ...]`` -> ``[B, max, ...]`` (padded slots hold zeros)."""
        if not self.full:
            t = scatter_rows(t, self.flat, self.B * self.max)
        return t.view(self.B, self.max, *t.shape[1:])

    def unpad(self, t: torch.Tensor) -> torch.Tensor:
        """``[B, max, ...]`` -> ``[T, ...]``."""
        t = t.reshape(self.B * self.max, *t.shape[2:])
        return t if self.full else gather_rows(t, self.flat)


# ---------------------------------------------------------------------------------- varlen
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


def varlen_backend(inner: nn.Module, x: torch.Tensor, plan: KeyframePlan, lead: int,
                   memory: Optional[torch.Tensor] = None, memory_key_padding_mask: Optional[torch.Tensor] = None,
                   lead_padding: Optional[torch.Tensor] = None) -> Tuple[torch.Tensor, torch.Tensor]:
    """Packed tokens with no padding through PyTorch's own layers (:func:`varlen_packed`); only
    the attention pads. Custom layers, hooks on layers, padded lead tokens and static shapes
    (``torch.compile``, :func:`~smdm_plugin.core.checks.static_mode`) fall back to ``compact``."""
    if lead_padding is not None or static_shapes() or not supports_packed(inner):
        return compact_backend(inner, x, plan, lead, memory, memory_key_padding_mask, lead_padding)
    keep = torch.cat([plan.mask.new_ones(plan.batch, lead), plan.mask], 1)
    h, pq = varlen_packed(inner, x, keep, memory, memory_key_padding_mask)
    # packed rows are batch-major in sequence order: sample b's lead tokens, then its keyframes
    start = pq.cu[:-1]                                                 # [B]
    slot = torch.arange(lead + plan.capacity, device=x.device)[:, None]
    ok = torch.cat([plan.mask.new_ones(lead, plan.batch), plan.valid.t()], 0)
    rows = torch.where(ok, start[None, :] + slot, start[None, :])
    return h, rows


def supports_packed(inner: nn.Module) -> bool:
    """Whether :func:`varlen_packed` can run ``inner``'s layers."""
    return all(_supports_varlen(layer) for layer in inner.layers)


register_backend("masked", masked_backend)
register_backend("compact", compact_backend)
register_backend("varlen", varlen_backend, static_shapes=False, supports=supports_packed)


def _lead_rows(h: torch.Tensor, rows: torch.Tensor, lead: int, B: int) -> torch.Tensor:
    """``[lead, B, d]``: the lead tokens' output rows; a view when they are ``h``'s first rows (the
    compact backend's rows: its cached arange)."""
    if not static_compiling() and rows.is_contiguous() and rows.numel() == h.shape[0] \
            and rows.data_ptr() == consts.arange(rows.numel(), rows.device).data_ptr():
        return h[:lead * B].view(lead, B, -1)
    return gather_rows(h, rows[:lead].reshape(-1)).view(lead, B, h.shape[-1])


def fill_frames(h: torch.Tensor, rows: torch.Tensor, plan: KeyframePlan, lead: int,
                interpolate: bool = True) -> torch.Tensor:
    """Every output token ``[lead + N, B, d]`` from a backend's rows: lead tokens as they are,
    frames linearly interpolated between the keyframe rows around them (or, with
    ``interpolate=False``, keyframes as they are and zeros elsewhere)."""
    d = h.shape[-1]
    B, N = plan.mask.shape
    frame_rows = rows[lead:]                                           # [K, B]
    if interpolate and plan.slots is not None:                         # both ends in one gather
        pairs = frame_rows.gather(0, plan.slots.t())                   # [2N, B]: prev rows, next rows
        out = _LerpRowPairs.apply(h, pairs.reshape(-1), plan.weight.t().unsqueeze(-1).to(h.dtype))
        out = out.view(N, B, d)
        if lead:
            out = torch.cat([_lead_rows(h, rows, lead, B), out], 0)
        return out
    prev = frame_rows.gather(0, plan.prev_slot.t())                    # [N, B]
    if interpolate:
        out = lerp_rows(h, prev.reshape(-1), frame_rows.gather(0, plan.next_slot.t()).reshape(-1),
                        plan.weight.t().unsqueeze(-1).to(h.dtype))
    else:
        out = h.index_select(0, prev.reshape(-1)) * plan.mask.t().reshape(-1, 1).to(h.dtype)
    out = out.view(N, B, d)
    if lead:
        out = torch.cat([_lead_rows(h, rows, lead, B), out], 0)
    return out